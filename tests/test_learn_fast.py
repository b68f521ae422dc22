"""Fast training: DataLoader workers (the same batches in the same order, the same weights
whatever their number), mixed precision on the CPU, images/s without validation and
checkpoint time, and torchrun DistributedDataParallel with 2 gloo processes against one
process with the whole batch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the learn extra (torch) is not installed")
pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

from sceneforge.errors import SceneforgeError  # noqa: E402
from sceneforge.learn import trainer as trainer_module  # noqa: E402
from sceneforge.learn.dataset import SplitConfig, StoreDataset, index_stores  # noqa: E402
from sceneforge.learn.train import TrainConfig, load_run, read_config, read_metrics, train  # noqa: E402
from sceneforge.learn.trainer import (  # noqa: E402
    Checkpoint,
    EpochLoop,
    EpochSampler,
    MetricsLog,
    Position,
    Trainer,
    _to,
    collate,
    default_workers,
    make_loader,
    memory_format,
    resolve_amp,
)

from .conftest import render_learn_store  # noqa: E402

TINY = 0.125
CPU = torch.device("cpu")
#: seconds a DataLoader worker may take for a batch before the test fails (a deadlock)
WORKER_TIMEOUT = 60


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    """3 bundled toy houses × 2 views, 64×48 frontal, 32×32 overhead."""
    return render_learn_store(tmp_path_factory.mktemp("fast"))


def small_config(store: str, tmp_path: Path, **kw) -> TrainConfig:
    defaults = dict(stage="depth", batch_size=4, max_steps=3, width=TINY, log_every=1, bn_momentum=0.1,
                    split=SplitConfig(0.0, 0.0, file=str(tmp_path / "split.json")))
    return TrainConfig(stores=(store,), **{**defaults, **kw})


def _weights(run) -> dict:
    return load_run(run)[1]["depth"].state_dict()


# ----------------------------------------------------------------------------- workers


@pytest.mark.parametrize("start", [None, "forkserver"])
def test_two_workers_give_the_batches_of_none_in_the_same_order(store, start):
    fields = ("rgb", "depth", "seg", "overhead_height", "overhead_seg", "camera")
    ds = StoreDataset(index_stores([store, store]), fields)
    ds[0]  # this process has read the stores: zarr's IO thread runs when the workers start
    sampler = EpochSampler(len(ds), seed=3, batch_size=5)
    sampler.set_epoch(1)
    serial = list(make_loader(ds, CPU, 0, batch_sampler=sampler))
    # a worker that deadlocks fails the test after WORKER_TIMEOUT s instead of hanging it
    loader = make_loader(ds, CPU, 2, batch_sampler=sampler, timeout=WORKER_TIMEOUT, start=start)
    assert loader.persistent_workers
    for epoch in (1, 2):  # the same workers serve the next epoch, in its own order
        sampler.set_epoch(epoch)
        parallel = list(loader)
        if epoch == 2:
            serial = list(make_loader(ds, CPU, 0, batch_sampler=sampler))
        assert [b["index"].tolist() for b in parallel] == [b["index"].tolist() for b in serial]
        assert len(parallel) == 3 and sorted(sum((b["index"].tolist() for b in parallel), [])) == list(range(12))
        for a, b in zip(serial, parallel):
            assert a.keys() == b.keys()
            for key in a:
                torch.testing.assert_close(a[key], b[key], equal_nan=True, rtol=0, atol=0)


def _reference_sample(store, view: int, fields) -> dict[str, np.ndarray]:
    """A sample as it was read before batches were read at once: one zarr read per array of
    the view (``store.view``), the targets made view by view."""
    from sceneforge.evaluate.learning import seg_targets
    from sceneforge.learn.dataset import EMPTY, SAMPLE_FIELDS, normalize_rgb, segmentation_target

    raw = store.view(view)
    out = {}
    if "rgb" in fields:
        out["rgb"] = normalize_rgb(raw["rgb"])
    if "depth" in fields:
        out["depth"] = raw["depth"].astype(np.float32)
    if "seg" in fields:
        out["seg"] = seg_targets(raw["category"][None], raw["depth"][None], EMPTY)[0]
    if "overhead_height" in fields:
        height, floor = raw["overhead_height"].astype(np.float32), np.isfinite(raw["overhead_depth"][4])
        out["overhead_height"] = np.where(~np.isfinite(height) & floor, np.float32(0), height)
        out["overhead_foreground"] = np.isfinite(height)
    if "overhead_seg" in fields:
        out["overhead_seg"] = segmentation_target(raw["overhead_category"],
                                                  np.isnan(raw["overhead_depth"]).all(axis=0))
    if "camera" in fields:
        out.update({name: raw[name].astype(np.float64) for name in SAMPLE_FIELDS["camera"]})
    return out


def test_a_batch_read_at_once_is_its_views_read_one_by_one(store):
    from sceneforge.store import open_store

    fields = ("rgb", "depth", "seg", "overhead_height", "overhead_seg", "camera")
    ds = StoreDataset(index_stores([store, store]), fields)
    raw = open_store(store)
    indices = [7, 0, 11, 3, 7, 6]  # both stores, out of order, a repeat
    batch = ds.batch(indices)
    assert batch["index"].tolist() == indices
    for j, i in enumerate(indices):
        for key, want in _reference_sample(raw, int(ds.index.view[i]), fields).items():
            got = batch[key][j].numpy()
            assert got.dtype == want.dtype and got.shape == want.shape, key
            np.testing.assert_array_equal(got, want, err_msg=key)
    # what a DataLoader does: __getitems__, collated; and one sample alone; and a Subset
    collated = torch.utils.data.default_collate(ds.__getitems__(indices))
    single = ds[indices[2]]
    subset = next(iter(torch.utils.data.DataLoader(torch.utils.data.Subset(ds, indices), batch_size=6)))
    for key in batch:
        torch.testing.assert_close(collated[key], batch[key], equal_nan=True, rtol=0, atol=0)
        torch.testing.assert_close(subset[key], batch[key], equal_nan=True, rtol=0, atol=0)
        torch.testing.assert_close(single[key], batch[key][2], equal_nan=True, rtol=0, atol=0)


def test_workers_fork_only_where_zarr_survives_it(monkeypatch):
    import sceneforge.store
    from sceneforge.learn.trainer import worker_context

    assert sceneforge.store.reads_survive_fork()  # the zarr installed here resets after a fork
    assert worker_context().get_start_method() == "fork"
    monkeypatch.setattr(sceneforge.store, "reads_survive_fork", lambda: False)
    assert worker_context().get_start_method() == "forkserver"


def test_training_gives_the_same_weights_whatever_the_worker_count(store, tmp_path):
    opts = dict(device="cpu", tensorboard=False)
    serial = train(small_config(store, tmp_path), tmp_path / "w0", workers=0, **opts)
    parallel = train(small_config(store, tmp_path), tmp_path / "w2", workers=2, **opts)
    assert serial.steps == parallel.steps == 3
    for (name, a), b in zip(_weights(tmp_path / "w0").items(), _weights(tmp_path / "w2").values()):
        assert torch.equal(a, b), name


def test_default_workers_are_the_usable_cores_at_most_4(monkeypatch):
    for cores, processes, expected in ((16, 1, 4), (2, 1, 2), (1, 1, 1), (16, 8, 2), (4, 8, 1)):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, n=cores: set(range(n)))
        assert default_workers(processes) == expected, (cores, processes)


def test_the_epoch_sampler_shares_every_batch_among_processes():
    one = EpochSampler(11, seed=5, batch_size=4)
    shares = [EpochSampler(11, seed=5, batch_size=4, rank=r, world_size=2) for r in (0, 1)]
    for epoch, start in ((0, 0), (3, 1)):
        for s in (one, *shares):
            s.set_epoch(epoch, start)
        whole = list(one)
        assert len(whole) == len(shares[0]) == len(shares[1]) == 3 - start
        for batch, a, b in zip(whole, *shares):
            assert a + b == batch  # rank 0 the first half, rank 1 the second
    assert [len(b) for b in whole] == [4, 3] and [len(b) for b in shares[1]] == [2, 1]
    # a short last batch of 1 view among 2 processes: the one left without repeats it
    one, lone = EpochSampler(5, 0, 4), EpochSampler(5, 0, 4, rank=1, world_size=2)
    assert list(lone)[-1] == list(one)[-1]
    with pytest.raises(SceneforgeError, match="--batch-size 5 is not shared evenly by 2 processes"):
        EpochSampler(10, 0, 5, world_size=2)


# ---------------------------------------------------------------------- mixed precision


class _Views(torch.utils.data.Dataset):
    """n random 16×16 views with depth targets."""

    def __init__(self, n: int, size: int = 16):
        g = torch.Generator().manual_seed(n)
        self.rgb = torch.randn(n, 3, size, size, generator=g)
        self.depth = torch.rand(n, 5, size, size, generator=g) + 1

    def __len__(self):
        return len(self.rgb)

    def __getitem__(self, i):
        return {"index": i, "rgb": self.rgb[i], "depth": self.depth[i]}


def _trainer(**kw) -> Trainer:
    return Trainer(TrainConfig(stage="depth", stores=("unread",), **{"batch_size": 2, "width": TINY, **kw}),
                   {}, None, CPU)


def test_bf16_autocast_on_the_cpu_runs_the_nets_in_bf16_with_losses_close_to_float32():
    assert resolve_amp("auto", CPU) == "off" and resolve_amp("bf16", CPU) == "bf16"
    batch = next(iter(torch.utils.data.DataLoader(_Views(4), batch_size=4)))
    full, half = _trainer(amp="off"), _trainer(amp="bf16")
    dtypes = []
    conv = next(m for m in half.nets["depth"].modules() if isinstance(m, torch.nn.Conv2d))
    conv.register_forward_hook(lambda m, i, o: dtypes.append(o.dtype))
    losses = {"off": [], "bf16": []}
    for _ in range(3):
        losses["off"].append(float(full.step(batch, 0)["loss"]))
        losses["bf16"].append(float(half.step(batch, 0)["loss"]))
    assert set(dtypes) == {torch.bfloat16}  # autocast was on
    assert all(p.dtype == torch.float32 for p in half.nets["depth"].parameters())  # the weights stay float32
    for a, b in zip(losses["off"], losses["bf16"]):
        assert b == pytest.approx(a, rel=0.03), losses
    assert losses["bf16"] != losses["off"]


def test_bf16_on_the_cpu_trains_the_recipes_depth_net_with_finite_gradients():
    """PyTorch 2.13's bfloat16 backward of a dilated convolution on the CPU gives NaN
    gradients (or crashes) in channels-last: the recipe's depth net (width 0.5, 80×60)
    diverged at its first step. Autocast on the CPU keeps nets and images contiguous."""
    assert memory_format(CPU, "bf16") == torch.contiguous_format
    assert memory_format(CPU, "off") == torch.channels_last
    assert memory_format(torch.device("cuda"), "bf16") == torch.channels_last
    trainer = Trainer(TrainConfig(stage="depth", stores=("unread",), batch_size=8, width=0.5, amp="bf16",
                                  bn_momentum=0.1), {}, None, CPU)
    views = _Views(8, size=64)
    batch = collate([views[i] for i in range(8)])  # as a loader's worker hands it: channels-last
    for step in range(2):
        loss = trainer.step(_to(batch, CPU, trainer.layout), step)["loss"]
        assert torch.isfinite(loss), step
        bad = [n for n, p in trainer.nets["depth"].named_parameters() if not torch.isfinite(p).all()]
        assert not bad, (step, bad[:3])


def test_bf16_on_a_cpu_that_emulates_it_warns(monkeypatch):
    assert trainer_module.cpu_has_bf16("flags\t\t: fpu avx2 avx512f avx512_bf16 sha_ni\n")
    assert trainer_module.cpu_has_bf16("flags : fpu amx_bf16 amx_tile\n")
    assert not trainer_module.cpu_has_bf16("flags\t\t: fpu avx2 avx512f avx512bw\nbugs : avx512_bf16\n")
    monkeypatch.setattr(trainer_module, "cpu_has_bf16", lambda: False)
    with pytest.warns(UserWarning, match="emulates bfloat16"):
        _trainer(amp="bf16")
    monkeypatch.setattr(trainer_module, "cpu_has_bf16", lambda: True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _trainer(amp="bf16")
        _trainer(amp="off")


def test_fp16_scales_the_loss_and_saves_the_scaler(tmp_path):
    trainer = _trainer(amp="fp16")
    assert trainer.scaler.is_enabled()
    batch = next(iter(torch.utils.data.DataLoader(_Views(2), batch_size=2)))
    trainer.step(batch, 0)
    trainer.scaler.update(1024.0)  # a scale of its own, which the checkpoint must carry
    checkpoint = Checkpoint(tmp_path / "checkpoint.pt")
    checkpoint.save(trainer, Position(1, 0, 1))
    assert checkpoint.load()["scaler"]["scale"] == 1024.0
    fresh = _trainer(amp="fp16")
    assert fresh.scaler.get_scale() != 1024.0
    checkpoint.restore(fresh)
    assert fresh.scaler.get_scale() == 1024.0
    unscaled = Checkpoint(tmp_path / "off.pt")
    unscaled.save(_trainer(), Position())
    assert "scaler" not in unscaled.load()


def test_the_resolved_amp_is_saved_and_resumed(store, tmp_path):
    opts = dict(device="cpu", tensorboard=False, workers=0)
    train(small_config(store, tmp_path, max_steps=1), tmp_path / "auto", **opts)
    assert read_config(tmp_path / "auto").amp == "off"  # auto on the CPU
    train(small_config(store, tmp_path, amp="bf16", max_steps=1), tmp_path / "bf16", **opts)
    assert json.loads((tmp_path / "bf16" / "config.json").read_text())["amp"] == "bf16"
    with pytest.raises(SceneforgeError, match=r"different config \(amp\)"):
        train(small_config(store, tmp_path, amp="off", max_steps=2), tmp_path / "bf16", resume=True, **opts)
    result = train(small_config(store, tmp_path, amp="bf16", max_steps=2), tmp_path / "bf16", resume=True, **opts)
    assert result.steps == 2 and read_config(tmp_path / "bf16").amp == "bf16"


# ---------------------------------------------------------------------------- images/s


class _Clock:
    def __init__(self):
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def test_images_per_s_leave_out_validation_and_checkpoints(tmp_path, monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(trainer_module, "time", clock)
    trainer = _trainer(batch_size=2, epochs=2, log_every=4, checkpoint_every=1)

    def step(batch, number):  # every step takes 0.1 s
        clock.now += 0.1
        return {"loss": 1.0}

    def validate(dataset, workers=0, loader=None):  # validation 10 s
        clock.now += 10.0
        return {"loss": 1.0}

    save = Checkpoint.save

    def slow_save(self, trainer, at):  # every checkpoint 5 s
        clock.now += 5.0
        save(self, trainer, at)

    monkeypatch.setattr(trainer, "step", step)
    monkeypatch.setattr(trainer, "validate", validate)
    monkeypatch.setattr(Checkpoint, "save", slow_save)
    log = MetricsLog(tmp_path, (), None, tensorboard=False)
    # 4 views in batches of 2: 2 steps an epoch; the one train row spans both epochs,
    # the validation after the first and 4 + 1 checkpoints
    loop = EpochLoop(trainer, _Views(4), _Views(2), 4, log, Checkpoint(tmp_path / "c.pt"))
    loop.run(Position())
    rows = [r for r in read_metrics(tmp_path / "metrics.csv") if r["split"] == "train"]
    assert len(rows) == 1 and int(rows[0]["step"]) == 4
    assert float(rows[0]["images_per_s"]) == pytest.approx(8 / 0.4)  # 8 images in 4 steps of 0.1 s
    assert loop.images_per_s == pytest.approx(20.0)


# --------------------------------------------------------------------------------- DDP


#: run by torchrun in every process: 2 optimiser steps in float64 on this rank's half of 4
#: synthetic views, rank 0 saving the weights; then the command line (the arguments after
#: the output folder) in the same process group
DDP_SCRIPT = """
import sys
import torch
from sceneforge.cli.main import cli
from sceneforge.learn.distributed import Distributed
from tests.test_learn_fast import ddp64_steps

