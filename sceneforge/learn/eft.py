"""The Epipolar Feature Transformer: frontal feature maps → the overhead view (docs/spec.md §10.3).

Frames and conventions are those of :mod:`sceneforge.conventions`; what the EFT needs
of them:

- The frontal camera is a pinhole camera with OpenCV axes; ``K`` is given for the feature
  map's resolution (:func:`scale_intrinsics` adapts it), pixel centres at integer + 0.5.
  The ray of pixel ``(i, j)`` is ``X(z) = z · K⁻¹ (j + 0.5, i + 0.5, 1)ᵀ`` in camera
  coordinates, ``z`` its planar depth.
- The overhead camera is :class:`sceneforge.overhead.OverheadCamera` (orthographic, OpenCV
  axes, z = straight down, half-extent ``e`` metres, ``R × R`` pixels): a point with
  overhead-camera coordinates ``(x, y, z)`` falls in the pixel that
  :func:`sceneforge.conventions.overhead_pixel` gives, at overhead depth ``z``
  (``tests/test_eft.py`` pins this to ``OverheadCamera.project``). ``floor_depth`` is the
  overhead depth of the floor (the camera's ``tz``). ``R`` is the stores' overhead
  resolution: the data's, given to the transformer, not a setting of it.

The transform *(paper §4, ref)* spreads every frontal pixel's feature vector along the
overhead image of a segment of its ray:

- **volume** gating: the segment ``(Da, Db)`` (``(D1, D2)`` or ``(D3, D4)``) is clipped to
  the overhead image and sampled at the midpoints of ``n = ceil(L · samples_per_pixel)``
  equal parts, ``L`` its length in overhead pixels along the major axis — the density of
  the reference's Bresenham lines. Every overhead pixel a sample falls in receives the
  feature once (weight 1 per ray and pixel); the output is the mean over the rays that
  reach a pixel, 0 where none does.
- **surface** gating: only the points ``Da`` and ``Db`` are projected and each overhead
  pixel keeps the feature of the highest point (smallest overhead depth; ties: lowest
  frontal pixel index) — the paper's z-buffer.

How it is computed. Both gatings are the same operation: every overhead pixel of a
segment set takes the mean (volume) or the one entry (surface) of a *bag* of frontal
pixels, so a transfer is an ``embedding_bag`` — a gather and a sum per pixel, no atomic
scatter, no sparse matrix — over the pairs sorted by overhead pixel, one call per feature
map (the frontal nets' channels-last maps are row tables as they are), its rows copied
into the assembled image's channels; its backward is another ``embedding_bag`` over the
same pairs grouped by ray (:class:`Bags`). The pairs of both segment sets are found once
per batch, vectorised over the batch and every ray: the segments are grouped by their
sample count into buckets a quarter of an octave wide and each bucket is sampled as dense
``(segments, n)`` blocks (no per-sample gather); the pairs of one ray come out in sample
order, where consecutive duplicates are the only duplicates (a straight line's rows and
columns are monotone). At most ``max_samples`` samples are held at a time. What depends
only on the cameras (the rays' interval inside the overhead square, the frustum mask) is
computed once per :class:`EpipolarGeometry` and kept on it, what depends only on the grid
(pixel centres, sample offsets) once per size and device, and the D1–D4 points are
projected once for the best guess and surface gating. Under ``torch.no_grad`` (the frozen
nets' features of the overhead stage) nothing for the backward is built.

The geometry — rays, clipping, sample positions, pixel indices — is computed in float64 by
the same separate operations on every device, so CPU and GPU pick the same overhead
pixels; the features are gathered in their own dtype (float16 / bfloat16 under AMP on a
GPU, where the kernel sums in float32; float32 on the CPU, which has no fast half
arithmetic) and the output is differentiable with respect to them (not the depths).
``torch.compile`` is not used: on the CPU it fuses the sampling's float64 arithmetic
(Inductor keeps multiplies and adds apart there), but compiling costs ~20 s per process
for ~15 ms a batch, and Triton fuses multiplies and adds by default (``enable_fp_fusion``),
which would let a GPU pick other pixels than the CPU.

The previous implementation — a sparse COO matrix ``A`` per transfer (``G = A F``, its
transpose as CSR for the backward) over pairs sorted by (frontal pixel, overhead pixel) —
is kept as the reference: ``reference=True`` on :func:`transfer_volume`,
:func:`transfer_surface`, :func:`best_guess_height` and :class:`EpipolarFeatureTransformer`.
The tests compare the two, forward and backward; ``benchmarks/bench_learn.py`` times them
side by side.

Also here: the **frustum mask** (the transform of a constant 1 along whole rays, computed
exactly per overhead pixel as "the vertical segment between the overhead camera and the
floor meets the frontal view frustum") and the **best-guess height** (z-buffer of the
D1–D4 points, as height above the floor, 0 where no point lands). :class:`EpipolarFeatureTransformer`
assembles the overhead nets' input: best guess (1) + frustum mask (1) + for ``(D1, D2)``
then ``(D3, D4)``: RGB (3) + depth features + segmentation features, which is
1 + 1 + 2 × (3 + 48 + 64) = 232 channels at the paper's widths.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from sceneforge.conventions import OBJECT_SEGMENTS, overhead_pixel, overhead_pixel_centre, tol

from .config import EFTConfig  # defined without torch, for the CLI and the schema


@dataclass(frozen=True, eq=False)
class EpipolarGeometry:
    """Frontal rays expressed in the overhead camera, for a batch of views.

    origin      : (B, 3) float64      frontal camera centre, overhead-camera coordinates (m)
    directions  : (B, H*W, 3) float64 per frontal pixel (row-major), the ray point at planar
                  depth z is ``origin + z * direction``
    extent      : (B,) float64        overhead half-extent e (m)
    floor_depth : (B,) float64        overhead depth of the floor (m)
    resolution  : int                 overhead pixels per side
    frontal_hw  : (H, W)              frontal feature map size
    K, cam_to_world, overhead_cam_to_world : the inputs, float64, for the frustum mask
    cache       : what depends only on these cameras, computed on first use and shared by
                  every transfer of the batch (:func:`ray_box`, :func:`frustum_mask`)
    """

    origin: Tensor
    directions: Tensor
    extent: Tensor
    floor_depth: Tensor
    resolution: int
    frontal_hw: tuple[int, int]
    K: Tensor
    cam_to_world: Tensor
    overhead_cam_to_world: Tensor
    cache: dict = field(default_factory=dict, repr=False)

    @property
    def batch(self) -> int:
        return self.origin.shape[0]

    @property
    def device(self) -> torch.device:
        return self.origin.device


def scale_intrinsics(K: Tensor, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> Tensor:
    """(..., 3, 3) intrinsics of an image of ``from_hw`` pixels → the same camera at ``to_hw``.

    Pixel edges scale with the image, so centres stay at integer + 0.5.
    """
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    scale = torch.tensor([[sx], [sy], [1.0]], dtype=K.dtype, device=K.device)
    return K * scale


@functools.lru_cache(maxsize=16)
def _pixel_centres(H: int, W: int, device: torch.device) -> Tensor:
    """(H·W, 3) float64 ``(j + ½, i + ½, 1)`` of every frontal pixel, row-major; one per grid
    and device, shared: read only."""
    f64 = dict(dtype=torch.float64, device=device)
    v, u = torch.meshgrid(torch.arange(H, **f64) + 0.5, torch.arange(W, **f64) + 0.5, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(H * W, **f64)], dim=1)


def epipolar_geometry(
    K: Tensor,
    cam_to_world: Tensor,
    overhead_cam_to_world: Tensor,
    overhead_extent: Tensor,
    floor_depth: Tensor,
    frontal_hw: tuple[int, int],
    resolution: int,
) -> EpipolarGeometry:
    """Express the rays of an ``H × W`` frontal feature map in the overhead camera.

    K                     : (B, 3, 3)  frontal intrinsics at the feature map's resolution
    cam_to_world          : (B, 4, 4)  frontal pose, OpenCV axes
    overhead_cam_to_world : (B, 4, 4)  overhead pose, OpenCV axes (z = down)
    overhead_extent       : (B,)       overhead half-extent, metres
    floor_depth           : (B,)       overhead depth of the floor (``tz``), metres
    """
    f64 = dict(dtype=torch.float64)
    K, T, To = (torch.as_tensor(a).to(**f64) for a in (K, cam_to_world, overhead_cam_to_world))
    device = K.device
    T, To = T.to(device), To.to(device)
    extent = torch.as_tensor(overhead_extent, device=device).to(**f64).reshape(-1)
    floor = torch.as_tensor(floor_depth, device=device).to(**f64).reshape(-1)
    B = K.shape[0]
    if K.shape != (B, 3, 3) or T.shape != (B, 4, 4) or To.shape != (B, 4, 4):
        raise ValueError(f"K, cam_to_world, overhead_cam_to_world must be (B,3,3), (B,4,4), (B,4,4); "
                         f"got {tuple(K.shape)}, {tuple(T.shape)}, {tuple(To.shape)}")
    if extent.shape != (B,) or floor.shape != (B,):
        raise ValueError(f"overhead_extent and floor_depth must be ({B},), "
                         f"got {tuple(extent.shape)} and {tuple(floor.shape)}")
    H, W = frontal_hw
    pix = _pixel_centres(int(H), int(W), device)
    d_cam = pix @ torch.linalg.inv(K).transpose(1, 2)  # (B, HW, 3), z = 1
    R_o = To[:, :3, :3]
    rot = R_o.transpose(1, 2) @ T[:, :3, :3]  # frontal camera → overhead camera
    directions = d_cam @ rot.transpose(1, 2)
    origin = ((T[:, :3, 3] - To[:, :3, 3]).unsqueeze(1) @ R_o).squeeze(1)
    return EpipolarGeometry(origin, directions, extent, floor, int(resolution), (int(H), int(W)),
                            K, T, To)


def _valid_depth(d: Tensor) -> Tensor:
    return torch.isfinite(d) & (d > 0)


# ------------------------------------------------------------- per camera set


def ray_box(geom: EpipolarGeometry) -> tuple[Tensor, Tensor]:
    """Each ray's planar-depth interval ``[zlo, zhi]`` inside the overhead square (x and y
    within ±e; Liang–Barsky), computed once per geometry.

    Returns zlo, zhi : (B, H*W) float64; ``zlo > zhi`` where the ray misses the square.
    Clipping a segment ``[z0, z1]`` to it is ``[max(z0, zlo), min(z1, zhi)]``: the same
    numbers as clipping it to the box directly.
    """
    if "ray_box" not in geom.cache:
        o, d = geom.origin[:, None, :2], geom.directions[..., :2]
        e = geom.extent.view(-1, 1, 1)
        flat = d.abs() < tol.clip_slope
        safe = torch.where(flat, torch.ones_like(d), d)
        za, zb = (-e - o) / safe, (e - o) / safe
        zlo = torch.where(flat, -torch.inf, torch.minimum(za, zb)).amax(dim=2)
        zhi = torch.where(flat, torch.inf, torch.maximum(za, zb)).amin(dim=2)
        miss = (flat & ((o < -e) | (o > e))).any(dim=2)
        geom.cache["ray_box"] = zlo.masked_fill(miss, torch.inf), zhi.masked_fill(miss, -torch.inf)
    return geom.cache["ray_box"]


@functools.lru_cache(maxsize=16)
def _overhead_centres(R: int, device: torch.device) -> Tensor:
    """(R·R, 2) float64 ``(x, y)`` of the overhead pixel centres for a half-extent of 1,
    row-major; one per grid and device, shared: read only."""
    c = overhead_pixel_centre(torch.arange(R, dtype=torch.float64, device=device), 1.0, R)
    y, x = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], dim=1)


def frustum_mask(geom: EpipolarGeometry) -> Tensor:
    """(B, 1, R, R) float32: 1 where the vertical segment through the overhead pixel centre,
    from the overhead camera (depth 0) down to the floor (``floor_depth``), meets the
    frontal view frustum (in front of the camera, inside the image's edges); else 0.

    This is the transform of a constant 1 along whole rays, evaluated exactly per overhead
    pixel instead of by rasterising every ray. Computed once per geometry (read only).
    """
    if "frustum_mask" not in geom.cache:
        geom.cache["frustum_mask"] = _frustum_mask(geom)
    return geom.cache["frustum_mask"]


def _frustum_mask(geom: EpipolarGeometry) -> Tensor:
    B, R, (H, W) = geom.batch, geom.resolution, geom.frontal_hw
    f64 = dict(dtype=torch.float64, device=geom.device)
    xy = _overhead_centres(R, geom.device).unsqueeze(0) * geom.extent.view(B, 1, 1)
    # the vertical segment in the overhead frame: (x, y, s · floor_depth), s ∈ [0, 1]; its
    # step is the same for every pixel, and so are its image-plane terms (aq)
    start = torch.cat([xy, torch.zeros_like(xy[..., :1])], dim=2)
    step = torch.zeros_like(start[:, :1])
    step[..., 2] = geom.floor_depth.view(B, 1)
    # → frontal camera coordinates, then image-plane constraints a · X ≥ 0
    Ro, to = geom.overhead_cam_to_world[:, :3, :3], geom.overhead_cam_to_world[:, :3, 3]
    Rf, tf = geom.cam_to_world[:, :3, :3], geom.cam_to_world[:, :3, 3]
    rot = Rf.transpose(1, 2) @ Ro
    shift = ((to - tf).unsqueeze(1) @ Rf)
    p0 = start @ rot.transpose(1, 2) + shift
    q = step @ rot.transpose(1, 2)
    K = geom.K
    uvw0, uvwq = p0 @ K.transpose(1, 2), q @ K.transpose(1, 2)
    # u ≥ 0, u ≤ W z, v ≥ 0, v ≤ H z, z ≥ 0 as a · (u, v, z) ≥ 0 along the segment
    planes = torch.tensor([[1, 0, 0], [-1, 0, W], [0, 1, 0], [0, -1, H], [0, 0, 1]], **f64)
    a0 = uvw0 @ planes.T  # (B, RR, 5)
    aq = uvwq @ planes.T
    s_lo = torch.zeros(a0.shape[:2], **f64)
    s_hi = torch.ones(a0.shape[:2], **f64)
    flat = aq.abs() < tol.clip_slope
    safe = torch.where(flat, torch.ones_like(aq), aq)
    root = -a0 / safe
    s_lo = torch.maximum(s_lo, torch.where(~flat & (aq > 0), root, -torch.inf).amax(dim=2))
    s_hi = torch.minimum(s_hi, torch.where(~flat & (aq < 0), root, torch.inf).amin(dim=2))
    inside = (s_lo <= s_hi) & ~(flat & (a0 < 0)).any(dim=2)
    return inside.reshape(B, 1, R, R).float()


# ------------------------------------------------------------------ bags


@dataclass(frozen=True, eq=False)
class Bags:
    """S transfers (segment sets) as bags. Key ``s·n_dst + pixel`` names overhead pixel
    ``pixel`` (flattened over B·R·R) of transfer ``s``; bag ``r`` gives key ``keys_hit[r]``
    the mean (``mode="mean"``) or the sum of the frontal feature rows
    ``index[offsets[r]:offsets[r + 1]]``. Keys without a bag receive 0.

    Integer tensors are int32 where the sizes allow (``embedding_bag`` takes int32 or int64
    indices, the same for both).

    n_src, n_dst, sets : frontal pixels (B·H·W), overhead pixels (B·R·R), transfers S
    keys_hit : (n,) int64 the key of each bag, increasing
    index    : (P,) frontal pixel of every pair, grouped by bag (the forward)
    offsets  : (n + 1,) start of each bag's pairs in ``index``
    keys     : (P,) the key of every pair in the order the pairs were made: grouped by
               ray segment (one *entry*), the backward's bags
    entry_offsets : (M + 1,) start of each entry's pairs in ``keys``
    entry_src     : (M,) int64 the frontal pixel of each entry
    mode     : "mean" (volume gating) or "sum" (surface gating: one pair per bag)
    cache    : the pairs' weights per dtype (:meth:`forward` on the CPU)
    """

    n_src: int
    n_dst: int
    sets: int
    keys_hit: Tensor
    index: Tensor
    offsets: Tensor
    keys: Tensor
    entry_offsets: Tensor
    entry_src: Tensor
    mode: str
    cache: dict = field(default_factory=dict, repr=False)

    def forward(self, table: Tensor, span: tuple[int, int] | None = None) -> Tensor:
        """(n_src, c) features → (n, c) one row per bag (``span = (a, b)``: bags a to b - 1),
        same dtype (half on a GPU sums in float32)."""
        index, offsets, start, end = self.index, self.offsets, 0, len(self.index)
        if span is not None:
            offsets = offsets[span[0]:span[1] + 1]
            start, end = offsets[[0, -1]].tolist()
            index, offsets = index[start:end], offsets - start
        table = table.detach()  # embedding_bag's backward bookkeeping is for weights that need grad
        if table.device.type == "cpu":
            # the CPU's unweighted kernels keep a bag index per pair for a backward; the
            # weighted sum (1 / bag size for the mean) does not: two thirds of the time
            return F.embedding_bag(index, table, offsets, mode="sum", include_last_offset=True,
                                   per_sample_weights=self._weights(table.dtype)[start:end])
        return F.embedding_bag(index, table, offsets, mode=self.mode, include_last_offset=True)

    def _weights(self, dtype: torch.dtype) -> Tensor:
        """(P,) each pair's weight in ``index`` order, 1 / its bag's size for the mean, 1 for
        the sum; made once per dtype."""
        if dtype not in self.cache:
            if self.mode == "mean":
                size = self.offsets[1:] - self.offsets[:-1]
                weight = torch.repeat_interleave(size.to(dtype).reciprocal_(), size, output_size=len(self.index))
            else:
                weight = torch.ones(len(self.index), dtype=dtype, device=self.index.device)
            self.cache[dtype] = weight
        return self.cache[dtype]

    def backward(self, grad: Tensor) -> Tensor:
        """(n, C) gradient of the bags' rows → (n_src, C) gradient of the features: per entry
        the sum over its pairs (weighted by 1 / bag size for the mean), then the entries of
        each frontal pixel (one per transfer) added."""
        bag = torch.full((self.sets * self.n_dst,), -1, dtype=self.keys.dtype, device=grad.device)
        bag[self.keys_hit] = torch.arange(len(self.keys_hit), dtype=bag.dtype, device=bag.device)
        bag = bag[self.keys]
        weight = None
        if self.mode == "mean":
            size = (self.offsets[1:] - self.offsets[:-1]).to(grad.dtype)
            weight = size.reciprocal_()[bag]
        per_entry = F.embedding_bag(bag, grad, self.entry_offsets, mode="sum", per_sample_weights=weight,
                                    include_last_offset=True)
        return grad.new_zeros(self.n_src, grad.shape[1]).index_add_(0, self.entry_src, per_entry)

    def blocks(self) -> list[tuple[int, int]]:
        """The bags of each transfer: ``(start, end)`` per s."""
        bounds = torch.arange(self.sets + 1, device=self.keys_hit.device) * self.n_dst
        edges = torch.searchsorted(self.keys_hit, bounds).tolist()
        return list(zip(edges[:-1], edges[1:]))


def _index_dtype(*sizes: int) -> torch.dtype:
    return torch.int32 if max(sizes) < 2**31 else torch.int64


def _offsets(counts: Tensor, dtype: torch.dtype) -> Tensor:
    """(n,) counts → (n + 1,) offsets ``[0, c0, c0 + c1, …]``."""
    return torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)]).to(dtype)


class _Transfer(torch.autograd.Function):
    """The overhead image of the S transfers of ``bags``, channels-last: ``(B·R·R, K + S·C)``
    in the dtype of ``fixed``, its K channels first (no gradient), then per transfer the
    channels of every feature table in turn (C in all), 0 where the transfer has no bag.
    Each table (n_src, c) is gathered by its own ``embedding_bag`` per transfer: the frontal
    nets' channels-last maps are such tables as they are, with no concatenation, and the
    bags' rows stay small. Backward: the bags' rows gathered from the gradient, then
    :meth:`Bags.backward`."""

    @staticmethod
    def forward(ctx, bags: Bags, fixed: Tensor, *tables: Tensor) -> Tensor:
        K, widths = fixed.shape[1], [t.shape[1] for t in tables]
        C = sum(widths)
        out = fixed.new_zeros(bags.n_dst, K + bags.sets * C)
        out[:, :K] = fixed
        blocks = bags.blocks()
        for s, (a, b) in enumerate(blocks):
            pixels, start = bags.keys_hit[a:b] - s * bags.n_dst, K + s * C
            for table, width in zip(tables, widths):
                rows = bags.forward(table, (a, b)).to(out.dtype)
                out[:, start:start + width].index_copy_(0, pixels, rows)
                start += width
        ctx.bags, ctx.blocks, ctx.K, ctx.C = bags, blocks, K, C
        ctx.widths, ctx.dtypes = widths, [t.dtype for t in tables]
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        bags, K, C = ctx.bags, ctx.K, ctx.C
        if grad.stride(1) != 1:  # an NCHW gradient: rows are gathered from channels-last
            grad = grad.contiguous()
        rows = grad.new_empty(len(bags.keys_hit), C)
        for s, (a, b) in enumerate(ctx.blocks):
            torch.index_select(grad[:, K + s * C:K + (s + 1) * C], 0, bags.keys_hit[a:b] - s * bags.n_dst,
                               out=rows[a:b])
        per_src = bags.backward(rows)
        grads, start = [], 0
        for width, dtype in zip(ctx.widths, ctx.dtypes):
            grads.append(per_src[:, start:start + width].to(dtype))
            start += width
        return None, None, *grads


def _flat(features: Tensor) -> Tensor:
    """(B, C, H, W) → (B·H·W, C) contiguous: a view of a channels-last map, else a copy."""
    return features.permute(0, 2, 3, 1).reshape(-1, features.shape[1])


def _unflat(flat: Tensor, B: int, R: int) -> Tensor:
    """(B·R·R, C) → (B, C, R, R), channels-last in memory."""
    return flat.reshape(B, R, R, -1).permute(0, 3, 1, 2)


def _transfer(tables: list[Tensor], bags: Bags, fixed: Tensor | None, B: int, R: int) -> Tensor:
    """(B·H·W, c) feature tables → (B, K + S·C, R, R) channels-last, the ``fixed`` (B·R·R, K) first."""
    if fixed is None:
        fixed = tables[0].new_zeros(B * R * R, 0)
    return _unflat(_Transfer.apply(bags, fixed, *tables), B, R)


# ------------------------------------------------------------- volume gating


def _segment_entries(geom: EpipolarGeometry, segments, samples_per_pixel: float):
    """The ray segments of S segment sets clipped to the overhead square: one *entry* per
    set and frontal pixel (in that order) where both ends are finite and > 0 and the
    segment meets the square.

    segments : S pairs ``(near, far)`` of (B, H, W) planar depths (order free)
    Returns src (M,) frontal pixel (flattened over B·H·W), base (M,) float64 the key of its
    set's overhead pixel (0, 0) (``s·B·R² + b·R²``), uv0 and duv (M, 2) float64 the clipped
    segment in overhead pixels, n (M,) int64 its samples.
    """
    B, (H, W), R = geom.batch, geom.frontal_hw, geom.resolution
    zlo, zhi = (z.reshape(-1) for z in ray_box(geom))
    directions = geom.directions.reshape(-1, 3)[:, :2]
    parts = []
    for s, (near, far) in enumerate(segments):
        near = near.detach().to(geom.device, torch.float64).reshape(-1)
        far = far.detach().to(geom.device, torch.float64).reshape(-1)
        z0 = torch.maximum(torch.minimum(near, far), zlo)
        z1 = torch.minimum(torch.maximum(near, far), zhi)
        src = (_valid_depth(near) & _valid_depth(far) & (z0 <= z1)).nonzero().squeeze(1)
        z0, z1, b = z0[src], z1[src], src // (H * W)
        o, d, e = geom.origin[b, :2], directions[src], geom.extent[b].unsqueeze(1)
        uv0 = overhead_pixel(o + z0.unsqueeze(1) * d, e, R)
        duv = overhead_pixel(o + z1.unsqueeze(1) * d, e, R) - uv0
        n = torch.ceil(duv.abs().amax(dim=1) * samples_per_pixel).clamp(min=1).long()
        parts.append((src, ((s * B + b) * (R * R)).to(torch.float64), uv0, duv, n))
    return tuple(torch.cat(p) for p in zip(*parts))


def _bucket_sizes(largest: int) -> list[int]:
    """Sample counts of the buckets: 1..8, then four per octave (10, 12, 14, 16, 20, …)."""
    sizes, step = list(range(1, 9)), 2
    while sizes[-1] < largest:
        sizes += [sizes[-1] + step * k for k in range(1, 5)]
        step *= 2
    return sizes


@functools.lru_cache(maxsize=16)
def _sample_offsets(n: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """``k + ½`` (float64) and ``k`` (int64) for k < n; one per length and device, read only."""
    k = torch.arange(n, device=device)
    return k.to(torch.float64) + 0.5, k


def _sample_segments(src: Tensor, base: Tensor, uv0: Tensor, duv: Tensor, n: Tensor, R: int,
                     n_keys: int, max_samples: int):
    """Sample every entry's segment ``uv0 + t · duv`` (overhead pixels) at ``t = (k + ½) / n``,
    k < n, and keep each overhead pixel once per entry: its key is ``base + row · R + col``.

    Entries are grouped by sample count into buckets (:func:`_bucket_sizes`), each sampled
    as dense ``(entries, N)`` blocks of at most ``max_samples`` samples. Returns the pairs'
    frontal pixels and keys (P,) grouped by entry, the entries' pair counts (M,) and frontal
    pixels (M,); entries in bucket order, in entry order within a bucket.

    Every float64 step is a separate multiply, add or divide (no fused multiply-add) and
    the pixel is ``floor`` of the coordinate clamped to the image (a truncation of the
    clamped value), the same numbers on every device and as the reference's
    (:func:`_rasterise`).
    """
    device = src.device
    dtype = _index_dtype(n_keys, int(src.max()) + 1 if len(src) else 1)
    sizes = _bucket_sizes(int(n.max()) if len(n) else 1)
    bucket = torch.searchsorted(torch.tensor(sizes, device=device), n).to(dtype)
    order = torch.argsort(bucket, stable=True)
    counts = torch.bincount(bucket, minlength=len(sizes)).tolist()
    # per entry, in bucket order: samples, start, step, key of its image's pixel (0, 0)
    table = torch.cat([n.unsqueeze(1).to(torch.float64), uv0, duv, base.unsqueeze(1)], dim=1)[order]
    entry_src = src.to(dtype)[order]
    half_k, k = _sample_offsets(sizes[-1], device)
    out_keys, out_counts = [], []
    a = 0
    for N, count in zip(sizes, counts):
        step = max(1, max_samples // N)
        for c in range(a, a + count, step):
            e = table[c:min(c + step, a + count)]
            t = half_k[:N] / e[:, :1]
            col = (t * e[:, 3:4]).add_(e[:, 1:2]).clamp_(0, R - 1).to(dtype)
            row = t.mul_(e[:, 4:5]).add_(e[:, 2:3]).clamp_(0, R - 1).to(dtype)
            keys = torch.add(col, row, alpha=R).add_(e[:, 5:6].to(dtype))
            keep = k[:N] < e[:, :1]
            keep[:, 1:] &= keys[:, 1:] != keys[:, :-1]
            out_keys.append(keys.masked_select(keep))
            out_counts.append(torch.count_nonzero(keep, dim=1))
        a += count
    if not out_keys:
        empty = torch.zeros(0, dtype=dtype, device=device)
        return empty, empty, empty.long(), empty.long()
    kept = torch.cat(out_counts)
    return torch.repeat_interleave(entry_src, kept), torch.cat(out_keys), kept, entry_src.long()


def volume_bags(geom: EpipolarGeometry, segments, config: EFTConfig | None = None) -> Bags:
    """The bags of volume gating of S segment sets, all sampled together.

    segments : S pairs ``(near, far)`` of (B, H, W) planar depths, NaN = no segment
    """
    config = config or EFTConfig()
    B, (H, W), R, S = geom.batch, geom.frontal_hw, geom.resolution, len(segments)
    n_dst = B * R * R
    src, base, uv0, duv, n = _segment_entries(geom, segments, config.samples_per_pixel)
    pair_src, keys, entry_counts, entry_src = _sample_segments(src, base, uv0, duv, n, R, S * n_dst,
                                                               config.max_samples)
    dtype = _index_dtype(B * H * W, S * n_dst, len(keys) + 1)
    keys = keys.to(dtype)
    sorted_keys, order = torch.sort(keys, stable=True)  # stable: the same sums in the same order
    keys_hit, counts = torch.unique_consecutive(sorted_keys, return_counts=True)
    return Bags(B * H * W, n_dst, S, keys_hit.long(), pair_src.to(dtype)[order], _offsets(counts, dtype),
                keys, _offsets(entry_counts, dtype), entry_src, "mean")


# ----------------------------------------------------------- points: surface, best guess


def layer_points(geom: EpipolarGeometry, depth: Tensor) -> tuple[Tensor, Tensor]:
    """Project every frontal point of ``depth`` into the overhead image (dense: no list of
    points, the same pixels and depths as :func:`point_hits`).

    depth : (B, L, H, W) planar depths; points with a finite depth > 0 take part
    Returns ``dst`` (B, L, H*W) int64, the overhead pixel flattened over B·R·R (B·R·R where
    the point is missing or lands outside), and ``z`` (B, L, H*W) float64 its overhead
    depth (inf there).
    """
    B, (H, W), R = geom.batch, geom.frontal_hw, geom.resolution
    z = depth.detach().to(geom.device, torch.float64).reshape(B, -1, H * W)
    inside = _valid_depth(z)
    z = torch.where(inside, z, 0.0)

    def coordinate(k):  # origin + z · direction, one axis at a time
        return (z * geom.directions[..., k].unsqueeze(1)).add_(geom.origin[:, k].view(B, 1, 1))

    e = geom.extent.view(B, 1, 1)
    col, row = (overhead_pixel(coordinate(k), e, R) for k in (0, 1))
    inside &= (col >= 0) & (col < R) & (row >= 0) & (row < R)  # as floor(col) in [0, R)
    b = torch.arange(B, device=geom.device).view(B, 1, 1)
    dst = torch.where(inside, (row.floor_().long() + b * R) * R + col.floor_().long(), B * R * R)
    return dst, torch.where(inside, coordinate(2), torch.inf)


def _top(dst: Tensor, z: Tensor, n_dst: int) -> Tensor:
    """(n_dst + 1,) the smallest ``z`` landing in each overhead pixel (inf where none; the
    last slot collects the points that land nowhere)."""
    top = torch.full((n_dst + 1,), torch.inf, dtype=z.dtype, device=z.device)
    return top.scatter_reduce_(0, dst.reshape(-1), z.reshape(-1), reduce="amin")


def surface_bags(geom: EpipolarGeometry, dst: Tensor, z: Tensor, sets) -> Bags:
    """The bags of surface gating of S sets of layers: each overhead pixel takes the highest
    of a set's points (smallest z; ties: lowest frontal pixel index).

    dst, z : (B, L, H*W) from :func:`layer_points`; sets : S tuples of layer indices
    """
    B, (H, W), R = geom.batch, geom.frontal_hw, geom.resolution
    n_dst, big = B * R * R, torch.iinfo(torch.long).max
    winners = []
    for layers in sets:
        d, zz = dst[:, list(layers)], z[:, list(layers)]
        src = torch.arange(B * H * W, device=geom.device).view(B, 1, H * W).expand_as(d)
        best = torch.where(zz == _top(d, zz, n_dst)[d], d, n_dst)
        winner = torch.full((n_dst + 1,), big, dtype=torch.long, device=geom.device)
        winners.append(winner.scatter_reduce_(0, best.reshape(-1), src.reshape(-1), reduce="amin")[:n_dst])
    winner = torch.cat(winners)
    keys_hit = (winner != big).nonzero().squeeze(1)
    dtype = _index_dtype(len(sets) * n_dst, B * H * W, len(keys_hit) + 1)
    index, ones = winner[keys_hit], torch.ones_like(keys_hit)
    return Bags(B * H * W, n_dst, len(sets), keys_hit, index.to(dtype), _offsets(ones, dtype),
                keys_hit.to(dtype), _offsets(ones, dtype), index, "sum")


def _height(geom: EpipolarGeometry, top: Tensor) -> Tensor:
    """(B·R·R,) float32 height above the floor of the z-buffer ``top`` (B·R·R,), 0 where inf."""
    floor = geom.floor_depth.repeat_interleave(geom.resolution ** 2)
    return torch.where(torch.isfinite(top), floor - top, 0.0).float()


# -------------------------------------------------------------- public transfers


def transfer_volume(features: Tensor, geom: EpipolarGeometry, near: Tensor, far: Tensor,
                    config: EFTConfig | None = None, *, reference: bool = False) -> Tensor:
    """Volume gating: mean of the features of the rays whose ``(near, far)`` segment reaches
    each overhead pixel; 0 where none does.

    features  : (B, C, H, W) float  frontal feature map (differentiable)
    near, far : (B, H, W)           segment ends, planar depth (NaN = no segment)
    reference : the previous implementation (sparse matrices), for tests and benchmarks
    Returns (B, C, R, R), same dtype and device as ``features``, channels-last in memory.
    """
    if reference:
        return _reference_transfer_volume(features, geom, near, far, config)
    bags = volume_bags(geom, [(near, far)], config)
    return _transfer([_flat(features)], bags, None, features.shape[0], geom.resolution)


def transfer_surface(features: Tensor, geom: EpipolarGeometry, points: Tensor, *,
                     reference: bool = False) -> Tensor:
    """Surface gating: each overhead pixel takes the feature of the highest point landing in it.

    features : (B, C, H, W) float  frontal feature map (differentiable)
    points   : (B, L, H, W)        planar depths of the points (e.g. D1 and D2), NaN = none
    reference : the previous implementation, for tests and benchmarks
    Returns (B, C, R, R), channels-last in memory; 0 where no point lands.
    """
    if reference:
        return _reference_transfer_surface(features, geom, points)
    bags = surface_bags(geom, *layer_points(geom, points), [tuple(range(points.shape[1]))])
    return _transfer([_flat(features)], bags, None, features.shape[0], geom.resolution)


def best_guess_height(geom: EpipolarGeometry, depth: Tensor, *, reference: bool = False) -> Tensor:
    """The frontal points' overhead height map: z-buffer of the ``depth`` points (D1–D4).

    depth : (B, L, H, W) planar depths, NaN = none
    Returns (B, 1, R, R) float32: height above the floor (``floor_depth`` − overhead depth)
    of the highest point per overhead pixel, 0 where no point lands.
    """
    if reference:
        return _reference_best_guess_height(geom, depth)
    B, R = geom.batch, geom.resolution
    dst, z = layer_points(geom, depth)
    return _height(geom, _top(dst, z, B * R * R)[:-1]).reshape(B, 1, R, R)


# ----------------------------------------------------------------------- module


class EpipolarFeatureTransformer(nn.Module):
    """Frontal RGB, features and layers + overhead camera → the overhead nets' input.

    resolution : the overhead image size R (square), from the data: the stores' overhead
                 resolution (``ViewIndex.shapes["Wo"]``)
    reference  : run the previous implementation (sparse matrices, one transfer at a
                 time), for tests and benchmarks; the same output up to float rounding

    forward(rgb (B, 3, H, W), depth_features (B, Cd, H, W), seg_features (B, Cs, H, W),
    depth (B, 4, H, W) planar D1..D4 with NaN where a layer is empty, geometry for R)
    returns (B, 2 + 2·(3 + Cd + Cs), R, R) float32 (float64 for float64 features): best-guess
    height, frustum mask, then the ``(D1, D2)`` and ``(D3, D4)`` transfers
    (``conventions.OBJECT_SEGMENTS``) of ``[rgb, depth_features, seg_features]`` (surface
    gating uses the segment ends as points). Its memory format is that of
    ``depth_features``: channels-last from the trainer's channels-last nets (the transfers
    write channels-last; the nets read it so), contiguous otherwise (one transposition).
    """

    def __init__(self, config: EFTConfig | None = None, *, resolution: int, reference: bool = False):
        super().__init__()
        if int(resolution) < 1:
            raise ValueError(f"resolution must be at least 1 pixel, got {resolution}")
        self.config = config or EFTConfig()
        self.resolution = int(resolution)
        self.reference = reference

    @staticmethod
    def out_channels(depth_features: int, seg_features: int) -> int:
        """Channels of the assembly: 232 for 48 depth and 64 segmentation features."""
        return 2 + 2 * (3 + depth_features + seg_features)

    def transfer(self, features: Tensor, geom: EpipolarGeometry, near: Tensor, far: Tensor) -> Tensor:
        """Carry ``features`` along the ``(near, far)`` segments with the configured gating."""
        if self.config.gating == "volume":
            return transfer_volume(features, geom, near, far, self.config, reference=self.reference)
        return transfer_surface(features, geom, torch.stack([near, far], dim=1), reference=self.reference)

    def forward(self, rgb: Tensor, depth_features: Tensor, seg_features: Tensor, depth: Tensor,
                geom: EpipolarGeometry) -> Tensor:
        B, _, H, W = rgb.shape
        for name, t in (("depth_features", depth_features), ("seg_features", seg_features)):
            if t.shape[0] != B or t.shape[2:] != (H, W):
                raise ValueError(f"{name} is {tuple(t.shape)}, expected (B={B}, C, {H}, {W})")
        if depth.shape != (B, 4, H, W):
            raise ValueError(f"depth must be (B, 4, H, W) = ({B}, 4, {H}, {W}), got {tuple(depth.shape)}")
        if geom.frontal_hw != (H, W) or geom.batch != B:
            raise ValueError(f"geometry is for {geom.batch} views of {geom.frontal_hw}, "
                             f"features are {B} of {(H, W)}")
        if geom.resolution != self.resolution:
            raise ValueError(f"geometry is for a {geom.resolution}-pixel overhead image, "
                             f"the transformer for {self.resolution}")
        dtype = torch.promote_types(torch.float32, torch.result_type(rgb, depth_features))
        with torch.autocast(rgb.device.type, enabled=False):
            if self.reference:
                return self._reference_forward(rgb, depth_features, seg_features, depth, geom, dtype)
            # the features are gathered in the nets' half precision on a GPU (its kernel sums
            # in float32); the CPU has no fast half arithmetic and gathers float32
            half = rgb.is_cuda and depth_features.dtype in (torch.float16, torch.bfloat16)
            work = depth_features.dtype if half else dtype
            tables = [_flat(t.to(work)) for t in (rgb, depth_features, seg_features)]  # views if channels-last
            dst, z = layer_points(geom, depth)
            height = _height(geom, _top(dst, z, B * self.resolution ** 2)[:-1])
            fixed = torch.stack([height, frustum_mask(geom).reshape(-1)], dim=1).to(dtype)
            if self.config.gating == "volume":
                bags = volume_bags(geom, [(depth[:, a], depth[:, b]) for a, b in OBJECT_SEGMENTS], self.config)
            else:
                bags = surface_bags(geom, dst, z, OBJECT_SEGMENTS)
            out = _transfer(tables, bags, fixed, B, self.resolution)  # channels-last
            channels_last = (depth_features.is_contiguous(memory_format=torch.channels_last)
                             and not depth_features.is_contiguous())
            return out if channels_last else out.contiguous()

    def _reference_forward(self, rgb, depth_features, seg_features, depth, geom, dtype) -> Tensor:
        """The previous assembly: one transfer at a time, then a concatenation."""
        features = torch.cat([rgb, depth_features, seg_features], dim=1).to(dtype)
        parts = [best_guess_height(geom, depth, reference=True), _frustum_mask(geom)]
        parts += [self.transfer(features, geom, depth[:, a], depth[:, b]) for a, b in OBJECT_SEGMENTS]
        return torch.cat([p.to(dtype) for p in parts], dim=1)


# ------------------------------------------------------------------ the reference
#
# The previous implementation, kept as the reference the tests compare against and the
# benchmark times beside the bags: per transfer, the (frontal pixel, overhead pixel) pairs
# sorted by frontal pixel, one uncoalesced COO matrix for the forward and a CSR transpose
# for the backward; the points as a list.


def _clip(origin: Tensor, direction: Tensor, z0: Tensor, z1: Tensor, lo: Tensor, hi: Tensor):
    """Clip ray pieces ``origin + z * direction``, ``z ∈ [z0, z1]``, to the box ``[lo, hi]``.

    origin, lo, hi : (n, 3); direction : (n, 3); z0, z1 : (n,)  (Liang–Barsky)
    Returns the clipped ``z0, z1`` (n,) and ``inside`` (n,) bool.
    """
    flat = direction.abs() < tol.clip_slope
    safe = torch.where(flat, torch.ones_like(direction), direction)
    za, zb = (lo - origin) / safe, (hi - origin) / safe
    zmin = torch.where(flat, torch.full_like(za, -torch.inf), torch.minimum(za, zb))
    zmax = torch.where(flat, torch.full_like(za, torch.inf), torch.maximum(za, zb))
    z0 = torch.maximum(z0, zmin.amax(dim=1))
    z1 = torch.minimum(z1, zmax.amin(dim=1))
    inside = (z0 <= z1) & ~(flat & ((origin < lo) | (origin > hi))).any(dim=1)
    return z0, z1, inside



def segment_pairs(geom: EpipolarGeometry, near: Tensor, far: Tensor, config: EFTConfig | None = None
                  ) -> tuple[Tensor, Tensor]:
    """Every (frontal pixel, overhead pixel) pair a ray segment reaches (volume gating).

    near, far : (B, H, W) planar depths of the segment ends (order free); a pixel takes part
                where both are finite and > 0
    Returns ``src`` and ``dst`` (P,) int64, unique pairs sorted by (src, dst): ``src`` indexes
    the flattened frontal batch (B·H·W), ``dst`` the flattened overhead batch (B·R·R).
    """
    config = config or EFTConfig()
    B, (H, W), R = geom.batch, geom.frontal_hw, geom.resolution
    near = near.detach().to(geom.device, torch.float64).reshape(B, H * W)
    far = far.detach().to(geom.device, torch.float64).reshape(B, H * W)
    ok = _valid_depth(near) & _valid_depth(far)
    b, p = ok.nonzero(as_tuple=True)
    z0, z1 = torch.minimum(near[b, p], far[b, p]), torch.maximum(near[b, p], far[b, p])
    o, d = geom.origin[b], geom.directions[b, p]
    e = geom.extent[b].unsqueeze(1)
    inf = torch.full_like(e, torch.inf)
    lo = torch.cat([-e, -e, -inf], dim=1)
    hi = torch.cat([e, e, inf], dim=1)
    z0, z1, inside = _clip(o, d, z0, z1, lo, hi)
    b, p, o, d, z0, z1 = b[inside], p[inside], o[inside], d[inside], z0[inside], z1[inside]
    e = geom.extent[b].unsqueeze(1)
    uv0 = overhead_pixel((o + z0.unsqueeze(1) * d)[:, :2], e, R)
    duv = overhead_pixel((o + z1.unsqueeze(1) * d)[:, :2], e, R) - uv0
    n = torch.ceil(duv.abs().amax(dim=1) * config.samples_per_pixel).clamp(min=1).long()
    return _rasterise(b * (H * W) + p, b, uv0, duv, n, R, config.max_samples)


def _rasterise(src: Tensor, batch: Tensor, uv0: Tensor, duv: Tensor, n: Tensor, R: int,
               max_samples: int) -> tuple[Tensor, Tensor]:
    """Sample segment ``uv0 + s · duv`` (pixels) at ``s = (k + ½) / n``, k < n, per segment.

    src, batch, n : (m,) int64, segments sorted by ``src``; uv0, duv : (m, 2) float64.
    Returns the unique (src, dst) pairs sorted by (src, dst).

    The pixels of a straight segment have monotone rows and monotone columns, so they come
    out sorted without a global sort: the samples are visited in the direction of
    increasing rows, and runs of equal rows are reversed where columns decrease.
    """
    device = src.device
    first = torch.cumsum(n, 0) - n
    up = duv[:, 1] < 0  # visit these from s = 1 down, so that rows never decrease
    left = (duv[:, 0] < 0) != up  # columns decrease along the visit
    # per segment, gathered once per sample: floats (u0, v0, du, dv, n), ints (offset, up, left, n - 1)
    floats = torch.cat([uv0, duv, n.unsqueeze(1).to(torch.float64)], dim=1)
    ints = torch.stack([batch * R * R, up.long(), left.long(), n - 1], dim=1)
    # chunks of whole segments starting in the same block of max_samples samples
    sizes = torch.unique_consecutive(first // max_samples, return_counts=True)[1].tolist()
    chunks_src, chunks_dst = [], []
    a = 0
    for size in sizes:
        c = a + size
        cn = n[a:c]
        seg = torch.repeat_interleave(torch.arange(a, c, device=device), cn)
        f, i = floats[seg], ints[seg]
        pos = torch.arange(len(seg), device=device)
        k = pos - torch.repeat_interleave(first[a:c] - first[a], cn)
        k = torch.where(i[:, 1] == 1, i[:, 3] - k, k)
        s = (k.to(torch.float64) + 0.5) / f[:, 4]
        # clipping puts every sample inside up to rounding; clamp the last ulp back in
        col = (f[:, 0] + s * f[:, 2]).floor_().long().clamp_(0, R - 1)
        row = (f[:, 1] + s * f[:, 3]).floor_().long().clamp_(0, R - 1)
        run_start = torch.ones_like(pos, dtype=torch.bool)
        run_start[1:] = (row[1:] != row[:-1]) | (seg[1:] != seg[:-1])
        starts = run_start.nonzero(as_tuple=True)[0]
        ends = torch.cat([starts[1:], starts.new_tensor([len(pos)])])
        run = torch.cumsum(run_start, 0) - 1
        target = torch.where(i[:, 2] == 1, (starts + ends - 1)[run] - pos, pos)
        dst = torch.empty_like(pos)
        dst[target] = i[:, 0] + row * R + col  # runs never cross segments: seg stays put
        keep = torch.ones_like(run_start)
        keep[1:] = (dst[1:] != dst[:-1]) | (seg[1:] != seg[:-1])
        chunks_src.append(src[seg[keep]])
        chunks_dst.append(dst[keep])
        a = c
    if not chunks_src:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    return torch.cat(chunks_src), torch.cat(chunks_dst)


def point_hits(geom: EpipolarGeometry, depth: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Project frontal points into the overhead image.

    depth : (B, L, H, W) planar depths of L layers; points with a finite depth > 0 take part
    Returns ``src`` (frontal pixel, flattened over B·H·W), ``dst`` (overhead pixel,
    flattened over B·R·R) int64 and ``z`` (overhead depth, m) float64 (P,), for the points
    that land inside the overhead image.
    """
    B, (H, W), R = geom.batch, geom.frontal_hw, geom.resolution
    depth = depth.detach().to(geom.device, torch.float64).reshape(B, -1, H * W)
    ok = _valid_depth(depth)
    b, _, p = ok.nonzero(as_tuple=True)
    z = depth[ok]
    pts = geom.origin[b] + z.unsqueeze(1) * geom.directions[b, p]
    uv = overhead_pixel(pts[:, :2], geom.extent[b].unsqueeze(1), R)
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    inside = (col >= 0) & (col < R) & (row >= 0) & (row < R)
    dst = (b * R + row) * R + col
    return (b * (H * W) + p)[inside], dst[inside], pts[inside, 2]


