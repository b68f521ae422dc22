"""The up axis of a generic scene (glTF, OBJ, PLY, a scene folder), told from its geometry.

Scenes come +Y up (glTF by its spec, Blender's OBJ export) or +Z up (Blender, 3ds Max and
scanners' own axes, many PLY files); sceneforge works +Y up. :func:`detect_up_axis` decides
between +Y and +Z from three kinds of evidence, each voting for one axis or for neither:

- **names**: the meshes a name map classes ``floor`` or ``ceiling``. Their faces lie flat to
  the up axis: a vote when at least ``named_share`` of their area faces one axis (its normal
  within ``acos(flat_cos)`` of it) and ``named_ratio`` times as much as the other;
- **gravity**: objects stand on the floor. Along a candidate +A, the lowest points of the
  meshes spanning at most half the scene along A are grouped by height (points closer than
  ``cluster`` × the scene's size are one height); the largest group in the lowest
  ``bottom`` of the scene counts the objects standing at the bottom. Along a horizontal
  axis only the objects pushed against one wall line up so. A vote when at least
  ``min_objects`` stand at the bottom and ``gravity_ratio`` times as many as along the
  other axis;
- **area**: floors, ceilings, table tops, seats and beds face the up axis, the walls are
  shared out between the two horizontal axes. A vote when the share of the area facing
  one axis is ``area_ratio`` times the other's and the scene is not flat (its extent along
  each axis at least ``flat`` × its size: a plane could be a floor or a wall).

The axis some evidence votes for while none votes for the other is chosen; no vote, or
votes both ways, is undecided (:attr:`UpAxis.axis` None). A glTF scene (``prefer_y``) is +Y
up by its spec: it is read +Z up only when the names or gravity vote for Z and nothing for
Y, else +Y. The decision depends on the geometry and names only (not on the order of
equal-height objects, not on the units), so a scene always gets the same axis.

Which way up is told apart too (:attr:`UpAxis.upside_down`), since sceneforge reads only +Y and +Z
up: a scene exported upside down (−Y or −Z up) has its named floors above its named
ceilings (or, with only one of the two, in the top half of the scene, or the ceilings in
the bottom half), and its objects hang from the top at one height (``gravity`` along −A
at least ``gravity_ratio`` times as many as along +A, and ``min_objects``); it is upside
down when some evidence says so and none says it is upright.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Part", "UpAxis", "detect_up_axis"]

_AXES = {"y": 1, "z": 2}


@dataclass(frozen=True)
class Part:
    """One mesh as the source file has it, for :func:`detect_up_axis`.

    vertices : (n, 3) float   source axes and units
    faces    : (m, 3) int     indices into ``vertices``
    kind     : ``"floor"`` or ``"ceiling"`` when a name map classes the mesh so, else None
    """

    vertices: np.ndarray
    faces: np.ndarray
    kind: str | None = None


@dataclass(frozen=True)
class UpAxis:
    """What :func:`detect_up_axis` decided: ``axis`` ``"y"``, ``"z"`` or None (it cannot
    tell), and ``reason``, the evidence in words; ``upside_down``, with an axis, why the
    scene looks upside down along it, in words (module doc), else None."""

    axis: str | None
    reason: str
    upside_down: str | None = None


@dataclass(frozen=True)
class _Evidence:
    """The three kinds of evidence, per axis ``"y"`` / ``"z"`` (module doc)."""

    named: dict[str, float] | None  # share of the named floors' and ceilings' area facing each axis
    named_count: int
    standing: dict[str, int]  # objects standing at the bottom along +axis
    hanging: dict[str, int]  # objects hanging at the top along +axis (standing along -axis)
    area: dict[str, float]  # share of all the area facing each axis
    flat: bool
    objects: int
    #: (3,) area-weighted mean position of the faces of the meshes named ``floor`` and of
    #: those named ``ceiling`` (a kind without any left out), and the scene's middle
    levels: dict[str, np.ndarray]
    middle: np.ndarray


def detect_up_axis(
    parts: Sequence[Part],
    *,
    prefer_y: bool = False,
    flat_cos: float = float(np.cos(np.radians(15))),
    named_share: float = 0.5,
    named_ratio: float = 3.0,
    cluster: float = 0.002,
    bottom: float = 0.25,
    min_objects: int = 3,
    gravity_ratio: float = 2.0,
    area_ratio: float = 1.5,
    flat: float = 0.01,
) -> UpAxis:
    """The up axis of a scene made of ``parts`` (module doc for the rule and the parameters).

    prefer_y : the source is glTF (+Y up by its spec): +Z only on clear evidence
    """
    ev = _evidence([p for p in parts if len(p.faces)], flat_cos, cluster, bottom, flat)
    votes: dict[str, str] = {}  # kind of evidence → the axis it votes for
    if ev.named is not None:
        axis, other = _ranked(ev.named)
        if ev.named[axis] >= named_share and ev.named[axis] >= named_ratio * ev.named[other]:
            votes["names"] = axis
    axis, other = _ranked(ev.standing)
    if ev.standing[axis] >= min_objects and ev.standing[axis] >= gravity_ratio * ev.standing[other]:
        votes["gravity"] = axis
    axis, other = _ranked(ev.area)
    if not ev.flat and ev.area[axis] > 0 and ev.area[axis] >= area_ratio * ev.area[other]:
        votes["area"] = axis
    said = {
        "names": _named_words(ev, votes.get("names") or _ranked(ev.named or {"y": 0, "z": 0})[0]),
        "gravity": _standing_words(ev, votes.get("gravity") or _ranked(ev.standing)[0]),
        "area": _area_words(ev, votes.get("area") or _ranked(ev.area)[0]),
    }
    chosen = set(votes.values())
    if prefer_y and chosen != {"y"} and not (chosen == {"z"} and ("names" in votes or "gravity" in votes)):
        return UpAxis("y", "glTF's convention, the evidence being unclear: " + "; ".join(
            said[k] for k in ("names", "gravity", "area")), _upside_down(ev, "y", min_objects, gravity_ratio))
    if len(chosen) == 1:
        axis = chosen.pop()
        return UpAxis(axis, "detected: " + "; ".join(said[k] for k in votes),
                      _upside_down(ev, axis, min_objects, gravity_ratio))
    if chosen:
        both = "; ".join(f"{said[k]}: {a.upper()}" for k, a in votes.items())
        return UpAxis(None, f"the evidence disagrees: {both}")
    return UpAxis(None, "; ".join(said[k] for k in ("names", "gravity", "area")))


def _upside_down(ev: _Evidence, axis: str, min_objects: int, gravity_ratio: float) -> str | None:
    """Why the scene looks upside down along +``axis``, in words; None when nothing says so
    or something says it is upright (module doc)."""
    k, up, down = _AXES[axis], ev.standing[axis], ev.hanging[axis]
    flipped, upright = [], []
    level = {kind: float(at[k]) for kind, at in ev.levels.items()}
    if "floor" in level and "ceiling" in level:
        (flipped if level["floor"] > level["ceiling"] else upright).append(
            f"the meshes named as floors lie {'above' if level['floor'] > level['ceiling'] else 'below'} "
            f"those named as ceilings along +{axis.upper()}")
    elif level:
        (kind, h), = level.items()
        top = h > float(ev.middle[k])
        ((flipped if top == (kind == "floor") else upright)
         .append(f"the meshes named as {kind}s lie in the {'top' if top else 'bottom'} half along +{axis.upper()}"))
    if down >= min_objects and down >= gravity_ratio * up:
        flipped.append(f"{down} objects hang at the top along +{axis.upper()}, {up} stand at the bottom")
    elif up >= min_objects and up >= gravity_ratio * down:
        upright.append(f"{up} objects stand at the bottom along +{axis.upper()}")
    return "; ".join(flipped) if flipped and not upright else None


def _ranked(values: dict) -> tuple[str, str]:
    """(the axis with the larger value, the other); Y on a tie, so the order is fixed."""
    return ("z", "y") if values["z"] > values["y"] else ("y", "z")


def _evidence(parts: list[Part], flat_cos: float, cluster: float, bottom: float, flat: float) -> _Evidence:
    if not parts:
        zero = {"y": 0.0, "z": 0.0}
        return _Evidence(None, 0, {"y": 0, "z": 0}, {"y": 0, "z": 0}, zero, True, 0, {}, np.zeros(3))
    lows, highs, facing, areas, named, named_count = [], [], [], [], np.zeros(3), 0
    at = {"floor": [np.zeros(3), 0.0], "ceiling": [np.zeros(3), 0.0]}  # Σ 2 × area × centre, Σ 2 × area
    for p in parts:
        v = np.asarray(p.vertices, dtype=np.float64).reshape(-1, 3)
        tri = v[np.asarray(p.faces, dtype=np.int64).reshape(-1, 3)]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (m, 3), |n| = 2 × area
        double_area = np.linalg.norm(normal, axis=1)
        ok = double_area > 0
        along = np.abs(normal[ok]) >= flat_cos * double_area[ok, None]  # (m', 3) faces flat to each axis
        per_axis = (double_area[ok, None] * along).sum(0) / 2  # (3,) area facing each axis
        facing.append(per_axis)
        areas.append(double_area[ok].sum() / 2)
        if p.kind in ("floor", "ceiling"):
            named += per_axis
            named_count += 1
            at[p.kind][0] += double_area @ tri.mean(axis=1)
            at[p.kind][1] += float(double_area.sum())
        used = v[np.unique(p.faces)]
        lows.append(used.min(0))
        highs.append(used.max(0))
    lows, highs = np.array(lows), np.array(highs)  # (p, 3)
    lo, hi = lows.min(0), highs.max(0)
    extent = hi - lo
    size = float(extent.max())
    total = float(sum(areas)) or 1.0
    facing_total = np.sum(facing, axis=0) / total
    named_area = sum(a for a, p in zip(areas, parts, strict=True) if p.kind in ("floor", "ceiling"))
    standing, hanging = {}, {}
    for name, k in _AXES.items():
        small = highs[:, k] - lows[:, k] <= 0.5 * extent[k]
        standing[name] = _standing(lows[small, k], lo[k], extent[k], cluster * size, bottom)
        # hanging: standing along -axis (the highest points, negated)
        hanging[name] = _standing(-highs[small, k], -hi[k], extent[k], cluster * size, bottom)
    return _Evidence(
        named={a: float(named[k] / named_area) for a, k in _AXES.items()} if named_area > 0 else None,
        named_count=named_count,
        standing=standing,
        hanging=hanging,
        area={a: float(facing_total[k]) for a, k in _AXES.items()},
        flat=bool(min(extent[1], extent[2]) < flat * size) if size > 0 else True,
        objects=len(parts),
        levels={kind: total / weight for kind, (total, weight) in at.items() if weight > 0},
        middle=(lo + hi) / 2,
    )


def _standing(lowest: np.ndarray, base: float, extent: float, near: float, bottom: float) -> int:
    """How many objects stand at the bottom: the largest group of ``lowest`` points (one per
    object) lying within ``near`` above the first of the group, that first in the lowest
    ``bottom`` of ``extent`` above ``base``; 0 for none or a scene of no extent."""
    h = np.sort(lowest)
    if not len(h) or extent <= 0:
        return 0
    count = np.searchsorted(h, h + near, side="right") - np.arange(len(h))
    at_bottom = h <= base + bottom * extent
    return int(count[at_bottom].max()) if at_bottom.any() else 0


def _other(axis: str) -> str:
    return "z" if axis == "y" else "y"


def _named_words(ev: _Evidence, axis: str) -> str:
    if ev.named is None:
        return "no mesh named as a floor or ceiling"
    what = "1 mesh named as a floor or ceiling faces" if ev.named_count == 1 else \
        f"{ev.named_count} meshes named as floors or ceilings face"
    whose = "its" if ev.named_count == 1 else "their"
    return (f"{what} ±{axis.upper()} with {_pct(ev.named[axis])} of {whose} area, "
            f"±{_other(axis).upper()} with {_pct(ev.named[_other(axis)])}")


def _standing_words(ev: _Evidence, axis: str) -> str:
    if ev.objects < 2:
        return "one mesh, no objects standing on a floor"
    n, other = ev.standing[axis], _other(axis)
    objects = "1 object stands" if n == 1 else f"{n} objects stand"
    return f"{objects} at the bottom along +{axis.upper()}, {ev.standing[other]} along +{other.upper()}"


def _area_words(ev: _Evidence, axis: str) -> str:
    other = _other(axis)
    words = (f"{_pct(ev.area[axis])} of the area faces ±{axis.upper()}, "
             f"{_pct(ev.area[other])} ±{other.upper()}")
    return words + " and the scene is flat" if ev.flat else words


def _pct(share: float) -> str:
    return f"{100 * share:.0f} %"
