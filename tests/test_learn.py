"""Models and training: losses with analytic values, networks' shapes, the dataset over a tiny
store, the stage registry, the trainer's pieces, a 2-step CPU smoke test of every stage,
resume, overfitting, predictions and the CLI."""

from __future__ import annotations

import json
import math
import pickle
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the learn extra (torch) is not installed")
pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

from sceneforge.conventions import NYU40_IDS  # noqa: E402
from sceneforge.errors import SceneforgeError  # noqa: E402
from sceneforge.learn.config import FROZEN, PredictConfig  # noqa: E402
from sceneforge.learn.dataset import (  # noqa: E402
    BACKGROUND,
    CLASS_TO_NYU40,
    EMPTY,
    RGB_MEAN,
    SplitConfig,
    StoreDataset,
    index_stores,
    normalize_rgb,
    segmentation_target,
    split_houses,
)
from sceneforge.learn.losses import LossConfig, depth_loss, height_loss, segmentation_loss  # noqa: E402
from sceneforge.learn.networks import (  # noqa: E402
    DEPTH_NET,
    SEG_NET,
    CameraProposalNet,
    FrontalDepthNet,
    FrontalSegNet,
    OverheadNet,
    masked_layers,
)
from sceneforge.learn.predict import predict, proposed_overhead_cameras  # noqa: E402
from sceneforge.learn.stages import REGISTRY, get_stage, overhead_input  # noqa: E402
from sceneforge.learn.train import STAGES, TrainConfig, load_run, read_config, read_metrics, train  # noqa: E402
from sceneforge.learn.trainer import (  # noqa: E402
    Checkpoint,
    EpochLoop,
    EpochSampler,
    MetricsLog,
    Position,
    Trainer,
    check_finite,
)

from .conftest import render_learn_store  # noqa: E402

TINY = 0.125  # network width multiplier of every test


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> str:
    """3 bundled toy houses × 2 views, 64×48 frontal, 32×32 overhead."""
    return render_learn_store(tmp_path_factory.mktemp("learn"))


@pytest.fixture(scope="module")
def frontal_runs(store, tmp_path_factory) -> dict[str, str]:
    """Depth and segmentation runs of 2 steps each, for the stages that freeze them."""
    root = tmp_path_factory.mktemp("runs")
    runs = {}
    for stage in ("depth", "seg"):
        runs[stage] = str(root / stage)
        train(small_config(stage, store), runs[stage], device="cpu", tensorboard=False)
    return runs


def small_config(stage: str, store: str, **kw) -> TrainConfig:
    defaults = dict(batch_size=3, max_steps=2, width=TINY, log_every=1, split=SplitConfig(0.0, 0.0))
    return TrainConfig(stage=stage, stores=(store,), **{**defaults, **kw})


# --------------------------------------------------------------------------- losses


def test_depth_loss_is_equation_1():
    target = torch.full((2, 5, 4, 4), 2.0)
    target[0, :, :, 1:] = torch.nan  # example 0: 4 valid pixels per layer, example 1: 16
    target[1, 2:4] = torch.nan  # example 1 has no D3, D4
    pred = torch.where(torch.isnan(target), torch.tensor(100.0), target + 0.5)
    pred[:, 4] = target[:, 4] + 3.0  # envelope off by 3 m: linear part of the Huber loss
    small, big = 0.5 * 0.5 ** 2, 3.0 - 0.5  # Huber(0.5), Huber(3) with δ = 1
    expected0 = 4 * small + 0.5 * big
    expected1 = 2 * small + 0.5 * big
    loss = depth_loss(pred, target)
    assert loss.item() == pytest.approx((expected0 + expected1) / 2)
    heavier = depth_loss(pred, target, LossConfig(envelope_weight=1.0))
    assert heavier.item() == pytest.approx((expected0 + expected1) / 2 + 0.5 * big)


def test_segmentation_targets_merge_the_envelope_into_background():
    names = ("void", "wall", "floor", "ceiling", "door", "window", "curtain", "picture", "floor_mat")
    assert all(segmentation_target(np.uint8(NYU40_IDS[n])) == BACKGROUND for n in names)
    chair, lamp = NYU40_IDS["chair"], NYU40_IDS["lamp"]
    classes = segmentation_target(np.array([[chair, lamp]], np.uint8))
    assert classes.dtype == np.int64 and classes.tolist() == [[chair - 1, lamp - 1]]
    assert CLASS_TO_NYU40[classes].tolist() == [[chair, lamp]] and CLASS_TO_NYU40[BACKGROUND] == 0


def test_segmentation_and_height_losses():
    target = torch.tensor([[[[3, 0], [7, 39]], [[0, 0], [5, 5]]]])  # (1, 2, 2, 2)
    uniform = torch.zeros(1, 80, 2, 2)
    assert segmentation_loss(uniform, target).item() == pytest.approx(math.log(40))  # the layers' mean
    sure = torch.full((1, 2, 40, 2, 2), -30.0)
    sure.scatter_(2, target.unsqueeze(2), 30.0)
    assert segmentation_loss(sure.reshape(1, 80, 2, 2), target).item() < 1e-6
    # empty pixels (the ray hits nothing) are ignored: wrong scores there change nothing,
    # unless they are counted as background
    empty = target.clone()
    empty[0, 0, 0, 0] = EMPTY
    wrong = sure.clone()
    wrong[0, 0, :, 0, 0] = 0.0
    wrong[0, 0, 5, 0, 0] = 30.0
    assert segmentation_loss(wrong.reshape(1, 80, 2, 2), empty).item() < 1e-6
    as_background = segmentation_loss(wrong.reshape(1, 80, 2, 2), empty, LossConfig(seg_empty="background"))
    assert as_background.item() == pytest.approx(30 / 4 / 2, rel=1e-4)  # 30 on one pixel of 4, one layer of 2

    height = torch.tensor([[[1.0, torch.nan], [0.5, torch.nan]]])
    pred = torch.tensor([[[[1.5, 99.0], [0.0, -99.0]]]])
    assert height_loss(pred, height).item() == pytest.approx(0.5)
    assert height_loss(pred, height, torch.tensor([[[True, True], [False, False]]])).item() == pytest.approx(0.5)


