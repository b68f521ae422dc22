"""The overhead stage's feature cache: cached inputs give the overhead nets' outputs that
recomputing them gives, a changed frozen net or setting is never read from an old cache, and
training with the cache learns the weights training without it does."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the learn extra (torch) is not installed")
pytest.importorskip("zarr", reason="the store extra (zarr) is not installed")

from sceneforge.learn.cache import CACHE_DIR, CachedDataset, FeatureCache, cache_key, cached_datasets  # noqa: E402
from sceneforge.learn.dataset import StoreDataset, index_stores  # noqa: E402
from sceneforge.learn.eft import EpipolarFeatureTransformer  # noqa: E402
from sceneforge.learn.stages import get_stage  # noqa: E402
from sceneforge.learn.train import frontal_nets, load_run, train  # noqa: E402

from . import test_learn  # noqa: E402

# the tiny store and 2-step frozen runs of the learning tests (fixtures of this module's own)
store, frontal_runs = test_learn.store, test_learn.frontal_runs
pytestmark = pytest.mark.usefixtures("one_torch_thread")
small_config = test_learn.small_config

CPU = torch.device("cpu")
STAGE = get_stage("overhead")


def overhead_config(store, frontal_runs, **kw):
    # the store's layers: the 2-step frozen seg net sees no object, which would empty the
    # predicted ones and leave only zeros to transfer
    kw = {"eft_layers": "truth", **kw}
    return small_config("overhead", store, depth_run=frontal_runs["depth"], seg_run=frontal_runs["seg"], **kw)


def pieces(config):
    """The frozen nets, the EFT, the overhead stage's dataset and freshly built overhead nets (eval)."""
    frontal = frontal_nets(config)
    index = index_stores(config.stores)
    eft = EpipolarFeatureTransformer(config.eft, resolution=index.shapes["Wo"])
    torch.manual_seed(0)
    nets = STAGE.build(config, frontal)
    for net in nets.values():
        net.eval()
    return frontal, eft, StoreDataset(index, STAGE.fields), nets


def batches(dataset, batch_size):
    return list(torch.utils.data.DataLoader(dataset, batch_size=batch_size))


def outputs(config, nets, frontal, eft, dataset):
    """The overhead nets' outputs and their input on every view, in the cache's batches."""
    with torch.no_grad():
        out = [STAGE.forward(config, nets, frontal, eft, b) for b in batches(dataset, config.batch_size)]
    return {k: torch.cat([o[k] for o in out]) for k in out[0]}


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_cached_features_give_the_same_overhead_outputs_as_recomputing_them(dtype, store, frontal_runs, tmp_path):
    config = overhead_config(store, frontal_runs, feature_cache=dtype)
    frontal, eft, dataset, nets = pieces(config)
    (cached,) = cached_datasets(config, tmp_path, frontal, eft, CPU, STAGE.targets, dataset)
    assert isinstance(cached, CachedDataset) and len(cached) == len(dataset) == 6
    files = list((tmp_path / CACHE_DIR).glob("*/*.npy"))
    assert len(files) == 6 and all(np.load(f).dtype == np.dtype(dtype) for f in files)
    assert "rgb" not in cached[0] and {"overhead_height", "overhead_seg"} <= set(cached[0])

    from sceneforge.learn.stages import overhead_input

    recomputed_input = torch.cat([overhead_input(frontal, eft, b, True)[0] for b in batches(dataset, 3)])
    cached_input = torch.cat([b["overhead_input"].float() for b in batches(cached, 3)])
    assert (cached_input[:, 2:].abs().sum(dim=(1, 2, 3)) > 0).all()  # features reached every view
    recomputed, from_cache = outputs(config, nets, frontal, eft, dataset), outputs(config, nets, frontal, eft, cached)
    if dtype == "float32":
        # the same features, computed in the same batches: bit for bit
        torch.testing.assert_close(cached_input, recomputed_input, atol=0, rtol=0)
        for name in recomputed:
            torch.testing.assert_close(from_cache[name], recomputed[name], atol=0, rtol=0)
    else:
        # float16 rounds each value to 11 significant bits (subnormals: to 2^-24)
        torch.testing.assert_close(cached_input, recomputed_input, atol=2.0 ** -24, rtol=2.0 ** -11)
        for name in recomputed:
            scale = recomputed[name].abs().max()
            assert (from_cache[name] - recomputed[name]).abs().max() <= 1e-3 * scale, name


