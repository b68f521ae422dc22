"""The virtual overhead camera of a frontal view and its ground truth (SPEC §6, §7).

Frames used here:

- **World**: metres, +Y up (SPEC §1).
- **Gravity-aligned frame** of a frontal camera (:class:`GravityFrame`): origin at the
  camera centre, coordinates ``(right, up, forward)`` where ``forward`` is the view
  direction flattened onto the floor plane, ``up`` is world +Y and ``right`` is
  ``forward × up``. The overhead box lives on its floor plane as ``(right, forward)``.
- **Overhead camera** (:class:`OverheadCamera`): orthographic, OpenCV axes like every
  camera of the project — z forward = straight down, image y (down) = −forward, so the
  top of the overhead image is where the frontal camera looks, and image x = right.

Three heuristics *(ref)* each propose a box on the floor plane (:class:`Candidate`, kept
with its weight and the reason it was rejected); their weighted average, padded to a
square, is the overhead camera's extent. Ground truth is traced straight down with the
frontal multi-hit rules (:func:`sceneforge.layers.layers_from_hits`) on a reduced set of
surfaces (:func:`overhead_truth`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .conventions import (
    ENVELOPE_LAYER,
    NYU40_IDS,
    OBJECT_SEGMENTS,
    in_classes,
    overhead_pixel,
    overhead_pixel_centre,
    tol,
)
from .errors import SceneforgeError
from .floors import floor_surfaces, level_at
from .layers import Layers, instance_labels, layers_from_frontal

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses import House

CANDIDATE_NAMES: tuple[str, ...] = ("depth_statistics", "envelope_frustum", "majority_room")
FLOOR = NYU40_IDS["floor"]
#: Where a view's floor height comes from, in the order they are tried (see
#: :func:`frontal_points_fast`): the top of the floor straight below the camera, the median
#: height of the view's D5 floor pixels, the tops of the floors of the camera's level, the
#: level's ``floor_y`` (for SUNCG the bottom of its bounding box).
FLOOR_SOURCES: tuple[str, ...] = ("room floor", "view floor pixels", "level floor", "level bbox")


@dataclass(frozen=True)
class OverheadConfig:
    """How the overhead camera is placed and its ground truth traced. Defaults: the reference."""

    #: weights of the (depth statistics, envelope/frustum, majority room) boxes
    weights: tuple[float, float, float] = (1.0, 1.0, 2.0)
    #: candidates covering less floor area than this (m²) get weight 0
    min_area: float = 0.5
    #: overhead image size in pixels (square)
    resolution: int = 300
    #: the camera sits this far (m) below the highest frontal point of D1, D2 and D5,
    #: so that it is under the ceiling
    below_top: float = 0.05

    #: depth statistics: fewest D1–D4 points
    stats_min_points: int = 40
    #: depth statistics: box half-size = this × standard deviation
    stats_std_scale: float = 1.5
    #: depth statistics: smallest half-size (m), per axis
    stats_min_half_size: float = 0.5
    #: depth statistics: the box centre is pulled to within this distance (m) of the camera
    stats_max_distance: float = 9.0

    #: envelope/frustum: centre distance = this × mean camera-z of the D5 points
    envelope_depth_scale: float = 0.8
    #: envelope/frustum: the centre distance is clamped to this range (m)
    envelope_depth_range: tuple[float, float] = (1.0, 7.0)
    #: envelope/frustum: with fewer D5 points than this, the centre distance is the default
    envelope_min_points: int = 10
    #: envelope/frustum: centre distance (m) when D5 has too few points
    envelope_default_depth: float = 4.0
    #: envelope/frustum: half-size = this × tan(horizontal half-FOV) × centre distance
    envelope_zoom: float = 0.9

    #: majority room: fewest visible object pixels voting for a room
    room_min_votes: int = 20
    #: majority room: fewest object points of the winning room
    room_min_points: int = 15
    #: majority room: object points are used between these distances (m) from the camera
    room_distance_range: tuple[float, float] = (1.5, 9.0)
    #: majority room: the box's half-size is multiplied by this
    room_growth: float = 1.05
    #: majority room: classes whose points are ignored (NYU40 names or source labels)
    room_excluded: tuple[str, ...] = ("void", "person", "plant", "chandelier", "decoration")

    #: ground truth: classes ignored when tracing down (NYU40 names or source labels)
    truth_excluded: tuple[str, ...] = (
        "void", "person", "plant", "chandelier", "ceiling_fan", "decoration",
    )
    #: ground truth: floor hits closer than this (m) to the overhead camera are ignored
    floor_clearance: float = 0.5

    def __post_init__(self):
        if len(self.weights) != 3 or min(self.weights) < 0:
            raise ValueError(f"weights must be 3 numbers >= 0, got {self.weights}")
        if self.resolution < 1:
            raise ValueError(f"resolution must be at least 1 pixel, got {self.resolution}")
        for name in ("envelope_depth_range", "room_distance_range"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name} must be (low, high) with 0 <= low <= high, got {(lo, hi)}")


# ---------------------------------------------------------------------------- frames


@dataclass(frozen=True, eq=False)
class GravityFrame:
    """The gravity-aligned frame of a frontal camera.

    origin  : (3,) float64  camera centre, world
    right   : (3,) float64  unit, horizontal
    forward : (3,) float64  unit, horizontal: the view direction flattened
    theta   : float         angle (rad) between the view direction and gravity (−Y)
    """

    origin: np.ndarray
    right: np.ndarray
    forward: np.ndarray
    theta: float

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) float64 rows ``right, up, forward`` in world coordinates."""
        return np.stack([self.right, np.array([0.0, 1.0, 0.0]), self.forward])

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """World points (n, 3) → frame coordinates (n, 3) ``(right, up, forward)``."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Frame coordinates (n, 3) ``(right, up, forward)`` → world points (n, 3)."""
        return np.asarray(points, dtype=np.float64) @ self.axes + self.origin


