"""Entry point of the ``sceneforge`` command.

Subcommands are imported only when used, so ``sceneforge --help`` stays instant and a
missing optional dependency only affects the command that needs it.

Expected failures end as one red line and an exit code from :mod:`sceneforge.errors`
(``EXIT_*``): an error the user can fix (:class:`SceneforgeError`, or an :class:`OSError`
such as an unwritable path or a full disk) exits with 1, a bad option with 2 (Click), work
done with some failures with 3, Ctrl-C with 130 (and SIGTERM is handled like it, so that
a store's lock is released).
"""

from __future__ import annotations

import difflib
import importlib
import logging
import signal

import click

from sceneforge.errors import EXIT_ERROR, EXIT_INTERRUPTED, Interrupted, SceneforgeError

#: command name → "module:attribute" under ``sceneforge.cli``
COMMANDS = {
    "houses": "houses:houses",
    "toy-houses": "toy_houses:toy_houses",
    "overhead-camera": "overhead_camera:overhead_camera",
    "evaluate": "evaluate:evaluate",
    "doctor": "doctor:doctor",
    "render": "render:render",
    "validate": "render:validate",
    "show": "render:show",
    "export": "render:export",
    "train": "train:train",
    "predict": "train:predict",
    "reconstruct": "reconstruct:reconstruct",
}


#: what a command interrupted by Ctrl-C says about going on (default: nothing; a command
#: whose next step depends on how far it got raises :class:`Interrupted` with its own hint)
ON_INTERRUPT = {
    "render": "run the same command again to resume",
}


class _WarningLines(logging.Handler):
    """Warnings of the library's loggers as yellow lines on stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        click.secho(f"warning: {record.getMessage()}", fg="yellow", err=True)


def _oserror_line(e: OSError) -> str:
    what = f"{e.filename}: " if e.filename else ""
    return f"{what}{e.strerror or e}"


def _own_line(e: SceneforgeError) -> str:
    """The error's own message: one raised in a DataLoader worker process comes back with
    PyTorch's "Caught ... in DataLoader worker process 0" and the worker's traceback in
    front of it, the message on the traceback's last line."""
    text = str(e)
    if "Original Traceback" not in text:
        return text
    last = text.rstrip().rsplit("\n", 1)[-1]
    return last.split(": ", 1)[1] if last.startswith(type(e).__module__) else last


class LazyGroup(click.Group):
    """A group that imports its subcommands on first use and prints expected errors in red."""

    def __init__(self, *args, lazy: dict[str, str] | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy = lazy or {}

    def list_commands(self, ctx):
        return sorted({*super().list_commands(ctx), *self.lazy})

    def get_command(self, ctx, name):
        if name in self.lazy:
            module, attr = self.lazy[name].split(":")
            return getattr(importlib.import_module(f"sceneforge.cli.{module}"), attr)
        return super().get_command(ctx, name)

    def resolve_command(self, ctx, args):
        name = click.utils.make_str(args[0]) if args else ""
        if args and not name.startswith("-") and self.get_command(ctx, name) is None:
            # Click suggests only among the commands imported: none of the lazy ones
            close = difflib.get_close_matches(name, self.list_commands(ctx), n=3)
            hint = f" Did you mean {' or '.join(map(repr, close))}?" if close else ""
            raise click.UsageError(f"No such command {name!r}.{hint}", ctx)
        return super().resolve_command(ctx, args)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except SceneforgeError as e:
            click.secho(f"error: {_own_line(e)}", fg="red", err=True)
            ctx.exit(EXIT_ERROR)
        except OSError as e:  # an unwritable path, a full disk, a file gone: the user's to fix
            click.secho(f"error: {_oserror_line(e)}", fg="red", err=True)
            ctx.exit(EXIT_ERROR)
        except KeyboardInterrupt as e:
            hint = e.hint if isinstance(e, Interrupted) else ON_INTERRUPT.get(ctx.invoked_subcommand or "")
            click.secho(f"interrupted{f': {hint}' if hint else ''}", fg="red", err=True)
            ctx.exit(EXIT_INTERRUPTED)


@click.group(cls=LazyGroup, lazy=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="sceneforge")
def cli():
    """sceneforge: 3D house models in, multi-layer depth training data out.

    Implements "3D Scene Reconstruction with Multi-layer Depth and Epipolar
    Transformers" (Shin et al., ICCV 2019). Conventions: metres, +Y up, OpenCV camera
    axes (x right, y down, z forward), planar depth, NaN = no surface, NYU40 labels.

    Exit codes: 0 done; 1 an error (one red line; what was written is kept); 2 a bad
    option or argument; 3 done, but some houses, views or checks failed; 130 interrupted.
    """
    logger = logging.getLogger("sceneforge")
    if not any(isinstance(h, _WarningLines) for h in logger.handlers):
        logger.addHandler(_WarningLines(logging.WARNING))
        logger.propagate = False


def _terminate(signum, frame):
    raise KeyboardInterrupt  # unwinds like Ctrl-C: locks released, "interrupted" printed


def main():
    signal.signal(signal.SIGTERM, _terminate)
    cli()
