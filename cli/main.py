"""Entry point of the ``sceneforge`` command."""

from __future__ import annotations

import click


@click.group()
def cli():
    """sceneforge: house meshes in, multi-layer depth training data out."""


def main():
    cli()
