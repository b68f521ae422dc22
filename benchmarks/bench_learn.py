"""EFT forward+backward time, and training images/s per stage.

EFT: batch 8, 240×320 frontal → 300×300 overhead, 115 channels (RGB 3 + depth features 48
+ segmentation features 64), volume gating of (D1, D2) and (D3, D4) as in the 232-channel
assembly, on synthetic layers seen by the default PBRS camera (pitched 11.31° down). In
the same run, a baseline does the same transfer the straightforward way: gather every
(ray, overhead pixel) pair's feature vector and ``index_add`` it (in chunks, to bound
memory); both use the same pairs and must agree. The ratio is sceneforge's sparse-matrix
transfer against it.

Training: images/s of each stage (depth, seg, overhead, camera) on a store at 320×240,
300×300 overhead (default: the bundled toy houses rendered into a temporary folder), at
``--width`` times the paper's network widths, after one warm-up step.

    python benchmarks/bench_learn.py [--quick] [--store PATH] [--width 0.25] [--device cpu]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from sceneforge.cameras import DEFAULT_PITCH, default_intrinsics, pose_from_view
from sceneforge.learn.eft import EFTConfig, epipolar_geometry, segment_pairs, transfer_volume


def synthetic_views(B: int, H: int, W: int, R: int, seed: int = 0):
    """Default PBRS cameras over a 4 m overhead box, and smooth random D1..D4 (70 % object pixels)."""
    rng = np.random.default_rng(seed)
    K = default_intrinsics(W, H)
    view = np.array([0.0, -math.sin(DEFAULT_PITCH), math.cos(DEFAULT_PITCH)])
    pose = pose_from_view((0.0, 1.5, 0.0), view)
    top = np.eye(4)
    # right = forward × up for forward +Z is -X; image up = forward (as OverheadCamera)
    top[:3, 0], top[:3, 1], top[:3, 2], top[:3, 3] = (-1, 0, 0), (0, 0, -1), (0, -1, 0), (0, 2.6, 4.0)
    coarse = lambda lo, hi: torch.nn.functional.interpolate(  # noqa: E731
        torch.tensor(rng.uniform(lo, hi, (B, 1, H // 16, W // 16))), size=(H, W), mode="bilinear")[:, 0]
    d1 = coarse(1.5, 6.0)
    d2 = d1 + coarse(0.2, 1.0)
    d3 = d2 + coarse(0.1, 1.0)
    d4 = d3 + coarse(0.2, 1.0)
    objects = torch.tensor(rng.random((B, H, W)) < 0.7)
    d1, d2 = (torch.where(objects, d, torch.nan) for d in (d1, d2))
    second = objects & torch.tensor(rng.random((B, H, W)) < 0.6)
    d3, d4 = (torch.where(second, d, torch.nan) for d in (d3, d4))
    rep = lambda a: torch.tensor(a).expand(B, *a.shape).clone()  # noqa: E731
    geom = epipolar_geometry(rep(K), rep(pose), rep(top), torch.full((B,), 4.0), torch.full((B,), 2.6),
                             (H, W), R)
    return geom, (d1, d2), (d3, d4)


def baseline_transfer(features, geom, near, far, chunk: int = 1 << 20):
    """Volume gating by gather + index_add over every pair (the obvious vectorisation)."""
    B, C = features.shape[:2]
    R = geom.resolution
    src, dst = segment_pairs(geom, near, far)
    flat = features.permute(0, 2, 3, 1).reshape(-1, C)
    count = torch.bincount(dst, minlength=B * R * R).clamp(min=1).to(features.dtype)
    out = features.new_zeros(B * R * R, C)
    for a in range(0, len(src), chunk):
        out = out.index_add(0, dst[a:a + chunk], flat[src[a:a + chunk]])
    return (out / count[:, None]).reshape(B, R, R, C).permute(0, 3, 1, 2)


def time_eft(fn, features, geom, segments, repeats: int) -> tuple[float, torch.Tensor]:
    best, out = math.inf, None
    for _ in range(repeats):
        features.grad = None
        t = time.perf_counter()
        out = torch.cat([fn(features, geom, near, far) for near, far in segments], dim=1)
        out.square().sum().backward()
        best = min(best, time.perf_counter() - t)
    return best, out.detach()


def bench_eft(quick: bool) -> None:
    B, H, W, R, C = (2, 120, 160, 150, 115) if quick else (8, 240, 320, 300, 115)
    geom, seg1, seg2 = synthetic_views(B, H, W, R)
    features = torch.randn(B, C, H, W, requires_grad=True)
    pairs = sum(len(segment_pairs(geom, *s)[0]) for s in (seg1, seg2))
    t = time.perf_counter()
    for s in (seg1, seg2):
        segment_pairs(geom, *s, EFTConfig())
    t_pairs = time.perf_counter() - t
    repeats = 2 if quick else 3
    ours, out = time_eft(transfer_volume, features, geom, (seg1, seg2), repeats)
    grad = features.grad.clone()
    base, out_base = time_eft(baseline_transfer, features, geom, (seg1, seg2), repeats)
    torch.testing.assert_close(out, out_base, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(grad, features.grad, atol=1e-4, rtol=1e-4)
    print(f"EFT, batch {B}, {H}x{W} -> {R}x{R}, {C} channels, (D1,D2)+(D3,D4), CPU "
          f"({torch.get_num_threads()} threads), {pairs / 1e6:.1f} M ray-pixel pairs:")
    print(f"  sampling the segments (pairs)          {t_pairs:7.3f} s")
    print(f"  sceneforge forward+backward            {ours:7.3f} s   ({ours / B * 1000:.0f} ms/view)")
    print(f"  baseline gather+index_add fwd+bwd      {base:7.3f} s")
    print(f"  ratio baseline / sceneforge            {base / ours:7.2f}x")


def bench_training(store: str | None, width: float, device: str, quick: bool) -> None:
    from sceneforge.learn.train import TrainConfig, read_metrics, train

    with tempfile.TemporaryDirectory() as tmp:
        if store is None:
            from sceneforge.config import load_config
            from sceneforge.pipeline import render_dataset

            store = str(Path(tmp) / "toy.zarr")
            t = time.perf_counter()
            render_dataset("bundled:toy", store, load_config(None, {"views_per_house": 4}))
            print(f"rendered {store} (3 toy houses x 4 views, 320x240) in {time.perf_counter() - t:.1f} s")
        batch, steps = (2, 2) if quick else (4, 4)
        print(f"training throughput, width {width}, batch {batch}, {steps} steps after 1 warm-up, {device}:")
        runs = {}
        for stage in ("depth", "seg", "overhead", "camera"):
            runs[stage] = Path(tmp) / stage
            frozen = {"depth_run": str(runs["depth"]) if stage in ("overhead", "camera") else None,
                      "seg_run": str(runs["seg"]) if stage == "overhead" else None}
            config = TrainConfig(stage=stage, stores=(store,), batch_size=batch, max_steps=steps + 1,
                                 width=width, log_every=1, **frozen)
            result = train(config, runs[stage], device=device, tensorboard=False)
            rows = [r for r in read_metrics(runs[stage] / "metrics.csv") if r["split"] == "train"][1:]
            rate = np.mean([float(r["images_per_s"]) for r in rows])
            print(f"  {stage:<9} {rate:7.2f} images/s   (last loss {result.train_loss:.3f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    parser.add_argument("--store", default=None, help="store to train on (default: render the toy houses)")
    parser.add_argument("--width", type=float, default=0.25, help="network width multiplier (paper: 1)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-training", action="store_true")
    args = parser.parse_args()
    bench_eft(args.quick)
    if not args.skip_training:
        bench_training(args.store, args.width, args.device, args.quick)


if __name__ == "__main__":
    main()
