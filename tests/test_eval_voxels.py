"""Voxel IoU: layer intervals and solid mesh occupancy in the camera's grid (docs/spec.md §11.4)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sceneforge.cameras import look_at_camera
from sceneforge.evaluate import (
    Mesh,
    VoxelConfig,
    concatenate,
    frustum_mask,
    layer_occupancy,
    mesh_occupancy,
    score_voxels,
    voxel_iou,
)
from sceneforge.frustum import clip_triangles, frustum_planes, weld

CAMERA = look_at_camera((1.0, 1.5, -2.0), (0.3, -0.2, 1.0))  # 320×240, pitched and turned
SHAPE = (CAMERA.height, CAMERA.width)
# 2.5 cm voxels over a 4 m cube: the paper's voxel size, a smaller grid
SMALL = VoxelConfig(resolution=160, size=4.0)
# a box in camera coordinates with faces on voxel boundaries (multiples of 2.5 cm from -2 m)
BOX = np.array([[-0.5, -0.25, 2.0], [0.5, 0.5, 3.0]])


def box_mesh(lo, hi) -> Mesh:
    """The closed box [lo, hi] given in camera coordinates, as a world-space mesh."""
    b = trimesh.creation.box(bounds=np.array([lo, hi]))
    pose = CAMERA.cam_to_world
    return Mesh(b.vertices @ pose[:3, :3].T + pose[:3, 3], b.faces)


def box_layers(lo, hi, K=CAMERA.K, shape=SHAPE) -> np.ndarray:
    """(5, H, W) layers of the box [lo, hi] (camera coordinates) traced analytically: D1 and
    D2 where each pixel's ray enters and leaves it (slab test), nothing else."""
    h, w = shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1: t is planar depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (np.asarray(lo) - 0) / d, (np.asarray(hi) - 0) / d
    near = np.nanmax(np.minimum(t0, t1), axis=-1)
    far = np.nanmin(np.maximum(t0, t1), axis=-1)
    hit = (far > near) & (near > 0)
    layers = np.full((5, h, w), np.nan, dtype=np.float32)
    layers[0] = np.where(hit, near, np.nan)
    layers[1] = np.where(hit, far, np.nan)
    return layers


def voxel_count(lo, hi, config=SMALL) -> int:
    return int(np.prod(np.round((np.asarray(hi) - lo) / config.voxel)))


def test_box_against_itself_is_1_on_the_paper_grid():
    score = score_voxels(box_layers(*BOX), CAMERA.K, CAMERA.cam_to_world, box_mesh(*BOX))
    assert score.iou == 1.0
    assert score.truth == voxel_count(*BOX, VoxelConfig()) == 40 * 30 * 40


def test_box_against_a_half_overlapping_box_is_one_third():
    shifted = BOX + [[0.5, 0, 0], [0.5, 0, 0]]
    score = score_voxels(box_layers(*BOX), CAMERA.K, CAMERA.cam_to_world, box_mesh(*shifted), SMALL)
    assert score.iou == pytest.approx(1 / 3, abs=1e-12)
    assert score.predicted == score.truth == voxel_count(*BOX)


def test_occluded_box_fills_from_d3_d4():
    # the second box behind the first, in layers 3 and 4 of the pixels that see both
    back = np.array([[-0.25, -0.25, 3.25], [0.25, 0.25, 3.5]])
    front, rear = box_layers(*BOX), box_layers(*back)
    layers = front.copy()
    both = np.isfinite(front[0]) & np.isfinite(rear[0])
    layers[2][both], layers[3][both] = rear[0][both], rear[1][both]
    occupied = layer_occupancy(layers, CAMERA.K, SMALL)
    assert occupied.sum() == voxel_count(*BOX) + voxel_count(*back)


def test_interpenetrating_closed_parts_fill_their_union():
    # parity over the whole mesh would empty the overlap; per component it is filled
    a = np.array([[-0.5, -0.25, 2.0], [0.0, 0.25, 2.5]])
    b = np.array([[-0.25, -0.25, 2.25], [0.25, 0.25, 2.75]])
    occupied = mesh_occupancy(concatenate([box_mesh(*a), box_mesh(*b)]), CAMERA.K, CAMERA.cam_to_world,
                              SHAPE, SMALL)
    overlap = voxel_count([-0.25, -0.25, 2.25], [0.0, 0.25, 2.5])
    assert occupied.sum() == voxel_count(*a) + voxel_count(*b) - overlap


def test_frustum_clipped_mesh_voxelises_like_the_whole_one():
    # a box reaching out of the left of the image, cut at the frustum as in docs/spec.md §5.1: the
    # cut leaves it open, but rays from the camera never cross the cut
    lo, hi = np.array([-2.0, -0.25, 2.0]), np.array([0.0, 0.25, 3.0])
    whole = box_mesh(lo, hi)
    cut, _ = clip_triangles(whole.triangles, frustum_planes(CAMERA))
    clipped = Mesh(*weld(cut))
    assert clipped.area < whole.area
    full = mesh_occupancy(whole, CAMERA.K, CAMERA.cam_to_world, SHAPE, SMALL)
    part = mesh_occupancy(clipped, CAMERA.K, CAMERA.cam_to_world, SHAPE, SMALL)
    inside = frustum_mask(CAMERA.K, SHAPE, SMALL)
    assert 0 < (part & inside).sum() < voxel_count(lo, hi)
    np.testing.assert_array_equal(part & inside, full & inside)


def test_open_surface_has_no_inside():
    b = trimesh.creation.box(bounds=BOX)
    top = b.faces[np.isclose(b.vertices[b.faces][:, :, 1], BOX[0, 1]).all(axis=1)]
    pose = CAMERA.cam_to_world
    sheet = Mesh(b.vertices @ pose[:3, :3].T + pose[:3, 3], top)
    assert not mesh_occupancy(sheet, CAMERA.K, CAMERA.cam_to_world, SHAPE, SMALL).any()


def test_frustum_and_empty_cases():
    inside = frustum_mask(CAMERA.K, SHAPE, SMALL)
    xy, z = SMALL.centres()
    # at depth z the image is 2 z tan(half-FOV) wide: the mask's width follows it
    k = 79  # z ≈ 2 m
    width = inside[k, SMALL.resolution // 2].sum() * SMALL.voxel
    assert width == pytest.approx(2 * z[k] * 160 / CAMERA.K[0, 0], abs=2 * SMALL.voxel)
    nothing = np.zeros((160,) * 3, dtype=bool)
    assert np.isnan(voxel_iou(nothing, nothing, inside).iou)
    assert not mesh_occupancy(Mesh.empty(), CAMERA.K, CAMERA.cam_to_world, SHAPE, SMALL).any()
    with pytest.raises(ValueError, match="unskewed"):
        skewed = CAMERA.K.copy()
        skewed[0, 1] = 1.0
        frustum_mask(skewed, SHAPE, SMALL)
