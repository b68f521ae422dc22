"""Options shared by every command that reads houses."""

from __future__ import annotations

import functools

import click

from sceneforge.houses import FORMATS, LoadOptions


def house_options(func):
    """Add the house-reading options and pass a ``load_options`` (:class:`LoadOptions`)."""

    @click.option("--format", "fmt", type=click.Choice(FORMATS), default=None,
                  help="Source format. Default: detected from the path.")
    @click.option("--strict", is_flag=True,
                  help="Fail on unknown categories instead of mapping them to void.")
    @click.option("--scale", type=float, default=1.0, show_default=True,
                  help="glTF/OBJ/PLY: multiply coordinates by this to get metres.")
    @click.option("--up-axis", type=click.Choice(["y", "z"]), default="y", show_default=True,
                  help="glTF/OBJ/PLY: the source's up axis; z-up is converted to +Y up.")
    @click.option("--name-map", type=click.Path(exists=True, dir_okay=False), default=None,
                  help="glTF/OBJ/PLY: JSON [regex, NYU40 name] rules replacing the bundled map.")
    @click.option("--future-dir", type=click.Path(exists=True, file_okay=False), default=None,
                  help="3D-FRONT: folder of 3D-FUTURE models (default: beside the scenes).")
    @functools.wraps(func)
    def wrapper(*args, fmt, strict, scale, up_axis, name_map, future_dir, **kwargs):
        if scale <= 0:
            raise click.BadParameter(f"must be > 0, got {scale}", param_hint="--scale")
        opts = LoadOptions(format=fmt, strict=strict, scale=scale, up_axis=up_axis,
                           name_map=name_map, future_dir=future_dir)
        return func(*args, load_options=opts, **kwargs)

    return wrapper
