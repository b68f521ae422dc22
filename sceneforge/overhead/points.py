"""A frontal view's points in its gravity-aligned frame, what the heuristics need
(:func:`frontal_points_fast`), and the view's floor height."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..conventions import ENVELOPE_LAYER, OBJECT_SEGMENTS
from ..errors import SceneforgeError
from ..floors import floor_surfaces, level_at
from ..layers import Layers
from .config import FLOOR, OverheadConfig, class_mask
from .frame import GravityFrame
from .heuristics import FrontalPoints

if TYPE_CHECKING:
    from ..cameras import Camera
    from ..houses import House

#: Where a view's floor height comes from, in the order they are tried (see
#: :func:`frontal_points_fast`): the top of the floor straight below the camera, the median
#: height of the view's D5 floor pixels, the tops of the floors of the camera's level, the
#: level's ``floor_y`` (for SUNCG the bottom of its bounding box).
FLOOR_SOURCES: tuple[str, ...] = ("room floor", "view floor pixels", "level floor", "level bbox")


def level_floor_y(house: "House", y: float) -> float:
    """``floor_y`` of the storey a point at height ``y`` is on (the lowest if it is below all):
    the last resort of a view's floor height, as it may be a bounding box's bottom."""
    return level_at(house, y).floor_y


def _room_codes(house: "House") -> tuple[tuple, np.ndarray]:
    """The house's room ids sorted by ``str``, and (n_instances + 1,) int32 each instance's
    index among them (-1: no room); the extra last entry (-1) is what instance -1 indexes."""
    ids = [i.room_id for i in house.instances]
    room_ids = tuple(sorted({r for r in ids if r is not None}, key=str))
    code = {r: k for k, r in enumerate(room_ids)}
    return room_ids, np.array([code.get(r, -1) for r in ids] + [-1], dtype=np.int32)


def _frame_rays(camera: "Camera", frame: GravityFrame) -> np.ndarray:
    """(3, H*W) float64: frame coordinates ``(right, up, forward)`` of each pixel's point at
    planar depth 1, relative to the camera centre, row-major pixels.

    The point of pixel (u, v) at planar depth z is z·K⁻¹[u, v, 1] in camera coordinates, so
    its frame coordinates are z·A[u, v, 1] with A = axes·R·K⁻¹. With this table a layer's
    points are a gather and a product per axis: no world points, no per-layer transform.
    Stored per axis, so that gathers and the points' columns are contiguous.
    """
    H, W = camera.shape
    A = frame.axes @ camera.cam_to_world[:3, :3] @ np.linalg.inv(camera.K)
    u, v = np.arange(W) + 0.5, np.arange(H) + 0.5
    table = np.empty((3, H, W))
    np.add((A[:, 1:2] * v + A[:, 2:3])[:, :, None], (A[:, 0:1] * u)[:, None, :], out=table)
    return table.reshape(3, H * W)


def _take_columns(table: np.ndarray, idx: np.ndarray, out: np.ndarray) -> None:
    """``out[:] = table[:, idx]`` for a (3, m) table, one contiguous row at a time.

    ``mode="clip"`` (the indices are in range) lets ``take`` write straight into ``out``;
    the default mode goes through a buffer.
    """
    for axis in range(3):
        table[axis].take(idx, out=out[axis], mode="clip")


def _layer_pixels(finite: np.ndarray) -> dict[int, np.ndarray]:
    """Per layer, the flat indices of its finite pixels; ``finite : (5, H*W) bool``.

    When D2 has D1's pixels (D4 D3's), its entry *is* D1's array: :func:`_object_points`
    tests that with ``is`` to reuse D1's gathers.
    """
    pixels = {}
    for front, back in OBJECT_SEGMENTS:
        pixels[front] = np.flatnonzero(finite[front])
        # D2 is usually finite where D1 is, and D4 where D3 is: gather their rays once.
        same = np.array_equal(finite[back], finite[front])
        pixels[back] = pixels[front] if same else np.flatnonzero(finite[back])
    pixels[ENVELOPE_LAYER] = np.flatnonzero(finite[ENVELOPE_LAYER])
    return pixels


def _object_points(
    rays: np.ndarray, depth: np.ndarray, instance: np.ndarray, pixels: dict[int, np.ndarray], offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The frame points of D1..D4's finite pixels and the instance of each one's layer.

    rays     : (3, H*W) float64  :func:`_frame_rays`
    depth    : (5, H*W) float    planar depths, NaN: no surface
    instance : (2, H*W) int      D1 and D3 instances
    pixels   : :func:`_layer_pixels`
    offset   : (3,) float64      the camera centre in the frame

    Returns ``objects : (3, n) float64`` (D1, D2, D3, D4 pixels in that order, one row per
    axis) and ``inst : (n,)`` of ``instance``'s dtype: D1's instance for D1 and D2, D3's
    for D3 and D4.
    """
    n = sum(len(pixels[layer]) for segment in OBJECT_SEGMENTS for layer in segment)
    objects = np.empty((3, n))  # returned transposed: (n, 3) with contiguous columns
    inst = np.empty(n, dtype=instance.dtype)
    start = 0
    for inst_layer, (front, back) in enumerate(OBJECT_SEGMENTS):
        i_front, i_back = pixels[front], pixels[back]
        mid = start + len(i_front)
        end = mid + len(i_back)
        out_front, out_back = objects[:, start:mid], objects[:, mid:end]
        _take_columns(rays, i_back, out_back)
        instance[inst_layer].take(i_back, out=inst[mid:end], mode="clip")
        if i_front is i_back:  # the same pixels: scale the back layer's rays
            np.multiply(out_back, depth[front].take(i_front), out=out_front)
            inst[start:mid] = inst[mid:end]
        else:
            _take_columns(rays, i_front, out_front)
            out_front *= depth[front].take(i_front)
            instance[inst_layer].take(i_front, out=inst[start:mid], mode="clip")
        out_back *= depth[back].take(i_back)
        start = end
    if offset.any():
        objects += offset[:, None]
    return objects, inst


