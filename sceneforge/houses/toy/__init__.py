"""Procedural toy houses (see :mod:`.planner`)."""

from .planner import (
    BUNDLE_COUNT,
    BUNDLE_SEED,
    Opening,
    ToyHouse,
    build_toy_house,
    generate_house,
    house_seed,
    toy_house_id,
    write_bundle,
    write_toy_houses,
)

__all__ = [
    "BUNDLE_COUNT", "BUNDLE_SEED", "Opening", "ToyHouse", "build_toy_house",
    "generate_house", "house_seed", "toy_house_id", "write_bundle", "write_toy_houses",
]
