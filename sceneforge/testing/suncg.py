"""SUNCG writer: a house into a SUNCG root (house.json, room and object OBJs, category
table); the reader and the layout are in :mod:`sceneforge.houses.formats.suncg`."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np

from ..conventions import NYU40_IDS, NYU40_NAMES
from ..errors import HouseError
from ..houses.formats.meshio import Mesh
from ..houses.formats.suncg import CATEGORY_CSV, CSV_FIELDS, ROOM_PARTS, VERSION
from ..houses.model import House, Instance, Level, Room
from .obj import write_obj


def _safe(name: str) -> str:
    return re.sub(r"[^\w.-]", "_", name) or "_"


def _bbox(instances: list[Instance]) -> dict:
    if not instances:
        return {"min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}
    v = np.concatenate([i.vertices for i in instances])
    return {"min": v.min(0).tolist(), "max": v.max(0).tolist()}


def _merge(instances: list[Instance]) -> Mesh:
    """One mesh from several, with the material of the first (uv only when all have some)."""
    offsets = np.cumsum([0] + [len(i.vertices) for i in instances])
    v = np.concatenate([i.vertices for i in instances])
    f = np.concatenate([i.faces + o for i, o in zip(instances, offsets[:-1], strict=True)])
    uv = None if any(i.uv is None for i in instances) else np.concatenate([i.uv for i in instances])
    return Mesh(v, f, uv, instances[0].material)


def _write_categories(path: Path, rows: list[dict]) -> None:
    """Merge ``rows`` into the category table (rows of the same model id are replaced)."""
    old = []
    if path.is_file():
        with open(path, newline="", encoding="utf-8") as fh:
            old = list(csv.DictReader(fh))
    new_ids = {r["model_id"] for r in rows}
    merged = [r for r in old if r.get("model_id") not in new_ids] + rows
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS, extrasaction="ignore")
        w.writeheader()
        for i, r in enumerate(merged):
            w.writerow({**{k: "" for k in CSV_FIELDS}, **r, "index": i})


def write_house(house: House, root: str | Path) -> Path:
    """Write ``house`` into the SUNCG root ``root`` and return the path of its ``house.json``.

    - Instances of class wall, floor or ceiling that belong to a room are merged per room
      into ``room/<id>/<room>{w,f,c}.obj`` (one instance each when read back, labelled
      ``wall``/``floor``/``ceiling``, with the first part's material); a room's id becomes
      its ``modelId`` (characters other than letters, digits, ``_ . -`` become ``_``).
    - A floor outside any room becomes a Ground node.
    - Every other instance becomes an Object node with its own model
      ``object/<house>_<k>/<house>_<k>.obj``, in coordinates relative to the centre of its
      base, placed by a column-major translation; its label and NYU40 class go into
      ``metadata/ModelCategoryMapping.csv`` (merged with the rows already there).
    - An instance belongs to its room's level, or when it has no room to the highest level
      whose floor is at or below its lowest point. A level's ``bbox`` bottom is its floor
      height ``floor_y`` (how the loader reads it back).

    Read back, instances come level by level: first every room's floor, ceiling and walls
    (rooms in ``house.rooms`` order, then rooms known only from instances), then the other
    instances in house order.
    """
    root = Path(root)
    house_dir = root / "house" / house.id
    room_dir = root / "room" / house.id
    for d in (house_dir, room_dir, root / "object"):
        d.mkdir(parents=True, exist_ok=True)
    levels = list(house.levels) or [Level(0, 0.0)]
    level_pos = {lv.id: k for k, lv in enumerate(levels)}
    by_height = sorted(range(len(levels)), key=lambda k: levels[k].floor_y)

    def level_by_height(y: float) -> int:
        below = [k for k in by_height if levels[k].floor_y <= y + 1e-6]
        return below[-1] if below else by_height[0]

    rooms = list(house.rooms)
    known = {r.id for r in rooms}
    for inst in house.instances:
        if inst.room_id is not None and inst.room_id not in known:
            rooms.append(Room(inst.room_id, "", levels[level_by_height(inst.vertices[:, 1].min())].id))
            known.add(inst.room_id)
    for r in rooms:
        if r.level not in level_pos:
            raise HouseError(house.id, None,
                             f"room {r.id} is on level {r.level}, which the house does not list")
    room_level = {r.id: level_pos[r.level] for r in rooms}
    model_ids: dict[str, str] = {}
    for r in rooms:
        mid = _safe(r.id)
        while mid in model_ids.values():
            mid += "_"
        model_ids[r.id] = mid

    part_of = {NYU40_IDS[name]: suffix for suffix, name, _ in ROOM_PARTS}
    parts: dict[str, dict[str, list[Instance]]] = {r.id: {} for r in rooms}
    others: list[list[Instance]] = [[] for _ in levels]
    for inst in house.instances:
        if inst.room_id is not None and inst.category in part_of:
            parts[inst.room_id].setdefault(part_of[inst.category], []).append(inst)
        else:
            if inst.room_id is not None:
                others[room_level[inst.room_id]].append(inst)
            else:
                others[level_by_height(inst.vertices[:, 1].min())].append(inst)

    rows: list[dict] = []
    index_of = {id(inst): k for k, inst in enumerate(house.instances)}
    doc_levels = []
    for li, level in enumerate(levels):
        nodes: list[dict] = []
        level_rooms = [r for r in rooms if room_level[r.id] == li]
        for r in level_rooms:
            node = {"id": f"{li}_{len(nodes)}", "type": "Room", "valid": 1, "modelId": model_ids[r.id],
                    "roomTypes": r.type.split(",") if r.type else [], "nodeIndices": []}
            for suffix, _, hide in ROOM_PARTS:
                group = parts[r.id].get(suffix, [])
                node[hide] = 0 if group else 1
                if group:
                    write_obj(room_dir / f"{model_ids[r.id]}{suffix}.obj", [_merge(group)])
            node["bbox"] = _bbox([i for g in parts[r.id].values() for i in g]
                                 + [i for i in others[li] if i.room_id == r.id])
            nodes.append(node)
        room_node = {r.id: nodes[k] for k, r in enumerate(level_rooms)}
        for inst in others[li]:
            k = index_of[id(inst)]
            node = {"id": f"{li}_{len(nodes)}", "valid": 1, "bbox": _bbox([inst])}
            if inst.category == NYU40_IDS["floor"] and inst.room_id is None:
                mid = f"{_safe(house.id)}_ground{k}"
                write_obj(room_dir / f"{mid}f.obj", [Mesh(inst.vertices, inst.faces, inst.uv, inst.material)])
                node.update(type="Ground", modelId=mid)
            else:
                mid = f"{_safe(house.id)}_{k}"
                lo, hi = inst.vertices.min(0), inst.vertices.max(0)
                origin = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
                write_obj(root / "object" / mid / f"{mid}.obj",
                          [Mesh(inst.vertices - origin, inst.faces, inst.uv, inst.material)])
                m = np.eye(4)
                m[:3, 3] = origin
                node.update(type="Object", modelId=mid, transform=m.T.reshape(-1).tolist())
                rows.append({"model_id": mid, "fine_grained_class": inst.label,
                             "coarse_grained_class": inst.label,
                             "nyuv2_40class": NYU40_NAMES[inst.category]})
            if inst.room_id is not None:
                room_node[inst.room_id]["nodeIndices"].append(len(nodes))
            nodes.append(node)
        bbox = _bbox([i for r in level_rooms for g in parts[r.id].values() for i in g] + others[li])
        bbox["min"][1] = float(level.floor_y)
        doc_levels.append({"id": str(level.id), "bbox": bbox, "nodes": nodes})

    _write_categories(root / CATEGORY_CSV, rows)
    doc = {"version": VERSION, "id": house.id, "up": [0, 1, 0], "front": [0, 0, 1],
           "scaleToMeters": 1, "levels": doc_levels}
    path = house_dir / "house.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path