def test_class_balance_weighs_each_class_of_a_layer_alike():
    from sceneforge.learn.losses import class_balance_weights

    # layer 1: background ×3 and class 7 ×1; layer 2: class 5 ×2, background ×1 and one empty pixel
    target = torch.tensor([[[[0, 0], [0, 7]], [[5, 5], [0, EMPTY]]]])
    w = class_balance_weights(target, 1.0)
    torch.testing.assert_close(w, torch.tensor([[[[1 / 3, 1 / 3], [1 / 3, 1.0]], [[0.5, 0.5], [1.0, 0.0]]]]))
    torch.testing.assert_close(class_balance_weights(target, 0.5)[0, 0, 0, 0], torch.tensor(3 ** -0.5))
    # per-pixel losses 1 (background), 3 (class 7) in layer 1: plain mean (1·3 + 3) / 4, balanced
    # (1 + 3) / 2; layer 2 all 2; the loss is the mean of the layers
    logits = torch.zeros(1, 2, 40, 2, 2)
    logits[0, :, 0] = 1.0  # both layers favour background
    plain = segmentation_loss(logits.reshape(1, 80, 2, 2), target).item()
    balanced = segmentation_loss(logits.reshape(1, 80, 2, 2), target, LossConfig(seg_balance=1.0)).item()
    p_bg = math.log(math.e + 39) - 1  # cross-entropy of the favoured class
    p_other = math.log(math.e + 39)
    assert plain == pytest.approx(((3 * p_bg + p_other) / 4 + (2 * p_other + p_bg) / 3) / 2, rel=1e-5)
    assert balanced == pytest.approx(((p_bg + p_other) / 2 + (p_other + p_bg) / 2) / 2, rel=1e-5)
    with pytest.raises(ValueError, match="seg_balance must be in"):
        LossConfig(seg_balance=2.0)
    for bad in ({"huber_delta": 0.0}, {"envelope_weight": -1.0}, {"overhead_seg_weight": float("nan")}):
        with pytest.raises(ValueError, match="must be"):
            LossConfig(**bad)


def test_changing_the_floors_height_target_leaves_the_height_loss_unchanged(store):
    from sceneforge.learn.stages import overhead_height_loss

    batch = next(iter(torch.utils.data.DataLoader(StoreDataset(index_stores([store]), ("overhead_height",)),
                                                  batch_size=3)))
    floor = ~batch["overhead_foreground"] & torch.isfinite(batch["overhead_height"])
    assert floor.any() and batch["overhead_foreground"].any()
    np.testing.assert_array_equal(batch["overhead_height"][floor].numpy(), 0.0)
    raised = {**batch, "overhead_height": torch.where(floor, torch.tensor(2.5), batch["overhead_height"])}
    pred = torch.rand(3, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    paper = small_config("overhead", store)
    assert not paper.floor_as_zero
    assert overhead_height_loss(paper, pred, raised).item() == overhead_height_loss(paper, pred, batch).item()
    alternative = small_config("overhead", store, floor_as_zero=True)
    assert overhead_height_loss(alternative, pred, raised).item() > overhead_height_loss(alternative, pred, batch).item()


def test_the_floor_leaves_predicted_heights_by_the_overhead_segmentation():
    from sceneforge.learn.predict import overhead_heights

    height = torch.tensor([[[0.02, 0.3, 0.8]]])
    logits = torch.zeros(1, 40, 1, 3)
    logits[0, BACKGROUND, 0, 1] = 1.0  # background at the 30 cm pixel
    logits[0, 7, 0, [0, 2]] = 1.0
    paper = overhead_heights(height, logits)
    assert torch.isnan(paper[0, 0, :2]).all() and paper[0, 0, 2] == pytest.approx(0.8)
    by_height = overhead_heights(height, logits, floor="height")
    assert torch.isnan(by_height[0, 0, 0]) and by_height[0, 0, 1:].tolist() == pytest.approx([0.3, 0.8])


def test_validation_metrics_against_hand_computed_values():
    from sceneforge.learn.metrics import Metrics, depth_errors, height_error, segmentation_iou

    m = Metrics()
    target = torch.full((1, 5, 1, 2), torch.nan)
    target[0, 0] = torch.tensor([[2.0, 4.0]])
    pred = torch.zeros(1, 5, 1, 2)
    pred[0, 0] = torch.tensor([[3.0, 4.0]])
    depth_errors(pred, target, m)
    depth_errors(pred, target, m)  # a second batch: pooled, not averaged per batch
    r = m.result()
    assert r["d1_absrel"] == pytest.approx(0.25) and r["d1_rmse"] == pytest.approx(math.sqrt(0.5))
    assert math.isnan(r["d2_absrel"])  # no finite target
    m = Metrics()
    logits = torch.zeros(1, 40, 1, 4)
    logits[0, [1, 1, 2, 2], 0, [0, 1, 2, 3]] = 1  # predicted classes 1 1 2 2
    segmentation_iou(logits, torch.tensor([[[1, 2, 2, EMPTY]]]), m, "miou")
    assert m.result()["miou"] == pytest.approx((1 / 2 + 1 / 2) / 2)  # class 1: 1/2, class 2: 1/2
    m = Metrics()
    height_error(torch.tensor([[[[0.5, 0.0, 9.0]]]]), torch.tensor([[[0.3, 0.04, torch.nan]]]), m)
    assert m.result()["height_l1_above_5cm"] == pytest.approx(0.2)


def test_masked_layers_empty_the_background():
    depth = torch.arange(5.0).view(1, 5, 1, 1).expand(1, 5, 1, 3).clone()
    logits = torch.zeros(1, 2, 40, 1, 3)
    logits[0, 0, 4, 0, :2] = 1  # layer 1: an object at pixels 0 and 1
    logits[0, 1, 6, 0, 1:] = 1  # layer 3: an object at pixels 1 and 2 (2 has no layer 1)
    out = masked_layers(depth, logits.reshape(1, 80, 1, 3))[0, :, 0]
    finite = torch.isfinite(out)
    assert finite.tolist() == [[True, True, False], [True, True, False], [False, True, False],
                               [False, True, False], [True, True, True]]


def test_a_least_object_probability_only_removes_pixels_the_arg_max_keeps():
    from sceneforge.learn.networks import object_pixels
    from sceneforge.learn.predict import overhead_heights

    # three pixels: background sure (p_bg 0.8), an object sure (p_bg 0.05), an object by
    # the arg-max but spread over two classes against background (p_bg 0.3, objects 0.35 each)
    p = torch.zeros(1, 40, 1, 3)
    p[0, BACKGROUND, 0] = torch.tensor([0.8, 0.05, 0.3])
    p[0, 4, 0] = torch.tensor([0.2, 0.95, 0.35])
    p[0, 5, 0, 2] = 0.35
    logits = p.clamp_min(1e-9).log()
    assert object_pixels(logits)[0, 0].tolist() == [False, True, True]
    assert object_pixels(logits, 0.65)[0, 0].tolist() == [False, True, True]  # 1 - 0.3 = 0.7
    assert object_pixels(logits, 0.9)[0, 0].tolist() == [False, True, False]
    assert object_pixels(logits, 0.0)[0, 0].tolist() == [False, True, True]  # never adds a pixel
    height = torch.tensor([[[0.5, 0.5, 0.5]]])
    assert torch.isfinite(overhead_heights(height, logits, min_probability=0.9))[0, 0].tolist() == [False, True, False]
    # frontal: layer 1 and layer 3 both get the threshold; D3/D4 need layer 1's object too
    depth = torch.ones(1, 5, 1, 3)
    both = torch.stack([logits, logits], dim=1).reshape(1, 80, 1, 3)
    kept = torch.isfinite(masked_layers(depth, both, 0.9))[0, :, 0]
    assert kept.tolist() == [[False, True, False]] * 4 + [[True, True, True]]
    with pytest.raises(ValueError, match="between 0 and 1"):
        PredictConfig(min_object_probability=1.5)


# -------------------------------------------------------------------------- networks


@pytest.mark.parametrize("hw", [(48, 64), (30, 41)])
def test_frontal_nets_keep_the_image_size(hw):
    x = torch.randn(2, 3, *hw)
    depth = FrontalDepthNet(DEPTH_NET.scaled(TINY))(x)
    assert depth.prediction.shape == (2, 5, *hw)
    assert depth.features.shape == (2, round(48 * TINY), *hw)
    seg = FrontalSegNet(SEG_NET.scaled(TINY))(x)
    assert seg.prediction.shape == (2, 80, *hw) and seg.features.shape == (2, round(64 * TINY), *hw)
    cam = CameraProposalNet(depth.features.shape[1], depth.encoding.shape[1])
    assert cam(depth.features, depth.encoding).shape == (2, 3)


def test_overhead_net_takes_232_channels_at_full_width():
    net = OverheadNet(232, 40)
    assert net.trunk.encoders[0][0].in_channels == 232
    assert net(torch.randn(1, 232, 20, 20)).shape == (1, 40, 20, 20)


# --------------------------------------------------------------------------- dataset


def test_normalisation_and_house_split():
    mean = np.broadcast_to(np.array(RGB_MEAN, np.float32), (2, 2, 3))
    np.testing.assert_allclose(normalize_rgb(mean), 0, atol=1e-6)
    assert normalize_rgb(np.zeros((2, 3, 3), np.uint8)).shape == (3, 2, 3)

    ids = [f"h{i}" for i in range(20)] * 3
    split = split_houses(ids, SplitConfig(0.1, 0.2, seed=1))
    assert [len(split[s]) for s in ("train", "val", "test")] == [14, 2, 4]
    assert sorted(sum(split.values(), [])) == sorted(set(ids))
    assert split == split_houses(list(reversed(ids)), SplitConfig(0.1, 0.2, seed=1))
    assert split != split_houses(ids, SplitConfig(0.1, 0.2, seed=2))


def test_dataset_reads_lazily_and_works_with_workers(store):
    index = index_stores([store, store])
    assert len(index) == 12 and index.shapes == {"H": 48, "W": 64, "Ho": 32, "Wo": 32}
    split = split_houses(index.house, SplitConfig(0.34, 0.0))
    train_index, val_index = index.subset(split["train"]), index.subset(split["val"])
    assert not set(train_index.house) & set(val_index.house) and len(train_index) + len(val_index) == 12

    fields = ("rgb", "depth", "seg", "overhead_height", "overhead_seg", "camera")
    ds = StoreDataset(index, fields)
    s = ds[0]
    assert s["rgb"].shape == (3, 48, 64) and s["rgb"].dtype == torch.float32
    assert s["depth"].shape == (5, 48, 64) and s["seg"].shape == (2, 48, 64) and s["seg"].dtype == torch.int64
    assert s["overhead_height"].shape == (32, 32) and s["overhead_seg"].shape == (32, 32)
    assert s["K"].shape == (3, 3) and s["overhead_params"].shape == (5,)
    assert int(s["seg"].max()) < 40 and (s["seg"] != BACKGROUND).any()

    from sceneforge.store import open_store

    raw = open_store(store).view(int(index.view[0]))
    floor_only = np.isnan(raw["overhead_height"]) & np.isfinite(raw["overhead_depth"][4])
    assert floor_only.any()
    np.testing.assert_array_equal(s["overhead_height"].numpy()[floor_only], 0.0)
    nothing = np.isnan(raw["overhead_height"]) & ~floor_only
    assert np.isnan(s["overhead_height"].numpy()[nothing]).all()
    np.testing.assert_array_equal(s["overhead_foreground"].numpy(), np.isfinite(raw["overhead_height"]))
    void = np.isnan(raw["overhead_depth"]).all(axis=0)
    np.testing.assert_array_equal(s["overhead_seg"].numpy() == EMPTY, void)
    np.testing.assert_array_equal(s["seg"].numpy() == EMPTY, np.isnan(raw["depth"][[0, 2]]) & np.isnan(raw["depth"][4]))

    pickle.loads(pickle.dumps(ds))  # no zarr handle travels to workers
    serial = list(torch.utils.data.DataLoader(ds, batch_size=4))
    parallel = list(torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2))
    for a, b in zip(serial, parallel):
        for key in a:
            torch.testing.assert_close(a[key], b[key], equal_nan=True)


