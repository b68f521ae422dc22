"""``sceneforge toy-houses``: write procedural toy houses."""

from __future__ import annotations

import dataclasses

import click

from sceneforge.config import field_docs
from sceneforge.houses.toy import ToyOptions


def _case_options(func):
    """A ``--x/--no-x`` flag per :class:`ToyOptions` field, its help the field's ``#:`` doc."""
    docs = field_docs(ToyOptions)
    for f in reversed(dataclasses.fields(ToyOptions)):
        flag = f.name.replace("_", "-")
        func = click.option(f"--{flag}/--no-{flag}", f.name, default=f.default, show_default=True,
                            help=docs[f.name][:1].upper() + docs[f.name][1:] + ".")(func)
    return func


@click.command("toy-houses")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--count", "-n", type=click.IntRange(min=1), default=3, show_default=True,
              help="Number of houses to write.")
@click.option("--seed", "-s", type=click.IntRange(min=0), default=0, show_default=True,
              help="Batch seed; house i is generated from a seed derived from (seed, i).")
@_case_options
def toy_houses(out, count, seed, **cases):
    """Write COUNT procedural toy houses into OUT/<id>/ in sceneforge's house format.

    Each house is a grid of 2-4 furnished rooms with closed walls, door and window
    openings, floors and ceilings; ids are toy_<seed>_<i>. The same seed always writes
    the same bytes. Prints one line per house: id, rooms, instances, triangles.
    The houses shipped with sceneforge are `toy-houses OUT --count 3 --seed 0`.
    The flags below add the hard cases of real data (all off by default).
    """
    from sceneforge.houses.toy import write_toy_houses

    from .output import check_output

    check_output(out, "output folder", kind="folder")

    def report(house, folder):
        click.echo(f"{house.id}  rooms {len(house.rooms)}  instances {len(house.instances)}  "
                   f"triangles {house.triangle_count:,}  -> {folder}")

    write_toy_houses(out, count, seed, progress=report, options=ToyOptions(**cases))
