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

Both are vectorised over the batch and every ray (index and scatter operations, no
Python loop over pixels, no sort); rays are processed in chunks of at most ``max_samples``
samples to bound memory. Volume gating builds the transposed matrix its backward needs
only when autograd will call it (grad enabled and features that require grad): under
``torch.no_grad`` (the frozen nets' features of the overhead stage) it builds none. The geometry is computed in float64 so CPU and GPU pick the same overhead
pixels; the output is differentiable with respect to the features (not the depths).

Also here: the **frustum mask** (the transform of a constant 1 along whole rays, computed
exactly per overhead pixel as "the vertical segment between the overhead camera and the
floor meets the frontal view frustum") and the **best-guess height** (z-buffer of the
D1–D4 points, as height above the floor, 0 where no point lands). :class:`EpipolarFeatureTransformer`
assembles the overhead nets' input: best guess (1) + frustum mask (1) + for ``(D1, D2)``
then ``(D3, D4)``: RGB (3) + depth features + segmentation features, which is
1 + 1 + 2 × (3 + 48 + 64) = 232 channels at the paper's widths.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor, nn

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
    v, u = torch.meshgrid(torch.arange(H, device=device, **f64) + 0.5,
                          torch.arange(W, device=device, **f64) + 0.5, indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(H * W, device=device, **f64)], dim=1)
    d_cam = pix @ torch.linalg.inv(K).transpose(1, 2)  # (B, HW, 3), z = 1
    R_o = To[:, :3, :3]
    rot = R_o.transpose(1, 2) @ T[:, :3, :3]  # frontal camera → overhead camera
    directions = d_cam @ rot.transpose(1, 2)
    origin = ((T[:, :3, 3] - To[:, :3, 3]).unsqueeze(1) @ R_o).squeeze(1)
    return EpipolarGeometry(origin, directions, extent, floor, int(resolution), (int(H), int(W)),
                            K, T, To)


# ----------------------------------------------------------------------- clipping


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


def _valid_depth(d: Tensor) -> Tensor:
    return torch.isfinite(d) & (d > 0)


# ------------------------------------------------------------------- sampled pairs


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


# --------------------------------------------------------------------- transfers


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


def _flat(features: Tensor) -> Tensor:
    """(B, C, H, W) → (B·H·W, C)."""
    return features.permute(0, 2, 3, 1).reshape(-1, features.shape[1])


def _unflat(flat: Tensor, B: int, R: int) -> Tensor:
    """(B·R·R, C) → (B, C, R, R), channels-last in memory (the assembly's concatenation copies)."""
    return flat.reshape(B, R, R, -1).permute(0, 3, 1, 2)


def transfer_volume(features: Tensor, geom: EpipolarGeometry, near: Tensor, far: Tensor,
                    config: EFTConfig | None = None) -> Tensor:
    """Volume gating: mean of the features of the rays whose ``(near, far)`` segment reaches
    each overhead pixel; 0 where none does.

    features  : (B, C, H, W) float  frontal feature map (differentiable)
    near, far : (B, H, W)           segment ends, planar depth (NaN = no segment)
    Returns (B, C, R, R), same dtype and device as ``features``. The backward's matrix is
    built only where autograd needs it (module docstring).
    """
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


def transfer_surface(features: Tensor, geom: EpipolarGeometry, points: Tensor) -> Tensor:
    """Surface gating: each overhead pixel takes the feature of the highest point landing in it.

    features : (B, C, H, W) float  frontal feature map (differentiable)
    points   : (B, L, H, W)        planar depths of the points (e.g. D1 and D2), NaN = none
    Returns (B, C, R, R); 0 where no point lands.
    """
    B, C = features.shape[:2]
    R = geom.resolution
    src, dst, z = point_hits(geom, points)
    hit, winner, _ = _zbuffer(src, dst, z, B * R * R)
    flat = features.new_zeros(B * R * R, C)
    flat = flat.index_copy(0, hit, _flat(features)[winner])
    return _unflat(flat, B, R)


