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
from .textures import mesh_of


def _safe(name: str) -> str:
    return re.sub(r"[^\w.-]", "_", name) or "_"


def _bbox(instances: list[Instance]) -> dict:
    if not instances:
        return {"min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}
    v = np.concatenate([i.vertices for i in instances])
    return {"min": v.min(0).tolist(), "max": v.max(0).tolist()}


def _merge(instances: list[Instance]) -> Mesh:
    """One mesh from several, each one's materials its face groups (uv only when all have some)."""
    offsets = np.cumsum([0] + [len(i.vertices) for i in instances])
    v = np.concatenate([i.vertices for i in instances])
    f = np.concatenate([i.faces + o for i, o in zip(instances, offsets[:-1], strict=True)])
    uv = None if any(i.uv is None for i in instances) else np.concatenate([i.uv for i in instances])
    meshes = [mesh_of(i) for i in instances]
    starts = np.cumsum([0] + [len(m.materials) for m in meshes])
    materials = tuple(x for m in meshes for x in m.materials)
    group = np.concatenate([m.face_materials() + s for m, s in zip(meshes, starts[:-1], strict=True)])
    return Mesh(v, f, uv, materials if len(materials) > 1 else materials[0], face_material=group if len(materials) > 1 else None)


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
    for d in (root / "house" / house.id, root / "room" / house.id, root / "object"):
        d.mkdir(parents=True, exist_ok=True)
    writer = _Writer(house, root)
    doc_levels = [writer.level(li) for li in range(len(writer.levels))]
    _write_categories(root / CATEGORY_CSV, writer.rows)
    doc = {"version": VERSION, "id": house.id, "up": [0, 1, 0], "front": [0, 0, 1],
           "scaleToMeters": 1, "levels": doc_levels}
    path = root / "house" / house.id / "house.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


class _Writer:
    """One house going into a SUNCG root: which level, room file or model each instance goes
    to, and the category table rows of the models written so far."""

    def __init__(self, house: House, root: Path):
        self.house, self.root = house, root
        self.room_dir = root / "room" / house.id
        self.levels = list(house.levels) or [Level(0, 0.0)]
        self.index_of = {id(inst): k for k, inst in enumerate(house.instances)}
        #: rows for ModelCategoryMapping.csv, one per Object node written
        self.rows: list[dict] = []
        self.rooms = self._rooms()
        #: room id → index of its level in ``levels``
        self.room_level = self._room_levels()
        self.model_ids = self._model_ids()
        self.parts, self.others = self._sort_instances()

    def level_by_height(self, y: float) -> int:
        """Index of the highest level whose floor is at or below ``y`` (else the lowest level)."""
        by_height = sorted(range(len(self.levels)), key=lambda k: self.levels[k].floor_y)
        below = [k for k in by_height if self.levels[k].floor_y <= y + 1e-6]
        return below[-1] if below else by_height[0]

    def _rooms(self) -> list[Room]:
        """``house.rooms``, then the rooms known only from instances, on the level of their lowest point."""
        rooms = list(self.house.rooms)
        known = {r.id for r in rooms}
        for inst in self.house.instances:
            if inst.room_id is not None and inst.room_id not in known:
                level = self.levels[self.level_by_height(inst.vertices[:, 1].min())]
                rooms.append(Room(inst.room_id, "", level.id))
                known.add(inst.room_id)
        return rooms

    def _room_levels(self) -> dict[str, int]:
        level_pos = {lv.id: k for k, lv in enumerate(self.levels)}
        for r in self.rooms:
            if r.level not in level_pos:
                raise HouseError(self.house.id, None,
                                 f"room {r.id} is on level {r.level}, which the house does not list")
        return {r.id: level_pos[r.level] for r in self.rooms}

    def _model_ids(self) -> dict[str, str]:
        """Room id → its ``modelId``: the id made a safe file name, unique in the house."""
        model_ids: dict[str, str] = {}
        for r in self.rooms:
            mid = _safe(r.id)
            while mid in model_ids.values():
                mid += "_"
            model_ids[r.id] = mid
        return model_ids

    def _sort_instances(self):
        """(room id → room file suffix → its floor/ceiling/wall instances, per level: the other instances)."""
        part_of = {NYU40_IDS[name]: suffix for suffix, name, _ in ROOM_PARTS}
        parts: dict[str, dict[str, list[Instance]]] = {r.id: {} for r in self.rooms}
        others: list[list[Instance]] = [[] for _ in self.levels]
        for inst in self.house.instances:
            if inst.room_id is not None and inst.category in part_of:
                parts[inst.room_id].setdefault(part_of[inst.category], []).append(inst)
            elif inst.room_id is not None:
                others[self.room_level[inst.room_id]].append(inst)
            else:
                others[self.level_by_height(inst.vertices[:, 1].min())].append(inst)
        return parts, others

    def level(self, li: int) -> dict:
        """The house.json entry of level ``li``: its Room nodes, then a node per other instance."""
        nodes: list[dict] = []
        level_rooms = [r for r in self.rooms if self.room_level[r.id] == li]
        for r in level_rooms:
            nodes.append(self.room_node(r, li, f"{li}_{len(nodes)}"))
        room_node = {r.id: nodes[k] for k, r in enumerate(level_rooms)}
        for inst in self.others[li]:
            if inst.room_id is not None:
                room_node[inst.room_id]["nodeIndices"].append(len(nodes))
            nodes.append(self.instance_node(inst, f"{li}_{len(nodes)}"))
        bbox = _bbox([i for r in level_rooms for g in self.parts[r.id].values() for i in g] + self.others[li])
        bbox["min"][1] = float(self.levels[li].floor_y)
        return {"id": str(self.levels[li].id), "bbox": bbox, "nodes": nodes}

    def room_node(self, room: Room, li: int, node_id: str) -> dict:
        """The Room node of ``room``; its floor, ceiling and walls are written, one OBJ each."""
        mid = self.model_ids[room.id]
        node = {"id": node_id, "type": "Room", "valid": 1, "modelId": mid,
                "roomTypes": room.type.split(",") if room.type else [], "nodeIndices": []}
        parts = self.parts[room.id]
        for suffix, _, hide in ROOM_PARTS:
            group = parts.get(suffix, [])
            node[hide] = 0 if group else 1
            if group:
                write_obj(self.room_dir / f"{mid}{suffix}.obj", [_merge(group)])
        node["bbox"] = _bbox([i for g in parts.values() for i in g]
                             + [i for i in self.others[li] if i.room_id == room.id])
        return node

    def instance_node(self, inst: Instance, node_id: str) -> dict:
        """A Ground node for a floor outside any room, else an Object node with a model of its own."""
        k = self.index_of[id(inst)]
        node = {"id": node_id, "valid": 1, "bbox": _bbox([inst])}
        if inst.category == NYU40_IDS["floor"] and inst.room_id is None:
            mid = f"{_safe(self.house.id)}_ground{k}"
            write_obj(self.room_dir / f"{mid}f.obj", [mesh_of(inst)])
            node.update(type="Ground", modelId=mid)
            return node
        mid = f"{_safe(self.house.id)}_{k}"
        lo, hi = inst.vertices.min(0), inst.vertices.max(0)
        origin = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
        write_obj(self.root / "object" / mid / f"{mid}.obj",
                  [mesh_of(inst, inst.vertices - origin)])
        m = np.eye(4)
        m[:3, 3] = origin
        node.update(type="Object", modelId=mid, transform=m.T.reshape(-1).tolist())
        self.rows.append({"model_id": mid, "fine_grained_class": inst.label, "coarse_grained_class": inst.label,
                          "nyuv2_40class": NYU40_NAMES[inst.category]})
        return node
