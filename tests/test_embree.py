"""sceneforge's Embree extension against the Open3D engine on real houses: every array of
a view's ground truth (layers, overhead truth, mesh) bit-identical, and the extension built
wherever Embree is installed."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sceneforge import depth_mesh, layers
from sceneforge.cameras import CameraSamplerConfig, sample_cameras
from sceneforge.houses import BUNDLED_TOY, discover, load
from sceneforge.raytrace import HouseTracer
from sceneforge.raytrace import embree_backend as embree
from sceneforge.view import ViewConfig, compute_view

from .conftest import BREAKFAST_ROOM

NO_EXTENSION = pytest.mark.skipif(not embree.AVAILABLE, reason="sceneforge's Embree extension is not built")
EMBREE_HEADERS = [Path(root) / "include" / f"embree{major}" / "rtcore.h"
                  for root in ("/usr", "/usr/local") for major in (3, 4)]


def houses():
    yield from (pytest.param(s, id=s.id) for s in discover(BUNDLED_TOY))
    yield pytest.param(BREAKFAST_ROOM, id="breakfast_room", marks=pytest.mark.skipif(
        not BREAKFAST_ROOM.exists(), reason=f"{BREAKFAST_ROOM} is absent (shared scenes not checked out)"))


def view_arrays(view) -> dict[str, np.ndarray]:
    """Every array of a view's ground truth."""
    out = {f"layers.{k}": getattr(view.layers, k) for k in ("depth", "category", "instance", "normal")}
    out |= {f"overhead.layers.{k}": getattr(view.overhead.layers, k) for k in ("depth", "category", "instance")}
    out |= {"overhead.height": view.overhead.height, "overhead.category": view.overhead.category}
    for part in ("objects", "envelope"):
        mesh = getattr(view.mesh, part)
        out |= {f"mesh.{part}.vertices": mesh.vertices, f"mesh.{part}.faces": mesh.faces}
    return out


@NO_EXTENSION
@pytest.mark.parametrize("source", list(houses()))
def test_views_are_bit_identical_to_the_open3d_engine(source, monkeypatch):
    """Two sampled 320×240 views of each house: cameras (the sampler's first-hit queries and
    distances), frontal layers, overhead truth and mesh the same to the last bit. The Open3D
    side runs as it does where the extension is missing: numpy layer rules and numpy
    triangulation (the embree side: both compiled)."""
    house = load(source)
    ours, theirs = HouseTracer(house, "embree"), HouseTracer(house, "open3d")
    sampler = CameraSamplerConfig()
    if house.id == "BreakfastRoom":  # window openings: let more of a view escape
        sampler = replace(sampler, max_escape_fraction=0.5)
    cameras, _ = sample_cameras(house, 2, np.random.default_rng(0), sampler, theirs)
    again, _ = sample_cameras(house, 2, np.random.default_rng(0), sampler, ours)
    assert len(cameras) == 2
    for a, b in zip(cameras, again):
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
    for camera in cameras:
        got = view_arrays(compute_view(house, camera, ViewConfig(), ours))
        with monkeypatch.context() as fallback:
            fallback.setattr(layers, "COMPILED_RULES", False)
            fallback.setattr(depth_mesh, "COMPILED", False)
            want = view_arrays(compute_view(house, camera, ViewConfig(), theirs))
        assert np.isfinite(got["layers.depth"][0]).any()
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_the_extension_is_built_where_embree_is_installed():
    """``pip install -e .`` leaves the extension out, silently apart from a warning, when it
    cannot build it: fail here rather than fall back to Open3D unnoticed."""
    headers = [h for h in EMBREE_HEADERS if h.is_file()]
    if not headers:
        pytest.skip("Embree's headers are not installed (scripts/system-deps.sh installs them)")
    assert embree.AVAILABLE, (
        f"Embree is installed ({headers[0]}) but sceneforge.raytrace._embree is not built: "
        "run `pip install -e .` again and read its warnings")
