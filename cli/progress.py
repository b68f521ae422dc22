"""The progress bar every long-running command shows."""

from __future__ import annotations


class RichProgress:
    """Progress of a run on a rich bar: done/total, rate and time left."""

    def __init__(self, bar):
        self.bar, self.task = bar, None

    def start(self, step: str, total: int, unit: str, done: int = 0) -> None:
        if self.task is not None:
            self.bar.update(self.task, visible=False)
        self.task = self.bar.add_task(step, total=total, completed=done, unit=unit)

    def advance(self, n: int) -> None:
        self.bar.advance(self.task, n)


def progress_bar(console):
    """A rich progress bar showing done/total, the rate in the task's unit and the time left."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class Rate(ProgressColumn):
        def render(self, task):
            speed = task.finished_speed or task.speed
            return Text("" if speed is None else f"{speed:.1f} {task.fields['unit']}/s")

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), Rate(),
                    TextColumn("ETA"), TimeRemainingColumn(), console=console)
