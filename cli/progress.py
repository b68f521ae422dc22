"""The progress bar every long-running command shows."""

from __future__ import annotations

import contextlib


class RichProgress:
    """Progress of a run on a rich bar: done/total, rate and time left."""

    def __init__(self, bar):
        self.bar, self.task = bar, None

    def start(self, step: str, total: int, unit: str, done: int = 0) -> None:
        if not self.bar.live.is_started:  # shown from the first step on (progress_bar)
            self.bar.start()
        if self.task is not None:
            self.bar.update(self.task, visible=False)
        self.task = self.bar.add_task(step, total=total, completed=done, unit=unit, initial=done)

    def advance(self, n: int) -> None:
        self.bar.advance(self.task, n)


@contextlib.contextmanager
def progress_bar(console, transient: bool = False):
    """A rich progress bar showing done/total, the rate in the task's unit and the time left
    (``transient``: removed when done, leaving the command's output as it was).

    The bar appears with its first step (:meth:`RichProgress.start`): a command that fails
    before any (a wrong path, a refused option) prints its one line and no empty bar line
    before it."""
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
        """Work done in this step over its wall time since it started: the rate the
        command's last line reports (rich's own speed leaves out the wait for the first
        result, e.g. the workers starting)."""

        def render(self, task):
            elapsed = task.finished_time if task.finished else task.elapsed
            done = task.completed - task.fields.get("initial", 0)
            if not elapsed or done <= 0:
                return Text("")
            return Text(f"{done / elapsed:.1f} {task.fields['unit']}/s")

    bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), Rate(),
                   TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=transient,
                   disable=transient and not console.is_terminal)
    with shown_from_first_task(bar):
        yield bar


@contextlib.contextmanager
def shown_from_first_task(bar):
    """Run the block with the rich Progress ``bar`` not yet shown: its user starts it with
    its first task (``if not bar.live.is_started: bar.start()``); stopped at the end."""
    try:
        yield bar
    finally:
        if bar.live.is_started:
            bar.stop()
