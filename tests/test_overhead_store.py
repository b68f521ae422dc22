"""``overhead-camera`` explains what render stored: sampled cameras are render's, and
``--store S --view I`` gives exactly the overhead camera the store holds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.config import load_config
from sceneforge.houses import bundled_toy_dir
from sceneforge.pipeline import render_dataset
from sceneforge.pipeline.explain import explain_overhead_cameras, explain_stored_view
from sceneforge.store import open_store

pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

TINY = {"width": 32, "height": 24, "views_per_house": 3, "view": {"overhead": {"resolution": 16}},
        "rgb": {"enabled": False}, "seed": 5}


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("explain") / "toy.zarr"
    render_dataset("bundled:toy", str(out), load_config(None, TINY))
    return out


def test_a_stored_view_is_explained_exactly(store):
    s = open_store(str(store))
    for i in range(len(s)):
        explained = explain_stored_view(str(store), i)
        np.testing.assert_array_equal(explained.overhead.params, s.view(i)["overhead_params"])
        np.testing.assert_array_equal(explained.overhead.cam_to_world, s.view(i)["overhead_cam_to_world"])
    res = CliRunner().invoke(cli, ["overhead-camera", "--store", str(store), "--view", "4"])
    assert res.exit_code == 0, res.output
    tx, ty, tz, theta, sigma = s.view(4)["overhead_params"]
    assert f"overhead: tx {tx:.3f}  ty {ty:.3f}  tz {tz:.3f}  theta {theta:.4f}  sigma {sigma:.3f}" in res.output
    bad = CliRunner().invoke(cli, ["overhead-camera", "--store", str(store), "--view", "99"])
    assert bad.exit_code == 1 and bad.output.strip() == f"error: view 99: {store} has 9 views"


def test_sampled_cameras_are_the_ones_render_samples(store):
    s = open_store(str(store))
    config = s.config
    found = explain_overhead_cameras(bundled_toy_dir() / "toy_0_001", 3, sampler=config.sampler, seed=5,
                                     config=config.view.overhead)
    for k, view in enumerate(found.views):
        np.testing.assert_array_equal(view.camera.cam_to_world, s.view(3 + k)["cam_to_world"])
        np.testing.assert_array_equal(view.overhead.params, s.view(3 + k)["overhead_params"])