def gravity_frame(camera: "Camera") -> GravityFrame:
    """The gravity-aligned frame of ``camera``. Raises for a camera looking straight up or down."""
    T = np.asarray(camera.cam_to_world, dtype=np.float64)
    view = T[:3, 2] / np.linalg.norm(T[:3, 2])
    flat = np.array([view[0], 0.0, view[2]])
    if np.linalg.norm(flat) < tol.horizontal_view:
        raise SceneforgeError(
            "the frontal camera looks straight up or down: its view direction has no "
            "horizontal part to align the overhead camera with"
        )
    forward = flat / np.linalg.norm(flat)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    theta = float(np.arccos(np.clip(-view[1], -1.0, 1.0)))
    return GravityFrame(origin=T[:3, 3].copy(), right=right, forward=forward, theta=theta)


# ----------------------------------------------------------------------- candidates


@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box on the floor plane of a gravity-aligned frame.

    lo, hi : (2,) float64  corners as ``(right, forward)``, metres
    """

    lo: np.ndarray
    hi: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """(2,) float64 ``(right, forward)``."""
        return 0.5 * (self.lo + self.hi)

    @property
    def half_size(self) -> np.ndarray:
        """(2,) float64 half widths along ``(right, forward)``."""
        return 0.5 * (self.hi - self.lo)

    @property
    def area(self) -> float:
        """Floor area, m²."""
        w = self.hi - self.lo
        return float(w[0] * w[1])

    def square(self) -> "Box":
        """The smallest square with the same centre that contains this box."""
        half = float(self.half_size.max())
        return Box(self.center - half, self.center + half)

    def __repr__(self) -> str:
        return (f"Box(right {self.lo[0]:.3f}..{self.hi[0]:.3f}, "
                f"forward {self.lo[1]:.3f}..{self.hi[1]:.3f})")


@dataclass(frozen=True)
class Candidate:
    """One heuristic's proposal: its box (None when it could not make one), the weight
    it got in the average (0 when rejected), why it was rejected, and how many points
    it used. The heuristics return weight 1 with a box and 0 without; :func:`combine`
    sets the final weights."""

    name: str
    box: Box | None
    weight: float
    reason: str | None = None
    n_points: int = 0


@dataclass(frozen=True, eq=False)
class FrontalPoints:
    """What the heuristics need from a frontal view, in its gravity-aligned frame.

    objects         : (n, 3) float64  D1–D4 points ``(right, up, forward)``, metres
    object_room     : (n,) int        room of each point's instance, as an index into
                      ``room_ids`` (-1: no room)
    object_excluded : (n,) bool       the point's instance is of a class the room box ignores
    envelope_z      : (k,) float64    planar depth (camera z) of the D5 points
    room_votes      : (r,) int64      visible object pixels (D1) of each room of ``room_ids``
    room_ids        : (r,) tuple      the house's room ids, sorted by ``str``: rooms are
                      integer codes so that voting is a ``bincount``, and this order makes
                      the smallest code the smallest room id (the vote's tie rule)
    top             : float           highest ``up`` of the D1, D2 and D5 points
    """

    objects: np.ndarray
    object_room: np.ndarray
    object_excluded: np.ndarray
    envelope_z: np.ndarray
    room_votes: np.ndarray
    room_ids: tuple
    top: float


def _rejected(name: str, reason: str, n_points: int = 0) -> Candidate:
    return Candidate(name, None, 0.0, reason, n_points)


def depth_statistics_box(objects: np.ndarray, config: OverheadConfig) -> Candidate:
    """Heuristic 1: mean ± scale·std of the D1–D4 points on the floor plane.

    All four object layers are used (the reference used D1, D2 twice by mistake). Per
    axis, the half-size is at least ``stats_min_half_size``; a centre further than
    ``stats_max_distance`` from the camera (on the floor plane) is pulled back onto that
    circle, as the reference does, instead of rejecting the box.
    """
    name = CANDIDATE_NAMES[0]
    pts = np.asarray(objects, dtype=np.float64).reshape(-1, 3)
    if len(pts) < config.stats_min_points:
        return _rejected(name, f"{len(pts)} object points < {config.stats_min_points}", len(pts))
    # Per column, without copying them out: frontal_points_fast's columns are contiguous.
    right, forward = pts[:, 0], pts[:, 2]
    mean = np.array([right.mean(), forward.mean()])
    std = np.array([right.std(), forward.std()])
    half = np.maximum(config.stats_std_scale * std, config.stats_min_half_size)
    dist = float(np.linalg.norm(mean))
    if dist > config.stats_max_distance:
        mean = mean * (config.stats_max_distance / dist)
    return Candidate(name, Box(mean - half, mean + half), 1.0, None, len(pts))


def envelope_frustum_box(
    envelope_z: np.ndarray, tan_half_fov: float, config: OverheadConfig
) -> Candidate:
    """Heuristic 2: a square on the flattened principal axis, sized by the frustum.

    Its centre is at distance d = ``envelope_depth_scale`` × mean D5 camera-z (clamped to
    ``envelope_depth_range``; ``envelope_default_depth`` with too few D5 points) straight
    ahead; its half-size is ``envelope_zoom`` × tan(horizontal half-FOV) × d.
    """
    z = np.asarray(envelope_z, dtype=np.float64).ravel()
    if len(z) < config.envelope_min_points:
        d = config.envelope_default_depth
    else:
        d = float(np.clip(config.envelope_depth_scale * z.mean(), *config.envelope_depth_range))
    half = config.envelope_zoom * tan_half_fov * d
    centre = np.array([0.0, d])
    return Candidate(CANDIDATE_NAMES[1], Box(centre - half, centre + half), 1.0, None, len(z))


def majority_room_box(
    objects: np.ndarray,
    object_room: np.ndarray,
    object_excluded: np.ndarray,
    room_votes: np.ndarray,
    room_ids: tuple,
    config: OverheadConfig,
) -> Candidate:
    """Heuristic 3: bounding box of the object points of the room most pixels see.

    Visible object pixels vote for their instance's room (ties: the smallest room id);
    the winner's object points between ``room_distance_range`` from the camera (3D
    distance), excluding ``room_excluded`` classes, are boxed and the box's half-size
    is grown by ``room_growth``.

    Rooms are codes into ``room_ids`` (see :class:`FrontalPoints`): ``object_room`` per
    point (-1: none), ``room_votes`` per room. ``room_ids`` must be sorted by ``str``, which
    makes the first of the most voted codes the winner of the tie rule.
    """
    name = CANDIDATE_NAMES[2]
    votes = np.asarray(room_votes, dtype=np.int64).ravel()
    if len(votes) != len(room_ids):
        raise ValueError(f"{len(votes)} room votes for {len(room_ids)} room ids")
    n_votes = int(votes.sum())
    # At least one vote, whatever room_min_votes says: with none there is no winner.
    if n_votes < max(config.room_min_votes, 1):
        return _rejected(name, f"{n_votes} room votes < {max(config.room_min_votes, 1)}")
    code = int(np.argmax(votes))
    room = room_ids[code]
    pts = np.asarray(objects, dtype=np.float64).reshape(-1, 3)
    # The distances are only needed for the winner's points: select them first, per
    # column (contiguous in frontal_points_fast's objects).
    sel = np.flatnonzero((np.asarray(object_room) == code) & ~np.asarray(object_excluded, bool))
    x, y, z = (pts[:, axis].take(sel) for axis in range(3))
    dist = x * x
    dist += y * y
    dist += z * z
    np.sqrt(dist, out=dist)  # the same sums, in the same order, as np.linalg.norm(axis=1)
    lo_d, hi_d = config.room_distance_range
    use = (dist >= lo_d) & (dist <= hi_d)
    n = int(np.count_nonzero(use))
    if n < config.room_min_points:
        return _rejected(name, f"{n} points of room {room!r} < {config.room_min_points}", n)
    x, z = x[use], z[use]
    lo, hi = np.array([x.min(), z.min()]), np.array([x.max(), z.max()])
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half = half * config.room_growth
    return Candidate(name, Box(centre - half, centre + half), 1.0, None, n)


def combine(candidates: tuple[Candidate, ...], config: OverheadConfig) -> tuple[tuple[Candidate, ...], Box]:
    """Weigh the candidates and average their corners.

    A candidate without a box or covering less than ``min_area`` gets weight 0 (and a
    reason); the others get their ``weights`` entry. Returns the weighted candidates and
    the averaged (not yet square) box. Raises :class:`SceneforgeError` when every weight
    is 0.
    """
    weighted = []
    for cand, w in zip(candidates, config.weights):
        if cand.box is None:
            weighted.append(cand)
        elif cand.box.area < config.min_area:
            weighted.append(Candidate(cand.name, cand.box, 0.0,
                                      f"area {cand.box.area:.3f} m² < {config.min_area} m²",
                                      cand.n_points))
        else:
            weighted.append(Candidate(cand.name, cand.box, float(w), None, cand.n_points))
    weights = np.array([c.weight for c in weighted])
    if not weights.sum() > 0:
        raise SceneforgeError(
            "no overhead box candidate is usable: "
            + "; ".join(f"{c.name}: {c.reason or 'weight 0'}" for c in weighted)
        )
    lo = sum(c.weight * c.box.lo for c in weighted if c.weight > 0) / weights.sum()
    hi = sum(c.weight * c.box.hi for c in weighted if c.weight > 0) / weights.sum()
    return tuple(weighted), Box(lo, hi)


# --------------------------------------------------------------------------- camera


@dataclass(frozen=True, eq=False)
class OverheadCamera:
    """An orthographic camera looking straight down (OpenCV axes: z = world −Y).

    cam_to_world : (4, 4) float64  pose; column 1 (image down) is −forward of the frontal
                   view, so the frontal view direction points to the top of the image
    half_extent  : float           half the side of the square it sees, metres
    resolution   : int             image width = height, pixels; pixel centres at integer + 0.5
    params       : (5,) float64    ``tx, ty`` box centre (right, forward of the frontal
                   camera), ``tz`` camera height above the floor, ``theta`` angle between
                   the frontal view direction and gravity, ``sigma`` half-diagonal of the box
    floor_y      : float           world height of the floor the heights refer to
    box          : Box             the square it sees, in the frontal gravity-aligned frame
    candidates   : the three heuristic boxes with their weights and rejection reasons
    floor_source : where ``floor_y`` came from, one of :data:`FLOOR_SOURCES` (None: given
                   by the caller)
    """

    cam_to_world: np.ndarray
    half_extent: float
    resolution: int
    params: np.ndarray
    floor_y: float
    box: Box
    candidates: tuple[Candidate, ...] = field(default=())
    floor_source: str | None = None

    @property
    def width(self) -> int:
        return self.resolution

    @property
    def height(self) -> int:
        return self.resolution

    def _pixel_centres(self) -> np.ndarray:
        """(resolution,) float64 camera-plane coordinate of the pixel centres along either
        image axis (x along a row, y down a column)."""
        return overhead_pixel_centre(np.arange(self.resolution), self.half_extent, self.resolution)

    def rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Parallel rays through the pixel centres, row-major.

        Returns origins (H*W, 3) float64 on the camera plane, directions (H*W, 3) float64
        (all world −Y) and depth_scale (H*W,) float64 (all 1: ray length = planar depth).
        ``directions`` and ``depth_scale`` are read-only broadcasts of one value (the
        tracer takes a broadcast direction as shared), and origins are one pass over the
        output: the sum of a per-column and a per-row term.
        """
        c = self._pixel_centres()
        R, t = self.cam_to_world[:3, :3], self.cam_to_world[:3, 3]
        n = self.resolution
        origins = np.empty((n, n, 3))
        # (t + x·R₀) + y·R₁ per pixel: column x, row y, summed in that order.
        np.add((t + c[:, None] * R[:, 0])[None, :, :], (c[:, None] * R[:, 1])[:, None, :], out=origins)
        origins = origins.reshape(n * n, 3)
        directions = np.broadcast_to(R[:, 2].copy(), origins.shape)
        depth_scale = np.broadcast_to(np.float64(1.0), (n * n,))
        return origins, directions, depth_scale

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (n, 3) → pixel coordinates uv (n, 2) (:func:`~sceneforge.conventions.overhead_pixel`)
        and depth below the camera z (n,)."""
        R, t = self.cam_to_world[:3, :3], self.cam_to_world[:3, 3]
        p = (np.asarray(points_world, dtype=np.float64) - t) @ R
        return overhead_pixel(p[:, :2], self.half_extent, self.resolution), p[:, 2]


def level_floor_y(house: "House", y: float) -> float:
    """``floor_y`` of the storey a point at height ``y`` is on (the lowest if it is below all):
    the last resort of a view's floor height, as it may be a bounding box's bottom."""
    return level_at(house, y).floor_y


def _class_mask(house: "House", names) -> np.ndarray:
    """(n_inst,) bool: the instance's NYU40 class or its source label is in ``names``."""
    names = frozenset(names)
    return np.array([in_classes(i.category, i.label, names) for i in house.instances], dtype=bool)


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

    The plain algorithm (SPEC §6), which ``plain_frontal_points`` in tests/test_overhead.py
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
    excluded = np.append(_class_mask(house, config.room_excluded), False)
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