# -------------------------------------------------------------------------- training


def test_the_registry_holds_every_stage_in_training_order():
    from sceneforge.learn.dataset import SAMPLE_FIELDS

    assert tuple(REGISTRY) == STAGES
    for position, (name, stage) in enumerate(REGISTRY.items()):
        assert stage.name == name and get_stage(name) is stage
        assert set(stage.fields) <= set(SAMPLE_FIELDS)
        assert set(stage.frozen) <= set(STAGES[:position])  # a stage freezes runs trained before it
    assert {n: s.frozen for n, s in REGISTRY.items()} == {"depth": (), "seg": (), "overhead": ("depth", "seg"),
                                                         "camera": ("depth",)}
    assert {n: s.frozen for n, s in REGISTRY.items() if s.frozen} == FROZEN  # what the torch-free CLI reads
    assert {n: s.predicts for n, s in REGISTRY.items()} == {"depth": ("depth",), "seg": ("seg",),
                                                           "overhead": ("depth", "seg", "overhead"),
                                                           "camera": ("camera",)}
    assert [n for n, s in REGISTRY.items() if s.uses_eft] == ["overhead"]
    assert [(n, s.predicts_with) for n, s in REGISTRY.items() if s.predicts_with] == [("camera", "overhead")]
    assert REGISTRY["overhead"].loss_parts == ("height_l1", "seg_ce")
    with pytest.raises(SceneforgeError, match="unknown training stage 'voxels'.*depth, seg, overhead, camera"):
        get_stage("voxels")


class _Views(torch.utils.data.Dataset):
    """n random 16×16 views with depth targets: what the depth stage reads, without a store."""

    def __init__(self, n: int):
        g = torch.Generator().manual_seed(n)
        self.rgb, self.depth = torch.randn(n, 3, 16, 16, generator=g), torch.rand(n, 5, 16, 16, generator=g) + 1

    def __len__(self):
        return len(self.rgb)

    def __getitem__(self, i):
        return {"index": i, "rgb": self.rgb[i], "depth": self.depth[i]}


def _depth_trainer(**kw) -> Trainer:
    config = TrainConfig(stage="depth", stores=("unread",), **{"batch_size": 2, "width": TINY, **kw})
    return Trainer(config, {}, None, torch.device("cpu"))


