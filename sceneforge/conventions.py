"""Conventions, defined once here and referred to everywhere else (docs/spec.md §1).

Every convention below is a constant or a function of this module; other modules and
docstrings refer to it rather than restating it, and a store records them through
:func:`record` (its ``conventions`` attribute).

- Units are metres (:data:`UNITS`); world up is +Y (:data:`UP`). Loaders of Z-up sources
  convert at load time.
- Camera poses are ``cam_to_world`` 4×4 float64 in **OpenCV axes** (:data:`CAMERA_AXES`:
  x right, y down, z forward). The single OpenCV ↔ OpenGL conversion is
  ``sceneforge.cameras.opencv_to_opengl``.
- Intrinsics ``K`` are 3×3 in pixels; pixel ``(row i, column j)`` covers
  ``[j, j+1) × [i, i+1)``, so its centre is at integer + :data:`PIXEL_CENTRE` (0.5).
- Depth is planar z-depth along the camera's forward axis, float32 metres.
  **NaN means "no surface in this layer"**, never 0 or inf.
- Layers: :data:`LAYER_NAMES` (D1..D5) and the index tuples after it say which layers
  are objects, which carry a class or an instance, and which support each mask.
- The overhead camera's pixel mapping: :func:`overhead_pixel` and
  :func:`overhead_pixel_centre` (used by ``overhead.OverheadCamera`` and the EFT).
- Labels are NYU40 class ids (1..40, 0 = void). The table below is the only copy.
- Room-envelope ("background") categories and the categories dropped at load time
  are decided by :func:`is_envelope` and :func:`is_dropped` only.
- Every tolerance is a field of :data:`tol`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

#: NYU40 class names, index = class id (official numbering; 0 = void).
NYU40_NAMES: tuple[str, ...] = (
    "void",
    "wall", "floor", "cabinet", "bed", "chair",
    "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "blinds", "desk", "shelves",
    "curtain", "dresser", "pillow", "mirror", "floor_mat",
    "clothes", "ceiling", "books", "refridgerator", "television",
    "paper", "towel", "shower_curtain", "box", "whiteboard",
    "person", "night_stand", "toilet", "sink", "lamp",
    "bathtub", "bag", "otherstructure", "otherfurniture", "otherprop",
)
NYU40_IDS: dict[str, int] = {name: i for i, name in enumerate(NYU40_NAMES)}
# Spellings seen in the wild for the same classes.
NYU40_ALIASES: dict[str, int] = {
    "refrigerator": NYU40_IDS["refridgerator"],
    "fridge": NYU40_IDS["refridgerator"],
    "tv": NYU40_IDS["television"],
    "nightstand": NYU40_IDS["night_stand"],
    "floormat": NYU40_IDS["floor_mat"],
    "rug": NYU40_IDS["floor_mat"],
    "bookcase": NYU40_IDS["bookshelf"],
    "none": 0,
    "": 0,
}

#: Room-envelope categories of the paper's appendix. ``fireplace`` and ``roof`` are not
#: NYU40 names: they are matched against an instance's source category (its ``label``).
ENVELOPE_NAMES: frozenset[str] = frozenset({
    "wall", "floor", "ceiling", "door", "floor_mat", "window", "curtain", "blinds",
    "picture", "mirror", "fireplace", "roof", "whiteboard",
})
#: Categories dropped at load time (PBRS ignores persons and plants).
DROPPED_NAMES: frozenset[str] = frozenset({"person", "plant"})
#: Floor covers: envelope lying on the floor that a camera may stand over (a room-sized rug
#: is the first surface below most of a furnished room). NYU40 ``floor_mat``, or a source
#: category rug/carpet (matched like every class list, :func:`in_classes`).
FLOOR_COVER_NAMES: frozenset[str] = frozenset({"floor_mat", "rug", "carpet"})

#: Order of the frontal depth layers in every array with a layer axis.
LAYER_NAMES: tuple[str, ...] = ("D1", "D2", "D3", "D4", "D5")
#: The object layers D1..D4: entry and exit of the first object on a ray, then of the next.
OBJECT_LAYERS: tuple[int, ...] = (0, 1, 2, 3)
#: (entry, exit) layer of each object a ray meets: (D1, D2), then (D3, D4).
OBJECT_SEGMENTS: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))
#: The entry layers D1, D3: they name the instance of their segment (``instance`` arrays).
FRONT_LAYERS: tuple[int, ...] = (0, 2)
#: The envelope layer D5, the first room-envelope surface on a ray.
ENVELOPE_LAYER: int = 4
#: The layers whose surface's NYU40 class is stored (``category`` arrays): D1, D3, D5.
CLASS_LAYERS: tuple[int, ...] = (*FRONT_LAYERS, ENVELOPE_LAYER)
#: Per layer, the layer whose support is its mask: M1 = M2 = finite D1, M3 = M4 = finite D3,
#: M5 = finite D5 (docs/spec.md §4.4).
MASK_LAYERS: tuple[int, ...] = (0, 0, 2, 2, 4)

#: Length unit of every coordinate and depth.
UNITS = "metres"
#: World up axis (docs/spec.md §1); Z-up sources are converted at load time.
UP = "+Y"
#: Camera axes of every pose and camera frame (OpenCV); poses are ``cam_to_world``.
CAMERA_AXES: dict[str, str] = {"x": "right", "y": "down", "z": "forward"}
#: Offset of a pixel's centre from its integer index, in pixels.
PIXEL_CENTRE = 0.5


def nyu40_id(name: str) -> int | None:
    """NYU40 id of a class name (case-insensitive, spaces/dashes as ``_``), or None."""
    key = name.strip().lower().replace(" ", "_").replace("-", "_")
    if key in NYU40_IDS:
        return NYU40_IDS[key]
    return NYU40_ALIASES.get(key)


def normalize_label(label: str | None) -> str:
    """A source category name in the form class lists use: lower case, ``_`` for spaces/dashes."""
    return (label or "").strip().lower().replace(" ", "_").replace("-", "_")


def in_classes(category: int, label: str | None, names) -> bool:
    """True when NYU40 ``category`` or the source ``label`` is one of ``names``.

    Class lists of the paper mix NYU40 names with source names NYU40 lacks (fireplace,
    plant, chandelier), so every such rule matches both.
    """
    return NYU40_NAMES[category] in names or normalize_label(label) in names


def is_envelope(category: int, label: str | None = None) -> bool:
    """True when an instance of NYU40 ``category`` (source category ``label``) is room envelope."""
    return in_classes(category, label, ENVELOPE_NAMES)


def is_dropped(category: int, label: str | None = None) -> bool:
    """True when an instance must be dropped at load time (persons and plants)."""
    return in_classes(category, label, DROPPED_NAMES)


def is_floor_cover(category: int, label: str | None = None) -> bool:
    """True when an instance is a floor cover (floor mat, rug, carpet)."""
    return in_classes(category, label, FLOOR_COVER_NAMES)


#: segmentation classes of the paper's nets, per layer *(paper appendix)*: class ``c > 0`` is
#: the NYU40 object class ``c + 1``; class 0 (:data:`SEG_BACKGROUND`, the slot of "wall") is
#: background: no object, and every room-envelope class merged into one
SEG_CLASSES = 40
SEG_BACKGROUND = 0
#: NYU40 id (index, 0..40) → segmentation class
NYU40_TO_SEG: tuple[int, ...] = tuple(SEG_BACKGROUND if k == 0 or is_envelope(k) else k - 1
                                      for k in range(len(NYU40_NAMES)))
#: segmentation class (index, 0..39) → NYU40 id (0 for background)
SEG_TO_NYU40: tuple[int, ...] = tuple(0 if c == SEG_BACKGROUND else c + 1 for c in range(SEG_CLASSES))


@dataclass(frozen=True)
class Tolerances:
    """Every tolerance of the project: metres unless a field says otherwise."""

    #: hits of the same instance closer than this along a ray count once (docs/spec.md §4)
    same_instance_hit: float = 1e-4
    #: object hits within this distance behind the first envelope hit still count (a rug)
    envelope_slack: float = 1e-3
    #: frustum clipping plane tolerance (docs/spec.md §5.1)
    clip: float = 1e-4
    #: faces whose vertices lie further than this behind D5 are dropped (docs/spec.md §5.1)
    behind_envelope: float = 0.1
    #: triangles with less area than this (m²) are degenerate and dropped at load time
    degenerate_area: float = 1e-12
    #: a pose's rotation R is orthonormal when RᵀR is the identity to this (plus numpy's
    #: default relative 1e-5, as ``np.isclose``), unitless. Cameras are built and stores
    #: validated with it: a pose a valid store holds must load as a Camera. Poses made by
    #: ``cameras.pose_from_view`` are orthonormal to ~1e-15, float32-rounded ones to ~1e-7.
    rotation: float = 1e-6
    #: depths are stored as float32 (an ulp is ~1e-6 m at 10 m): checks of the layer order
    #: on a store's depths allow this much
    stored_depth: float = 1e-5
    #: normals are stored as float32 unit vectors: their lengths, and two stored normals of
    #: one face (rotated into the camera frame by different routes), agree to this, unitless
    stored_normal: float = 1e-5
    #: a sampled eye is above the floor when the floor hit straight below it is at eye
    #: height to within this (the eye is placed at eye height over a floor triangle)
    eye_above_floor: float = 1e-3
    #: a floor cover (rug, carpet, floor mat) first hit straight below a sampled eye counts
    #: as the floor when its top is at most this far above the floor (rugs are 0.5–3 cm)
    floor_cover: float = 0.05
    #: a floor face is horizontal (walkable) when the y component of its unit normal is
    #: above this, unitless (0.9: slopes under 25.8°)
    floor_face_cos: float = 0.9
    #: a point is over a floor triangle when its barycentric coordinates in the x–z plane
    #: are at least minus this, unitless (a point on a shared edge is over both)
    floor_footprint: float = 1e-9
    #: a floor surface without a known room is on the highest level whose ``floor_y`` is at
    #: most this above it (a level's ``floor_y`` is at or below its floor tops)
    level_floor: float = 0.01
    #: a view direction and an up vector are parallel (no roll can be defined) when the
    #: sine of their angle is below this, unitless
    parallel: float = 1e-9
    #: a view direction whose horizontal part is shorter than this (unit vector) looks
    #: straight up or down and has no heading for the overhead camera, unitless
    horizontal_view: float = 1e-6
    #: the EFT's clipping (Liang–Barsky) treats a segment as parallel to a clip plane when
    #: its rate of change across the plane is below this (per metre of planar depth)
    clip_slope: float = 1e-12
    #: the reference ray tracer: barycentric slack, so that a ray through a shared edge
    #: hits both faces instead of neither, unitless
    ray_edge: float = 1e-12
    #: the reference ray tracer: a ray lies in a triangle's plane (no hit) when the sine of
    #: their angle is below this, unitless
    ray_parallel: float = 1e-12
    #: the reference ray tracer: leaf bounding boxes grow by this so that touching rays
    #: are never culled
    leaf_pad: float = 1e-6
    #: first hits: the triangles a ray crosses at most this much (relative, unitless)
    #: beyond its nearest float32 engine distance are its candidates, and the one of
    #: smallest float64 plane distance is its first hit (exact ties: lower instance, then
    #: lower triangle), whatever order a traversal meets them in; about 4 float32 steps,
    #: used as a float32 (sceneforge's extension holds the same constant)
    tie_window: float = 5e-7
    #: the Open3D engine puts two triangles of an instance in one Embree geometry only
    #: when their bounding boxes, grown by this, are apart along some axis: they can then
    #: never be crossed at the same float32 distance, which Open3D's list would report once
    tie_box_pad: float = 1e-4
    #: path tracing needs square pixels (Mitsuba's camera has one focal length): fx and fy
    #: may differ by this fraction of fx, and the skew by this fraction of fx, unitless.
    #: PBRS camera files give half-FOVs to 6 decimals (0.433896), up to 5e-7 rad off, which
    #: moves f by up to 1.3e-6 of itself at their FOVs (their fx, fy differ by 3.3e-7); using
    #: fx for both then moves a 240-row image's edge rows by at most 1e-5 · 120 = 0.0012 px
    square_pixels: float = 1e-5


tol = Tolerances()


def nyu40_table() -> list[dict]:
    """The NYU40 label table as records, for store attributes and docs."""
    return [
        {"id": i, "name": n, "envelope": n in ENVELOPE_NAMES}
        for i, n in enumerate(NYU40_NAMES)
    ]


def overhead_pixel(xy, half_extent, resolution):
    """Overhead-camera coordinates → continuous pixel coordinates of the overhead image.

    The overhead camera is orthographic (OpenCV axes, z straight down) and sees the square
    ``[-half_extent, half_extent]²`` of its x, y plane on ``resolution × resolution``
    pixels: ``(u, v) = (xy / half_extent + 1) · resolution / 2``, and the point falls in
    pixel ``(row, col) = (floor(v), floor(u))``. The one definition for numpy arrays and
    torch tensors alike (``overhead.OverheadCamera.project`` and the EFT's
    ``point_hits`` / ``segment_pairs``; ``tests/test_eft.py`` pins them to each other).

    xy          : (..., 2) float  ``(x, y)`` in the overhead camera frame, metres
    half_extent : float or (..., 1) float  metres
    Returns (..., 2) float ``(u, v)``.
    """
    return (xy / half_extent + 1.0) * (0.5 * resolution)


def overhead_pixel_centre(index, half_extent, resolution):
    """Overhead-camera x (or y) of the centres of pixel columns (or rows) ``index``: the
    inverse of :func:`overhead_pixel` at integer + :data:`PIXEL_CENTRE`.

    index : (n,) int or float array (numpy or torch); half_extent : float or broadcastable
    Returns (n,) float, metres.
    """
    return ((index + PIXEL_CENTRE) / resolution * 2.0 - 1.0) * half_extent


def record() -> dict:
    """The conventions as JSON-ready data, built from this module's constants: a store's
    ``conventions`` attribute (``schemas/store.schema.json``)."""
    return {
        "units": UNITS,
        "up": UP,
        "camera_axes": {"convention": "OpenCV", **CAMERA_AXES, "pose": "cam_to_world"},
        "pixel_centres": {"offset": PIXEL_CENTRE, "intrinsics": "K, pixels"},
        "depth": {"kind": "planar", "along": "camera z", "dtype": "float32", "no_surface": "NaN"},
        "layers": list(LAYER_NAMES),
        "object_layers": [LAYER_NAMES[k] for k in OBJECT_LAYERS],
        "envelope_layer": LAYER_NAMES[ENVELOPE_LAYER],
        "category_layers": [LAYER_NAMES[k] for k in CLASS_LAYERS],
        "instance_layers": [LAYER_NAMES[k] for k in FRONT_LAYERS],
        "labels": {"table": "nyu40", "void": 0},
        "tolerances": asdict(tol),
    }
