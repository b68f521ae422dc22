"""Epipolar Feature Transformer: against a slow per-pixel loop reference (kept here), forward
and backward; the bags against the previous, sparse-matrix implementation (``reference=True``),
pair for pair and output for output; and on scenes with analytic answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the learn extra (torch) is not installed")

from sceneforge.cameras import Camera, pose_from_view  # noqa: E402
from sceneforge.conventions import overhead_pixel  # noqa: E402
from sceneforge.learn.eft import (  # noqa: E402
    EFTConfig,
    EpipolarFeatureTransformer,
    best_guess_height,
    epipolar_geometry,
    frustum_mask,
    layer_points,
    point_hits,
    scale_intrinsics,
    segment_pairs,
    transfer_surface,
    transfer_volume,
    volume_bags,
)
from sceneforge.learn.train import TrainConfig  # noqa: E402
from sceneforge.overhead import Box, OverheadCamera  # noqa: E402

# ------------------------------------------------------------------ scene helpers


def frontal_pose(height: float, pitch: float = 0.0) -> np.ndarray:
    """Upright OpenCV pose at (0, height, 0) looking along world +Z, pitched down by ``pitch`` rad."""
    return pose_from_view((0.0, height, 0.0), (0.0, -math.sin(pitch), math.cos(pitch)))


def overhead_pose(centre_z: float, height: float) -> np.ndarray:
    """Straight-down OpenCV pose over (0, height, centre_z), built like ``OverheadCamera``:
    image up = world +Z (the frontal view direction), image x = right = world -X."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = (-1, 0, 0), (0, 0, -1), (0, -1, 0)
    pose[:3, 3] = (0, height, centre_z)
    return pose


def geometry(K, pose, opose, extent, floor_depth, hw, R, B=1):
    def rep(a):
        return torch.tensor(np.asarray(a, dtype=np.float64)).expand(B, *np.shape(a)).clone()

    return epipolar_geometry(rep(K), rep(pose), rep(opose), torch.full((B,), float(extent)),
                             torch.full((B,), float(floor_depth)), hw, R)


def random_inputs(seed: int, B=2, C=3, H=6, W=8, R=12):
    """Random cameras looking roughly at the overhead box, random segments, random features."""
    rng = np.random.default_rng(seed)
    K = np.stack([np.array([[rng.uniform(6, 10), 0, W / 2 + rng.uniform(-1, 1)],
                            [0, rng.uniform(6, 10), H / 2 + rng.uniform(-1, 1)], [0, 0, 1]])
                  for _ in range(B)])
    pose = np.stack([frontal_pose(rng.uniform(1.2, 1.8), rng.uniform(0.0, 0.4)) for _ in range(B)])
    pose[:, 0, 3] = rng.uniform(-0.3, 0.3, B)
    opose = np.stack([overhead_pose(rng.uniform(2.0, 3.0), 2.6) for _ in range(B)])
    extent = rng.uniform(1.5, 2.5, B)
    floor = np.full(B, 2.6)
    near = rng.uniform(0.5, 5.0, (B, H, W))
    far = near + rng.uniform(0.0, 1.5, (B, H, W))
    near[rng.random((B, H, W)) < 0.2] = np.nan  # empty pixels
    feats = rng.normal(size=(B, C, H, W))
    geom = epipolar_geometry(torch.tensor(K), torch.tensor(pose), torch.tensor(opose), torch.tensor(extent),
                             torch.tensor(floor), (H, W), R)
    return dict(K=K, pose=pose, opose=opose, extent=extent, floor=floor, near=near, far=far,
                feats=feats, geom=geom, R=R)


# ------------------------------------------------------------- slow references


def ray(K, pose, opose, i, j):
    """Frontal pixel (i, j)'s ray in overhead-camera coordinates: origin, direction per planar depth."""
    d_cam = np.linalg.inv(K) @ np.array([j + 0.5, i + 0.5, 1.0])
    Ro, to = opose[:3, :3], opose[:3, 3]
    return Ro.T @ (pose[:3, 3] - to), Ro.T @ pose[:3, :3] @ d_cam


def pixel_of(p, e, R):
    return int(math.floor((p[1] / e + 1) * R / 2)), int(math.floor((p[0] / e + 1) * R / 2))


