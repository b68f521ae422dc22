"""What ``sceneforge houses inspect`` reports: per-house summaries, top-down previews, and
folders of mesh files that look like one scene's objects."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..conventions import NYU40_IDS, NYU40_NAMES
from .categories import UNKNOWN
from .formats.generic import SUFFIXES
from .formats.scene import MANIFEST
from .model import House


@dataclass(frozen=True)
class HouseSummary:
    """Counts and checks of one loaded house.

    categories : NYU40 name → (instances, triangles), most instances first
    void_names : (label, instances, triangles, share of the house's triangles) of every
                 source name (label) whose instances are void, most triangles first
    bounds     : (2, 3) float64 min / max corner, metres
    problems   : what to look at before rendering: loader warnings (but the void names,
                 listed in ``void_names``), missing floors, walls or rooms, homeless instances
    notes      : what the loader decided (the up axis it detected, and why)
    """

    id: str
    source_format: str
    source_path: str | None
    instances: int
    triangles: int
    rooms: int
    levels: int
    categories: tuple[tuple[str, int, int], ...]
    void_names: tuple[tuple[str, int, int, float], ...]
    bounds: np.ndarray
    problems: tuple[str, ...]
    notes: tuple[str, ...] = ()


def summarize(house: House) -> HouseSummary:
    """Summary and problems of ``house`` (loader warnings plus structural checks)."""
    inst = Counter(i.category for i in house.instances)
    tris = Counter()
    for i in house.instances:
        tris[i.category] += len(i.faces)
    cats = tuple(
        (NYU40_NAMES[c], n, tris[c]) for c, n in sorted(inst.items(), key=lambda kv: (-kv[1], kv[0]))
    )
    void: dict[str, list[int]] = {}
    for i in house.instances:
        if i.category == 0:
            entry = void.setdefault(i.label or i.name, [0, 0])
            entry[0] += 1
            entry[1] += len(i.faces)
    total = max(house.triangle_count, 1)
    void_names = tuple((label, n, t, t / total)
                       for label, (n, t) in sorted(void.items(), key=lambda kv: (-kv[1][1], kv[0])))
    problems = [w for w in house.warnings if not w.startswith(UNKNOWN)]
    for needed in ("floor", "wall"):
        if NYU40_IDS[needed] not in inst:
            problems.append(f"no {needed} instance")
    if not house.rooms:
        problems.append("no rooms: the overhead camera's majority-room box is always rejected "
                        "(glTF/OBJ/PLY scenes get their rooms from their floor instances)")
    if void_names:
        share = sum(t for _, _, t, _ in void_names) / total
        problems.append(f"{len(void_names)} names fell to void ({100 * share:.1f} % of the triangles): "
                        "give them classes with --name-map")
    if house.rooms:
        room_ids = {r.id for r in house.rooms}
        homeless = sum(1 for i in house.instances if i.room_id not in room_ids)
        if homeless:
            problems.append(f"{homeless} instances belong to no room")
    return HouseSummary(
        id=house.id,
        source_format=house.source_format,
        source_path=house.source_path,
        instances=len(house.instances),
        triangles=house.triangle_count,
        rooms=len(house.rooms),
        levels=len(house.levels),
        categories=cats,
        void_names=void_names,
        bounds=house.bounds(),
        problems=tuple(problems),
        notes=tuple(house.notes),
    )


class SceneFolderHints:
    """Folders whose mesh files look like the objects of one scene, exported one file per
    object: at least two glTF/OBJ/PLY houses in one folder, fewer than half of which have a
    floor (the others fail, or load without one, and would fail to render: no floor to stand
    a camera on; a wall mesh that is a closed box may give one or two of them a floor of
    their own, :mod:`.cleanup`). :meth:`add` each house as it is read, :meth:`lines` at the end."""

    def __init__(self):
        self._floors: dict[Path, list[bool]] = {}
        self._suffixes: dict[Path, set[str]] = {}

    def add(self, source, house: House | None, error: Exception | None) -> None:
        """One house of :func:`~sceneforge.houses.iter_houses` (``source``, ``house``, ``error``)."""
        path = Path(source.path)
        if source.format not in set(SUFFIXES.values()) or not path.is_file():
            return
        has_floor = house is not None and any(i.category == NYU40_IDS["floor"] for i in house.instances)
        self._floors.setdefault(path.parent, []).append(has_floor)
        self._suffixes.setdefault(path.parent, set()).add(path.suffix.lower())

    def lines(self) -> list[str]:
        """One line per such folder: what to write, or which option to pass, to read it as one house."""
        out = []
        for folder, floors in self._floors.items():
            if len(floors) >= 2 and 2 * sum(floors) < len(floors):
                files = ", ".join(f'"*{s}"' for s in sorted(self._suffixes[folder]))
                out.append(f"these {len(floors)} files look like the objects of one scene: write "
                           f"{folder / MANIFEST} holding {{\"files\": [{files}]}} to read them as one house, "
                           "or pass --format scene")
        return out


def category_colors() -> np.ndarray:
    """(41, 3) uint8 a fixed colour per NYU40 class (void black), for every preview."""
    rng = np.random.default_rng(40)
    colors = rng.integers(40, 230, size=(len(NYU40_NAMES), 3)).astype(np.uint8)
    colors[0] = 0
    colors[NYU40_IDS["wall"]] = (70, 70, 70)
    colors[NYU40_IDS["floor"]] = (215, 205, 185)
    return colors


def write_preview(house: House, path: str | Path, size: int = 768) -> Path:
    """Write a top-down PNG of ``house`` (ceilings left out), coloured by NYU40 class.

    Triangles are painted lowest first, so what is seen from above ends on top; a legend
    names the classes present.
    """
    from PIL import Image, ImageDraw

    colors = category_colors()
    parts = [i for i in house.instances if i.category != NYU40_IDS["ceiling"]] or house.instances
    lo, hi = house.bounds()
    span = max(hi[0] - lo[0], hi[2] - lo[2], 1e-6)
    margin = 16
    scale = (size - 2 * margin) / span
    tri_xy, tri_top, tri_cat = [], [], []
    for inst in parts:
        v = inst.vertices[inst.faces]  # (m, 3, 3)
        tri_xy.append(np.stack([(v[..., 0] - lo[0]) * scale + margin, (v[..., 2] - lo[2]) * scale + margin], -1))
        tri_top.append(v[..., 1].max(1))
        tri_cat.append(np.full(len(v), inst.category))
    xy = np.concatenate(tri_xy)
    order = np.argsort(np.concatenate(tri_top), kind="stable")
    cats = np.concatenate(tri_cat)[order]
    xy = xy[order]
    width = int(np.ceil((hi[0] - lo[0]) * scale)) + 2 * margin
    height = int(np.ceil((hi[2] - lo[2]) * scale)) + 2 * margin
    present = sorted(set(cats.tolist()))
    legend_h = 18 * ((len(present) + 3) // 4) + 8
    img = Image.new("RGB", (max(width, 4 * 150), height + legend_h), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for tri, c in zip(xy, cats):
        draw.polygon([tuple(p) for p in tri], fill=tuple(int(x) for x in colors[c]))
    for k, c in enumerate(present):
        x0, y0 = 8 + 150 * (k % 4), height + 4 + 18 * (k // 4)
        draw.rectangle([x0, y0, x0 + 12, y0 + 12], fill=tuple(int(x) for x in colors[c]), outline=(0, 0, 0))
        draw.text((x0 + 18, y0), NYU40_NAMES[c], fill=(0, 0, 0))
    draw.text((8, 2), f"{house.id} (top view, +x right, +z down, 1 m = {scale:.0f} px)", fill=(0, 0, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
    return path