def place_overhead_camera(
    frame: GravityFrame,
    points: FrontalPoints,
    tan_half_fov: float,
    floor_y: float,
    config: OverheadConfig | None = None,
    floor_source: str | None = None,
) -> OverheadCamera:
    """The overhead camera from a frontal view's points (SPEC §6).

    tan_half_fov : tan of the frontal camera's horizontal half field of view
    floor_y      : world height of the floor (``tz`` is the camera height above it)
    floor_source : where ``floor_y`` came from (:data:`FLOOR_SOURCES`), kept with the camera
    """
    config = config or OverheadConfig()
    candidates = (
        depth_statistics_box(points.objects, config),
        envelope_frustum_box(points.envelope_z, tan_half_fov, config),
        majority_room_box(points.objects, points.object_room, points.object_excluded,
                          points.room_votes, points.room_ids, config),
    )
    candidates, box = combine(candidates, config)
    square = box.square()
    half = float(square.half_size[0])
    up = points.top - config.below_top
    tx, ty = square.center
    position = frame.to_world(np.array([[tx, up, ty]]))[0]
    pose = np.eye(4)
    pose[:3, 0] = frame.right
    pose[:3, 1] = -frame.forward
    pose[:3, 2] = (0.0, -1.0, 0.0)
    pose[:3, 3] = position
    params = np.array([tx, ty, position[1] - floor_y, frame.theta, half * np.sqrt(2.0)])
    return OverheadCamera(pose, half, int(config.resolution), params, float(floor_y), square,
                          candidates, floor_source)