def test_checkpoint_restores_the_trainer_and_survives_a_failed_save(tmp_path, monkeypatch):
    trainer = _depth_trainer()
    trainer.step(next(iter(torch.utils.data.DataLoader(_Views(2), batch_size=2))), 0)
    checkpoint = Checkpoint(tmp_path / "checkpoint.pt")
    checkpoint.save(trainer, Position(1, 0, 1))
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]

    def broken_save(state, path):
        path.write_bytes(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(trainer, Position(2, 0, 2))
    monkeypatch.undo()
    fresh = _depth_trainer(seed=1)
    assert checkpoint.restore(fresh) == Position(1, 0, 1)  # the whole previous checkpoint
    for (name, a), b in zip(trainer.nets["depth"].state_dict().items(), fresh.nets["depth"].state_dict().values()):
        assert torch.equal(a, b), name
    assert fresh.optimizer.state_dict()["state"].keys() == trainer.optimizer.state_dict()["state"].keys()


def test_a_diverged_loss_is_an_expected_error():
    batch = next(iter(torch.utils.data.DataLoader(_Views(2), batch_size=2)))
    batch["rgb"][0, 0, 0, 0] = torch.nan
    losses = _depth_trainer().step(batch, 7)  # the step waits for nothing: the loss stays on the device
    assert torch.is_tensor(losses["loss"]) and not losses["loss"].requires_grad
    with pytest.raises(SceneforgeError, match="step 7: the loss is nan"):
        check_finite([(6, torch.tensor(1.0)), (7, losses["loss"])])


def test_the_loop_stops_at_a_diverged_step_before_a_checkpoint_holds_its_weights(tmp_path):
    views = _Views(8)
    views.rgb[5, 0, 0, 0] = torch.nan
    trainer = _depth_trainer(batch_size=2, epochs=1, log_every=100, checkpoint_every=1)
    sampler = EpochSampler(8, trainer.config.seed, 2)
    diverged = next(k for k, batch in enumerate(sampler) if 5 in batch)
    checkpoint = Checkpoint(tmp_path / "checkpoint.pt")
    with pytest.raises(SceneforgeError, match=f"step {diverged}: the loss is nan \\(diverged\\)"):
        EpochLoop(trainer, views, None, 4, None, checkpoint).run(Position())
    # a checkpoint after every step before it and none after
    assert checkpoint.exists() == (diverged > 0)
    if diverged:
        state = checkpoint.load()
        assert state["step"] == diverged
        assert all(torch.isfinite(v).all() for v in state["models"]["depth"].values() if v.is_floating_point())


def test_the_epoch_loop_logs_validates_and_checkpoints_on_schedule(tmp_path):
    # 8 views in batches of 3: 3 steps an epoch, the last one of 2 views
    trainer = _depth_trainer(batch_size=3, epochs=2, log_every=2, checkpoint_every=100)
    log = MetricsLog(tmp_path, (), None, tensorboard=False, metrics=get_stage("depth").val_metrics)
    checkpoint, best = Checkpoint(tmp_path / "checkpoint.pt"), Checkpoint(tmp_path / "best.pt")
    loop = EpochLoop(trainer, _Views(8), _Views(3), 6, log, checkpoint, best=best)
    end = loop.run(Position())
    assert end == Position(6, 2, 0) and checkpoint.load()["step"] == 6
    rows = read_metrics(tmp_path / "metrics.csv")
    assert [(int(r["step"]), int(r["epoch"]), r["split"]) for r in rows] == [
        (2, 0, "train"), (3, 0, "val"), (4, 1, "train"), (6, 1, "train"), (6, 1, "val")]
    assert loop.train_loss == float(rows[3]["loss"]) and loop.val_loss == float(rows[4]["loss"])
    val = [r for r in rows if r["split"] == "val"]
    assert all(float(r[f"d{k}_{m}"]) > 0 for r in val for k in range(1, 6) for m in ("absrel", "rmse"))
    assert all(r["d1_rmse"] == "" for r in rows if r["split"] == "train")
    lowest = min(val, key=lambda r: float(r["loss"]))
    assert best.load()["step"] == int(lowest["step"])  # the best epoch's weights, beside the latest
    assert all(net.training for net in trainer.nets.values())  # validation hands them back in training mode

    stopped = EpochLoop(_depth_trainer(batch_size=3, epochs=2, log_every=2), _Views(8), _Views(3), 2, log,
                        checkpoint)
    assert stopped.run(Position()) == Position(2, 0, 2)  # mid-epoch: no validation, resumable position
    assert checkpoint.load()["batch"] == 2 and math.isnan(stopped.val_loss)



def test_the_cosine_schedule_falls_from_lr_to_zero_and_the_metrics_log_it(tmp_path):
    from sceneforge.learn.trainer import learning_rate

    config = TrainConfig(stage="depth", stores=("unread",), lr=1e-3, lr_schedule="cosine")
    assert [learning_rate(config, s, 10) for s in (0, 5, 10)] == pytest.approx([1e-3, 5e-4, 0.0])
    assert learning_rate(config, 2, 10) == pytest.approx(1e-3 * (1 + math.cos(math.pi * 0.2)) / 2)
    assert learning_rate(replace(config, lr_schedule="constant"), 7, 10) == 1e-3
    with pytest.raises(ValueError, match="lr_schedule must be one of"):
        replace(config, lr_schedule="step")
    trainer = _depth_trainer(batch_size=2, epochs=1, log_every=1, lr=1e-3, lr_schedule="cosine")
    log = MetricsLog(tmp_path, (), None, tensorboard=False)
    EpochLoop(trainer, _Views(8), None, 4, log, Checkpoint(tmp_path / "c.pt")).run(Position())
    # each train row logs the lr of the step it ends; the optimiser ran the last one
    lrs = [float(r["lr"]) for r in read_metrics(tmp_path / "metrics.csv")]
    assert lrs == pytest.approx([learning_rate(trainer.config, s, 4) for s in range(4)])
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(lrs[-1])


def test_mirroring_flips_half_the_views_by_seed_step_and_view_alone():
    from sceneforge.learn.trainer import mirrored

    g = torch.Generator().manual_seed(0)
    batch = {"index": torch.arange(64), "rgb": torch.randn(64, 3, 2, 3, generator=g),
             "seg": torch.randint(0, 40, (64, 2, 2, 3), generator=g), "K": torch.randn(64, 3, 3, generator=g)}
    out = mirrored(batch, ("rgb", "seg"), seed=0, step=3)
    flipped = torch.tensor([not torch.equal(out["rgb"][i], batch["rgb"][i]) for i in range(64)])
    assert 20 <= int(flipped.sum()) <= 44
    for i in range(64):
        for name in ("rgb", "seg"):
            want = batch[name][i].flip(-1) if flipped[i] else batch[name][i]
            assert torch.equal(out[name][i], want)
    assert out["K"] is batch["K"]  # not an image: left alone
    # the same views flip in a batch of other views (another process's share, a resumed run)
    share = {k: v[10:20] for k, v in batch.items()}
    again = mirrored(share, ("rgb", "seg"), seed=0, step=3)
    assert torch.equal(again["rgb"], out["rgb"][10:20])
    other_step = mirrored(batch, ("rgb",), seed=0, step=4)["rgb"]
    other_seed = mirrored(batch, ("rgb",), seed=1, step=3)["rgb"]
    assert not torch.equal(other_step, out["rgb"]) and not torch.equal(other_seed, out["rgb"])
    # stages whose targets are not image-aligned are never mirrored
    assert {n: s.flip_fields for n, s in REGISTRY.items()} == {"depth": ("rgb", "depth"), "seg": ("rgb", "seg"),
                                                              "overhead": (), "camera": ()}


@pytest.mark.parametrize("stage", ["depth", "seg", "overhead", "camera"])
def test_every_stage_trains_two_steps_on_cpu(stage, store, frontal_runs, tmp_path):
    kw = {}
    if stage in ("overhead", "camera"):
        kw["depth_run"] = frontal_runs["depth"]
    if stage == "overhead":
        kw["seg_run"] = frontal_runs["seg"]
    config = small_config(stage, store, **kw)
    run = tmp_path / stage
    result = train(config, run, device="auto", tensorboard=False)
    assert result.steps == 2 and math.isfinite(result.train_loss)
    rows = read_metrics(run / "metrics.csv")
    assert [int(r["step"]) for r in rows] == [1, 2] and all(float(r["loss"]) > 0 for r in rows)
    assert set(get_stage(stage).val_metrics) <= set(rows[0])  # the validation metrics' columns
    saved = read_config(run)
    assert saved == TrainConfig.from_dict(json.loads((run / "config.json").read_text()))
    # the EFT's resolution is the stores' (32 here), not a saved setting: a mismatch with the
    # 32 × 32 overhead targets would have failed the overhead stage's loss
    assert saved.stage == stage and "resolution" not in saved.to_dict()["eft"]
    assert json.loads((run / "split.json").read_text())["train"]["views"] == 6
    assert (run / "loss_curve.png").stat().st_size > 1000
    _, nets = load_run(run)
    assert all(not n.training for n in nets.values())
    if stage == "overhead":
        assert {"height_l1", "seg_ce"} <= set(rows[0]) and float(rows[0]["seg_ce"]) > 0


def test_resume_continues_exactly(store, tmp_path):
    opts = dict(device="cpu", tensorboard=False)
    whole = train(small_config("depth", store, max_steps=4), tmp_path / "whole", **opts)
    first = train(small_config("depth", store, max_steps=2), tmp_path / "split", **opts)
    with pytest.raises(SceneforgeError, match="already holds a run"):
        train(small_config("depth", store, max_steps=4), tmp_path / "split", **opts)
    with pytest.raises(SceneforgeError, match="different config"):
        train(small_config("depth", store, max_steps=4, lr=1e-3), tmp_path / "split", resume=True, **opts)
    second = train(small_config("depth", store, max_steps=4), tmp_path / "split", resume=True, **opts)
    assert (first.steps, second.steps, whole.steps) == (2, 4, 4)
    assert [int(r["step"]) for r in read_metrics(tmp_path / "split" / "metrics.csv")] == [1, 2, 3, 4]
    a, b = load_run(tmp_path / "whole")[1]["depth"], load_run(tmp_path / "split")[1]["depth"]
    for (name, pa), pb in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(pa, pb, msg=name)


def test_missing_frozen_run_is_an_expected_error(store, tmp_path):
    with pytest.raises(SceneforgeError, match="not a training run"):
        nope = str(tmp_path / "nope")
        train(small_config("overhead", store, depth_run=nope, seg_run=nope), tmp_path / "o", device="cpu")
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_depth_net_overfits_four_views(store, tmp_path):
    # one house held out for validation leaves 4 views: every step sees all of them
    config = small_config("depth", store, batch_size=4, epochs=60, max_steps=None, lr=2e-3,
                          split=SplitConfig(0.34, 0.0, file=str(tmp_path / "split.json")))
    result = train(config, tmp_path / "overfit", device="cpu", tensorboard=False)
    rows = [r for r in read_metrics(tmp_path / "overfit" / "metrics.csv") if r["split"] == "train"]
    assert json.loads((tmp_path / "overfit" / "split.json").read_text())["train"]["views"] == 4
    losses = [float(r["loss"]) for r in rows]
    assert len(losses) == 60 and result.epochs == 60
    assert np.mean(losses[-5:]) <= losses[0] / 10, (losses[0], losses[-5:])
    val = [r for r in read_metrics(tmp_path / "overfit" / "metrics.csv") if r["split"] == "val"]
    assert len(val) == 60 and all(math.isfinite(float(r["loss"])) for r in val)


def _fixed_batch(stage: str, store: str, frontal: dict, eft) -> dict:
    """Views 0..3 of the store as one batch of ``stage``'s fields; the overhead stage's
    input computed once by the frozen nets (what its feature cache holds)."""
    dataset = StoreDataset(index_stores([store]), get_stage(stage).fields)
    batch = torch.utils.data.default_collate([dataset[i] for i in range(4)])
    if eft is not None:
        batch["overhead_input"] = overhead_input(frontal, eft, batch)[0]
    return batch


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["depth", "seg", "overhead", "camera"])
def test_every_net_overfits_a_fixed_batch_of_four_views(stage, store, frontal_runs):
    from sceneforge.learn.eft import EpipolarFeatureTransformer
    from sceneforge.learn.train import frontal_nets

    kw = {f"{s}_run": frontal_runs[s] for s in FROZEN.get(stage, ())}
    config = small_config(stage, store, batch_size=4, lr=2e-3, bn_momentum=0.1, **kw)
    frontal = frontal_nets(config)
    eft = EpipolarFeatureTransformer(config.eft, resolution=32) if get_stage(stage).uses_eft else None
    trainer = Trainer(config, frontal, eft, torch.device("cpu"))
    batch = _fixed_batch(stage, store, frontal, eft)

    start = trainer.loss(batch)[0].item()
    for step in range(200):
        end = float(trainer.step(batch, step)["loss"])
    # the loss the optimiser drives (training mode): with 4 views a BatchNorm's batch statistics
    # differ from its running ones, which eval mode uses, by more than the overfitted loss itself
    assert end <= 0.1 * start, (stage, start, end)
    for net in trainer.nets.values():
        net.eval()
    with torch.no_grad():
        outputs = trainer.stage.forward(config, trainer.nets, frontal, eft, batch)
    assert all(torch.isfinite(v).all() for v in outputs.values())
    if stage == "seg":
        B, _, H, W = outputs["seg"].shape
        guess = outputs["seg"].reshape(B, 2, -1, H, W).argmax(dim=2)
        counted = batch["seg"] != EMPTY
        accuracy = (guess[counted] == batch["seg"][counted]).float().mean().item()
        assert counted.sum() > 0.5 * counted.numel() and accuracy >= 0.95, accuracy