def reference_segment_pixels(inp, b, i, j, spp=1.0):
    """Overhead pixels (row, col) the segment of frontal pixel (i, j) reaches, one at a time."""
    z0, z1 = inp["near"][b, i, j], inp["far"][b, i, j]
    if not (np.isfinite(z0) and np.isfinite(z1) and z0 > 0 and z1 > 0):
        return set()
    z0, z1 = min(z0, z1), max(z0, z1)
    o, d = ray(inp["K"][b], inp["pose"][b], inp["opose"][b], i, j)
    e, R = inp["extent"][b], inp["R"]
    for a in (0, 1):  # clip to the image square, axis by axis
        if abs(d[a]) < 1e-12:
            if not -e <= o[a] <= e:
                return set()
            continue
        za, zb = (-e - o[a]) / d[a], (e - o[a]) / d[a]
        z0, z1 = max(z0, min(za, zb)), min(z1, max(za, zb))
    if z0 > z1:
        return set()
    uv0 = ((o + z0 * d)[:2] / e + 1) * R / 2
    uv1 = ((o + z1 * d)[:2] / e + 1) * R / 2
    n = max(1, math.ceil(np.abs(uv1 - uv0).max() * spp))
    pixels = set()
    for k in range(n):
        u, v = uv0 + (k + 0.5) / n * (uv1 - uv0)
        pixels.add((min(max(int(math.floor(v)), 0), R - 1), min(max(int(math.floor(u)), 0), R - 1)))
    return pixels


def reference_volume(inp, grad_out):
    """Loop reference of volume gating: forward output and the gradient w.r.t. the features."""
    F = inp["feats"]
    B, C, H, W = F.shape
    R = inp["R"]
    total, count = np.zeros((B, C, R, R)), np.zeros((B, R, R))
    reach = {}
    for b in range(B):
        for i in range(H):
            for j in range(W):
                reach[b, i, j] = reference_segment_pixels(inp, b, i, j)
                for r, c in reach[b, i, j]:
                    total[b, :, r, c] += F[b, :, i, j]
                    count[b, r, c] += 1
    out = total / np.maximum(count, 1)[:, None]
    grad = np.zeros_like(F)
    for (b, i, j), pixels in reach.items():
        for r, c in pixels:
            grad[b, :, i, j] += grad_out[b, :, r, c] / count[b, r, c]
    return out, grad


def reference_zbuffer(inp, points):
    """Per overhead pixel: (overhead depth, frontal pixel index) of the highest point."""
    B, L, H, W = points.shape
    R = inp["R"]
    best = {}
    for b in range(B):
        for layer in range(L):
            for i in range(H):
                for j in range(W):
                    z = points[b, layer, i, j]
                    if not (np.isfinite(z) and z > 0):
                        continue
                    o, d = ray(inp["K"][b], inp["pose"][b], inp["opose"][b], i, j)
                    p = o + z * d
                    r, c = pixel_of(p, inp["extent"][b], R)
                    if 0 <= r < R and 0 <= c < R:
                        cand = (p[2], i * W + j)
                        best[b, r, c] = min(best.get((b, r, c), cand), cand)
    return best


# ----------------------------------------------------------------- vs reference


@pytest.mark.parametrize("reference", [False, True], ids=["bags", "sparse"])
@pytest.mark.parametrize("seed", [0, 1])
def test_volume_matches_loop_reference_forward_and_backward(seed, reference):
    inp = random_inputs(seed)
    F = torch.tensor(inp["feats"], requires_grad=True)
    out = transfer_volume(F, inp["geom"], torch.tensor(inp["near"]), torch.tensor(inp["far"]), reference=reference)
    grad_out = np.random.default_rng(seed + 100).normal(size=tuple(out.shape))
    out.backward(torch.tensor(grad_out))
    ref_out, ref_grad = reference_volume(inp, grad_out)
    assert (np.abs(ref_out).sum(axis=1) > 0).sum() > 20  # the inputs reach many pixels
    np.testing.assert_allclose(out.detach().numpy(), ref_out, atol=1e-12)
    np.testing.assert_allclose(F.grad.numpy(), ref_grad, atol=1e-12)


class _Counting:
    """Wraps a function and counts its calls."""

    def __init__(self, fn):
        self.fn, self.calls = fn, 0

    def __call__(self, *args, **kw):
        self.calls += 1
        return self.fn(*args, **kw)