def overhead_camera_and_points(
    house: "House", camera: "Camera", layers: Layers, config: OverheadConfig | None = None
) -> tuple[OverheadCamera, FrontalPoints]:
    """The overhead camera of a frontal view and the frontal points it was chosen from."""
    config = config or OverheadConfig()
    frame = gravity_frame(camera)
    points, floor_y, source = frontal_points_fast(house, camera, layers, frame, config)
    tan_half_fov = float(np.tan(camera.half_fov[0]))
    return place_overhead_camera(frame, points, tan_half_fov, floor_y, config, source), points


def overhead_camera(
    house: "House", camera: "Camera", layers: Layers, config: OverheadConfig | None = None
) -> OverheadCamera:
    """The overhead camera of a frontal view (SPEC §6)."""
    return overhead_camera_and_points(house, camera, layers, config)[0]


# ---------------------------------------------------------------------- ground truth


@dataclass(frozen=True, eq=False)
class OverheadTruth:
    """Ground truth seen by an overhead camera (SPEC §7).

    layers   : Layers                 5 overhead depth layers (planar = distance below the
               camera), classes and instances, same rules as the frontal ones
    height   : (H, W) float32         height above ``floor_y`` of the first object hit;
               NaN where only the floor or nothing is hit
    category : (H, W) uint8           NYU40 class of the first object hit, else of the
               floor below, else 0
    floor_y  : float                  world height of the floor
    """

    layers: Layers
    height: np.ndarray
    category: np.ndarray
    floor_y: float