def _zbuffer(src: Tensor, dst: Tensor, z: Tensor, n_dst: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per overhead pixel, the highest point (smallest z; ties: smallest src).

    Returns the overhead pixels hit (m,), the winning src (m,) and its z (m,).
    """
    top = torch.full((n_dst,), torch.inf, dtype=z.dtype, device=z.device)
    top = top.scatter_reduce(0, dst, z, reduce="amin")
    best = z == top[dst]
    big = torch.iinfo(torch.long).max
    winner = torch.full((n_dst,), big, dtype=torch.long, device=z.device)
    winner = winner.scatter_reduce(0, dst[best], src[best], reduce="amin")
    hit = (winner != big).nonzero(as_tuple=True)[0]
    return hit, winner[hit], top[hit]


class _SparseTransfer(torch.autograd.Function):
    """``G = A F`` with a constant sparse ``A`` (forward: :func:`_scatter`); backward ``dF = Aᵀ dG``."""

    @staticmethod
    def forward(ctx, features, src, dst, weight, n_dst, AT):
        ctx.AT = AT
        return _scatter(features, src, dst, weight, n_dst)

    @staticmethod
    def backward(ctx, grad):
        return ctx.AT @ grad.contiguous(), None, None, None, None, None


def _scatter(features: Tensor, src: Tensor, dst: Tensor, weight: Tensor, n_dst: int) -> Tensor:
    """``G[dst] += weight · F[src]`` over every pair: ``A F`` without building ``A``.

    features : (n_src, C); src, dst, weight : (P,), pairs sorted by (src, dst)
    Returns (n_dst, C). An uncoalesced COO matrix multiplies without sorting its pairs on
    the CPU (one pass in the pairs' order, the same sums whatever the thread count); on a
    GPU torch coalesces it first.
    """
    A = torch.sparse_coo_tensor(torch.stack([dst, src]), weight, (n_dst, features.shape[0]),
                                is_coalesced=False, check_invariants=False)
    return torch.sparse.mm(A, features)


def _csr(rows: Tensor, cols: Tensor, values: Tensor, shape: tuple[int, int]) -> Tensor:
    """CSR matrix from (row, col) pairs sorted by row then col, without duplicates."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=shape[0]), 0)
    with warnings.catch_warnings():
        # torch flags its CSR support as beta on every construction; the ops used are stable
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
        return torch.sparse_csr_tensor(crow, cols, values, shape, check_invariants=False)


def _reference_transfer_volume(features: Tensor, geom: EpipolarGeometry, near: Tensor, far: Tensor,
                    config: EFTConfig | None = None) -> Tensor:
    """:func:`transfer_volume` by a sparse COO matrix ``A`` (``G = A F``) over the pairs of
    :func:`segment_pairs`, ``Aᵀ`` as CSR for the backward, built only where autograd needs it."""
    B, C = features.shape[:2]
    R = geom.resolution
    src, dst = segment_pairs(geom, near, far, config)
    n_src, n_dst = B * geom.frontal_hw[0] * geom.frontal_hw[1], B * R * R
    count = torch.bincount(dst, minlength=n_dst).to(features.dtype)
    weight = 1.0 / count[dst]
    flat = _flat(features).contiguous()
    if not (torch.is_grad_enabled() and features.requires_grad):
        # nothing will call backward: no transposed matrix for it
        return _unflat(_scatter(flat, src, dst, weight, n_dst), B, R)
    AT = _csr(src, dst, weight, (n_src, n_dst))  # the pairs' (src, dst) order is CSR order of Aᵀ
    return _unflat(_SparseTransfer.apply(flat, src, dst, weight, n_dst, AT), B, R)


def _reference_transfer_surface(features: Tensor, geom: EpipolarGeometry, points: Tensor) -> Tensor:
    """:func:`transfer_surface` from the point list of :func:`point_hits`: the winners' rows
    gathered and copied into a zero image."""
    B, C = features.shape[:2]
    R = geom.resolution
    src, dst, z = point_hits(geom, points)
    hit, winner, _ = _zbuffer(src, dst, z, B * R * R)
    flat = features.new_zeros(B * R * R, C)
    flat = flat.index_copy(0, hit, _flat(features)[winner])
    return _unflat(flat, B, R)


def _reference_best_guess_height(geom: EpipolarGeometry, depth: Tensor) -> Tensor:
    """:func:`best_guess_height` from the point list of :func:`point_hits`."""
    B, R = geom.batch, geom.resolution
    src, dst, z = point_hits(geom, depth)
    hit, _, top = _zbuffer(src, dst, z, B * R * R)
    height = torch.zeros(B * R * R, dtype=torch.float64, device=geom.device)
    height[hit] = geom.floor_depth[hit // (R * R)] - top
    return height.reshape(B, 1, R, R).float()