def test_reference_volume_builds_nothing_for_backward_under_no_grad(monkeypatch):
    import sceneforge.learn.eft as eft

    inp = random_inputs(4)
    near, far = torch.tensor(inp["near"]), torch.tensor(inp["far"])
    csr, sort = _Counting(eft._csr), _Counting(torch.sort)
    monkeypatch.setattr(eft, "_csr", csr)
    monkeypatch.setattr(torch, "sort", sort)
    F = torch.tensor(inp["feats"], requires_grad=True)
    with_grad = transfer_volume(F, inp["geom"], near, far, reference=True)
    assert with_grad.requires_grad and csr.calls == 1  # the backward's matrix, so the counter counts
    with torch.no_grad():
        no_grad = transfer_volume(F, inp["geom"], near, far, reference=True)
    frozen = transfer_volume(F.detach(), inp["geom"], near, far, reference=True)  # nothing to differentiate
    assert (csr.calls, sort.calls) == (1, 0) and not no_grad.requires_grad and not frozen.requires_grad
    # one forward for both: the same pairs summed in the same order
    torch.testing.assert_close(no_grad, with_grad.detach(), atol=0, rtol=0)
    torch.testing.assert_close(frozen, no_grad, atol=0, rtol=0)


def test_volume_builds_no_sparse_matrix_and_nothing_for_backward_under_no_grad(monkeypatch):
    import sceneforge.learn.eft as eft

    inp = random_inputs(4)
    near, far = torch.tensor(inp["near"]), torch.tensor(inp["far"])
    coo, csr = _Counting(torch.sparse_coo_tensor), _Counting(torch.sparse_csr_tensor)
    backward = _Counting(eft.Bags.backward)
    monkeypatch.setattr(torch, "sparse_coo_tensor", coo)
    monkeypatch.setattr(torch, "sparse_csr_tensor", csr)
    monkeypatch.setattr(eft.Bags, "backward", lambda bags, grad: backward(bags, grad))
    F = torch.tensor(inp["feats"], requires_grad=True)
    with_grad = transfer_volume(F, inp["geom"], near, far)
    with torch.no_grad():
        no_grad = transfer_volume(F, inp["geom"], near, far)
    frozen = transfer_volume(F.detach(), inp["geom"], near, far)
    assert with_grad.requires_grad and not no_grad.requires_grad and not frozen.requires_grad
    assert backward.calls == 0  # the backward's bags are made by the backward
    with_grad.sum().backward()
    assert (coo.calls, csr.calls, backward.calls) == (0, 0, 1)
    torch.testing.assert_close(no_grad, with_grad.detach(), atol=0, rtol=0)
    torch.testing.assert_close(frozen, no_grad, atol=0, rtol=0)


@pytest.mark.parametrize("reference", [False, True], ids=["bags", "sparse"])
@pytest.mark.parametrize("seed", [0, 1])
def test_surface_matches_loop_reference_forward_and_backward(seed, reference):
    inp = random_inputs(seed)
    B, C, H, W = inp["feats"].shape
    points = np.stack([inp["near"], inp["far"]], axis=1)
    F = torch.tensor(inp["feats"], requires_grad=True)
    out = transfer_surface(F, inp["geom"], torch.tensor(points), reference=reference)
    grad_out = np.random.default_rng(seed + 200).normal(size=tuple(out.shape))
    out.backward(torch.tensor(grad_out))

    best = reference_zbuffer(inp, points)
    ref_out, ref_grad = np.zeros(out.shape), np.zeros_like(inp["feats"])
    for (b, r, c), (_, src) in best.items():
        i, j = divmod(src, W)
        ref_out[b, :, r, c] = inp["feats"][b, :, i, j]
        ref_grad[b, :, i, j] += grad_out[b, :, r, c]
    assert len(best) > 20
    np.testing.assert_array_equal(out.detach().numpy(), ref_out)
    np.testing.assert_allclose(F.grad.numpy(), ref_grad, atol=1e-12)


