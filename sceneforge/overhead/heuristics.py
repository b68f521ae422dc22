"""The three heuristics that each propose a box on the floor plane (:class:`Candidate`), from a
frontal view's points (:class:`FrontalPoints`), and their weighted average (:func:`combine`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SceneforgeError
from .config import OverheadConfig
from .frame import Box

CANDIDATE_NAMES: tuple[str, ...] = ("depth_statistics", "envelope_frustum", "majority_room")


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
