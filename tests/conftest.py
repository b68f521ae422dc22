"""Shared test helpers: tiny hand-made houses with known geometry, and a tiny rendered store."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from sceneforge.houses import House, Room, make_instance

SHARED = Path(__file__).resolve().parents[2] / "shared"
BREAKFAST_ROOM = SHARED / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"


def box_instance(house: House, name: str, category: int, extents, center, room_id="r0", label=None):
    """Add an axis-aligned closed box (extents (3,), centre (3,), metres) to ``house``."""
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(center)
    return make_instance(house, name=name, category=category, label=label or name, room_id=room_id,
                         vertices=b.vertices, faces=b.faces)


def box_room(name: str, size: float, height: float, room_type: str = "room") -> House:
    """A size × height × size m room around the origin, floor top at y = 0: floor, ceiling
    and four walls, each a closed 0.1 m thick box (instances floor, ceiling, wall0..wall3)."""
    h = House(id=name, instances=[], rooms=[Room("r0", room_type, 0)])
    half, t = size / 2, 0.1
    box_instance(h, "floor", 2, (size, t, size), (0, -t / 2, 0))
    box_instance(h, "ceiling", 22, (size, t, size), (0, height + t / 2, 0))
    for i, (ext, c) in enumerate([((t, height, size), (-half - t / 2, height / 2, 0)),
                                  ((t, height, size), (half + t / 2, height / 2, 0)),
                                  ((size, height, t), (0, height / 2, -half - t / 2)),
                                  ((size, height, t), (0, height / 2, half + t / 2))]):
        box_instance(h, f"wall{i}", 1, ext, c)
    return h


@pytest.fixture(scope="session")
def tiny_toy_store(tmp_path_factory) -> Path:
    """The bundled toy houses rendered at 64×48, one view each, no RGB (3 views), for the
    tests that only read a store (evaluate, its scripts)."""
    from click.testing import CliRunner
    from sceneforge.cli.render import render

    out = tmp_path_factory.mktemp("tiny_toy") / "toy.zarr"
    res = CliRunner().invoke(render, ["bundled:toy", str(out), "--views-per-house", "1",
                                      "--resolution", "64x48", "--no-rgb"])
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture
def small_house() -> House:
    """A 4 × 3 × 4 m room (floor, ceiling, four walls) with a table, a chair and a cup."""
    h = box_room("small", size=4.0, height=3.0, room_type="kitchen")
    box_instance(h, "table", 7, (1.2, 0.05, 0.8), (0, 0.725, 0))
    box_instance(h, "chair", 5, (0.45, 0.45, 0.45), (0, 0.225, 0.7))
    box_instance(h, "cup", 40, (0.08, 0.1, 0.08), (0.2, 0.8, 0.1), label="cup")
    return h


def assert_same_geometry(a: House, b: House, atol=1e-6):
    """Same instances (order, name-independent), categories, rooms and geometry."""
    assert len(a.instances) == len(b.instances)
    for ia, ib in zip(a.instances, b.instances):
        assert ia.category == ib.category, (ia.name, ib.name)
        assert ia.envelope == ib.envelope
        assert ia.room_id == ib.room_id
        ma = trimesh.Trimesh(ia.vertices, ia.faces, process=False)
        mb = trimesh.Trimesh(ib.vertices, ib.faces, process=False)
        np.testing.assert_allclose(ma.bounds, mb.bounds, atol=atol)
        np.testing.assert_allclose(ma.area, mb.area, rtol=1e-6, atol=atol)
        assert len(ia.faces) == len(ib.faces)
