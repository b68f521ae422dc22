"""The overhead stage's frozen work: the EFT under ``no_grad``, and epochs with the feature cache.

EFT: the 232-channel assembly's forward under ``torch.no_grad`` (best guess, frustum mask,
volume gating of (D1, D2) and (D3, D4), 115 channels each) on the synthetic views of
``bench_learn.py``, against a baseline in the same run: the previous transfer, which built
the backward's transposed matrix and sorted the pairs for the forward's even under
``no_grad``. Both must agree.

Cache: seconds per epoch of the overhead stage on the bundled toy houses (rendered into a
temporary folder), frozen depth and seg runs of one step, ``--width`` times the paper's
widths, with ``feature_cache`` off (the frozen nets and the EFT on every step), float16 and
float32, the EFT on the store's layers; the first epoch is left out and the cache's
one-off fill (before the first step) timed apart. No validation split. Times are this
process's CPU time (the machine may be shared) with the wall time beside.

    python benchmarks/bench_feature_cache.py [--quick] [--width 0.125] [--epochs 3]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from pathlib import Path

import torch
from bench_learn import synthetic_batch  # benchmarks/, the script's folder, is on sys.path

import sceneforge.learn.eft as eft_module
from sceneforge.learn.eft import EFTConfig, EpipolarFeatureTransformer, segment_pairs
from sceneforge.learn.stages import geometry


def synthetic_views(B: int, H: int, W: int, R: int):
    """The EFT geometry and the (D1, D2), (D3, D4) layer pairs of ``bench_learn.py``'s
    synthetic batch."""
    batch = synthetic_batch(B, H, W, R)
    depth = batch["depth"]
    return geometry(batch, (H, W), R), (depth[:, 0], depth[:, 1]), (depth[:, 2], depth[:, 3])


def previous_transfer_volume(features, geom, near, far, config=None):
    """Volume gating as it was: Aᵀ (for the backward) and A (from a sort of the pairs by
    overhead pixel) built on every call, then the CSR product."""
    B, C = features.shape[:2]
    R = geom.resolution
    src, dst = segment_pairs(geom, near, far, config)
    n_src, n_dst = B * geom.frontal_hw[0] * geom.frontal_hw[1], B * R * R
    count = torch.bincount(dst, minlength=n_dst).to(features.dtype)
    weight = 1.0 / count[dst]
    eft_module._csr(src, dst, weight, (n_src, n_dst))
    order = torch.sort(dst, stable=True).indices
    A = eft_module._csr(dst[order], src[order], weight[order], (n_dst, n_src))
    return eft_module._unflat(A @ eft_module._flat(features).contiguous(), B, R)


def bench_eft(quick: bool) -> None:
    B, H, W, R = (2, 120, 160, 150) if quick else (4, 240, 320, 300)
    geom, (d1, d2), (d3, d4) = synthetic_views(B, H, W, R)
    depth = torch.stack([d1, d2, d3, d4], dim=1).float()
    rgb, fd, fs = torch.randn(B, 3, H, W), torch.randn(B, 48, H, W), torch.randn(B, 64, H, W)
    eft = EpipolarFeatureTransformer(EFTConfig(), resolution=R)
    ours = eft_module.transfer_volume

    def timed(fn, repeats=3):
        """The fastest of ``repeats`` calls: (CPU seconds of this process, wall seconds, result)."""
        best, out = (math.inf, math.inf), None
        for _ in range(repeats):
            c, t = time.process_time(), time.perf_counter()
            out = fn()
            best = min(best, (time.process_time() - c, time.perf_counter() - t))
        return (*best, out)

    def forward(transfer):
        eft_module.transfer_volume = transfer
        try:
            with torch.no_grad():
                return eft(rgb, fd, fs, depth, geom)
        finally:
            eft_module.transfer_volume = ours

    c_pairs, t_pairs, _ = timed(lambda: [segment_pairs(geom, near, far) for near, far in ((d1, d2), (d3, d4))])
    c_before, t_before, out_before = timed(lambda: forward(previous_transfer_volume))
    c_after, t_after, out_after = timed(lambda: forward(ours))
    torch.testing.assert_close(out_after, out_before, atol=1e-5, rtol=1e-5)
    print(f"EFT forward under no_grad, batch {B}, {H}x{W} -> {R}x{R}, 232 channels, CPU "
          f"({torch.get_num_threads()} threads), fastest of 3, CPU time (wall):")
    print(f"  of it, sampling the segments      {c_pairs * 1000:8.0f} ms/batch ({t_pairs * 1000:.0f})")
    print(f"  before (backward matrix + sort)   {c_before * 1000:8.0f} ms/batch ({t_before * 1000:.0f})")
    print(f"  after  (scatter, nothing else)    {c_after * 1000:8.0f} ms/batch ({t_after * 1000:.0f})   "
          f"{c_before / c_after:.2f}x; without the sampling {(c_before - c_pairs) / (c_after - c_pairs):.2f}x")


class _Clock:
    """A :class:`~sceneforge.learn.trainer.TrainProgress` noting this process's CPU time and
    the wall time when the loop starts and after every step."""

    def __init__(self):
        self.started = time.process_time(), time.perf_counter()
        self.at: list[tuple[float, float]] = []

    def start(self, total: int, done: int) -> None:
        self.at.append((time.process_time(), time.perf_counter()))

    def step(self, step: int, loss: float) -> None:
        self.at.append((time.process_time(), time.perf_counter()))


def bench_cache(width: float, epochs: int, quick: bool) -> None:
    from sceneforge.config import load_config
    from sceneforge.learn.dataset import SplitConfig
    from sceneforge.learn.train import TrainConfig, train
    from sceneforge.pipeline import render_dataset

    size = {"width": 160, "height": 120, "view": {"overhead": {"resolution": 150}}} if quick else {}
    with tempfile.TemporaryDirectory() as tmp:
        store = str(Path(tmp) / "toy.zarr")
        t = time.perf_counter()
        summary = render_dataset("bundled:toy", store, load_config(None, {"views_per_house": 2, **size}))
        print(f"rendered {summary.views} views of the toy houses in {time.perf_counter() - t:.1f} s")
        common = dict(stores=(store,), batch_size=3, width=width, log_every=1, split=SplitConfig(0.0, 0.0))
        runs = {s: str(Path(tmp) / s) for s in ("depth", "seg")}
        for stage, run in runs.items():
            train(TrainConfig(stage=stage, max_steps=1, **common), run, device="cpu", tensorboard=False)
        steps = math.ceil(summary.views / 3)
        # the store's layers: a one-step seg net sees no object, and its empty layers would
        # leave the EFT nothing to transfer
        print(f"overhead stage, width {width}, batch 3, EFT on the store's layers, {epochs} epochs of {steps} steps, "
              f"CPU ({torch.get_num_threads()} threads); CPU time (wall):")
        base = None
        for mode in ("off", "float16", "float32"):
            config = TrainConfig(stage="overhead", epochs=epochs, depth_run=runs["depth"], seg_run=runs["seg"],
                                 eft_layers="truth", feature_cache=mode, **common)
            clock = _Clock()
            train(config, Path(tmp) / f"overhead-{mode}", device="cpu", tensorboard=False, progress=clock)
            # the epochs after the first; before the loop: the cache's fill and the run's set-up
            (c0, t0), (c1, t1) = clock.at[steps], clock.at[-1]
            cpu, wall = (c1 - c0) / (epochs - 1), (t1 - t0) / (epochs - 1)
            base = base or cpu
            print(f"  feature_cache={mode:<8} {cpu:7.2f} s/epoch ({wall:.2f})  {base / cpu:5.2f}x   "
                  f"before the first step {clock.at[0][0] - clock.started[0]:5.1f} s "
                  f"({clock.at[0][1] - clock.started[1]:.1f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smaller images, for a smoke run")
    parser.add_argument("--width", type=float, default=0.125, help="network width multiplier (paper: 1)")
    parser.add_argument("--epochs", type=int, default=3, help="at least 2: the first is not timed")
    parser.add_argument("--skip-cache", action="store_true")
    args = parser.parse_args()
    if args.epochs < 2:
        parser.error("--epochs must be at least 2")
    warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
    bench_eft(args.quick)
    if not args.skip_cache:
        bench_cache(args.width, args.epochs, args.quick)


if __name__ == "__main__":
    main()
