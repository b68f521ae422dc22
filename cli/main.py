"""Entry point of the ``sceneforge`` command.

Subcommands are imported only when used, so ``sceneforge --help`` stays instant and a
missing optional dependency only affects the command that needs it.
"""

from __future__ import annotations

import importlib

import click

from sceneforge.errors import SceneforgeError

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

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except SceneforgeError as e:
            click.secho(f"error: {e}", fg="red", err=True)
            ctx.exit(1)


@click.group(cls=LazyGroup, lazy=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="sceneforge")
def cli():
    """sceneforge: 3D house models in, multi-layer depth training data out.

    Implements "3D Scene Reconstruction with Multi-layer Depth and Epipolar
    Transformers" (Shin et al., ICCV 2019). Conventions: metres, +Y up, OpenCV camera
    axes (x right, y down, z forward), planar depth, NaN = no surface, NYU40 labels.
    """


def main():
    cli()