def _envelope_points(
    rays: np.ndarray, depth: np.ndarray, env_category: np.ndarray, pixels: dict[int, np.ndarray], offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """D5's finite pixels: ``(envelope_z, env_up, env_category)``, each ``(k,)``.

    ``envelope_z`` float64 planar depths, ``env_up`` float64 heights in the frame,
    ``env_category`` their classes, from ``env_category : (H*W,)``; the other arguments as
    :func:`_object_points`. When D5 is finite everywhere, ``rays``' up row becomes
    ``env_up`` in place (no gathers, no new array): call this after the object points.
    """
    env_idx = pixels[ENVELOPE_LAYER]
    if len(env_idx) == depth.shape[1]:  # the usual case: D5 everywhere, no gathers
        envelope_z = depth[ENVELOPE_LAYER].astype(np.float64)
        env_up = np.multiply(rays[1], envelope_z, out=rays[1])  # the table is used up
    else:
        envelope_z = depth[ENVELOPE_LAYER].take(env_idx).astype(np.float64)
        env_up = rays[1].take(env_idx)
        env_up *= envelope_z
        env_category = env_category.take(env_idx)
    if offset[1]:
        env_up += offset[1]
    return envelope_z, env_up, env_category


def _room_votes(
    d1_instance: np.ndarray, d1_point_instance: np.ndarray, d1_point_room: np.ndarray, inst_room: np.ndarray,
    n_rooms: int,
) -> np.ndarray:
    """(n_rooms,) int64: per room, the pixels whose D1 instance (``d1_instance : (H*W,)``,
    >= 0: visible) is in it.

    ``d1_point_instance`` and ``d1_point_room``, ``(n1,)``, are the instances and rooms of
    the finite D1 pixels' points; ``inst_room`` is :func:`_room_codes`' table.
    """
    # Usually the visible pixels are all finite D1 pixels, whose rooms are at hand; else
    # every pixel's room is looked up.
    if np.count_nonzero(d1_instance >= 0) == np.count_nonzero(d1_point_instance >= 0):
        voters = d1_point_room
    else:
        voters = inst_room.take(d1_instance)
    return np.bincount(voters + 1, minlength=n_rooms + 1)[1:]


def _view_floor(
    house: "House", camera: "Camera", frame: GravityFrame, env_up: np.ndarray, env_category: np.ndarray
) -> tuple[float, str]:
    """The view's floor height and which of :data:`FLOOR_SOURCES` gave it (the rules of
    :func:`frontal_points_fast`), from the D5 points' ``env_up`` and ``env_category``,
    both ``(k,)`` (:func:`_envelope_points`)."""
    eye = camera.cam_to_world[:3, 3]
    surfaces = floor_surfaces(house)
    floor_y = surfaces.height_below(eye)
    if floor_y is not None:
        return floor_y, FLOOR_SOURCES[0]
    floor = env_category == FLOOR
    if floor.any():
        # The frame's up axis is world +Y from the frame origin.
        floor_y = float(np.median(env_up[floor], overwrite_input=True)) + float(frame.origin[1])
        return floor_y, FLOOR_SOURCES[1]
    floor_y = surfaces.level_height(level_at(house, float(eye[1])).id, float(eye[1]))
    if floor_y is not None:
        return floor_y, FLOOR_SOURCES[2]
    return level_floor_y(house, float(eye[1])), FLOOR_SOURCES[3]


def frontal_points_fast(
    house: "House", camera: "Camera", layers: Layers, frame: GravityFrame, config: OverheadConfig
) -> tuple[FrontalPoints, float, str]:
    """Collect the heuristics' inputs from a frontal view, the view's floor height and its source.

    The plain algorithm (docs/spec.md §6), which ``plain_frontal_points`` in tests/test_overhead.py
    spells out and ``test_frontal_points_fast_equals_the_plain_version_on_toy_views`` holds
    this to bit for bit: every finite pixel of D1..D4 gives the point of its ray at that
    planar depth, in the gravity frame, with the room and the exclusion of its layer's
    instance (D1 and D2: the D1 instance, D3 and D4: the D3 one); D5's finite pixels give
    their planar depths and heights; the top is the highest point of D1, D2 and D5; each
    pixel with a D1 instance votes for that instance's room. The floor height is the first
    of :data:`FLOOR_SOURCES` that exists: the top of the floor straight below the camera
    (:meth:`~sceneforge.floors.FloorSurfaces.height_below`: the camera's room, whatever
    rugs or objects hide in the view); else the median world height of the D5 pixels whose
    class is floor; else the area-weighted median top of the floors of the camera's level
    (:meth:`~sceneforge.floors.FloorSurfaces.level_height`); else that level's ``floor_y``.

    The fast kernel: every pass over a layer's pixels costs, so the points are built
    straight in the frame from one per-view table (:func:`_frame_rays`) into one
    preallocated array, D2 and D4 reuse the gathers of D1 and D3 when they have the same
    pixels (as traced layers do), and rooms are integer codes counted with ``bincount``.
    """
    if layers.shape != camera.shape:
        raise ValueError(f"layers are {layers.shape} pixels but the camera is {camera.shape} (H, W)")
    H, W = camera.shape
    rays = _frame_rays(camera, frame)
    # Frame coordinates of the camera centre: zero for the camera's own gravity frame.
    offset = frame.to_frame(camera.cam_to_world[None, :3, 3])[0]
    room_ids, inst_room = _room_codes(house)
    excluded = np.append(class_mask(house, config.room_excluded), False)
    depth = np.asarray(layers.depth).reshape(5, H * W)
    instance = np.asarray(layers.instance).reshape(2, H * W)
    pixels = _layer_pixels(np.isfinite(depth))
    objects, inst = _object_points(rays, depth, instance, pixels, offset)
    env_category = np.asarray(layers.envelope_category).reshape(H * W)
    envelope_z, env_up, env_category = _envelope_points(rays, depth, env_category, pixels, offset)

    d1, d2 = OBJECT_SEGMENTS[0]
    n1 = len(pixels[d1])
    n12 = n1 + len(pixels[d2])
    tops = [t for t in (objects[1, :n12], env_up) if len(t)]
    if not tops:
        raise SceneforgeError("the frontal view sees no surface: cannot place an overhead camera")
    # -1 (no instance) indexes the appended "no room, not excluded" entries.
    object_room = inst_room.take(inst)
    points = FrontalPoints(
        objects=objects.T,
        object_room=object_room,
        object_excluded=excluded.take(inst),
        envelope_z=envelope_z,
        room_votes=_room_votes(instance[0], inst[:n1], object_room[:n1], inst_room, len(room_ids)),
        room_ids=room_ids,
        top=float(max(t.max() for t in tops)),
    )
    floor_y, floor_source = _view_floor(house, camera, frame, env_up, env_category)
    return points, floor_y, floor_source