@pytest.mark.parametrize("reference", [False, True], ids=["dense", "points"])
def test_best_guess_height_matches_loop_reference(reference):
    inp = random_inputs(3)
    points = np.stack([inp["near"], inp["far"], inp["far"] + 0.3, inp["near"] * 0.5], axis=1)
    got = best_guess_height(inp["geom"], torch.tensor(points), reference=reference).numpy()
    ref = np.zeros(got.shape, dtype=np.float32)
    for (b, r, c), (z, _) in reference_zbuffer(inp, points).items():
        ref[b, 0, r, c] = inp["floor"][b] - z
    np.testing.assert_allclose(got, ref, atol=1e-6)
    assert got.dtype == np.float32


# --------------------------------------------- the bags against the sparse reference


def layers4(inp, seed):
    """(B, 4, H, W) D1..D4 from the random segments: a second object behind the first on
    about half the pixels, NaN elsewhere."""
    rng = np.random.default_rng(seed + 300)
    d3 = inp["far"] + rng.uniform(0.05, 1.0, inp["far"].shape)
    d4 = d3 + rng.uniform(0.0, 1.5, d3.shape)
    d3[rng.random(d3.shape) < 0.5] = np.nan
    return torch.tensor(np.stack([inp["near"], inp["far"], d3, d4], axis=1))


def frontal_features(seed, B, H, W, widths=(3, 5, 4), dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(B, c, H, W, generator=g, dtype=dtype).requires_grad_(True) for c in widths]