torch.set_num_threads(1)
dist = Distributed.from_env()
dist.start(torch.device("cpu"))
state = ddp64_steps(dist)
if dist.is_main:
    torch.save(state, sys.argv[1])
cli.main(args=sys.argv[2:], standalone_mode=False)
dist.stop()
"""


def ddp64_steps(dist=None) -> dict:
    """The depth net's weights after 2 float64 steps on 4 synthetic 24×32 views, this process
    taking its share of each batch (all 4 without ``dist``)."""
    torch.set_default_dtype(torch.float64)
    try:
        trainer = Trainer(TrainConfig(stage="depth", stores=("unread",), batch_size=4, width=TINY, bn_momentum=0.1),
                          {}, None, CPU, dist)
        rank, world = (dist.rank, dist.world_size) if dist else (0, 1)
        views = _Views(4, size=24)
        share = slice(rank * 4 // world, (rank + 1) * 4 // world)
        for step in range(2):
            trainer.step({"rgb": views.rgb[share].double(), "depth": views.depth[share].double()}, step)
        return {k: v.clone() for k, v in trainer.nets["depth"].state_dict().items()}
    finally:
        torch.set_default_dtype(torch.float32)


def test_two_gloo_processes_match_one_process_with_the_whole_batch(store, tmp_path):
    """torchrun with 2 CPU processes of 2 views each against 1 process of 4 views.

    - In float64 the weights after 2 steps agree to 1e-9: the averaged gradients and
      BatchNorm over the whole batch are one process's (float32 cannot show this: the
      1-process CPU BatchNorm's float32 statistics alone move the gradients by ~1 %).
    - ``sceneforge train --resume`` of a 1-process run's first step, on 2 processes, logs
      the losses of the 1-process run's steps 2 and 3 (the same views in each step) to
      1e-4; without synchronised BatchNorm they differ by ~1 %. Rank 0 alone writes.
    """
    opts = dict(device="cpu", tensorboard=False, workers=0)
    train(small_config(store, tmp_path), tmp_path / "one", **opts)
    train(small_config(store, tmp_path, max_steps=1), tmp_path / "two", **opts)
    root = Path(__file__).resolve().parents[1]
    script = tmp_path / "ddp_check.py"
    script.write_text(DDP_SCRIPT)
    run = tmp_path / "two"
    # the last of steps 2 and 3 is an epoch's short batch: 1 view in each process
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", str(script),
           str(tmp_path / "ddp64.pt"), "train", "--config", str(run / "config.json"), "--run-dir", str(run),
           "--resume", "--max-steps", "3", "--device", "cpu", "--workers", "0", "--no-tensorboard"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)}
    done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr

    two = torch.load(tmp_path / "ddp64.pt", weights_only=True)
    for name, a in ddp64_steps().items():
        torch.testing.assert_close(two[name], a, rtol=0, atol=1e-9, msg=name)

    assert " ".join((done.stdout + done.stderr).split()).count(": 3 steps") == 1  # rank 0 alone reports
    rows, reference = read_metrics(run / "metrics.csv"), read_metrics(tmp_path / "one" / "metrics.csv")
    assert [int(r["step"]) for r in rows] == [1, 2, 3]  # rank 0 alone writes
    for a, b in zip(rows[1:], reference[1:]):
        assert float(a["loss"]) == pytest.approx(float(b["loss"]), rel=1e-4)
    assert torch.load(run / "checkpoint.pt", weights_only=True)["step"] == 3
