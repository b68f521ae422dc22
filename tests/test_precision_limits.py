"""``benchmarks/precision_limits.py``: each row swaps exactly one ingredient of a prediction
for the truth, and a prediction that is the truth scores as the truth on every row."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "precision_limits.py"


@pytest.fixture(scope="module")
def limits():
    spec = importlib.util.spec_from_file_location("precision_limits", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _arrays(seed=0):
    rng = np.random.default_rng(seed)
    true_depth = rng.uniform(1.0, 4.0, (5, 6, 8)).astype(np.float32)
    true_height = rng.uniform(0.0, 1.0, (6, 6)).astype(np.float32)
    depth = (true_depth * 1.25).astype(np.float32)
    depth[:4, :2] = np.nan  # the predicted masks leave the top rows out
    height = true_height + np.float32(0.1)
    height[0] = np.nan
    return depth, height, true_depth, true_height


def test_true_depths_keep_the_predicted_masks(limits):
    depth, height, true_depth, true_height = _arrays()
    d, h = limits.true_depths(depth, height, true_depth, true_height)
    np.testing.assert_array_equal(np.isfinite(d), np.isfinite(depth))
    np.testing.assert_array_equal(d[:4, 2:], true_depth[:4, 2:])
    np.testing.assert_array_equal(d[4], depth[4])  # D5 is not a masked layer: the prediction's
    np.testing.assert_array_equal(np.isfinite(h), np.isfinite(height))
    np.testing.assert_array_equal(h[1:], true_height[1:])


def test_the_true_overhead_mask_keeps_the_predicted_heights_above_5_cm(limits):
    depth, height, true_depth, true_height = _arrays()
    d, h = limits.true_overhead_mask(depth, height, true_depth, true_height)
    assert d is depth
    objects = true_height > 0.05
    np.testing.assert_array_equal(h[objects], height[objects])
    assert np.isnan(h[~objects]).all()


def test_the_per_view_scale_undoes_a_uniform_scale_error(limits):
    depth, height, true_depth, true_height = _arrays()
    d, h = limits.depth_scale_per_view(depth, height, true_depth, true_height)
    np.testing.assert_allclose(d[:4, 2:], true_depth[:4, 2:], rtol=1e-6)
    assert h is height


def test_the_truth_as_its_own_prediction_scores_the_same_on_every_row(tiny_toy_store):
    store = tiny_toy_store
    out = subprocess.run([sys.executable, str(SCRIPT), str(store), str(store), "--density", "1000"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("3 views of ")
    assert lines[1].split() == ["D1", "D1-4", "overhead", "D1-4", "&", "overhead"]
    rows = {line[:30].strip(): line[30:].split("(")[0].split() for line in lines[2:]}
    assert list(rows) == ["prediction", "true depths, predicted masks", "true overhead mask",
                          "depth scale per view", "truth"]
    assert len(set(map(tuple, rows.values()))) == 1, rows
    precision = float(rows["truth"][-3])  # D1-4 & overhead: precision / recall
    assert precision > 0.8
