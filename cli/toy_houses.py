"""``sceneforge toy-houses``: write procedural toy houses."""

from __future__ import annotations

import click


@click.command("toy-houses")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--count", "-n", type=click.IntRange(min=1), default=3, show_default=True,
              help="Number of houses to write.")
@click.option("--seed", "-s", type=click.IntRange(min=0), default=0, show_default=True,
              help="Batch seed; house i is generated from a seed derived from (seed, i).")
def toy_houses(out, count, seed):
    """Write COUNT procedural toy houses into OUT/<id>/ in sceneforge's house format.

    Each house is a grid of 2-4 furnished rooms with closed walls, door and window
    openings, floors and ceilings; ids are toy_<seed>_<i>. The same seed always writes
    the same bytes. Prints one line per house: id, rooms, instances, triangles.
    The houses shipped with sceneforge are `toy-houses OUT --count 3 --seed 0`.
    """
    from sceneforge.houses.toy import write_toy_houses

    from .output import check_output

    check_output(out, "output folder", kind="folder")

    def report(house, folder):
        click.echo(f"{house.id}  rooms {len(house.rooms)}  instances {len(house.instances)}  "
                   f"triangles {house.triangle_count:,}  -> {folder}")

    write_toy_houses(out, count, seed, progress=report)
