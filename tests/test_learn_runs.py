"""Training runs and their files: Ctrl-C and SIGTERM save a checkpoint a resumed run goes on
from as if never stopped, the split file belongs to its stores (not to their folder), and
the run folder never takes over data training did not write."""

from __future__ import annotations

import hashlib
import json
import shutil
import signal
from pathlib import Path

import pytest

torch = pytest.importorskip("torch", reason="the learn extra (torch) is not installed")
pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

from click.testing import CliRunner  # noqa: E402
from sceneforge.cli.main import _terminate, cli  # noqa: E402

from sceneforge.errors import Interrupted, SceneforgeError  # noqa: E402
from sceneforge.learn.dataset import SplitConfig, index_stores  # noqa: E402
from sceneforge.learn.predict import predict  # noqa: E402
from sceneforge.learn.split import (  # noqa: E402
    LEGACY_SPLIT_FILE,
    default_split_file,
    draw_split,
    read_split,
    split_file_name,
)
from sceneforge.learn.train import TrainConfig, read_config, read_metrics, train  # noqa: E402
from sceneforge.learn.trainer import Trainer, make_loader  # noqa: E402
from sceneforge.store import open_store  # noqa: E402

from .conftest import render_learn_store  # noqa: E402

TINY = 0.125
OPTS = dict(device="cpu", tensorboard=False, workers=0)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    """3 bundled toy houses × 2 views, 64×48 frontal, 32×32 overhead."""
    return render_learn_store(tmp_path_factory.mktemp("runs"))


def small_config(store: str, split_file: Path | None, **kw) -> TrainConfig:
    """One house of 3 held out for validation: 4 training views, 2 steps an epoch of batch 2."""
    defaults = dict(stage="depth", batch_size=2, max_steps=5, width=TINY, log_every=1, bn_momentum=0.1,
                    split=SplitConfig(0.34, 0.0, file=split_file and str(split_file)))
    return TrainConfig(stores=(store,), **{**defaults, **kw})


