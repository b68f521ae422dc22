"""The seeded camera sampler (docs/spec.md §3): cameras placed per room of a house, each candidate
traced and checked, the best kept (:func:`sample_cameras`, set by :class:`CameraSamplerConfig`).
Its generator is passed in; the cameras themselves are :class:`sceneforge.cameras.Camera`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .cameras import DEFAULT_HALF_FOV_X, DEFAULT_PITCH, Camera, default_intrinsics, pose_from_view
from .conventions import NYU40_IDS, is_floor_cover, tol
from .errors import HouseError
from .floors import floor_surfaces
from .layers import instance_labels, layers_from_frontal
from .raytrace import HouseTracer

if TYPE_CHECKING:
    from .floors import FloorSurfaces
    from .houses.model import House

#: Why :func:`sample_cameras` turned a candidate down, in the order the checks run; the
#: last, ``outscored``, is a valid candidate its room had better ones than.
REJECT_REASONS = (
    "not_above_floor", "too_close", "escapes", "mostly_void", "mostly_envelope", "few_objects", "outscored",
)
#: The terms of a candidate's score (:meth:`CameraSamplerConfig.score`), in the order of
#: ``score_weights`` and ``score_saturation``.
SCORE_TERMS = ("objects", "d3_fraction", "envelope_distance")


@dataclass(frozen=True)
class CameraSamplerConfig:
    """How :func:`sample_cameras` places cameras. Field docs become the config schema's descriptions."""

    #: camera height above the floor under it, metres
    eye_height: float = 1.5
    #: downward pitch of the view direction, radians (default: tan = 0.2, 11.31°)
    pitch: float = DEFAULT_PITCH
    #: image width of the sampled cameras, pixels
    width: int = 320
    #: image height of the sampled cameras, pixels
    height: int = 240
    #: horizontal half field of view, radians
    half_fov_x: float = DEFAULT_HALF_FOV_X
    #: reject a camera closer than this to any surface, metres
    min_surface_distance: float = 0.4
    #: reject a view where fewer pixels than this fraction see a labelled (not void) object first
    min_object_fraction: float = 0.1
    #: reject a view where more pixels than this fraction hit nothing (escape the house)
    max_escape_fraction: float = 0.05
    #: reject a view where more pixels than this fraction see a void (unlabelled) object
    #: first: geometry the name map did not recognise, often walls (no view of the bundled
    #: toy houses or the breakfast room sees any void; void walls fill 50–80 % of a view)
    max_void_fraction: float = 0.3
    #: reject a view where more pixels than this fraction see the room envelope first (a
    #: view of a bare wall or floor; 22–63 % of the candidates standing free in the bundled
    #: toy houses and the breakfast room are above 0.9)
    max_envelope_fraction: float = 0.9
    #: width of the low-resolution image the view checks and the score trace (same field of view)
    check_width: int = 80
    #: height of the low-resolution image the view checks and the score trace
    check_height: int = 60
    #: give up on a room after this many candidates per camera it is to get
    candidates_per_camera: int = 50
    #: valid candidates scored per requested camera of a room; the best-scoring are kept
    #: (1: the first valid candidates, no choice)
    pool_per_camera: int = 4
    #: weights of the score terms (distinct objects seen, fraction of pixels with a D3,
    #: median D5 depth)
    score_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: each score term counts up to this value and no further (objects, D3 fraction, metres)
    score_saturation: tuple[float, float, float] = (8.0, 0.08, 4.0)
    #: the cameras kept in a room stand at least this far apart (m) where its valid
    #: candidates allow it, so that the best spot of a room is not taken twice
    min_separation: float = 1.0

    def __post_init__(self):
        if not self.eye_height > 0:
            raise ValueError(f"eye_height must be positive, got {self.eye_height}")
        if not -math.pi / 2 < self.pitch < math.pi / 2:
            raise ValueError(f"pitch must be in (-pi/2, pi/2) radians, got {self.pitch}")
        for name in ("min_object_fraction", "max_escape_fraction", "max_void_fraction", "max_envelope_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("width", "height", "check_width", "check_height", "candidates_per_camera",
                     "pool_per_camera"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if len(self.score_weights) != 3 or min(self.score_weights) < 0:
            raise ValueError(f"score_weights must be 3 numbers >= 0, got {self.score_weights}")
        if len(self.score_saturation) != 3 or not min(self.score_saturation) > 0:
            raise ValueError(f"score_saturation must be 3 numbers > 0, got {self.score_saturation}")
        if self.min_separation < 0:
            raise ValueError(f"min_separation must be >= 0, got {self.min_separation}")

    def view_direction(self, yaw: float) -> np.ndarray:
        """(3,) float64 unit view direction for a yaw (radians, 0 = +Z, pi/2 = +X) at the pitch."""
        c = math.cos(self.pitch)
        return np.array([c * math.sin(yaw), -math.sin(self.pitch), c * math.cos(yaw)])

    def score(self, stats: "ViewStats") -> float:
        """How informative a view is, the way PBRS chose its cameras: the weighted sum of
        :data:`SCORE_TERMS`, each divided by its saturation and capped at 1 (0 for a view
        with no envelope in sight)."""
        distance = stats.envelope_distance if math.isfinite(stats.envelope_distance) else 0.0
        terms = (stats.objects, stats.d3_fraction, distance)
        return float(sum(w * min(t / s, 1.0)
                         for w, t, s in zip(self.score_weights, terms, self.score_saturation)))


@dataclass(frozen=True)
class ViewStats:
    """What a view sees, from its layers (:class:`~sceneforge.layers.Layers`, any size).

    The fractions are of the view's pixels and say what each pixel sees first: nothing
    (``escape``), the envelope, a void (unlabelled) object, a labelled object; they sum to 1.
    ``objects`` counts the distinct labelled object instances of D1, ``d3_fraction`` is the
    fraction of pixels with a D3 (an occluded second object), ``envelope_distance`` the
    median planar depth of D5 in metres (NaN: no envelope in view).
    """

    objects: int
    d3_fraction: float
    envelope_distance: float
    escape_fraction: float
    envelope_fraction: float
    void_fraction: float
    object_fraction: float

    @classmethod
    def of(cls, layers) -> "ViewStats":
        d1, d5 = np.isfinite(layers.depth[0]), np.isfinite(layers.depth[4])
        labelled = d1 & (layers.category[0] != 0)
        env = layers.depth[4][d5]
        return cls(
            objects=int(len(np.unique(layers.instance[0][labelled]))),
            d3_fraction=float(np.isfinite(layers.depth[2]).mean()),
            envelope_distance=float(np.median(env)) if len(env) else math.nan,
            escape_fraction=float((~d1 & ~d5).mean()),
            envelope_fraction=float((~d1 & d5).mean()),
            void_fraction=float((d1 & ~labelled).mean()),
            object_fraction=float(labelled.mean()),
        )

    def to_dict(self) -> dict:
        """JSON-ready, rounded to 4 decimals; a NaN distance is None."""
        return {k: (None if isinstance(v, float) and math.isnan(v) else round(v, 4) if isinstance(v, float) else v)
                for k, v in asdict(self).items()}


@dataclass
class RoomSampling:
    """One room's part of a sampling: its floor, its share of the cameras and what came of it.

    ``room`` is None for floors without a room (one entry per level).
    """

    room: str | None
    level: int
    floor_area: float
    share: int
    candidates: int = 0
    valid: int = 0
    accepted: int = 0


@dataclass
class SampledView:
    """An accepted camera's room, level, score and what it sees at the check resolution."""

    room: str | None
    level: int
    score: float
    stats: ViewStats


@dataclass
class SamplerReport:
    """What :func:`sample_cameras` did: candidates tried, why each rejected one failed, each
    room's share, the rooms skipped and why, and the accepted views' statistics (in the
    order of the cameras)."""

    requested: int
    accepted: int = 0
    candidates: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECT_REASONS, 0))
    rooms: list[RoomSampling] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    views: list[SampledView] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready: counts, per-reason rejections, rooms, skipped rooms, per-view stats."""
        return {
            "requested": self.requested,
            "accepted": self.accepted,
            "candidates": self.candidates,
            "rejected": dict(self.rejected),
            "rooms": [{**asdict(r), "floor_area": round(r.floor_area, 3)} for r in self.rooms],
            "skipped": dict(self.skipped),
            "views": [{"room": v.room, "level": v.level, "score": round(v.score, 4), **v.stats.to_dict()}
                      for v in self.views],
        }

    def lines(self) -> list[str]:
        """The report as text: one summary line, the rejections, each room, each view."""
        out = [f"cameras: {self.accepted} of {self.requested} accepted from {self.candidates} candidates"]
        rejected = ", ".join(f"{k} {v}" for k, v in self.rejected.items() if v)
        out.append(f"  rejected: {rejected or 'none'}")
        for r in self.rooms:
            out.append(f"  room {r.room or '(none)'} (level {r.level}, floor {r.floor_area:.1f} m²): share {r.share}, "
                       f"{r.candidates} candidates, {r.valid} valid, {r.accepted} accepted")
        for room, why in self.skipped.items():
            out.append(f"  room {room} skipped: {why}")
        for i, v in enumerate(self.views):
            st = v.stats
            out.append(f"  view {i}: room {v.room or '(none)'}, {st.objects} objects, D3 on "
                       f"{100 * st.d3_fraction:.1f} % of pixels, envelope at {st.envelope_distance:.2f} m "
                       f"(median), score {v.score:.3f}")
        return out


@dataclass(eq=False)
class _Candidate:
    """A valid candidate: its camera, eye, score and statistics, and the order it came in."""

    order: int
    camera: Camera
    score: float
    stats: ViewStats


def _floor_triangles(house: "House") -> "FloorSurfaces":
    """The walkable floor triangles of ``house`` (:func:`sceneforge.floors.floor_surfaces`).

    Raises :class:`HouseError` when there are none.
    """
    surfaces = floor_surfaces(house)
    if not len(surfaces):
        raise HouseError(house.id, house.source_path, "no horizontal floor surface to place cameras on")
    return surfaces


def _rooms_to_sample(house: "House", surfaces: "FloorSurfaces", n: int, report: SamplerReport) -> list:
    """The rooms with a floor, each with its floor triangles and share of ``n`` cameras.

    Rooms are taken in ``house.rooms`` order, then rooms only instances name (by id), then
    floors without a room, one per level. Each gets ``n // rooms`` cameras, and the
    remainder goes one each to the largest floors. Rooms without a floor go to
    ``report.skipped`` with the reason.
    """
    floor_rooms = {i.room_id for i in house.instances if i.category == NYU40_IDS["floor"]}
    walkable = set(surfaces.room.tolist())
    keys = []
    for room in house.rooms:
        if room.id in walkable:
            keys.append((room.id, None))
        else:
            report.skipped[str(room.id)] = ("its floor has no up-facing horizontal face" if room.id in floor_rooms
                                            else "no floor instance")
    known = {room.id for room in house.rooms}
    keys += [(r, None) for r in sorted(walkable - known - {None}, key=str)]
    keys += [(None, lv) for lv in sorted({int(lv) for lv, r in zip(surfaces.level, surfaces.room) if r is None})]
    cells = []
    for room, level in keys:
        keep = np.array([r == room if room is not None else r is None and lv == level
                         for r, lv in zip(surfaces.room, surfaces.level)], dtype=bool)
        tris = surfaces.subset(keep)
        cells.append((RoomSampling(room, int(tris.level[0]), float(tris.area.sum()), n // len(keys)), tris))
    by_area = sorted(range(len(cells)), key=lambda k: -cells[k][0].floor_area)
    for k in by_area[: n % len(cells)]:
        cells[k][0].share += 1
    return cells


def _select(valid: list[_Candidate], k: int, min_separation: float) -> list[_Candidate]:
    """The ``k`` best-scoring candidates (ties: the earlier one), skipping those closer than
    ``min_separation`` to one already kept while others remain."""
    ranked = sorted(valid, key=lambda c: (-c.score, c.order))
    kept: list[_Candidate] = []
    for c in ranked:
        if len(kept) == k:
            break
        if all(np.linalg.norm(c.camera.position - o.camera.position) >= min_separation for o in kept):
            kept.append(c)
    for c in ranked:  # not enough far apart: fill up with the best of the rest
        if len(kept) == k:
            break
        if c not in kept:
            kept.append(c)
    return sorted(kept, key=lambda c: (-c.score, c.order))


class _ViewCheck:
    """The rejection rules of :func:`sample_cameras`, for one house and config.

    Calling it with a candidate's ``eye : (3,) float64`` and ``yaw`` (radians) gives
    ``(reason, camera, stats)``: the first rule the view breaks and ``(None, None)``, or
    ``None`` with its :class:`Camera` at ``config.width``×``config.height`` and the
    :class:`ViewStats` of its layers traced at ``check_width``×``check_height``.
    """

    def __init__(self, house: "House", config: CameraSamplerConfig, tracer: "HouseTracer"):
        self.config = config
        self.tracer = tracer
        self.K = default_intrinsics(config.width, config.height, config.half_fov_x)
        self.inst_category, _ = instance_labels(house)
        # index -1 (no hit) reads the extra False at the end
        self.is_floor = np.array([i.category == NYU40_IDS["floor"] for i in house.instances] + [False])
        self.is_cover = np.array([is_floor_cover(i.category, i.label) for i in house.instances] + [False])
        #: straight down, the one ray of the ``not_above_floor`` check: (1, 3) float64
        self.down = np.array([[0.0, -1.0, 0.0]])

    def __call__(self, eye: np.ndarray, yaw: float) -> tuple[str | None, Camera | None, ViewStats | None]:
        reason = self._placement(eye)
        if reason is not None:
            return reason, None, None
        camera = Camera(self.K, pose_from_view(eye, self.config.view_direction(yaw)),
                        self.config.width, self.config.height)
        stats = self._stats(camera)
        reason = self._content(stats)
        if reason is not None:
            return reason, None, None
        return None, camera, stats

    def _placement(self, eye: np.ndarray) -> str | None:
        """``not_above_floor`` or ``too_close`` for ``eye : (3,) float64``, else None.

        These need two rays, not a view, so they run before the view is traced.
        """
        h = self.config.eye_height
        below = self.tracer.first_hit(eye[None], self.down)
        k, t = below.instance[0], below.t[0]
        on_floor = self.is_floor[k] and abs(t - h) < tol.eye_above_floor
        on_cover = self.is_cover[k] and h - tol.floor_cover <= t <= h + tol.eye_above_floor
        if not (on_floor or on_cover):
            return "not_above_floor"
        if self.tracer.closest_distance(eye[None])[0] < self.config.min_surface_distance:
            return "too_close"
        return None

    def _stats(self, camera: Camera) -> ViewStats:
        """The statistics of ``camera``'s layers, traced at the small check resolution (the
        same field of view) because a candidate only needs to be judged, not rendered."""
        small = camera.resized(self.config.check_width, self.config.check_height)
        origins, directions, depth_scale = small.rays()
        layers = layers_from_frontal(self.tracer.frontal_query(origins, directions), depth_scale,
                                     self.inst_category, small.shape)
        return ViewStats.of(layers)

    def _content(self, stats: ViewStats) -> str | None:
        """The first of ``escapes``, ``mostly_void``, ``mostly_envelope``, ``few_objects``
        that ``stats`` breaks, else None."""
        config = self.config
        if stats.escape_fraction > config.max_escape_fraction:
            return "escapes"
        if stats.void_fraction > config.max_void_fraction:
            return "mostly_void"
        if stats.envelope_fraction > config.max_envelope_fraction:
            return "mostly_envelope"
        if stats.object_fraction < config.min_object_fraction:
            return "few_objects"
        return None


def _draw_eye(tris: "FloorSurfaces", p_tri: np.ndarray, eye_height: float,
              rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A candidate's ``eye : (3,) float64``, ``eye_height`` above a point uniform by area on
    ``tris`` (``p_tri : (n,) float64``, their areas' shares), and its uniform yaw in radians.

    Consumes ``rng`` as the sampler always has: the triangle, two barycentric draws, the yaw.
    """
    k = rng.choice(len(tris), p=p_tri)
    r1, r2, yaw = rng.random(), rng.random(), rng.random() * 2 * math.pi
    # sqrt(r1) makes the point uniform over the triangle's area, not crowded at corner a
    s = math.sqrt(r1)
    a, b, c = tris.corners[k]
    eye = (1 - s) * a + s * (1 - r2) * b + s * r2 * c + [0.0, eye_height, 0.0]
    return eye, yaw