def best_guess_height(geom: EpipolarGeometry, depth: Tensor) -> Tensor:
    """The frontal points' overhead height map: z-buffer of the ``depth`` points (D1–D4).

    depth : (B, L, H, W) planar depths, NaN = none
    Returns (B, 1, R, R) float32: height above the floor (``floor_depth`` − overhead depth)
    of the highest point per overhead pixel, 0 where no point lands.
    """
    B, R = geom.batch, geom.resolution
    src, dst, z = point_hits(geom, depth)
    hit, _, top = _zbuffer(src, dst, z, B * R * R)
    height = torch.zeros(B * R * R, dtype=torch.float64, device=geom.device)
    height[hit] = geom.floor_depth[hit // (R * R)] - top
    return height.reshape(B, 1, R, R).float()


def frustum_mask(geom: EpipolarGeometry) -> Tensor:
    """(B, 1, R, R) float32: 1 where the vertical segment through the overhead pixel centre,
    from the overhead camera (depth 0) down to the floor (``floor_depth``), meets the
    frontal view frustum (in front of the camera, inside the image's edges); else 0.

    This is the transform of a constant 1 along whole rays, evaluated exactly per overhead
    pixel instead of by rasterising every ray.
    """
    B, R, (H, W) = geom.batch, geom.resolution, geom.frontal_hw
    f64 = dict(dtype=torch.float64, device=geom.device)
    c = overhead_pixel_centre(torch.arange(R, **f64), 1.0, R)
    y, x = torch.meshgrid(c, c, indexing="ij")
    xy = torch.stack([x.reshape(-1), y.reshape(-1)], dim=1).unsqueeze(0) * geom.extent.view(B, 1, 1)
    # the vertical segment in the overhead frame: (x, y, s · floor_depth), s ∈ [0, 1]
    start = torch.cat([xy, torch.zeros_like(xy[..., :1])], dim=2)
    step = torch.zeros_like(start)
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


# ----------------------------------------------------------------------- module


class EpipolarFeatureTransformer(nn.Module):
    """Frontal RGB, features and layers + overhead camera → the overhead nets' input.

    resolution : the overhead image size R (square), from the data: the stores' overhead
                 resolution (``ViewIndex.shapes["Wo"]``)

    forward(rgb (B, 3, H, W), depth_features (B, Cd, H, W), seg_features (B, Cs, H, W),
    depth (B, 4, H, W) planar D1..D4 with NaN where a layer is empty, geometry for R)
    returns (B, 2 + 2·(3 + Cd + Cs), R, R) float32: best-guess height, frustum mask, then
    the ``(D1, D2)`` and ``(D3, D4)`` transfers (``conventions.OBJECT_SEGMENTS``) of
    ``[rgb, depth_features, seg_features]`` (surface gating uses the segment ends as points).
    """

    def __init__(self, config: EFTConfig | None = None, *, resolution: int):
        super().__init__()
        if int(resolution) < 1:
            raise ValueError(f"resolution must be at least 1 pixel, got {resolution}")
        self.config = config or EFTConfig()
        self.resolution = int(resolution)

    @staticmethod
    def out_channels(depth_features: int, seg_features: int) -> int:
        """Channels of the assembly: 232 for 48 depth and 64 segmentation features."""
        return 2 + 2 * (3 + depth_features + seg_features)

    def transfer(self, features: Tensor, geom: EpipolarGeometry, near: Tensor, far: Tensor) -> Tensor:
        """Carry ``features`` along the ``(near, far)`` segments with the configured gating."""
        if self.config.gating == "volume":
            return transfer_volume(features, geom, near, far, self.config)
        return transfer_surface(features, geom, torch.stack([near, far], dim=1))

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
        # the transfer is geometry, done in float32 under any autocast: torch has no bf16
        # sparse product on the CPU, and half-precision sums over long segments lose the mean
        dtype = torch.promote_types(torch.float32, torch.result_type(rgb, depth_features))
        with torch.autocast(rgb.device.type, enabled=False):
            features = torch.cat([rgb, depth_features, seg_features], dim=1).to(dtype)
            parts = [best_guess_height(geom, depth), frustum_mask(geom)]
            parts += [self.transfer(features, geom, depth[:, a], depth[:, b]) for a, b in OBJECT_SEGMENTS]
            return torch.cat([p.to(dtype) for p in parts], dim=1)