# ------------------------------------------------------------------------- predicting


def test_predict_writes_the_store_layout(store, frontal_runs, tmp_path):
    from sceneforge.store import array_digests, open_store, validate_store

    run = tmp_path / "overhead"
    train(small_config("overhead", store, depth_run=frontal_runs["depth"], seg_run=frontal_runs["seg"],
                       max_steps=1), run, device="cpu", tensorboard=False)
    out = tmp_path / "pred.zarr"
    summary = predict(run, store, str(out), device="cpu", batch_size=4, split="all", workers=2)
    assert summary.predicted == summary.views == 6 and summary.stages == ("depth", "seg", "overhead")
    in_process = tmp_path / "pred0.zarr"
    predict(run, store, str(in_process), device="cpu", batch_size=4, split="all", workers=0)
    assert array_digests(str(out)) == array_digests(str(in_process))  # workers read, they don't decide
    sure = tmp_path / "sure.zarr"  # the least object probabilities keep a subset, and are recorded
    predict(run, store, str(sure), device="cpu", batch_size=4, split="all", workers=0,
            min_object_probability=0.99, min_overhead_object_probability=0.99)
    assert open_store(str(sure)).attrs["prediction"]["min_object_probability"] == 0.99
    assert open_store(str(in_process)).attrs["prediction"]["min_overhead_object_probability"] is None
    for name in ("depth", "overhead_height"):
        every, fewer = (np.isfinite(np.asarray(open_store(str(s)).array(name)[:])) for s in (in_process, sure))
        assert (fewer <= every).all() and fewer.sum() < every.sum(), name
        if name == "depth":
            assert (fewer[:, 4] == every[:, 4]).all()  # D5 is no object layer
    pred, truth = open_store(str(out)), open_store(store)
    assert len(pred) == 6 and pred.attrs["prediction"]["stage"] == "overhead"
    # schema, layout and attributes hold; what a 2-step net predicts fails content checks
    assert [p for p in validate_store(str(out)) if not p.startswith(("view ", "... "))] == []
    for i in range(6):
        p, t = pred.view(i), truth.view(i)
        assert p["depth"].shape == t["depth"].shape and p["overhead_height"].shape == (32, 32)
        assert np.isfinite(p["depth"][4]).all()
        no_d1 = ~np.isfinite(p["depth"][0])
        assert (p["category"][0][no_d1] == 0).all() and (p["category"][2] == 0).all()
        with np.errstate(invalid="ignore"):
            assert not (p["overhead_height"] <= 0.05).any()
        for name in ("K", "cam_to_world", "overhead_cam_to_world", "overhead_params"):
            np.testing.assert_array_equal(p[name], t[name])
        assert str(p["house_id"]) == str(t["house_id"]) and p["camera_id"] == t["camera_id"]
    with pytest.raises(SceneforgeError, match="exists"):
        predict(run, store, str(out), device="cpu")

    camera = tmp_path / "camera"
    train(small_config("camera", store, depth_run=frontal_runs["depth"], max_steps=1), camera, device="cpu",
          tensorboard=False)
    summary = predict(run, store, str(out), camera_run=camera, device="cpu", overwrite=True, split="all")
    assert summary.stages == ("depth", "seg", "overhead", "camera")
    p, t = open_store(str(out)).view(0), open_store(store).view(0)
    np.testing.assert_allclose(p["overhead_params"][[2, 3]], t["overhead_params"][[2, 3]])  # tz, theta known
    assert not np.allclose(p["overhead_params"][[0, 1, 4]], t["overhead_params"][[0, 1, 4]])
    R = p["overhead_cam_to_world"][:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R[:, 2], [0, -1, 0])  # looks straight down
    assert p["overhead_extent"] == pytest.approx(p["overhead_params"][4] / math.sqrt(2))
    with pytest.raises(SceneforgeError, match="camera run"):
        predict(run, store, str(tmp_path / "x.zarr"), camera_run=frontal_runs["depth"], device="cpu")
    with pytest.raises(SceneforgeError, match="is a camera run: give the overhead run it goes with as RUN"):
        predict(camera, store, str(tmp_path / "x.zarr"), device="cpu")
    with pytest.raises(SceneforgeError, match="needs an overhead run"):
        predict(frontal_runs["depth"], store, str(tmp_path / "x.zarr"), camera_run=camera, device="cpu")