def _valid_candidates(room: RoomSampling, tris: "FloorSurfaces", check: _ViewCheck,
                      config: CameraSamplerConfig, rng: np.random.Generator,
                      report: SamplerReport) -> list[_Candidate]:
    """Draw candidates on ``room``'s floor ``tris`` until it has ``pool_per_camera`` valid
    ones per camera of its share or ``candidates_per_camera`` per camera ran out.

    Counts each draw in ``room.candidates`` and ``report.candidates``, each rejection in
    ``report.rejected``, and the valid ones in ``room.valid``.
    """
    p_tri = tris.area / tris.area.sum()
    valid: list[_Candidate] = []
    while (len(valid) < room.share * config.pool_per_camera
           and room.candidates < room.share * config.candidates_per_camera):
        room.candidates += 1
        report.candidates += 1
        eye, yaw = _draw_eye(tris, p_tri, config.eye_height, rng)
        reason, camera, stats = check(eye, yaw)
        if reason is not None:
            report.rejected[reason] += 1
            continue
        valid.append(_Candidate(report.candidates, camera, config.score(stats), stats))
    room.valid = len(valid)
    return valid


def _fill_and_report(chosen: list[tuple[RoomSampling, list[_Candidate]]],
                     spare: list[tuple[RoomSampling, _Candidate]], n: int,
                     report: SamplerReport) -> list[Camera]:
    """The cameras, room by room, best first: each room's ``chosen`` ones, then the best of
    the ``spare`` valid candidates for the cameras rooms could not fill.

    The spares left over count as ``outscored``; every camera gets its
    ``report.views`` entry, and ``report.accepted`` and each room's ``accepted`` are set.
    """
    missing = n - sum(len(kept) for _, kept in chosen)
    spare.sort(key=lambda rc: (-rc[1].score, rc[1].order))
    extra = spare[:max(missing, 0)]
    report.rejected["outscored"] += len(spare) - len(extra)

    cameras: list[Camera] = []
    for room, kept in chosen + [(room, [c]) for room, c in extra]:
        room.accepted += len(kept)
        for c in kept:
            cameras.append(c.camera)
            report.views.append(SampledView(room.room, room.level, c.score, c.stats))
    report.accepted = len(cameras)
    return cameras


