"""``benchmarks/compare_pbrs.py`` (issue 40): finds PBRS images in both layouts (per-house
folders as PBRS released them, one flat folder as ``shared/scenes/suncg_pbrs/pbrs`` ships),
prints the table per region kind and writes the side-by-side PNG."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare_pbrs.py"


@pytest.fixture(scope="module")
def compare():
    spec = importlib.util.spec_from_file_location("compare_pbrs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["compare_pbrs"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _write_frames(store_path, folder: Path, pattern: str, tint=(1.0, 1.0, 1.0), scale=1) -> list[tuple[str, int]]:
    """Each view's own RGB (× ``tint``) as its 'PBRS' image at ``pattern``, ``scale`` times
    the size (the script resizes PBRS's 640×480 to the store's frames)."""
    from sceneforge.store import open_store

    store = open_store(str(store_path))
    written = []
    for k in range(len(store)):
        view = store.view(k)
        house, camera = str(view["house_id"]), int(view["camera_id"])
        rgb = np.clip(np.asarray(view["rgb"]) * np.asarray(tint), 0, 255).astype(np.uint8)
        path = folder / pattern.format(house=house, camera=camera)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rgb).resize((rgb.shape[1] * scale, rgb.shape[0] * scale), Image.NEAREST).save(path)
        written.append((house, camera))
    return written


def test_the_same_frames_agree_in_every_region(compare, small_store, tmp_path):
    _write_frames(small_store, tmp_path, "{house}/{camera:06d}_mlt.png")
    result = compare.compare(str(small_store), tmp_path, min_pixels=5)
    assert result.missing == 0 and result.views == 6 and result.rows
    table = result.table(0.05, 1.0)
    assert table[0]["kind"] == "objects" and table[-1]["kind"] == "all"
    assert {t["kind"] for t in table} >= {"wall", "floor"}
    for row in table:
        assert row["chroma_within"] == row["stops_within"] == 1.0, row
    assert all(abs(r["stops"]) < 0.05 and r["chroma"] < 0.01 for r in result.rows)
    # windows burnt out as much here as there (the share of their pixels at or near white)
    assert result.window_white and all(w[1] == w[2] and w[3] == w[4] for w in result.window_white)


def test_window_white_counts_burnt_out_windows(compare, small_store, tmp_path):
    """A reference brighter by 4× (clipped) has more window pixels at and near white."""
    _write_frames(small_store, tmp_path, "{house}/{camera:06d}_mlt.png", tint=(4.0, 4.0, 4.0))
    result = compare.compare(str(small_store), tmp_path, min_pixels=5)
    assert sum(w[2] for w in result.window_white) > sum(w[1] for w in result.window_white)
    assert all(w[4] >= w[3] and w[4] >= w[2] for w in result.window_white)


def test_a_tinted_reference_fails_colour_not_layout(compare, small_store, tmp_path):
    _write_frames(small_store, tmp_path, "{house}/{camera:06d}_mlt.png", tint=(1.0, 0.6, 0.6))
    result = compare.compare(str(small_store), tmp_path, min_pixels=5)
    assert result.views == 6
    assert result.table(0.05, 1.0)[-1]["chroma_within"] < 0.5


def test_flat_folder_is_found_for_one_house_only(compare, small_store, tmp_path):
    """A flat folder of ``<camera>_mlt.png`` cannot tell houses apart: it is tried for a store
    of one house (the shared SUNCG house), and a store of several needs ``--pattern``."""
    written = _write_frames(small_store, tmp_path, "{camera:06d}_mlt.png")
    house, camera = written[0]
    flat = tmp_path / f"{camera:06d}_mlt.png"
    assert compare.pbrs_path(tmp_path, None, house, camera, houses=1) == flat
    assert compare.pbrs_path(tmp_path, None, house, camera, houses=3) is None
    assert compare.pbrs_path(tmp_path, "{camera:06d}_mlt.png", house, camera, houses=3) == flat
    # per-house folders win where both exist
    _write_frames(small_store, tmp_path, "{house}/{camera:06d}_mlt.png")
    assert compare.pbrs_path(tmp_path, None, house, camera, houses=1) == \
        tmp_path / house / f"{camera:06d}_mlt.png"
    assert compare.compare(str(small_store), tmp_path / "nothing").missing == 6


def test_command_prints_the_table_and_writes_the_figure(small_store, tmp_path):
    _write_frames(small_store, tmp_path / "pbrs", "{house}/{camera:06d}_mlt.png", scale=2)
    figure = tmp_path / "side.png"
    out = subprocess.run([sys.executable, str(SCRIPT), str(small_store), str(tmp_path / "pbrs"),
                          "--min-pixels", "5", "--figure", str(figure), "--with", str(small_store),
                          "--regions", "--json", str(tmp_path / "t.json")],
                         capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    assert lines[0].startswith("6 views") and lines[1].split()[:2] == ["kind", "regions"]
    assert lines[2].startswith("objects") and any(line.startswith("all ") for line in lines)
    assert "(counter)" in out  # --regions names each instance and its label
    width, height = Image.open(figure).size
    assert (width, height) == (3 * (32 + 4) + 4, 6 * (24 + 14 + 4) + 4)  # ours | --with | PBRS, a row per view


def test_window_ratio_undoes_the_soft_curve(compare):
    """The window / frame median luminance: as shown it is the ratio of the displayed
    (linear) values; with the ``soft`` curve undone it is the ratio before the curve, exact
    below byte 255 (here a window 8.3x the frame, which the curve's shoulder compresses)."""
    from sceneforge.colour import linear_to_srgb
    from sceneforge.render.tonemap import soft

    frame, window_value = 0.18, 1.5  # exposed linear luminances, grey (the window above the knee)
    h, w = 4, 8
    radiance = np.full((h, w), frame)
    window = np.zeros((h, w), bool)
    window[:, :3] = True
    radiance[window] = window_value
    rgb = np.round(np.repeat(linear_to_srgb(soft(radiance))[..., None], 3, -1) * 255).astype(np.uint8)
    seen = np.ones((h, w), bool)
    shown = compare.window_ratio(rgb, window, seen)
    before = compare.window_ratio(rgb, window, seen, "soft")
    assert shown == pytest.approx(float(soft(window_value)) / frame, rel=0.02)
    assert before == pytest.approx(window_value / frame, rel=0.02)  # the curve undone
    assert shown < 0.9 * before
    assert compare.window_ratio(rgb, window, seen, "aces") is None  # not inverted