@pytest.mark.parametrize("max_samples", [7, 1 << 21], ids=["chunked", "whole"])
@pytest.mark.parametrize("gating", ["volume", "surface"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_module_matches_the_reference_forward_and_backward(seed, gating, max_samples):
    # long segments over a 40-pixel overhead image: many sample-count buckets; max_samples 7
    # samples one entry at a time wherever a segment has more than 3 samples
    inp = random_inputs(seed, B=3, H=18, W=24, R=40)
    depth = layers4(inp, seed)
    B, _, H_, W_ = depth.shape
    config = EFTConfig(gating=gating, max_samples=max_samples)
    rgb, df, sf = frontal_features(seed, B, H_, W_)
    new = EpipolarFeatureTransformer(config, resolution=40)(rgb, df, sf, depth, inp["geom"])
    ref = EpipolarFeatureTransformer(config, resolution=40, reference=True)(rgb, df, sf, depth, inp["geom"])
    assert new.shape == ref.shape == (B, 2 + 2 * 12, 40, 40) and new.dtype == ref.dtype == torch.float64
    assert (ref[:, 2:].abs().sum(dim=1) > 0).sum() > 500  # the transfers reach many pixels
    torch.testing.assert_close(new, ref, atol=1e-12, rtol=0)
    grad = torch.randn(new.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    for got, want in zip(torch.autograd.grad(new, (rgb, df, sf), grad),
                         torch.autograd.grad(ref, (rgb, df, sf), grad)):
        assert want.abs().sum() > 0
        torch.testing.assert_close(got, want, atol=1e-12, rtol=0)


@pytest.mark.parametrize("gating", ["volume", "surface"])
def test_module_matches_the_reference_in_float32(gating):
    inp = random_inputs(5, B=2, H=18, W=24, R=40)
    depth = layers4(inp, 5)
    rgb, df, sf = frontal_features(5, 2, 18, 24, widths=(3, 48, 64), dtype=torch.float32)
    config = EFTConfig(gating=gating)
    new = EpipolarFeatureTransformer(config, resolution=40)(rgb, df, sf, depth, inp["geom"])
    ref = EpipolarFeatureTransformer(config, resolution=40, reference=True)(rgb, df, sf, depth, inp["geom"])
    assert new.shape == (2, 232, 40, 40) and new.dtype == torch.float32
    torch.testing.assert_close(new, ref, atol=1e-6, rtol=1e-5)
    (new * ref.detach()).sum().backward()
    got = [t.grad.clone() for t in (rgb, df, sf)]
    for t in (rgb, df, sf):
        t.grad = None
    (ref * ref.detach()).sum().backward()
    for g, t in zip(got, (rgb, df, sf)):
        torch.testing.assert_close(g, t.grad, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("max_samples", [5, 1 << 21], ids=["chunked", "whole"])
@pytest.mark.parametrize("samples_per_pixel", [1.0, 2.5, 0.3])
def test_volume_bags_hold_exactly_the_reference_pairs(samples_per_pixel, max_samples):
    inp = random_inputs(8, B=2, H=18, W=24, R=40)
    depth = layers4(inp, 8)
    geom, config = inp["geom"], EFTConfig(samples_per_pixel=samples_per_pixel, max_samples=max_samples)
    segments = [(depth[:, 0], depth[:, 1]), (depth[:, 2], depth[:, 3])]
    bags = volume_bags(geom, segments, config)
    key = torch.repeat_interleave(bags.keys_hit, (bags.offsets[1:] - bags.offsets[:-1]).long())
    got = torch.stack([key // bags.n_dst, bags.index.long(), key % bags.n_dst], dim=1)
    want = torch.cat([torch.stack([torch.full_like(src, s), src, dst], dim=1)
                      for s, (near, far) in enumerate(segments)
                      for src, dst in [segment_pairs(geom, near, far, config)]])
    assert len(got) == len(want) > 1000  # and so, with the sets equal, no pair twice
    assert set(map(tuple, got.tolist())) == set(map(tuple, want.tolist()))
    # the backward's view of the same pairs: grouped by ray segment, each ray's frontal pixel
    entry = torch.repeat_interleave(bags.entry_src, (bags.entry_offsets[1:] - bags.entry_offsets[:-1]).long())
    mirrored = torch.stack([bags.keys.long() // bags.n_dst, entry, bags.keys.long() % bags.n_dst], dim=1)
    assert set(map(tuple, mirrored.tolist())) == set(map(tuple, want.tolist()))


def test_layer_points_are_the_point_hits():
    inp = random_inputs(9, B=2, H=12, W=16, R=24)
    depth = layers4(inp, 9)
    dst, z = layer_points(inp["geom"], depth)
    src, dst_ref, z_ref = point_hits(inp["geom"], depth)
    lands = dst < 2 * 24 * 24
    assert 0 < lands.sum() < lands.numel()
    np.testing.assert_array_equal(dst[lands].numpy(), dst_ref.numpy())
    np.testing.assert_array_equal(z[lands].numpy(), z_ref.numpy())
    assert torch.isinf(z[~lands]).all()


def test_what_depends_only_on_the_cameras_is_computed_once_per_geometry(monkeypatch):
    import sceneforge.learn.eft as eft

    inp = random_inputs(10, B=2, H=6, W=8, R=12)
    depth = layers4(inp, 10)
    frustum = _Counting(eft._frustum_mask)
    monkeypatch.setattr(eft, "_frustum_mask", frustum)
    module = EpipolarFeatureTransformer(resolution=12)
    first = module(*frontal_features(10, 2, 6, 8), depth, inp["geom"])
    again = module(*frontal_features(11, 2, 6, 8), depth, inp["geom"])
    assert frustum.calls == 1 and eft.ray_box(inp["geom"]) is eft.ray_box(inp["geom"])
    torch.testing.assert_close(first[:, :2], again[:, :2], atol=0, rtol=0)


@pytest.mark.parametrize("gating", ["volume", "surface"])
def test_no_segment_gives_zeros_and_zero_gradients(gating):
    inp = random_inputs(11, B=2, H=6, W=8, R=12)
    depth = torch.full((2, 4, 6, 8), torch.nan, dtype=torch.float64)
    rgb, df, sf = frontal_features(11, 2, 6, 8)
    out = EpipolarFeatureTransformer(EFTConfig(gating=gating), resolution=12)(rgb, df, sf, depth, inp["geom"])
    assert (out[:, [0] + list(range(2, out.shape[1]))] == 0).all()
    out.sum().backward()
    assert all((t.grad == 0).all() for t in (rgb, df, sf))



def test_the_output_has_the_memory_format_of_the_features():
    # the trainer's nets are channels-last, and so the transfers write; contiguous otherwise
    inp = random_inputs(12, B=2, H=6, W=8, R=12)
    depth = layers4(inp, 12)
    features = frontal_features(12, 2, 6, 8, dtype=torch.float32)
    features_last = [t.detach().contiguous(memory_format=torch.channels_last).requires_grad_(True)
                     for t in features]
    module = EpipolarFeatureTransformer(resolution=12)
    plain = module(*features, depth, inp["geom"])
    last = module(*features_last, depth, inp["geom"])
    assert plain.is_contiguous() and last.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(last, plain, atol=0, rtol=0)
    grad = torch.randn(plain.shape, generator=torch.Generator().manual_seed(12))
    for a, b in zip(torch.autograd.grad(plain, features, grad), torch.autograd.grad(last, features_last, grad)):
        torch.testing.assert_close(a, b, atol=0, rtol=0)

# --------------------------------------------------------------- analytic scenes

H, W, FX = 48, 64, 40.0
K_BOX = np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]])


def box_layers(lo, hi, pose, K=K_BOX, hw=(H, W)):
    """D1, D2 (planar) of an axis-aligned box seen from ``pose`` (slab method), NaN off the box."""
    h, w = hw
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    d = d_cam @ pose[:3, :3].T
    o = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
    enter = np.minimum(t0, t1).max(-1)
    leave = np.maximum(t0, t1).min(-1)
    hit = (enter <= leave) & (enter > 0)
    return np.where(hit, enter, np.nan), np.where(hit, leave, np.nan)


def test_volume_features_land_exactly_on_the_box_footprint():
    # box x ∈ [-0.4, 0.4], z ∈ [2, 3]; overhead: 20 px of 0.1 m centred on (x 0, z 2.5),
    # so the footprint is rows 5..14 (z 3 → 2), columns 6..13, edges on pixel edges
    pose = frontal_pose(1.0)
    d1, d2 = box_layers((-0.4, 0.0, 2.0), (0.4, 0.8, 3.0), pose)
    assert np.isfinite(d1).sum() > 200 and (d2 > d1 + 0.5).any()
    geom = geometry(K_BOX, pose, overhead_pose(2.5, 2.5), 1.0, 2.5, (H, W), 20)
    ones = torch.ones(1, 1, H, W)
    out = transfer_volume(ones, geom, torch.tensor(d1)[None], torch.tensor(d2)[None])[0, 0].numpy()
    footprint = np.zeros((20, 20), bool)
    footprint[5:15, 6:14] = True
    np.testing.assert_array_equal(out > 0, footprint)
    np.testing.assert_allclose(out[footprint], 1.0, rtol=1e-6)  # a mean of ones


def overhead_camera_at(centre_z, height, extent, R):
    """The OverheadCamera whose pose is :func:`overhead_pose` (its other fields are unused)."""
    box = Box(np.array([-extent, -extent]), np.array([extent, extent]))
    return OverheadCamera(overhead_pose(centre_z, height), extent, R, np.zeros(5), 0.0, box)


def test_eft_maps_points_to_the_pixels_overhead_camera_project_gives():
    # The same overhead-frame coordinates give bit-identical pixels in numpy and torch ...
    R, e = 37, 1.7
    cam = overhead_camera_at(2.3, 2.6, e, R)
    rng = np.random.default_rng(11)
    world = rng.uniform([-2, 0, 0], [2, 2.5, 4.5], (2000, 3))
    uv, z = cam.project(world)
    local = (world - cam.cam_to_world[:3, 3]) @ cam.cam_to_world[:3, :3]
    np.testing.assert_array_equal(overhead_pixel(torch.tensor(local[:, :2]), torch.tensor(e, dtype=torch.float64), R).numpy(), uv)
    # ... and the EFT puts every frontal point in the pixel OverheadCamera.project puts it in.
    pose = frontal_pose(1.3, 0.3)
    frontal = Camera(K_BOX, pose, W, H)
    depth = rng.uniform(0.5, 6.0, (1, 1, H, W))
    geom = geometry(K_BOX, pose, cam.cam_to_world, e, 2.6, (H, W), R)
    src, dst, z_eft = point_hits(geom, torch.tensor(depth))
    origins, directions, scale = frontal.rays()
    points = origins + directions * (depth.reshape(-1) / scale)[:, None]
    uv, z = cam.project(points)
    col, row = np.floor(uv).astype(np.int64).T
    inside = (col >= 0) & (col < R) & (row >= 0) & (row < R)
    assert 1000 < inside.sum() < H * W
    np.testing.assert_array_equal(src.numpy(), np.flatnonzero(inside))
    np.testing.assert_array_equal(dst.numpy(), (row * R + col)[inside])
    np.testing.assert_allclose(z_eft.numpy(), z[inside], atol=1e-12)


def test_eft_footprint_of_a_box_is_the_box_projected_by_the_overhead_camera():
    # box x ∈ [-0.4, 0.4], z ∈ [2, 3] seen by a level camera; its overhead footprint is the
    # pixel rectangle OverheadCamera.project gives its corners (edges on pixel edges)
    pose, R = frontal_pose(1.0), 20
    cam = overhead_camera_at(2.5, 2.5, 1.0, R)
    d1, d2 = box_layers((-0.4, 0.0, 2.0), (0.4, 0.8, 3.0), pose)
    geom = geometry(K_BOX, pose, cam.cam_to_world, cam.half_extent, 2.5, (H, W), R)
    out = transfer_volume(torch.ones(1, 1, H, W), geom, torch.tensor(d1)[None], torch.tensor(d2)[None])
    uv, _ = cam.project([[x, 0.0, z] for x in (-0.4, 0.4) for z in (2.0, 3.0)])
    (u0, v0), (u1, v1) = np.round(uv.min(axis=0)).astype(int), np.round(uv.max(axis=0)).astype(int)
    footprint = np.zeros((R, R), bool)
    footprint[v0:v1, u0:u1] = True
    assert footprint.sum() == 80
    np.testing.assert_array_equal(out[0, 0].numpy() > 0, footprint)


def test_surface_gating_keeps_the_top_most_contribution():
    # a fronto-parallel plane at z = 2.5 seen by a level camera: every row of a column lands
    # on the same overhead pixel, the top row highest
    pose = frontal_pose(1.0)
    depth = torch.full((1, 1, H, W), 2.5, dtype=torch.float64)
    geom = geometry(K_BOX, pose, overhead_pose(2.5, 2.5), 2.0, 2.5, (H, W), 40)
    row = torch.arange(H, dtype=torch.float64).view(1, 1, H, 1).expand(1, 1, H, W)
    surface = transfer_surface(row, geom, depth)[0, 0]
    volume = transfer_volume(row, geom, depth[:, 0], depth[:, 0])[0, 0]
    hit = volume != 0
    assert hit.sum() >= 10
    np.testing.assert_array_equal(surface[hit].numpy(), 0.0)  # the top row wins
    np.testing.assert_allclose(volume[hit].numpy(), (H - 1) / 2)  # volume averages all rows
    # overhead row of z = 2.5 is the middle one; nothing lands elsewhere
    assert set(torch.nonzero(hit)[:, 0].tolist()) == {20}


def test_frustum_mask_equals_the_wedge_of_a_level_camera():
    # level camera at 1.0 m: the frustum's footprint is |x| <= z tan(hfov), z >= 0
    R, e = 40, 2.0
    geom = geometry(K_BOX, frontal_pose(1.0), overhead_pose(1.5, 2.5), e, 2.5, (H, W), R)
    mask = frustum_mask(geom)[0, 0].numpy()
    c = ((np.arange(R) + 0.5) / R * 2 - 1) * e
    x = c[None, :]
    z = 1.5 - c[:, None]  # image rows go from far (top) to near
    expected = (np.abs(x) <= z * (W / 2) / FX) & (z >= 0)
    assert 0 < expected.sum() < R * R
    np.testing.assert_array_equal(mask, expected)


def test_frustum_mask_equals_brute_force_footprint_of_a_pitched_camera():
    R, e, floor = 24, 2.5, 2.4
    pose = frontal_pose(1.4, 0.35)
    opose = overhead_pose(2.0, 2.4)
    mask = frustum_mask(geometry(K_BOX, pose, opose, e, floor, (H, W), R))[0, 0].numpy()
    c = ((np.arange(R) + 0.5) / R * 2 - 1) * e
    s = np.linspace(0, 1, 4001)
    expected = np.zeros((R, R), bool)
    for r in range(R):
        for col in range(R):
            p_over = np.stack([np.full_like(s, c[col]), np.full_like(s, c[r]), s * floor], 1)
            world = p_over @ opose[:3, :3].T + opose[:3, 3]
            cam = (world - pose[:3, 3]) @ pose[:3, :3]
            uvw = cam @ K_BOX.T
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
            expected[r, col] = ((cam[:, 2] > 0) & (u >= 0) & (u <= W) & (v >= 0) & (v <= H)).any()
    assert 0 < expected.sum() < R * R
    np.testing.assert_array_equal(mask, expected)


def test_module_assembles_232_channels_at_paper_widths():
    inp = random_inputs(5, B=2, H=6, W=8, R=12)
    B, H_, W_ = 2, 6, 8
    rng = np.random.default_rng(5)
    depth = torch.tensor(np.stack([inp["near"], inp["far"], inp["far"] + 0.2, inp["far"] + 0.9], 1))
    rgb, df, sf = (torch.tensor(rng.normal(size=(B, c, H_, W_)), dtype=torch.float32, requires_grad=True)
                   for c in (3, 48, 64))
    eft = EpipolarFeatureTransformer(EFTConfig(), resolution=12)
    out = eft(rgb, df, sf, depth, inp["geom"])
    assert out.shape == (B, 232, 12, 12) == (B, eft.out_channels(48, 64), 12, 12)
    assert out.dtype == torch.float32
    np.testing.assert_array_equal(out[:, 1:2].detach().numpy(), frustum_mask(inp["geom"]).numpy())
    np.testing.assert_array_equal(out[:, :1].detach().numpy(), best_guess_height(inp["geom"], depth).numpy())
    out[:, 2:].sum().backward()
    assert df.grad.abs().sum() > 0 and sf.grad.abs().sum() > 0 and rgb.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="depth must be"):
        eft(rgb, df, sf, depth[:, :3], inp["geom"])
    with pytest.raises(ValueError, match="12-pixel overhead image, the transformer for 16"):
        EpipolarFeatureTransformer(resolution=16)(rgb, df, sf, depth, inp["geom"])


def test_under_bf16_autocast_the_transfer_runs_in_float32():
    # torch has no bf16 sparse product on the CPU; nets under autocast hand over bf16 features
    inp = random_inputs(6, B=2, H=6, W=8, R=12)
    rng = np.random.default_rng(6)
    depth = torch.tensor(np.stack([inp["near"], inp["far"], inp["far"] + 0.2, inp["far"] + 0.9], 1))
    rgb = torch.tensor(rng.normal(size=(2, 3, 6, 8)), dtype=torch.float32)
    df, sf = (torch.tensor(rng.normal(size=(2, c, 6, 8)), dtype=torch.bfloat16) for c in (8, 4))
    eft = EpipolarFeatureTransformer(EFTConfig(), resolution=12)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = eft(rgb, df, sf, depth, inp["geom"])
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, eft(rgb, df.float(), sf.float(), depth, inp["geom"]), rtol=0, atol=0)


def test_the_overhead_resolution_comes_from_the_data_not_the_config():
    # A run config saved when EFTConfig still had a resolution loads, without it.
    config = TrainConfig.from_dict({"stage": "overhead", "stores": ["s.zarr"], "eft": {"resolution": 300, "gating": "surface"}})
    assert config.eft == EFTConfig(gating="surface")
    assert "resolution" not in config.to_dict()["eft"]
    with pytest.raises(ValueError, match="resolution"):
        EpipolarFeatureTransformer(resolution=0)


def test_scale_intrinsics_keeps_pixel_centres():
    K = torch.tensor(K_BOX)
    half = scale_intrinsics(K, (H, W), (H // 2, W // 2))
    # the centre of the half-size image's pixel (0, 0) sees the corner between 4 full pixels
    ray_full = torch.linalg.inv(K) @ torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    ray_half = torch.linalg.inv(half) @ torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64)
    torch.testing.assert_close(ray_full, ray_half)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cpu_and_gpu_agree():
    inp = random_inputs(7)
    near, far = torch.tensor(inp["near"]), torch.tensor(inp["far"])
    F = torch.tensor(inp["feats"], dtype=torch.float32)
    cpu = transfer_volume(F, inp["geom"], near, far)
    g = inp["geom"]
    gpu_geom = epipolar_geometry(g.K.cuda(), g.cam_to_world.cuda(), g.overhead_cam_to_world.cuda(),
                                 g.extent.cuda(), g.floor_depth.cuda(), g.frontal_hw, g.resolution)
    gpu = transfer_volume(F.cuda(), gpu_geom, near.cuda(), far.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-6, rtol=1e-6)
    points = torch.stack([near, far], 1)
    torch.testing.assert_close(transfer_surface(F.cuda(), gpu_geom, points.cuda()).cpu(),
                               transfer_surface(F, inp["geom"], points), atol=0, rtol=0)
    torch.testing.assert_close(frustum_mask(gpu_geom).cpu(), frustum_mask(inp["geom"]), atol=0, rtol=0)