def overhead_instances(house: "House", config: OverheadConfig | None = None) -> np.ndarray:
    """(n_instances,) bool: the instances an overhead view sees (SPEC §7): objects not of the
    ``truth_excluded`` classes, and floors; no other envelope surface."""
    config = config or OverheadConfig()
    category, envelope = instance_labels(house)
    return ~_class_mask(house, config.truth_excluded) & (~envelope | (category == FLOOR))


def overhead_truth(
    house: "House", camera: OverheadCamera, tracer, config: OverheadConfig | None = None
) -> OverheadTruth:
    """Trace straight down from ``camera`` and build the overhead layers and height map.

    tracer : a :class:`sceneforge.raytrace.HouseTracer` of ``house``
    """
    config = config or OverheadConfig()
    origins, directions, depth_scale = camera.rays()
    category, envelope = instance_labels(house)
    seen = overhead_instances(house, config)
    # The query itself applies SPEC §7's filters: only the instances an overhead view sees,
    # and the first floor beyond the clearance closes each ray as the envelope does in a
    # frontal view (tests/test_view.py checks this against tracing every hit and filtering).
    hits = tracer.frontal_query(origins, directions, objects=seen & ~envelope, envelope=seen & envelope,
                                envelope_near=config.floor_clearance)
    layers = layers_from_frontal(hits, depth_scale, category, (camera.height, camera.width))
    top = float(camera.cam_to_world[1, 3])
    height = (top - layers.depth[0].astype(np.float64) - camera.floor_y).astype(np.float32)
    first = np.isfinite(layers.depth[0])
    category = np.where(first, layers.category[0], layers.envelope_category).astype(np.uint8)
    return OverheadTruth(layers, height, category, camera.floor_y)