def sample_cameras(
    house: "House",
    n: int,
    rng: np.random.Generator,
    config: CameraSamplerConfig | None = None,
    tracer: "HouseTracer | None" = None,
) -> tuple[list[Camera], SamplerReport]:
    """Sample up to ``n`` cameras over the house's rooms, the most informative first (docs/spec.md §3).

    **Rooms.** Every room with a floor gets its share of the ``n`` cameras (equal shares,
    the remainder to the largest floors); floors without a room are sampled per level;
    each room stands its cameras on its own floor, so every level of a house is sampled
    with that level's floor. A room without a floor is skipped, with the reason in
    ``report.skipped``.

    **Candidates.** A candidate stands on a point drawn uniformly (by area) from its room's
    walkable floor triangles (:mod:`sceneforge.floors`), ``eye_height`` above it, at the
    fixed pitch and a uniform random yaw. It is rejected, in this order, when

    - ``not_above_floor``: straight down, the first surface is neither a floor at
      ``eye_height`` (to ``tol.eye_above_floor``) nor a floor cover (rug, carpet, floor
      mat: ``conventions.FLOOR_COVER_NAMES``) lying on it, its top at most
      ``tol.floor_cover`` higher (the eye is above or inside furniture, or above the
      ceiling of a low room);
    - ``too_close``: any surface is nearer than ``min_surface_distance``;
    - then, from its layers traced at ``check_width``×``check_height`` (same field of
      view; :class:`ViewStats`): ``escapes`` (more than ``max_escape_fraction`` of the
      pixels see nothing), ``mostly_void`` (more than ``max_void_fraction`` see a void
      object first), ``mostly_envelope`` (more than ``max_envelope_fraction`` see the
      envelope first), ``few_objects`` (fewer than ``min_object_fraction`` see a labelled
      object first).

    **Choice.** A room draws candidates until it has ``pool_per_camera`` valid ones per
    camera of its share (or ``candidates_per_camera`` candidates per camera ran out) and
    keeps the best by :meth:`CameraSamplerConfig.score` (objects seen, D3 coverage, distance
    to the envelope), at least ``min_separation`` apart where it can; the others count as
    ``outscored``. Cameras a room could not fill come from the best unused valid candidates
    of the other rooms.

    The result depends only on the house, ``config`` and the state of ``rng``. Cameras come
    room by room, best first; ``report.views`` gives each one's room, score and statistics.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    config = config or CameraSamplerConfig()
    tracer = tracer or HouseTracer(house)
    surfaces = _floor_triangles(house)
    report = SamplerReport(requested=n)
    cells = _rooms_to_sample(house, surfaces, n, report)
    report.rooms = [room for room, _ in cells]
    check = _ViewCheck(house, config, tracer)

    chosen: list[tuple[RoomSampling, list[_Candidate]]] = []
    spare: list[tuple[RoomSampling, _Candidate]] = []
    # Rooms draw in order from the one rng, so each room's candidates depend on the rooms before it.
    for room, tris in cells:
        valid = _valid_candidates(room, tris, check, config, rng, report)
        kept = _select(valid, room.share, config.min_separation)
        chosen.append((room, kept))
        spare += [(room, c) for c in valid if c not in kept]
    return _fill_and_report(chosen, spare, n, report), report
