"""CLI options generated from the config dataclasses: help and defaults from the fields,
defaults < --config FILE < options typed, unknown keys in one red line, schemas in sync."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner
from sceneforge.cli.main import cli
from sceneforge.cli.options import ConfigOption, config_options
from sceneforge.cli.render import RENDER_OPTIONS
from sceneforge.cli.train import TRAIN_OPTIONS

from sceneforge import schemas
from sceneforge.config import SCHEMAS, DatasetConfig, field_doc, resolve_config, schema
from sceneforge.errors import SceneforgeError
from sceneforge.learn.config import PredictConfig, TrainConfig


def echo_config(root, options):
    """A command with ``options`` that prints the config it resolves, as JSON."""
    @click.command()
    @config_options(root, options)
    def command(config):
        click.echo(json.dumps(config.to_dict()))

    return command


def resolved(root, options, *args) -> dict:
    res = CliRunner().invoke(echo_config(root, options), list(map(str, args)))
    assert res.exit_code == 0, res.output
    return json.loads(res.output)


def one_line(text: str) -> str:
    return " ".join(text.split())


@pytest.mark.parametrize("name", list(SCHEMAS))
def test_schema_files_are_the_ones_generated_from_the_dataclasses(name):
    path = Path(schemas.__file__).parent / f"{name}.schema.json"
    assert json.loads(path.read_text()) == schema(name), "run: python -m sceneforge.config"


def test_help_shows_the_field_docs_and_defaults():
    res = CliRunner().invoke(cli, ["train", "--help"])
    assert res.exit_code == 0
    text = one_line(res.output)
    for path in ("epochs", "bn_momentum", "split.val_fraction", "eft.gating"):
        doc = field_doc(TrainConfig, path)
        assert one_line(doc[0].upper() + doc[1:]) in text, path
    assert "--epochs INTEGER RANGE Passes over the training views (paper: 40). [default: 40; x>=1]" in text
    assert "--gating [volume|surface]" in text and "[default: volume]" in text
    text = one_line(CliRunner().invoke(cli, ["render", "--help"]).output)
    assert "[default: 320x240]" in text and "[default: raster]" in text and "--strict / --no-strict" in text
    assert "config default" not in text


def test_an_option_of_several_fields_says_its_own_help():
    with pytest.raises(TypeError, match="several fields"):
        ConfigOption("--size", ("width", "height"))
    with pytest.raises(TypeError, match="several fields"):
        ConfigOption("--seed", "seed", help="the seed")


def _commands(group: click.Group, ctx: click.Context, path: tuple = ()):
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        yield (*path, name), command
        if isinstance(command, click.Group):
            yield from _commands(command, ctx, (*path, name))


def test_every_option_help_reads_as_sentences():
    """No help glues two texts into one sentence (it read "... the store's saved config
    records it; render RGB images; without them ..."): every option of every command ends
    its help as a sentence ends, and an option of several fields says its own."""
    ctx = click.Context(cli)
    seen = 0
    for path, command in _commands(cli, ctx):
        for param in command.params:
            text = getattr(param, "help", None)
            if text:
                seen += 1
                assert text.rstrip().endswith((".", ")", "]")), f"{' '.join(path)} {param.opts[0]}: {text!r}"
    assert seen > 50
    text = one_line(CliRunner().invoke(cli, ["render", "--help"]).output)
    assert "records it; render" not in text and "pixels; frontal" not in text
    assert "--rgb [raster|pathtraced|none] How RGB images are made: raster" in text
    assert "--resolution WxH Frontal image size, width x height in pixels. [default: 320x240]" in text


def _with_default(monkeypatch, cls, name, value):
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    monkeypatch.setattr(f, "default", value)


def test_changing_a_dataclass_default_changes_help(monkeypatch):
    def help_text(root, options):
        return one_line(CliRunner().invoke(echo_config(root, options), ["--help"]).output)

    assert "--views-per-house INTEGER RANGE Cameras sampled per house" in help_text(DatasetConfig, RENDER_OPTIONS)
    assert "[default: 4; x>=1]" in help_text(DatasetConfig, RENDER_OPTIONS)
    _with_default(monkeypatch, DatasetConfig, "views_per_house", 9)
    _with_default(monkeypatch, DatasetConfig, "width", 640)
    text = help_text(DatasetConfig, RENDER_OPTIONS)
    assert "[default: 9; x>=1]" in text and "[default: 640x240]" in text
    _with_default(monkeypatch, TrainConfig, "batch_size", 5)
    assert "Views per batch (paper: 24). [default: 5; x>=1]" in help_text(TrainConfig, TRAIN_OPTIONS)


def test_options_typed_override_the_file_and_others_leave_it_alone(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"seed": 3, "views_per_house": 2, "rgb": {"enabled": False},
                                "view": {"overhead": {"resolution": 64}}, "houses": {"scale": 0.5}}))
    defaults = DatasetConfig().to_dict()
    assert resolved(DatasetConfig, RENDER_OPTIONS) == defaults
    got = resolved(DatasetConfig, RENDER_OPTIONS, "--config", path, "--seed", 7, "--resolution", "64x48")
    assert (got["seed"], got["views_per_house"], got["width"], got["height"]) == (7, 2, 64, 48)
    assert not got["rgb"]["enabled"] and got["view"]["overhead"]["resolution"] == 64
    assert got["houses"]["scale"] == 0.5 and got["houses"]["strict"] is False
    got = resolved(DatasetConfig, RENDER_OPTIONS, "--config", path, "--rgb", "raster", "--strict")
    assert got["rgb"]["enabled"] and got["houses"]["strict"] and got["seed"] == 3


def test_rgb_mode_option_sets_mode_and_enabled():
    assert resolved(DatasetConfig, RENDER_OPTIONS)["rgb"] | {"lighting": None} == {
        "enabled": True, "mode": "raster", "antialias": False, "samples": 64, "denoise": True, "lighting": None}
    got = resolved(DatasetConfig, RENDER_OPTIONS, "--rgb", "pathtraced", "--rgb-samples", 8)["rgb"]
    assert (got["enabled"], got["mode"], got["samples"]) == (True, "pathtraced", 8)
    assert resolved(DatasetConfig, RENDER_OPTIONS, "--no-rgb-denoise")["rgb"]["denoise"] is False
    assert resolved(DatasetConfig, RENDER_OPTIONS, "--rgb", "none")["rgb"]["enabled"] is False


def test_one_option_may_set_several_fields(tmp_path):
    got = resolved(TrainConfig, TRAIN_OPTIONS, "s.zarr", "--stage", "seg", "--seed", 4, "--gating", "surface")
    # the split has its own seed (issue 14): --seed leaves it alone
    assert (got["seed"], got["split"]["seed"], got["eft"]["gating"], got["stores"]) == (4, 0, "surface", ["s.zarr"])
    got = resolved(TrainConfig, TRAIN_OPTIONS, "s.zarr", "--stage", "seg", "--split-seed", 5)
    assert (got["seed"], got["split"]["seed"]) == (0, 5)
    path = tmp_path / "t.json"
    path.write_text(json.dumps({"stage": "depth", "stores": ["a.zarr", "b.zarr"], "split": {"seed": 9}}))
    got = resolved(TrainConfig, TRAIN_OPTIONS, "--config", path, "--lr", 0.01)
    assert (got["stage"], got["stores"], got["split"]["seed"], got["lr"]) == ("depth", ["a.zarr", "b.zarr"], 9, 0.01)


def test_required_fields_come_from_the_options_or_the_file():
    res = CliRunner().invoke(echo_config(TrainConfig, TRAIN_OPTIONS), ["s.zarr"])
    assert res.exit_code == 2 and "Missing option '--stage'" in res.output


@pytest.mark.parametrize("args", [
    ["render", "bundled:toy", "{tmp}/out.zarr"],
    ["train", "s.zarr", "--stage", "depth"],
    ["predict", "{tmp}", "s.zarr", "{tmp}/p.zarr"],
    ["evaluate", "voxels", "s.zarr"],
    ["overhead-camera", "bundled:toy"],
    ["houses", "inspect", "bundled:toy"],
])
def test_unknown_config_key_is_one_red_line_naming_it(args, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"foo": 2}))
    res = CliRunner().invoke(cli, [a.replace("{tmp}", str(tmp_path)) for a in args] + ["--config", str(bad)])
    assert res.exit_code == 1
    assert res.output.strip().splitlines() == [
        f"error: {bad}: unknown key 'foo': Additional properties are not allowed by the "
        f"{ {'train': 'train', 'predict': 'predict', 'evaluate': 'evaluate'}.get(args[0], 'config')} schema"]
    assert "Traceback" not in res.output
    assert not (tmp_path / "out.zarr").exists()


def test_nested_unknown_key_is_named_by_its_path_with_a_suggestion(tmp_path):
    with pytest.raises(SceneforgeError, match=r"^c.json: unknown keys 'foo', 'houses.bar': "):
        DatasetConfig.from_dict({"foo": 1, "houses": {"bar": 2}}, what="c.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"stage": "depth", "stores": ["s"], "split": {"val_fration": 0.2}}))
    res = CliRunner().invoke(cli, ["train", "--config", str(bad)])
    assert res.exit_code == 1 and res.output.count("\n") == 1
    assert "unknown key 'split.val_fration'" in res.output and "did you mean 'val_fraction'?" in res.output


def test_train_config_round_trips_and_is_validated_on_reload():
    config = TrainConfig(stage="overhead", stores=("a.zarr",), max_steps=3)
    assert TrainConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(SceneforgeError, match=r"run/config.json: unknown key 'eft.gate'"):
        TrainConfig.from_dict({**config.to_dict(), "eft": {"gate": "volume"}}, what="run/config.json")
    with pytest.raises(SceneforgeError, match=r"does not match the train schema: stage: 'walk' is not one of"):
        TrainConfig.from_dict({**config.to_dict(), "stage": "walk"})
    assert config.with_frozen_runs("runs").depth_run == str(Path("runs") / "depth")
    assert config.with_frozen_runs("runs").seg_run == str(Path("runs") / "seg")
    assert TrainConfig(stage="seg", stores=("a",)).with_frozen_runs("runs").depth_run is None


def test_the_learning_checks_config_files_are_valid_configs_of_their_stage():
    """benchmarks/learning_check.sh trains with these files; a renamed field must fail here,
    not minutes into the recipe."""
    root = Path(__file__).resolve().parents[1] / "benchmarks"
    script = (root / "learning_check.sh").read_text()
    # the 2-core CPU recipe, and the one-GPU recipe at the paper's sizes (RECIPE=benchmarks/learning/gpu)
    for recipe, size in ((root / "learning", (80, 60)), (root / "learning" / "gpu", (320, 240))):
        render = resolve_config(DatasetConfig, recipe / "render.json")
        assert (render.width, render.height) == size
        for stage in ("depth", "seg", "overhead"):
            path = recipe / f"{stage}.json"
            config = resolve_config(TrainConfig, path, {"stores": ["gt.zarr"]})
            assert config.stage == stage and config.lr_schedule == "cosine"
        predict = resolve_config(PredictConfig, recipe / "predict.json")
        # no threshold tuned on one seed: each run chooses its own on its validation houses
        assert predict.operating_point == "validation" and predict.min_object_probability is None
    assert '--config "$recipe/render.json"' in script and "for stage in depth seg overhead" in script
    assert '--config "$recipe/$stage.json"' in script and '--config "$recipe/predict.json"' in script
    assert 'recipe=${RECIPE:-' in script
    assert (root / "learning_check.sh").stat().st_mode & 0o111
    cpu = {stage: resolve_config(TrainConfig, root / "learning" / f"{stage}.json", {"stores": ["gt.zarr"]})
           for stage in ("depth", "seg", "overhead")}
    assert {c.amp for c in cpu.values()} == {"bf16"} and cpu["depth"].loss.huber_delta == 0.1


def _learning_check(tmp_path, amp: str | None) -> tuple[subprocess.CompletedProcess, list[str]]:
    """benchmarks/learning_check.sh run with a fake ``sceneforge`` that logs its calls (and
    ``AMP=amp`` when given): the finished process and the logged command lines."""
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "learning_check.sh"
    log = tmp_path / "calls.txt"
    fake = tmp_path / "sf"
    fake.write_text(f'#!/bin/sh\necho "$*" >> {log}\n')
    fake.chmod(0o755)
    (tmp_path / "houses").mkdir()
    env = {**os.environ, "SCENEFORGE": str(fake)}
    env.pop("RECIPE", None)
    env.pop("AMP", None)
    if amp:
        env["AMP"] = amp
    done = subprocess.run(["bash", str(script), str(tmp_path / "houses"), str(tmp_path / "work")], env=env,
                          capture_output=True, text=True)
    return done, log.read_text().splitlines() if log.exists() else []


@pytest.mark.parametrize("amp", ["auto", "bf16", "fp16", "off", None])
def test_the_learning_check_passes_amp_to_every_training_stage(tmp_path, amp):
    """AMP=… (each of train --amp's choices) reaches the three ``train`` commands; unset, the
    CPU recipe's bf16 stays where the CPU computes bfloat16 itself and becomes --amp off
    elsewhere."""
    from sceneforge.learn.config import AMPS

    assert amp is None or amp in AMPS
    done, calls = _learning_check(tmp_path, amp)
    assert done.returncode == 0, done.stderr
    trains = [line for line in calls if line.startswith("train ")]
    assert len(trains) == 3
    try:
        native = {"avx512_bf16", "amx_bf16"} & set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        native = set()
    want = amp or (None if native else "off")
    for line in trains:
        assert (f"--amp {want}" in line) if want else ("--amp" not in line), line


def test_the_learning_check_refuses_a_bad_amp_before_rendering(tmp_path):
    """A mistyped AMP is refused with one line before anything runs, not by the first
    ``train`` after the render; the script's list is train --amp's."""
    from sceneforge.learn.config import AMPS

    done, calls = _learning_check(tmp_path, "fp64")
    assert done.returncode == 2 and calls == []
    assert done.stderr.strip() == f"error: AMP=fp64 is not one of {', '.join(AMPS)} (train --amp)"


def test_help_imports_no_torch():
    code = ("import sys; from click.testing import CliRunner; from sceneforge.cli.main import cli; "
            "[CliRunner().invoke(cli, [*c, '--help']) for c in (['train'], ['predict'], ['render'], [])]; "
            "print(sorted(m for m in ('torch', 'zarr') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_overhead_explanation_is_one_library_call(small_house, tmp_path):
    from sceneforge.houses.formats.native import write_house
    from sceneforge.overhead import OverheadConfig
    from sceneforge.pipeline.explain import explain_overhead_cameras

    write_house(small_house, tmp_path / "small")
    cameras = tmp_path / "cameras.txt"
    cameras.write_text("0 1.5 1.6  0 -0.2 -1  0 1 0  0.5534 0.4339 0\n")
    explained = explain_overhead_cameras(tmp_path / "small", cameras, config=OverheadConfig(resolution=32))
    (view,) = explained.views
    assert view.index == 0 and explained.sampled is None and len(explained.cameras) == 1
    assert [c.name for c in view.overhead.candidates] == ["depth_statistics", "envelope_frustum", "majority_room"]
    assert view.overhead.resolution == 32 and len(view.points.objects) > 0
    with pytest.raises(SceneforgeError, match="view 3: small has 1 view$"):
        explain_overhead_cameras(tmp_path / "small", cameras, view_index=3)
