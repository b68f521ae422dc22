"""Every command that writes: an unwritable output is one red line and exit code 1, found
before any work; results are written before plots; a bad --device is one line."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli

from sceneforge.config import load_config
from sceneforge.errors import EXIT_ERROR
from sceneforge.houses import bundled_toy_dir
from sceneforge.pipeline import render_dataset

pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

#: one tiny view per toy house
TINY = {"width": 32, "height": 24, "views_per_house": 1, "view": {"overhead": {"resolution": 16}},
        "rgb": {"enabled": False}}


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("outputs") / "toy.zarr"
    render_dataset("bundled:toy", str(out), load_config(None, TINY))
    return out


@pytest.fixture
def blocked(tmp_path) -> Path:
    """A regular file: no output can be written under it."""
    path = tmp_path / "a_file"
    path.write_text("not a folder")
    return path


HOUSE = str(bundled_toy_dir() / "toy_0_000")
#: every command that writes, with {out} where its output goes and {store} a store to read
COMMANDS = {
    "show -o": ["show", "{store}", "--view", "0", "-o", "{out}/panel.png"],
    "show --3d": ["show", "{store}", "--view", "0", "-o", "{ok}/panel.png", "--3d", "{out}/view.ply"],
    "houses inspect --preview": ["houses", "inspect", HOUSE, "--preview", "{out}/previews"],
    "export": ["export", "{store}", "{out}/exr"],
    "evaluate coverage --plot": ["evaluate", "coverage", "{store}", "--density", "100", "--plot", "{out}/c.png"],
    "evaluate coverage --json": ["evaluate", "coverage", "{store}", "--density", "100", "--plot", "{ok}/c.png",
                                 "--json", "{out}/c.json"],
    "evaluate predictions --plot": ["evaluate", "predictions", "{store}", "{store}", "--plot", "{out}/p.png"],
    "evaluate voxels --plot": ["evaluate", "voxels", "{store}", "--resolution", "10", "--plot", "{out}/v.png"],
    "evaluate points --json": ["evaluate", "points", "{store}", "{store}", "--json", "{out}/p.json"],
    "overhead-camera --plot": ["overhead-camera", HOUSE, "--plot", "{out}/o.png"],
    "predict OUT": ["predict", "{ok}", "{store}", "{out}/pred.zarr"],
    "train --run": ["train", "{store}", "--stage", "depth", "--run", "{out}/run"],
    "render OUT": ["render", "bundled:toy", "{out}/toy.zarr"],
    "toy-houses OUT": ["toy-houses", "{out}/houses"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_an_unwritable_output_is_one_red_line_before_any_work(command, store, blocked, tmp_path, monkeypatch):
    import sceneforge.evaluate.coverage

    def no_scoring(*args, **kwargs):
        raise AssertionError("the output was not checked before the work")

    monkeypatch.setattr(sceneforge.evaluate.coverage, "evaluate_views", no_scoring)
    args = [a.format(store=store, out=blocked, ok=tmp_path) for a in COMMANDS[command]]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == EXIT_ERROR, res.output
    assert "Traceback" not in res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(blocked) in lines[0], res.output
    assert "cannot write" in lines[0]


def test_evaluate_writes_its_json_even_when_the_plot_fails(store, tmp_path, monkeypatch):
    import sceneforge.cli.evaluate

    def disk_full(fig, path, dpi=100):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(sceneforge.cli.evaluate, "save_figure", disk_full)
    values = tmp_path / "coverage.json"
    res = CliRunner().invoke(cli, ["evaluate", "coverage", str(store), "--density", "100", "--limit", "1",
                                   "--plot", str(tmp_path / "c.png"), "--json", str(values)])
    assert res.exit_code == EXIT_ERROR and "Traceback" not in res.output
    assert res.output.strip().splitlines()[-1] == f"error: {tmp_path / 'c.png'}: No space left on device"
    assert json.loads(values.read_text())  # the numbers were kept
    assert not list(tmp_path.glob("*.partial*"))


@pytest.mark.parametrize("device", ["gpu", "cuda:x", "cuda:7"])
@pytest.mark.parametrize("command", ["train", "predict"])
def test_a_bad_device_is_one_red_line(command, device, store, tmp_path):
    pytest.importorskip("torch")
    args = {"train": ["train", str(store), "--stage", "depth", "--run", str(tmp_path / "run")],
            "predict": ["predict", str(tmp_path), str(store), str(tmp_path / "pred.zarr")]}[command]
    res = CliRunner().invoke(cli, [*args, "--device", device])
    assert res.exit_code == EXIT_ERROR and "Traceback" not in res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: --device {device}"), res.output
    assert not (tmp_path / "run").exists() and not (tmp_path / "pred.zarr").exists()


def test_show_refuses_a_view_out_of_range(store, tmp_path):
    """``--view -1`` used to show the last view without a word; views are numbered 0..N-1."""
    res = CliRunner().invoke(cli, ["show", str(store), "--view", "-1", "-o", str(tmp_path / "p.png")])
    assert res.exit_code == 2
    assert "-1: the store has 3 views (numbered 0 to 2)" in res.output
    assert not (tmp_path / "p.png").exists()


def test_render_refuses_a_cameras_folder_with_no_camera_file(tmp_path):
    """A wrong ``--cameras`` folder used to fail every house into a store of no views."""
    (tmp_path / "cams" / "elsewhere").mkdir(parents=True)
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(tmp_path / "t.zarr"), "--cameras",
                                   str(tmp_path / "cams")])
    assert res.exit_code == EXIT_ERROR, res.output
    assert "no camera file for any of the 3 houses" in res.output
    assert str(tmp_path / "cams" / "toy_0_000" / "room_camera.txt") in res.output
    assert not (tmp_path / "t.zarr").exists()


def test_validate_calls_a_store_of_no_views_invalid(tmp_path, small_house):
    """A store whose every house failed holds no views: not valid."""
    from sceneforge.errors import EXIT_FAILURES
    from sceneforge.houses.formats.native import write_house

    small_house.instances = [i for i in small_house.instances if i.name != "floor"]  # no floor: no camera
    write_house(small_house, tmp_path / "houses" / "small")
    out = tmp_path / "none.zarr"
    render_dataset(str(tmp_path / "houses"), str(out), load_config(None, TINY))
    res = CliRunner().invoke(cli, ["validate", str(out)])
    assert res.exit_code == EXIT_FAILURES, res.output
    assert "no views: the store holds none (1 house failed" in res.output


def test_format_that_finds_nothing_names_the_format_found(tmp_path, small_house):
    """``--format front3d`` on a SUNCG root names the format that is there."""
    from sceneforge.testing.suncg import write_house

    write_house(small_house, tmp_path / "suncg")
    res = CliRunner().invoke(cli, ["houses", "inspect", str(tmp_path / "suncg"), "--format", "front3d"])
    assert res.exit_code == EXIT_ERROR, res.output
    assert "no front3d house found (--format front3d); it holds suncg houses: pass --format suncg" in res.output