@pytest.fixture
def signals():
    """Ctrl-C and SIGTERM as the ``sceneforge`` command takes them (both a KeyboardInterrupt),
    whatever the test runner set; restored after."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _terminate)
    yield
    for s, handler in before.items():
        signal.signal(s, handler)


def digest(path: str | Path) -> dict[str, str]:
    """Every file and folder at or under ``path``: a file by its SHA-256."""
    path = Path(path)
    entries = [path, *path.rglob("*")] if path.is_dir() else [path]
    return {str(p.relative_to(path.parent)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(entries)}


# ---------------------------------------------------------------------------- interrupts


@pytest.fixture(scope="module")
def whole_run(store, tmp_path_factory):
    """The uninterrupted run of :func:`small_config` of a number of steps, by that number."""
    runs = {}

    def run(steps: int) -> Path:
        if steps not in runs:
            root = tmp_path_factory.mktemp("whole")
            train(small_config(store, root / "split.json", max_steps=steps), root / "run", **OPTS)
            runs[steps] = root / "run"
        return runs[steps]
    return run


def _rows(run: Path) -> list[tuple]:
    return [(r["step"], r["epoch"], r["split"], round(float(r["loss"]), 5)) for r in read_metrics(run / "metrics.csv")]


def _state(path: Path) -> dict:
    return torch.load(path, weights_only=True)


@pytest.mark.parametrize("signum, where, steps", [
    pytest.param(signal.SIGINT, "step", 5, id="ctrl-c-in-a-step"),
    pytest.param(signal.SIGTERM, "validation", 5, id="sigterm-in-validation"),
    pytest.param(signal.SIGTERM, "validation", 4, id="sigterm-in-the-last-steps-validation")])
def test_an_interrupted_run_saves_its_last_whole_step_and_resumes_to_the_uninterrupted_run(
        signum, where, steps, store, whole_run, tmp_path, monkeypatch, signals):
    """The signal comes inside the third step (held until the step is whole, then saved at
    step 3) or inside the validation after epoch 1 (which changes nothing saved: the
    checkpoint is that epoch's end at step 4, which still owes the validation, also when
    step 4 is the run's last)."""
    calls, nth = {"step": 0, "validation": 0}, {"step": 3, "validation": 2}[where]
    step, validate = Trainer.step, Trainer.validate

    def signalling(name, original):
        def method(self, *args, **kw):
            calls[name] += 1
            if name == where and calls[name] == nth:
                signal.raise_signal(signum)
            return original(self, *args, **kw)
        return method

    monkeypatch.setattr(Trainer, "step", signalling("step", step))
    monkeypatch.setattr(Trainer, "validate", signalling("validation", validate))
    config, run = small_config(store, tmp_path / "split.json", max_steps=steps), tmp_path / "run"
    stopped_at = {"step": 3, "validation": 4}[where]
    with pytest.raises(Interrupted, match=f"^run it again with --resume to continue from step {stopped_at}$"):
        train(config, run, **OPTS)
    saved = _state(run / "checkpoint.pt")
    assert (saved["step"], saved["epoch"], saved["batch"]) == {"step": (3, 1, 1), "validation": (4, 1, 2)}[where]
    assert [int(r["step"]) for r in read_metrics(run / "metrics.csv")][-1] == stopped_at

    result, whole = train(config, run, resume=True, **OPTS), whole_run(steps)
    assert (result.steps, result.epochs) == (steps, 2)
    assert _rows(run) == _rows(whole)
    for name in ("checkpoint.pt", "best.pt"):
        ours, theirs = _state(run / name), _state(whole / name)
        assert [ours[k] for k in ("step", "epoch", "batch")] == [theirs[k] for k in ("step", "epoch", "batch")]
        for key, value in theirs["models"]["depth"].items():
            assert torch.equal(ours["models"]["depth"][key], value), (name, key)


def test_an_interrupt_before_the_first_step_says_to_start_again(store, tmp_path, signals):
    class SignalAtStart:
        def start(self, total, done):
            signal.raise_signal(signal.SIGINT)

        def step(self, step, loss):
            pass

    config, run = small_config(store, tmp_path / "split.json", max_steps=1), tmp_path / "run"
    with pytest.raises(Interrupted, match=r"^no step was taken, so there is nothing to resume: run the same "
                                          r"command again \(without --resume\)$"):
        train(config, run, progress=SignalAtStart(), **OPTS)
    assert (run / "config.json").exists() and not (run / "checkpoint.pt").exists()
    with pytest.raises(SceneforgeError, match="nothing to resume"):
        train(config, run, resume=True, **OPTS)
    assert train(config, run, **OPTS).steps == 1  # a run that never took a step starts again
    # resumed, and stopped before a step of its own: the checkpoint it resumed from is still there
    with pytest.raises(Interrupted, match="^run it again with --resume to continue from step 1$"):
        train(small_config(store, tmp_path / "split.json", max_steps=2), run, resume=True,
              progress=SignalAtStart(), **OPTS)


def test_the_command_says_what_to_run_after_ctrl_c(store, tmp_path, monkeypatch, signals):
    step = Trainer.step

    def interrupted(at_step: int, by_signal: bool):
        def method(self, batch, number):
            if number == at_step and not by_signal:
                raise KeyboardInterrupt  # before the step changes anything
            if number == at_step:
                signal.raise_signal(signal.SIGINT)
            return step(self, batch, number)
        return method

    run = tmp_path / "run"
    args = ["train", store, "--stage", "depth", "--run", str(run), "--max-steps", "3", "--batch-size", "2",
            "--width", str(TINY), "--val-fraction", "0", "--test-fraction", "0", "--split-file",
            str(tmp_path / "split.json"), "--device", "cpu", "--workers", "0", "--no-tensorboard"]
    runner = CliRunner()
    monkeypatch.setattr(Trainer, "step", interrupted(0, by_signal=False))
    res = runner.invoke(cli, args)
    assert res.exit_code == 130 and "Traceback" not in res.output
    assert res.output.splitlines()[-1] == ("interrupted: no step was taken, so there is nothing to resume: run the "
                                           "same command again (without --resume)")
    monkeypatch.setattr(Trainer, "step", interrupted(1, by_signal=True))
    res = runner.invoke(cli, args)
    assert res.exit_code == 130
    assert res.output.splitlines()[-1] == "interrupted: run it again with --resume to continue from step 2"
    monkeypatch.setattr(Trainer, "step", step)
    res = runner.invoke(cli, [*args, "--resume"])
    assert res.exit_code == 0 and "3 steps" in " ".join(res.output.split()), res.output


class _Handlers(torch.utils.data.Dataset):
    """One sample: whether the process reading it ignores SIGINT and SIGTERM."""

    def __len__(self):
        return 1

    def __getitem__(self, i):
        return torch.tensor([signal.getsignal(s) == signal.SIG_IGN for s in (signal.SIGINT, signal.SIGTERM)])


def test_loader_workers_leave_ctrl_c_and_sigterm_to_the_training_process():
    """A terminal's Ctrl-C and a scheduler's SIGTERM reach the whole process group: a worker
    they killed would fail the run before it saves its checkpoint."""
    assert next(iter(make_loader(_Handlers(), torch.device("cpu"), 1, timeout=60))).all()


# ---------------------------------------------------------------------------- split file


def test_the_split_file_is_named_by_its_stores(tmp_path):
    a, b, c = (str(tmp_path / "out" / n) for n in ("a.zarr", "b.zarr", "c"))
    assert default_split_file([a]) == str(tmp_path / "out" / "a.split.json")
    assert split_file_name([c]) == "c.split.json"
    assert split_file_name(["s3://bucket/x/a.zarr/"]) == "a.split.json"
    several = split_file_name([a, b])
    assert several.startswith("a+1.") and several.endswith(".split.json") and len(several) == len("a+1.") + 8 + 11
    assert len({several, split_file_name([a, c]), split_file_name([a, b, c]), split_file_name([b, a])}) == 4
    # the name stays when the folder moves with its stores
    moved = [str(tmp_path / "elsewhere" / n) for n in ("a.zarr", "b.zarr")]
    assert split_file_name(moved) == several


def test_a_legacy_split_json_is_read_for_its_own_stores_only(store, tmp_path):
    out = tmp_path / "out"
    a, b = out / "a.zarr", out / "b.zarr"
    for copy in (a, b):
        shutil.copytree(store, copy)
    houses = sorted(set(index_stores([str(a)]).house))
    legacy = out / LEGACY_SPLIT_FILE
    # what an earlier version wrote for a: split.json in the folder, recording its stores
    legacy.write_text(json.dumps(draw_split(houses, SplitConfig(0.0, 0.34), [str(a)]).to_dict()))
    before = digest(legacy)

    # b, beside a, with another split: refused before as if split.json were b's
    run_b = train(small_config(str(b), None, split=SplitConfig(0.0, 0.0), max_steps=1), tmp_path / "b", **OPTS).run
    assert read_config(run_b).split.file == str(out / "b.split.json") and (out / "b.split.json").exists()
    assert default_split_file([str(b)]) == str(out / "b.split.json")

    run_a = train(small_config(str(a), None, split=SplitConfig(0.0, 0.34), max_steps=1), tmp_path / "a", **OPTS).run
    assert read_config(run_a).split.file == str(legacy) and not (out / "a.split.json").exists()
    assert default_split_file([str(a)]) == str(legacy)  # evaluate's default, without a recorded file
    pred = str(tmp_path / "p.zarr")
    summary = predict(run_a, str(a), pred, device="cpu", workers=0)  # the test houses of the legacy split
    assert summary.predicted == 2 and summary.houses == 1 == len(read_split(legacy).of("test"))
    assert open_store(pred).attrs["prediction"]["split_file"] == str(legacy)
    assert digest(legacy) == before
    # another list of stores with a in front is not a's: its own file, the legacy one untouched
    assert default_split_file([str(a), str(b)]) != str(legacy)


# ---------------------------------------------------------------------------- run folder


@pytest.fixture(scope="module")
def depth_run(store, tmp_path_factory) -> str:
    run = tmp_path_factory.mktemp("frozen") / "depth"
    train(small_config(store, run.parent / "split.json", max_steps=1), run, **OPTS)
    return str(run)


def _case(name: str, store: str, depth_run: str, other_store: Path, tmp_path: Path):
    """(config, run folder, what must stay as it is, the refusal) of each case."""
    config = small_config(store, tmp_path / "split.json", max_steps=1)
    frozen = dict(stage="camera", depth_run=depth_run)
    notes = tmp_path / "notes"
    if name == "the store":
        return config, Path(store), store, "is the input store"
    if name == "inside the store":
        return config, Path(store) / "run", store, "inside the store"
    if name == "holds the store":
        copy = tmp_path / "data" / "toy.zarr"
        shutil.copytree(store, copy)
        return small_config(str(copy), None, max_steps=1), copy.parent, copy, "holds the input store"
    if name == "the depth run":
        return small_config(store, tmp_path / "split.json", **frozen), Path(depth_run), depth_run, "is the depth run"
    if name == "inside the seg run":
        overhead = small_config(store, tmp_path / "split.json", stage="overhead", depth_run=str(tmp_path / "depth"),
                                seg_run=depth_run)
        return overhead, Path(depth_run) / "overhead", depth_run, "is inside the seg run"
    if name == "holds the split file":
        split = tmp_path / "splits" / "toy.split.json"
        split.parent.mkdir()
        split.write_text("{}")
        return small_config(store, split, max_steps=1), split.parent, split, "holds the split file"
    if name == "inside another store":
        return config, other_store / "run", other_store, "inside the store"
    if name == "not a run":
        notes.mkdir()
        (notes / "thesis.tex").write_text("years of work")
        return config, notes, notes, "not a training run .*choose a new or empty run folder"
    if name == "a config.json not of a run":
        notes.mkdir()
        (notes / "config.json").write_text('{"theme": "dark"}')
        return config, notes, notes, "not a training run"
    raise AssertionError(name)


@pytest.mark.parametrize("name", ["the store", "inside the store", "holds the store", "the depth run",
                                  "inside the seg run", "holds the split file", "inside another store",
                                  "not a run", "a config.json not of a run"])
def test_a_run_folder_that_would_take_over_other_data_is_refused_before_writing(name, store, depth_run,
                                                                                tiny_toy_store, tmp_path):
    config, run, kept, refusal = _case(name, store, depth_run, tiny_toy_store, tmp_path)
    before = digest(kept)
    with pytest.raises(SceneforgeError, match=refusal) as e:
        train(config, run, **OPTS)
    assert "\n" not in str(e.value)
    assert digest(kept) == before


def test_a_run_that_never_took_a_step_starts_again(store, tmp_path):
    run = tmp_path / "run"
    config = small_config(store, tmp_path / "split.json", max_steps=1)
    run.mkdir()
    (run / "config.json").write_text(json.dumps(config.to_dict()))
    assert train(config, run, **OPTS).steps == 1
    with pytest.raises(SceneforgeError, match="already holds a run: pass --resume"):
        train(config, run, **OPTS)
