"""``benchmarks/bench_scale.py`` runs as the docs show it (a tiny run: one house, one view,
RGB off) and its figures come from the samples as stated: each tenth's rate, the time a
count was crossed, the memory trend."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_scale.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_scale", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_scale"] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules["bench_scale"]


def test_a_tiny_scale_run_prints_its_figures_and_plots(tmp_path):
    plot = tmp_path / "scale.png"
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--houses", "1", "--views-per-house", "1", "--resolution", "32x24",
         "--rgb", "none", "--workers", "1", "--sample", "0.2", "--plot", str(plot), "--keep", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    for line in ("views/s by tenth of the views", "worker resident memory", "kB per view", "500,000 views"):
        assert line in out.stdout
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_crossing_times_rates_and_memory_trend(bench):
    t = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    views = np.array([0.0, 0.0, 10.0, 20.0, 40.0])
    assert bench.crossing(t, views, 5) == 1.5  # halfway between the samples at 0 and 10 views
    assert bench.crossing(t, views, 30) == 3.5
    rates = bench.decile_rates(t, views, 40, start=1.0)
    assert [round(r, 3) for _, _, r in rates] == [10.0] * 5 + [20.0] * 5  # 4 views a tenth
    slope, mean = bench.memory_trend(np.array([0.0, 1000, 2000]), np.array([100.0, 102, 104]))
    assert (round(slope, 6), mean) == (2.0, 102.0)
