"""Conventions, defined once and referred to everywhere (SPEC §1).

- Units are metres; world up is +Y. Loaders of Z-up sources convert at load time.
- Camera poses are ``cam_to_world`` 4×4 float64 in **OpenCV axes** (x right, y down,
  z forward). The single OpenCV ↔ OpenGL conversion lives in ``sceneforge.cameras``.
- Intrinsics ``K`` are 3×3 in pixels; pixel centres are at integer + 0.5.
- Depth is planar z-depth along the camera's forward axis, float32 metres.
  **NaN means "no surface in this layer"**, never 0 or inf.
- Labels are NYU40 class ids (1..40, 0 = void). The table below is the only copy.
- Room-envelope ("background") categories and the categories dropped at load time
  are decided by :func:`is_envelope` and :func:`is_dropped` only.
"""

from __future__ import annotations

from dataclasses import dataclass

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

#: Order of the frontal depth layers in every array with a layer axis.
LAYER_NAMES: tuple[str, ...] = ("D1", "D2", "D3", "D4", "D5")


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


@dataclass(frozen=True)
class Tolerances:
    """Every geometric tolerance of the project, in metres."""

    #: hits of the same instance closer than this along a ray count once (SPEC §4)
    same_instance_hit: float = 1e-4
    #: object hits within this distance behind the first envelope hit still count (a rug)
    envelope_slack: float = 1e-3
    #: frustum clipping plane tolerance (SPEC §5)
    clip: float = 1e-4
    #: faces whose vertices lie further than this behind D5 are dropped (SPEC §5)
    behind_envelope: float = 0.1
    #: triangles with less area than this (m²) are degenerate and dropped at load time
    degenerate_area: float = 1e-12


tol = Tolerances()


def nyu40_table() -> list[dict]:
    """The NYU40 label table as records, for store attributes and docs."""
    return [
        {"id": i, "name": n, "envelope": n in ENVELOPE_NAMES}
        for i, n in enumerate(NYU40_NAMES)
    ]

