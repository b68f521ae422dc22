"""Training speed of each stage and of the EFT at the paper's sizes, with and without AMP.

Stages (depth, seg, overhead, camera): images/s of a whole training step — forward,
backward and Adam step, the trained nets in training mode, the frozen ones in eval mode —
on synthetic batches of the paper's sizes (320×240 RGB, 300×300 overhead, ``--width`` 1 =
the paper's widths: the depth net is ~118 GFLOP per image forward). Each stage runs the
project's own code (``sceneforge.learn.stages``: its nets, loss and EFT); data loading is
left out. The overhead stage's EFT reads the batch's layers (``eft_layers="truth"``):
the untrained frozen nets' layers would be noise, and the EFT's work depends on them.

EFT: milliseconds per batch (and images/s) of the overhead nets' 232-channel input
(geometry, best-guess height, frustum mask, (D1, D2) and (D3, D4) volume transfers of RGB +
48 + 64 features, channels-last as the trainer's frozen nets give them), forward under
``no_grad`` (how the overhead stage runs it, its inputs frozen) and forward + backward to
the features (a fixed gradient in the output's layout handed to ``backward``: the loss's
own work is not the EFT's), for sceneforge's EFT (bags, one ``embedding_bag``) beside its
reference (``reference=True``: the previous sparse-matrix implementation), in alternating
blocks of calls (two rounds), ``--eft-steps`` calls each (the median), with the ratio and
the largest difference of their outputs and gradients. ``--eft-baseline`` also times the transfers
done the obvious way (gather every (ray, overhead pixel) pair and ``index_add``, fp32)
against sceneforge's.

Each is measured in fp32 and under ``torch.autocast`` (done here, not by the trainer):
bf16 on the CPU, bf16 and fp16 on CUDA (fp16 with a gradient scaler), all in the same run;
the ratios are AMP's speed-up over fp32 (> 1: AMP is faster). Layers and cameras are
synthetic: the default PBRS camera (1.5 m high, pitched 11.31° down) over a 4 m overhead
box, smooth random D1..D4 with 70 % object pixels. GFLOP per image is counted by
``torch.utils.flop_counter`` (convolutions and matrix products of one training step).

    python benchmarks/bench_learn.py                   # paper sizes, every stage, CPU or GPU
    python benchmarks/bench_learn.py --quick           # smoke run: small images and nets
    python benchmarks/bench_learn.py --batch 2 --steps 2 --device cpu --stages depth,seg
    python benchmarks/bench_learn.py --stages none --precisions fp32   # the EFT against its reference
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from sceneforge.cameras import DEFAULT_PITCH, default_intrinsics, pose_from_view
from sceneforge.learn.dataset import EMPTY, SEG_CLASSES
from sceneforge.learn.eft import EpipolarFeatureTransformer, segment_pairs
from sceneforge.learn.networks import DEPTH_NET, SEG_NET
from sceneforge.learn.stages import get_stage
from sceneforge.learn.train import TrainConfig
from sceneforge.learn.trainer import memory_format

STAGES = ("depth", "seg", "overhead", "camera")
#: the paper's frontal image (H, W) and overhead resolution
PAPER_SIZE, PAPER_OVERHEAD = (240, 320), 300
EXTENT, FLOOR_DEPTH = 4.0, 2.6


@dataclass(frozen=True)
class Precision:
    """fp32, or autocast to ``dtype`` (with a gradient scaler for fp16)."""

    name: str
    dtype: torch.dtype | None = None

    def autocast(self, device: torch.device):
        if self.dtype is None:
            return nullcontext()
        return torch.autocast(device.type, dtype=self.dtype)

    @property
    def amp(self) -> str:
        """The trainer's name of this precision (``TrainConfig.amp``)."""
        return "off" if self.dtype is None else self.name


PRECISIONS = {"fp32": Precision("fp32"), "bf16": Precision("bf16", torch.bfloat16),
              "fp16": Precision("fp16", torch.float16)}