def test_the_operating_point_is_chosen_on_the_validation_houses_and_reported(store, tmp_path):
    import click
    from click.testing import CliRunner
    from sceneforge.cli.main import LazyGroup

    from sceneforge.learn.operating_point import GRID
    from sceneforge.learn.split import read_split
    from sceneforge.store import array_digests, open_store

    split = SplitConfig(0.34, 0.34, seed=3, file=str(tmp_path / "split.json"))
    for stage in ("depth", "seg"):  # one house each to train, validate and test on
        train(small_config(stage, store, split=split), tmp_path / stage, device="cpu", tensorboard=False)
    run = tmp_path / "overhead"
    train(small_config("overhead", store, depth_run=str(tmp_path / "depth"), seg_run=str(tmp_path / "seg"),
                       max_steps=1, split=split), run, device="cpu", tensorboard=False)
    (val,) = read_split(tmp_path / "split.json").of("val")
    out = tmp_path / "pred.zarr"
    summary = predict(run, store, str(out), device="cpu", workers=0, operating_point="validation")
    point = summary.operating_point
    assert point.rule == "validation" and (point.views, point.houses) == (2, 1)  # the validation house's 2 views
    assert point.min_object_probability in GRID and point.min_overhead_object_probability in GRID
    assert point.precision.shape == point.recall.shape == (len(GRID), len(GRID))
    recorded = open_store(str(out)).attrs["prediction"]["operating_point"]
    assert recorded == {**point.to_dict(), "seconds": recorded["seconds"]}
    assert val not in {str(open_store(str(out)).array("house_id")[i]) for i in summary_views(out)}
    # the chosen thresholds are the ones the test views were predicted with
    given = tmp_path / "given.zarr"
    predict(run, store, str(given), device="cpu", workers=0, min_object_probability=point.min_object_probability,
            min_overhead_object_probability=point.min_overhead_object_probability)
    assert array_digests(str(out)) == array_digests(str(given))
    with pytest.raises(SceneforgeError, match="give no --min-object-probability"):
        predict(run, store, str(tmp_path / "x.zarr"), device="cpu", operating_point="validation",
                min_object_probability=0.5)
    with pytest.raises(ValueError, match="leave them unset"):
        PredictConfig(operating_point="validation", min_overhead_object_probability=0.5)

    @click.group(cls=LazyGroup, lazy={"predict": "train:predict", "evaluate": "evaluate:evaluate"})
    def cli():
        pass

    cli_out = str(tmp_path / "cli.zarr")
    result = CliRunner().invoke(cli, ["predict", str(run), store, cli_out, "--device", "cpu", "--workers", "0",
                                      "--operating-point", "validation", "--operating-point-views", "1"])
    assert result.exit_code == 0, result.output
    assert "chosen on 1 views of 1 validation houses where precision meets recall" in result.output
    report = tmp_path / "evaluation.json"
    result = CliRunner().invoke(cli, ["evaluate", "predictions", cli_out, store, "--density", "200",
                                      "--plot", str(tmp_path / "p.png"), "--json", str(report)])
    assert result.exit_code == 0, result.output
    chosen = json.loads(report.read_text())["operating_point"]
    assert chosen["rule"] == "validation" and chosen["views"] == 1 and "operating point:" in result.output
    assert chosen == open_store(cli_out).attrs["prediction"]["operating_point"]
    result = CliRunner().invoke(cli, ["evaluate", "predictions", str(given), store, "--density", "200",
                                      "--plot", str(tmp_path / "g.png")])
    assert result.exit_code == 0, result.output
    assert "as given" in result.output