def test_a_cache_that_does_not_fit_or_cannot_be_written_is_not_used(store, frontal_runs, tmp_path):
    config = overhead_config(store, frontal_runs, feature_cache_gib=1e-6)
    frontal, eft, dataset, _ = pieces(config)
    assert FeatureCache(tmp_path, config, frontal, eft).view_bytes() * 6 > 1e-6 * 2 ** 30
    assert cached_datasets(config, tmp_path, frontal, eft, CPU, STAGE.targets, dataset, None) == [dataset, None]
    config = overhead_config(store, frontal_runs)
    (tmp_path / "run").write_text("a file where the run folder should be: nothing can be written below")
    assert cached_datasets(config, tmp_path / "run", frontal, eft, CPU, STAGE.targets, dataset) == [dataset]
    off = overhead_config(store, frontal_runs, feature_cache="off")
    assert cached_datasets(off, tmp_path, frontal, eft, CPU, STAGE.targets, dataset) == [dataset]
    assert not list(tmp_path.glob(f"{CACHE_DIR}/*/*.npy"))


def test_a_changed_frozen_net_or_setting_invalidates_the_cache(store, frontal_runs, tmp_path):
    config = overhead_config(store, frontal_runs, feature_cache="float32")
    frontal, eft, dataset, nets = pieces(config)
    key = cache_key(config, frontal, eft)
    assert key == cache_key(config, frontal_nets(config), eft)  # a content digest: reloading keeps it
    (old,) = cached_datasets(config, tmp_path, frontal, eft, CPU, STAGE.targets, dataset)
    old_input = torch.stack([old[i]["overhead_input"] for i in range(len(old))])

    with torch.no_grad():  # a retrained frozen depth net: one BatchNorm statistic moves
        next(b for n, b in frontal["depth"].named_buffers() if n.endswith("running_mean")).add_(0.5)
    assert cache_key(config, frontal, eft) != key
    from dataclasses import replace

    assert cache_key(replace(config, eft_layers="predicted"), frontal_nets(config), eft) != key
    assert cache_key(replace(config, feature_cache="float16"), frontal_nets(config), eft) != key

    (new,) = cached_datasets(config, tmp_path, frontal, eft, CPU, STAGE.targets, dataset)
    assert [p.name for p in (tmp_path / CACHE_DIR).iterdir()] == [cache_key(config, frontal, eft)]  # stale: gone
    new_input = torch.stack([new[i]["overhead_input"] for i in range(len(new))])
    assert not torch.equal(new_input, old_input)
    torch.testing.assert_close(outputs(config, nets, frontal, eft, new), outputs(config, nets, frontal, eft, dataset),
                               atol=0, rtol=0)


def test_training_with_the_cache_learns_the_weights_recomputing_does(store, frontal_runs, tmp_path):
    weights = {}
    for mode in ("off", "float32", "float16"):
        config = overhead_config(store, frontal_runs, feature_cache=mode, max_steps=4)
        result = train(config, tmp_path / mode, device="cpu", tensorboard=False)
        assert result.steps == 4
        cached = list((tmp_path / mode).glob(f"{CACHE_DIR}/*/*.npy"))
        assert len(cached) == (0 if mode == "off" else 6)
        nets = load_run(tmp_path / mode)[1]
        weights[mode] = {f"{n}.{k}": v for n in ("height", "overhead_seg") for k, v in nets[n].state_dict().items()}
    # float32: the same features, computed in other batches (the cache's, not the epoch's
    # shuffled ones), so equal to float rounding; float16: Adam's first steps are about
    # lr · sign(gradient), so a weight whose gradient is near 0 may step the other way:
    # at most 2 · lr per step apart
    lr = small_config("overhead", store).lr
    for name, w in weights["off"].items():
        torch.testing.assert_close(weights["float32"][name], w, atol=1e-5, rtol=1e-5, msg=name)
        assert (weights["float16"][name].float() - w.float()).abs().max() <= 2 * lr * 4 + 1e-6, name