# ------------------------------------------------------------------- synthetic data


def synthetic_batch(B: int, H: int, W: int, R: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A batch with every field a stage reads: default PBRS cameras over a 4 m overhead box,
    smooth random D1..D4 (70 % object pixels, 42 % with D3, D4), D5 behind them everywhere,
    random classes and overhead heights."""
    rng = np.random.default_rng(seed)
    K = default_intrinsics(W, H)
    view = np.array([0.0, -math.sin(DEFAULT_PITCH), math.cos(DEFAULT_PITCH)])
    pose = pose_from_view((0.0, 1.5, 0.0), view)
    top = np.eye(4)
    # right = forward × up for forward +Z is -X; image up = forward (as OverheadCamera)
    top[:3, 0], top[:3, 1], top[:3, 2], top[:3, 3] = (-1, 0, 0), (0, 0, -1), (0, -1, 0), (0, 2.6, 4.0)

    def coarse(lo, hi):
        x = torch.tensor(rng.uniform(lo, hi, (B, 1, H // 16, W // 16)), dtype=torch.float32)
        return torch.nn.functional.interpolate(x, size=(H, W), mode="bilinear")[:, 0]

    d1 = coarse(1.5, 6.0)
    d2 = d1 + coarse(0.2, 1.0)
    d3 = d2 + coarse(0.1, 1.0)
    d4 = d3 + coarse(0.2, 1.0)
    d5 = d4 + coarse(0.5, 2.0)
    objects = torch.tensor(rng.random((B, H, W)) < 0.7)
    second = objects & torch.tensor(rng.random((B, H, W)) < 0.6)
    nan = torch.tensor(torch.nan)
    depth = torch.stack([torch.where(objects, d1, nan), torch.where(objects, d2, nan),
                         torch.where(second, d3, nan), torch.where(second, d4, nan), d5], dim=1)
    seg = torch.tensor(rng.integers(0, SEG_CLASSES, (B, 2, H, W)))
    height = torch.tensor(rng.uniform(0, 2, (B, R, R)), dtype=torch.float32)
    foreground = torch.tensor(rng.random((B, R, R)) < 0.5)
    height = torch.where(foreground, height, torch.zeros(()))
    overhead_seg = torch.where(torch.tensor(rng.random((B, R, R)) < 0.05), EMPTY,
                               torch.tensor(rng.integers(0, SEG_CLASSES, (B, R, R))))
    rep = lambda a: torch.tensor(a, dtype=torch.float64).expand(B, *np.shape(a)).clone()  # noqa: E731
    return {
        "index": torch.arange(B),
        "rgb": torch.tensor(rng.normal(0, 0.25, (B, 3, H, W)), dtype=torch.float32),
        "depth": depth, "seg": seg,
        "overhead_height": height, "overhead_foreground": foreground, "overhead_seg": overhead_seg,
        "K": rep(K), "cam_to_world": rep(pose), "overhead_cam_to_world": rep(top),
        "overhead_extent": torch.full((B,), EXTENT, dtype=torch.float64),
        "overhead_params": rep([0.0, 2.6, FLOOR_DEPTH, 0.0, EXTENT]),
    }


def to_device(batch: dict[str, torch.Tensor], device: torch.device):
    """The batch on ``device``, contiguous (each precision's :func:`bench_stage` lays its
    images out)."""
    return {k: v.to(device) for k, v in batch.items()}


# ------------------------------------------------------------------------- timing


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, warmup: int, steps: int, device: torch.device) -> tuple[float, float | None]:
    """Seconds per call of ``fn`` (mean over ``steps`` after ``warmup`` calls) and, on CUDA,
    the peak GiB allocated."""
    for _ in range(warmup):
        fn()
    sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t = time.perf_counter()
    for _ in range(steps):
        fn()
    sync(device)
    seconds = (time.perf_counter() - t) / steps
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
    return seconds, peak


# ------------------------------------------------------------------------- stages


class Fp32EFT(EpipolarFeatureTransformer):
    """The EFT with autocast off and its features in fp32: what an AMP step must do where
    the EFT has no kernel for the AMP dtype (:func:`eft_amp_error`)."""

    def forward(self, rgb, depth_features, seg_features, depth, geom):
        with torch.autocast(rgb.device.type, enabled=False):
            return super().forward(rgb.float(), depth_features.float(), seg_features.float(), depth, geom)


def eft_amp_error(precision: Precision, device: torch.device) -> str | None:
    """Why the EFT cannot run under ``precision``'s autocast on ``device`` (None: it can),
    tried on a tiny batch."""
    if precision.dtype is None:
        return None
    from sceneforge.learn.stages import geometry

    batch = to_device(synthetic_batch(1, 32, 32, 16, seed=2), device)
    try:
        with torch.no_grad(), precision.autocast(device):
            x = torch.ones(1, 2, 32, 32, device=device, dtype=precision.dtype)
            EpipolarFeatureTransformer(resolution=16)(batch["rgb"], x, x, batch["depth"][:, :4],
                                                      geometry(batch, (32, 32), 16))
    except (NotImplementedError, RuntimeError) as e:
        return str(e).strip().splitlines()[0]
    return None


def stage_config(stage: str, width: float) -> TrainConfig:
    return TrainConfig(stage=stage, stores=("synthetic",), width=width, eft_layers="truth",
                       depth_run="synthetic" if stage in ("overhead", "camera") else None,
                       seg_run="synthetic" if stage == "overhead" else None)


def frozen_nets(stage: str, width: float, device: torch.device) -> dict:
    """Freshly initialised frontal nets, frozen as ``train`` freezes loaded runs (each
    precision's :func:`bench_stage` lays them out as it runs)."""
    nets = {}
    for name in get_stage(stage).frozen:
        nets.update(get_stage(name).build(stage_config(name, width), {}))
    for net in nets.values():
        net.to(device).eval().requires_grad_(False)
    return nets


def step_flops(stage: str, width: float, H: int, W: int, R: int) -> float:
    """Convolution and matrix-product FLOPs of one training step on one image (meta tensors:
    nothing is computed)."""
    config = stage_config(stage, width)
    with torch.device("meta"):
        frontal = {}
        for name in get_stage(stage).frozen:
            frontal.update(get_stage(name).build(stage_config(name, width), {}))
        nets = get_stage(stage).build(config, frontal)
        rgb = torch.zeros(1, 3, H, W)
        with FlopCounterMode(display=False) as counter:
            if stage in ("depth", "seg"):
                out = nets[stage](rgb).prediction
            elif stage == "camera":
                with torch.no_grad():
                    f = frontal["depth"](rgb)
                out = nets["camera"](f.features, f.encoding)
            else:
                with torch.no_grad():
                    d, s = frontal["depth"](rgb), frontal["seg"](rgb)
                x = torch.zeros(1, EpipolarFeatureTransformer.out_channels(d.features.shape[1],
                                                                           s.features.shape[1]), R, R)
                out = nets["height"](x).sum() + nets["overhead_seg"](x).sum()
            out.sum().backward()
    return counter.get_total_flops()


def layout(args, device: torch.device, precision: Precision) -> torch.memory_format:
    """The nets' and images' memory layout in ``precision``: the trainer's
    (:func:`~sceneforge.learn.trainer.memory_format`) unless ``--channels-last`` says."""
    if args.channels_last is None:
        return memory_format(device, precision.amp)
    return torch.channels_last if args.channels_last else torch.contiguous_format


def bench_stage(stage: str, precision: Precision, batch: dict, frontal: dict, args, device, R: int,
                eft_fp32: bool = False):
    """Seconds per training step and the peak GiB (CUDA) of one stage in one precision
    (``eft_fp32``: its EFT outside autocast, :class:`Fp32EFT`), nets and images in the
    precision's :func:`layout`."""
    config = stage_config(stage, args.width)
    spec = get_stage(stage)
    form = layout(args, device, precision)
    torch.manual_seed(0)
    nets = spec.build(config, frontal)
    for net in (*nets.values(), *frontal.values()):
        net.to(device, memory_format=form)
    for net in nets.values():
        net.train()
    batch = {**batch, "rgb": batch["rgb"].contiguous(memory_format=form)}
    params = [p for net in nets.values() for p in net.parameters()]
    optimizer = torch.optim.Adam(params, lr=config.lr)
    scaler = torch.amp.GradScaler(device.type, enabled=precision.name == "fp16")
    eft = (Fp32EFT if eft_fp32 else EpipolarFeatureTransformer)(config.eft, resolution=R) if spec.uses_eft else None

    def step():
        with precision.autocast(device):
            loss, _ = spec.loss(config, nets, frontal, eft, batch)
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()

    return timed(step, args.warmup, args.steps, device)


# --------------------------------------------------------------------------- EFT


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


def eft_inputs(batch: dict, args, device, dtype: torch.dtype, channels_last: bool = False):
    """The frontal features the EFT reads (random, at the paper's widths × ``--width``),
    in the dtype the nets give them (autocast: the AMP dtype), channels-last if asked."""
    B, _, H, W = batch["rgb"].shape
    cd = max(2, round(DEPTH_NET.channels[0] * args.width))
    cs = max(2, round(SEG_NET.channels[0] * args.width))
    g = torch.Generator().manual_seed(1)
    layout = torch.channels_last if channels_last else torch.contiguous_format
    depth_features = torch.randn(B, cd, H, W, generator=g).to(device, dtype, memory_format=layout)
    seg_features = torch.randn(B, cs, H, W, generator=g).to(device, dtype, memory_format=layout)
    return depth_features, seg_features


def bench_eft(precision: Precision, batch: dict, args, device, R: int, eft_fp32: bool = False) -> dict:
    """The EFT and its reference (``reference=True``), forward (no_grad) and forward +
    backward (``eft_fp32``: the features cast to fp32 and autocast off inside it,
    :class:`Fp32EFT`), in alternating blocks of calls: ``{(which, mode): ms per call}``
    (the median of ``--eft-steps`` calls) and the largest differences of their outputs and
    gradients (``"out"``, ``"grad"``)."""
    from sceneforge.learn.stages import geometry

    cls = Fp32EFT if eft_fp32 else EpipolarFeatureTransformer
    efts = {"new": cls(resolution=R), "reference": cls(resolution=R, reference=True)}
    dtype = precision.dtype or torch.float32
    # channels-last, as the trainer's frozen nets give them (it makes every net channels-last)
    depth_features, seg_features = eft_inputs(batch, args, device, dtype, channels_last=True)
    rgb, layers = batch["rgb"].contiguous(memory_format=torch.channels_last), batch["depth"][:, :4]
    grads, last = {}, {}

    def run(which: str, grad: bool):
        df = depth_features.detach().requires_grad_(grad)
        sf = seg_features.detach().requires_grad_(grad)
        with precision.autocast(device), torch.set_grad_enabled(grad):
            out = efts[which](rgb, df, sf, layers, geometry(batch, tuple(rgb.shape[-2:]), R))
        if grad:
            # the same gradient for both, in the output's layout (as a net's backward sends
            # it), made on the warm-up call
            if which not in grads:
                g = torch.Generator().manual_seed(2)
                grads[which] = torch.empty_like(out).copy_(torch.randn(out.shape, generator=g).to(out))
            out.backward(grads[which])
        last[which, grad] = out.detach(), (df.grad, sf.grad)

    times = {}
    for grad in (False, True):
        for _ in range(args.warmup):
            for which in efts:
                run(which, grad)
        # two rounds of a block of calls each, reference and new in turn: each runs in its
        # own steady state (as in a training loop), and a drift of the machine's load
        # reaches both
        for block in (args.eft_steps // 2, args.eft_steps - args.eft_steps // 2):
            for which in efts:
                for _ in range(block):
                    sync(device)
                    t = time.perf_counter()
                    run(which, grad)
                    sync(device)
                    times.setdefault((which, grad), []).append(time.perf_counter() - t)
    result = {key: 1000 * float(np.median(ts)) for key, ts in times.items()}
    result["out"] = (last["new", False][0].float() - last["reference", False][0].float()).abs().max().item()
    result["grad"] = max((a.float() - b.float()).abs().max().item()
                         for a, b in zip(last["new", True][1], last["reference", True][1]))
    return result


def bench_eft_baseline(batch: dict, args, device, R: int) -> tuple[float, float]:
    """ms per batch of the two volume transfers, fp32 forward + backward: sceneforge's bags
    and the gather + index_add baseline (checked equal)."""
    from sceneforge.learn.eft import transfer_volume
    from sceneforge.learn.stages import geometry

    rgb, layers = batch["rgb"], batch["depth"]
    depth_features, seg_features = eft_inputs(batch, args, device, torch.float32)
    features = torch.cat([rgb, depth_features, seg_features], dim=1).requires_grad_(True)
    geom = geometry(batch, tuple(rgb.shape[-2:]), R)
    segments = ((layers[:, 0], layers[:, 1]), (layers[:, 2], layers[:, 3]))
    results = {}
    for name, fn in (("sceneforge", transfer_volume), ("baseline", baseline_transfer)):
        def run(fn=fn, name=name):
            features.grad = None
            out = torch.cat([fn(features, geom, near, far) for near, far in segments], dim=1)
            out.square().sum().backward()
            results[name] = (out.detach(), features.grad.clone())
        results[name + "_ms"] = timed(run, args.warmup, args.steps, device)[0] * 1000
    torch.testing.assert_close(results["sceneforge"], results["baseline"], atol=1e-4, rtol=1e-4)
    return results["sceneforge_ms"], results["baseline_ms"]


# -------------------------------------------------------------------------- main


def describe(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)}, torch {torch.__version__})"
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"cpu ({cpu}, {torch.get_num_threads()} threads, torch {torch.__version__})"


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--device", default="auto", help="auto (CUDA when torch sees a GPU), cpu, cuda, cuda:N")
    parser.add_argument("--batch", type=int, default=None,
                        help="views per batch (default: 2 on the CPU, 24 = the paper's on a GPU; --quick: 1)")
    parser.add_argument("--steps", type=int, default=None,
                        help="timed steps per measurement (default: 2 on the CPU, 10 on a GPU; --quick: 1)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed steps before them (default: 1 on the CPU, 3 on a GPU)")
    parser.add_argument("--width", type=float, default=None,
                        help="network width multiplier (default: 1 = the paper's; --quick: 0.25)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 160x120 images, 150x150 overhead, width 0.25, batch 1, 1 step")
    parser.add_argument("--size", default=None, metavar="WxH",
                        help="frontal image size (default: 320x240, the paper's; --quick: 160x120; "
                             "the CPU learning recipe's: 80x60)")
    parser.add_argument("--overhead", type=int, default=None, metavar="R",
                        help="overhead map resolution (default: 300, the paper's; --quick: 150; the CPU recipe's: 64)")
    parser.add_argument("--stages", default=",".join(STAGES),
                        help="comma-separated stages to time (none: the EFT alone)")
    parser.add_argument("--precisions", default=None,
                        help="comma-separated from fp32, bf16, fp16 (default: fp32,bf16 on the CPU, "
                             "fp32,bf16,fp16 on a GPU)")
    parser.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                        help="nets and images in channels-last memory in every precision (default: as the "
                             "trainer lays them out: channels-last but for autocast on the CPU, where "
                             "PyTorch's channels-last bf16 backward of a dilated convolution gives NaN)")
    parser.add_argument("--no-eft", action="store_true", help="skip the EFT timings")
    parser.add_argument("--eft-steps", type=int, default=None,
                        help="timed calls of the EFT and of its reference each, the median reported "
                             "(default: 7 on the CPU, 20 on a GPU)")
    parser.add_argument("--eft-baseline", action="store_true",
                        help="also time the volume transfers against a gather + index_add baseline (fp32)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = parser.parse_args()
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: torch sees no CUDA GPU")
    gpu = device.type == "cuda"
    defaults = dict(batch=1, steps=1, warmup=1, width=0.25, eft_steps=3) if args.quick else \
        dict(batch=24 if gpu else 2, steps=10 if gpu else 2, warmup=3 if gpu else 1, width=1.0,
             eft_steps=20 if gpu else 7)
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.size is None:
        args.size = (120, 160) if args.quick else PAPER_SIZE
    else:
        try:
            W, H = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            parser.error(f"--size {args.size}: give WxH, e.g. 80x60")
        args.size = (H, W)
    H, W = args.size
    args.overhead = args.overhead or (150 if args.quick else PAPER_OVERHEAD)
    if min(H, W, args.overhead) < 1:
        parser.error("--size and --overhead must be positive")
    args.stages = [] if args.stages in ("", "none") else args.stages.split(",")
    args.precisions = (args.precisions or ("fp32,bf16,fp16" if gpu else "fp32,bf16")).split(",")
    unknown = set(args.precisions) - set(PRECISIONS) | set(args.stages) - set(STAGES)
    if unknown or args.precisions[0] != "fp32":
        parser.error(f"unknown stage or precision {sorted(unknown)}, or fp32 not first" if unknown
                     else "--precisions must start with fp32 (the ratios' reference)")
    if min(args.batch, args.steps, args.eft_steps, args.warmup + 1) < 1 or not args.width > 0:
        parser.error("--batch, --steps and --eft-steps must be >= 1, --warmup >= 0, --width > 0")
    if args.threads:
        torch.set_num_threads(args.threads)
    if gpu:
        torch.backends.cudnn.benchmark = True
    return args, device


def main() -> None:
    args, device = parse_args()
    (H, W), R = args.size, args.overhead
    print(f"device: {describe(device)}"
          + ("" if device.type == "cuda" or torch.cuda.is_available() else "; torch sees no GPU: CPU figures only"))
    print(f"sizes: {W}x{H} RGB, {R}x{R} overhead, width {args.width:g} (1 = the paper's), batch {args.batch}, "
          f"{args.steps} timed step(s) after {args.warmup} warm-up; layouts: "
          + ", ".join(f"{p} {'channels-last' if layout(args, device, PRECISIONS[p]) == torch.channels_last else 'contiguous'}"
                      for p in args.precisions))
    precisions = [PRECISIONS[p] for p in args.precisions]
    amp = precisions[1:]
    eft_fp32 = {}
    for p in amp:
        error = eft_amp_error(p, device)
        eft_fp32[p.name] = error is not None
        if error:
            print(f"EFT under {p.name} autocast on {device.type}: {error}; in {p.name} steps it runs in fp32 "
                  f"(autocast off, features cast up)")
    batch = to_device(synthetic_batch(args.batch, H, W, R), device)
    rows = []  # (what, GFLOP per image or None, {precision: value}, higher_is_better, {precision: peak GiB})

    for stage in args.stages:
        frontal = frozen_nets(stage, args.width, device)
        values, peaks = {}, {}
        for p in precisions:
            t0 = time.perf_counter()
            seconds, peak = bench_stage(stage, p, batch, frontal, args, device, R, eft_fp32.get(p.name, False))
            values[p.name], peaks[p.name] = args.batch / seconds, peak
            print(f"  {stage:<9} {p.name}: {values[p.name]:8.3f} images/s  ({seconds:.2f} s/step"
                  + (f", peak {peak:.1f} GiB" if peak is not None else "")
                  + f"; measured in {time.perf_counter() - t0:.0f} s)", flush=True)
        rows.append((f"{stage}: training step, images/s", step_flops(stage, args.width, H, W, R) / 1e9,
                     values, True, peaks))
        del frontal

    eft_rows = []  # (precision, mode, reference ms, new ms)
    if not args.no_eft:
        for p in precisions:
            e = bench_eft(p, batch, args, device, R, eft_fp32.get(p.name, False))
            for grad, label in ((False, "forward (no_grad)"), (True, "forward + backward")):
                ref, new = e["reference", grad], e["new", grad]
                eft_rows.append((p.name, label, ref, new))
                print(f"  EFT {label} {p.name}: {new:.0f} ms/batch ({1000 * args.batch / new:.3g} images/s), "
                      f"reference {ref:.0f} ms/batch ({1000 * args.batch / ref:.3g} images/s): "
                      f"{ref / new:.2f}x faster", flush=True)
            print(f"  EFT {p.name}: outputs differ from the reference's by <= {e['out']:.2g}, "
                  f"gradients by <= {e['grad']:.2g}", flush=True)
        for grad, label in ((False, "EFT forward (no_grad), ms/batch"),
                            (True, "EFT forward + backward, ms/batch")):
            mode = "forward (no_grad)" if not grad else "forward + backward"
            rows.append((label, None, {name: n for name, m, _, n in eft_rows if m == mode}, False, {}))

    cuda = device.type == "cuda"
    head = ["measure", "GFLOP/image"] + [p.name for p in precisions] + [f"{p.name} ÷ fp32" for p in amp]
    if cuda:
        head += [f"peak GiB {p.name}" for p in precisions]
    print()
    print("| " + " | ".join(head) + " |")
    print("| " + " | ".join("---" for _ in head) + " |")
    for what, gflop, values, higher, peaks in rows:
        fp32 = values["fp32"]
        cells = [what, f"{gflop:.3g}" if gflop is not None else "–"]
        cells += [f"{values[p.name]:.3g}" if higher else f"{values[p.name]:.0f}" for p in precisions]
        cells += [f"{(values[p.name] / fp32 if higher else fp32 / values[p.name]):.2f}×" for p in amp]
        if cuda:
            cells += [f"{peaks[p.name]:.1f}" if peaks.get(p.name) is not None else "–" for p in precisions]
        print("| " + " | ".join(cells) + " |")
    print("(ratios: AMP's speed-up over fp32 in this run, > 1 = faster; GFLOP/image: one training step's "
          "convolutions and matrix products)")
    for what, gflop, values, _, _ in rows:
        if gflop is not None:
            print(f"  {what.split(':')[0]}: fp32 reaches {gflop * values['fp32']:.3g} GFLOP/s")

    if eft_rows:
        print()
        print(f"| EFT, batch {args.batch}, {W}x{H} -> {R}x{R} | precision | reference ms/batch | "
              f"new ms/batch | reference images/s | new images/s | new ÷ reference |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for name, mode, ref, new in eft_rows:
            print(f"| {mode} | {name} | {ref:.0f} | {new:.0f} | {1000 * args.batch / ref:.3g} | "
                  f"{1000 * args.batch / new:.3g} | {ref / new:.2f}× |")
        print(f"(medians of {args.eft_steps} calls each, in two rounds of alternating blocks; "
              f"ratio > 1: the new EFT is faster)")

    if args.eft_baseline:
        ours, base = bench_eft_baseline(batch, args, device, R)
        print(f"EFT volume transfers, fp32 forward + backward: sceneforge {ours:.0f} ms/batch, "
              f"gather + index_add baseline {base:.0f} ms/batch: {base / ours:.2f}× faster")


if __name__ == "__main__":
    main()