def summary_views(path) -> list[int]:
    from sceneforge.store import open_store

    return open_store(str(path)).attrs["prediction"]["views"]


def test_true_camera_parameters_place_the_true_overhead_camera(store):
    from sceneforge.store import open_store

    s = open_store(store)
    get = lambda name: np.asarray(s.array(name)[:])  # noqa: E731
    params = get("overhead_params")
    pose, extent, out = proposed_overhead_cameras(get("K"), get("cam_to_world"), (48, 64),
                                                  get("overhead_cam_to_world"), params, params[:, [0, 1, 4]])
    np.testing.assert_allclose(pose, get("overhead_cam_to_world"), atol=1e-9)
    np.testing.assert_allclose(extent, get("overhead_extent"), rtol=1e-9)
    np.testing.assert_allclose(out, params, atol=1e-9)


# ------------------------------------------------------------------------------- CLI


def test_cli_train_and_predict(store, frontal_runs, tmp_path):
    import click
    from click.testing import CliRunner
    from sceneforge.cli.main import LazyGroup

    @click.group(cls=LazyGroup, lazy={"train": "train:train", "predict": "train:predict"})
    def cli():
        pass

    runner = CliRunner()
    run = tmp_path / "cam"
    args = ["train", store, "--stage", "camera", "--run", str(run), "--depth-run", frontal_runs["depth"],
            "--max-steps", "2", "--batch-size", "3", "--width", str(TINY), "--val-fraction", "0",
            "--test-fraction", "0", "--device", "cpu", "--no-tensorboard"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "2 steps" in " ".join(result.output.split()) and read_config(run).stage == "camera"
    again = runner.invoke(cli, args)
    assert again.exit_code == 1 and "already holds a run" in again.output and "Traceback" not in again.output

    out = str(tmp_path / "p.zarr")
    result = runner.invoke(cli, ["predict", frontal_runs["depth"], store, out, "--device", "cpu", "--split", "all"])
    assert result.exit_code == 0, result.output
    assert "6 of 6 views predicted (depth)" in " ".join(result.output.split())
    # the runs above split with no test houses: the default split is empty, and says how to fix it
    result = runner.invoke(cli, ["predict", frontal_runs["depth"], store, out + "2", "--device", "cpu"])
    assert result.exit_code == 1 and "no valid view of the 0 test houses" in result.output
    assert "--split all" in result.output and "Traceback" not in result.output

    # a predicted view under its truth; a truth of other views is one red line
    from sceneforge.cli.render import show

    png = tmp_path / "compare.png"
    result = runner.invoke(show, [out, "--view", "2", "--truth", store, "-o", str(png)])
    assert result.exit_code == 0, result.output
    from PIL import Image

    assert Image.open(png).size == (1760, 416)
    other = str(tmp_path / "other.zarr")
    from sceneforge.config import load_config
    from sceneforge.pipeline import render_dataset

    render_dataset("bundled:toy", other, load_config(None, {"width": 64, "height": 48, "views_per_house": 2,
                                                            "seed": 5, "rgb": {"enabled": False}}))
    bad = CliRunner().invoke(cli_show_group(), ["show", out, "--view", "2", "--truth", other, "-o", str(png)])
    assert bad.exit_code == 1 and "another camera pose" in bad.output and bad.output.count("\n") == 1


def cli_show_group():
    import click
    from sceneforge.cli.main import LazyGroup

    @click.group(cls=LazyGroup, lazy={"show": "render:show"})
    def cli():
        pass

    return cli


# ---------------------------------------------------------------------------- the split


def test_the_split_is_drawn_once_and_names_its_fixes(tmp_path):
    from sceneforge.learn.split import draw_split, fixed_split, read_split

    ids = [f"h{i}" for i in range(3)]
    with pytest.raises(SceneforgeError, match=r"3 houses cannot give a 0.1 validation split: use "
                                              r"--val-fraction >= 0.34 \(or 0 for none\) or more houses"):
        draw_split(ids, SplitConfig(0.1, 0.0))
    with pytest.raises(SceneforgeError, match="3 houses cannot give a 0.2 test split: use --test-fraction >= 0.34"):
        draw_split(ids, SplitConfig(0.0, 0.2))
    path = tmp_path / "split.json"
    first = fixed_split(ids, ["a.zarr"], SplitConfig(0.34, 0.34, seed=5, file=str(path)))
    assert [len(first.houses[s]) for s in ("train", "val", "test")] == [1, 1, 1]
    assert read_split(path) == first and path.exists()
    # a later stage reads the file, whatever it draws its weights with
    assert fixed_split(ids, ["a.zarr"], SplitConfig(0.34, 0.34, seed=5, file=str(path))) == first
    with pytest.raises(SceneforgeError, match="--split-seed 5: pass the same, or --split-file NEW.json"):
        fixed_split(ids, ["a.zarr"], SplitConfig(0.34, 0.34, seed=6, file=str(path)))
    with pytest.raises(SceneforgeError, match="splits other stores: 1 houses \\(h9\\)"):
        fixed_split([*ids, "h9"], ["a.zarr"], SplitConfig(0.34, 0.34, seed=5, file=str(path)))
    with pytest.raises(SceneforgeError, match="no split file .*train a run on these stores first"):
        read_split(tmp_path / "none.json")


def test_stages_share_the_split_and_predict_and_evaluate_use_its_test_houses(store, tmp_path):
    import click
    from click.testing import CliRunner
    from sceneforge.cli.main import LazyGroup

    from sceneforge.learn.split import read_split
    from sceneforge.store import open_store

    split_file = tmp_path / "split.json"
    split = SplitConfig(0.0, 0.34, seed=3, file=str(split_file))
    a = train(small_config("depth", store, max_steps=1, split=split), tmp_path / "a", device="cpu",
              tensorboard=False)
    # another training seed, the same houses: the split is the data's
    train(small_config("depth", store, max_steps=1, seed=9, split=split), tmp_path / "b", device="cpu",
          tensorboard=False)
    records = [json.loads((tmp_path / r / "split.json").read_text()) for r in ("a", "b")]
    assert records[0]["test"] == records[1]["test"] and records[0]["test"]["views"] == 2
    test_houses = read_split(split_file).of("test")
    assert len(test_houses) == 1 and records[0]["test"]["houses"] == sorted(test_houses)

    @click.group(cls=LazyGroup, lazy={"predict": "train:predict", "evaluate": "evaluate:evaluate"})
    def cli():
        pass

    out = str(tmp_path / "p.zarr")
    result = CliRunner().invoke(cli, ["predict", str(a.run), store, out, "--device", "cpu"])
    assert result.exit_code == 0, result.output
    assert "split: test (2 views of 1 house)" in result.output
    pred = open_store(out)
    predicted = pred.attrs["prediction"]["views"]
    assert len(predicted) == 2 and {str(pred.array("house_id")[i]) for i in predicted} == test_houses
    assert pred.attrs["prediction"]["split_file"] == str(split_file.resolve())

    result = CliRunner().invoke(cli, ["evaluate", "predictions", out, store, "--density", "200",
                                      "--plot", str(tmp_path / "p.png")])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0] == "split: test (2 views of 1 house)"
    result = CliRunner().invoke(cli, ["evaluate", "predictions", out, store, "--split", "train", "--density", "200",
                                      "--plot", str(tmp_path / "p.png")])
    assert result.exit_code == 1 and "no predicted view of the train split" in result.output


