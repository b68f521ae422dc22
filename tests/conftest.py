"""Shared test helpers: tiny hand-made houses with known geometry, a tiny rendered store, and
:func:`needs_shared` for the tests that read ``../shared`` (skipped, and counted, where it is absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from sceneforge.houses import House, Room, make_instance

#: the folder CI checks out beside the repo (real scenes, tools); a user's clone has none, so
#: every test that reads it carries :func:`needs_shared`
SHARED = Path(__file__).resolve().parents[2] / "shared"
BREAKFAST_ROOM = SHARED / "scenes" / "breakfast_room" / "BreakfastRoom.gltf"


def needs_shared(path: Path) -> pytest.MarkDecorator:
    """The mark of a test, or of a parameter, that reads ``path`` under :data:`SHARED`: it
    skips where ``path`` is absent, saying so as ``../shared/...`` (the machine's own path
    means nothing to a reader elsewhere), and the run's summary counts it."""
    return pytest.mark.needs_shared(path.relative_to(SHARED).as_posix())


def pytest_configure(config):
    config.addinivalue_line("markers", "needs_shared(relpath): reads ../shared/relpath; skips where it is absent")


def pytest_collection_modifyitems(items):
    # a skip mark, not pytest.skip in a hook: the skip is then reported at the test's own line
    for item in items:
        for mark in item.iter_markers("needs_shared"):
            if not (SHARED / mark.args[0]).exists():
                item.add_marker(pytest.mark.skip(
                    reason=f"needs ../shared/{mark.args[0]} (CI checks ../shared out beside the repo; "
                           "a user's clone has none)"))


def shared_summary(stats: dict, present: bool) -> str | None:
    """The line that says how many of the tests marked ``needs_shared`` ran and how many
    skipped, from the terminal reporter's ``stats`` (under xdist the workers' reports come
    back to the controller with their keywords); None where no such test was run."""
    marked = [r for reports in stats.values() for r in reports
              if isinstance(r, pytest.TestReport) and "needs_shared" in r.keywords]
    if not marked:
        return None
    ran = sum(r.when == "call" and not r.skipped for r in marked)
    skipped = sum(r.skipped for r in marked)
    where = "../shared present" if present else "../shared absent: a user's clone"
    return f"tests that need ../shared: {ran} ran, {skipped} skipped ({where})"


def pytest_terminal_summary(terminalreporter):
    # make test (CI's command too) shows whether the tests that need ../shared ran at all
    line = shared_summary(terminalreporter.stats, SHARED.is_dir())
    if line:
        terminalreporter.write_line(line)


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


@pytest.fixture(scope="module")
def one_torch_thread():
    """Torch on one thread for a module's tests: the test machines share two cores, and
    torch's thread pool spins for seconds under contention."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def render_learn_store(folder: Path) -> str:
    """The training tests' store in ``folder``: 3 bundled toy houses × 2 views, 64×48
    frontal, 32×32 overhead, with RGB."""
    pytest.importorskip("pyrender", reason="the render extra (pyrender) is not installed")
    from sceneforge.config import load_config
    from sceneforge.pipeline import render_dataset

    path = folder / "toy.zarr"
    config = load_config(None, {"width": 64, "height": 48, "views_per_house": 2,
                                "view": {"overhead": {"resolution": 32}}})
    summary = render_dataset("bundled:toy", str(path), config)
    assert summary.views == 6 and not summary.failed_houses
    return str(path)


#: two tiny views per toy house, four views per shard, normals and meshes kept: 6 views in 2
#: shards, every kind of array a store has
SMALL = {"width": 32, "height": 24, "views_per_house": 2, "view": {"overhead": {"resolution": 16}},
         "store": {"views_per_shard": 4, "normals": True, "gt_mesh": "all"}}


@pytest.fixture(scope="session")
def small_store(tmp_path_factory) -> Path:
    """The bundled toy houses rendered with :data:`SMALL`, for tests that read it (or copy it)."""
    from sceneforge.config import load_config
    from sceneforge.houses import BUNDLED_TOY
    from sceneforge.pipeline import render_dataset

    out = tmp_path_factory.mktemp("small") / "small.zarr"
    render_dataset(BUNDLED_TOY, str(out), load_config(None, SMALL))
    return out