# --------------------------------------------------------------------------- reconstruct


def test_reconstruct_a_rendered_photo_gives_a_mesh_inside_the_cameras_frustum(store, frontal_runs, tmp_path):
    import trimesh
    from click.testing import CliRunner
    from PIL import Image
    from sceneforge.cli.main import LazyGroup

    from sceneforge.store import open_store

    run = tmp_path / "overhead"
    train(small_config("overhead", store, depth_run=frontal_runs["depth"], seg_run=frontal_runs["seg"],
                       max_steps=1), run, device="cpu", tensorboard=False)
    view = open_store(store).view(0)
    photos = tmp_path / "photos"
    photos.mkdir()
    Image.fromarray(view["rgb"]).save(photos / "room.png")
    K = view["K"]
    cli = LazyGroup(name="sceneforge", lazy={"reconstruct": "reconstruct:reconstruct"})
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["reconstruct", str(run), str(photos), "--out", str(out), "--device", "cpu",
                                      "--K", *map(str, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])),
                                      "--resolution", "32", "--floor-removal", "height"])
    assert result.exit_code == 0, result.output
    assert "1 photos reconstructed" in " ".join(result.output.split())
    arrays = np.load(out / "room.npz")
    assert arrays["depth"].shape == (5, 48, 64) and arrays["overhead_height"].shape == (32, 32)
    np.testing.assert_allclose(arrays["K"], K)
    assert (out / "room.png").stat().st_size > 5000
    mesh = trimesh.load(out / "room.ply", process=False)
    assert len(mesh.faces) > 100
    pose = arrays["cam_to_world"]
    cam = (np.asarray(mesh.vertices) - pose[:3, 3]) @ pose[:3, :3]
    uv = cam @ K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    eps = 1e-6
    assert (cam[:, 2] > 0).all()
    assert ((u >= -eps) & (u <= 64 + eps) & (v >= -eps) & (v <= 48 + eps)).all()
    # the camera sits 1.5 m above the floor of a gravity-aligned frame: nothing is far below it
    assert np.asarray(mesh.vertices)[:, 1].min() > -1.5 - 0.5
    sure = tmp_path / "sure"  # least object probabilities: a subset of the points
    result = CliRunner().invoke(cli, ["reconstruct", str(run), str(photos), "--out", str(sure), "--device", "cpu",
                                      "--K", *map(str, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])), "--resolution", "32",
                                      "--min-object-probability", "0.99", "--min-overhead-object-probability", "0.99"])
    assert result.exit_code == 0, result.output
    thinned = np.load(sure / "room.npz")
    np.testing.assert_array_equal(thinned["overhead_params"], arrays["overhead_params"])  # same overhead camera
    for name in ("depth", "overhead_height"):  # (a 1-step height net has no height above 5 cm to thin)
        every, fewer = np.isfinite(arrays[name]), np.isfinite(thinned[name])
        assert (fewer <= every).all() and (fewer.sum() < every.sum() or name == "overhead_height"), name

    bad = CliRunner().invoke(cli, ["reconstruct", frontal_runs["depth"], str(photos), "--out", str(tmp_path / "x")])
    assert bad.exit_code == 1 and "reconstruct needs an overhead run" in bad.output
    # the photos' files are there already: replaced only with --overwrite
    again = ["reconstruct", str(run), str(photos), "--out", str(out), "--device", "cpu", "--resolution", "32"]
    kept = (out / "room.npz").read_bytes()
    bad = CliRunner().invoke(cli, again)
    assert bad.exit_code == 1 and "already holds room.npz and 3 more; pass --overwrite" in bad.output
    assert (out / "room.npz").read_bytes() == kept
    assert CliRunner().invoke(cli, [*again, "--overwrite"]).exit_code == 0


def test_reconstructed_overhead_heights_are_kept_inside_the_frustum():
    from sceneforge.learn.reconstruct import PhotoCamera, _one, _overhead_camera

    camera = PhotoCamera()
    K, pose = camera.intrinsics(32, 24), camera.pose()
    depth = np.full((5, 24, 32), np.nan, np.float32)
    depth[4] = 4.0  # a wall 4 m ahead
    top = _overhead_camera(depth, K, pose, camera, 16)
    assert top.params[2] == pytest.approx(camera.height + top.cam_to_world[1, 3])  # tz: above the floor at -1.5
    rec = _one("wall", np.zeros((24, 32, 3), np.uint8), depth, np.zeros((2, 24, 32), np.uint8),
               np.ones((16, 16), np.float32), np.zeros((16, 16), np.uint8), K, pose, top.cam_to_world,
               top.half_extent, top.params)
    kept = np.isfinite(rec.arrays["overhead_height"])
    assert 0 < kept.sum() < kept.size  # the overhead square reaches outside the frustum
    cam = (rec.vertices - pose[:3, 3]) @ pose[:3, :3]
    uv = cam @ K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    assert (cam[:, 2] > 0).all() and ((u >= -1e-6) & (u <= 32 + 1e-6) & (v >= -1e-6) & (v <= 24 + 1e-6)).all()
    heights = rec.vertices[:, 1] + camera.height
    assert np.isclose(heights, 1.0, atol=1e-6).sum() >= kept.sum()  # the 1 m heights are in the mesh
