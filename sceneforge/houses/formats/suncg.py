"""SUNCG houses: ``house.json`` with its ``room/``, ``object/`` and ``metadata/`` folders.

A SUNCG root, as released and as :func:`write_house` writes it::

    <root>/house/<house_id>/house.json
    <root>/room/<house_id>/<modelId>{f,c,w}.obj   floor, ceiling, walls of a room (scene space)
    <root>/object/<modelId>/<modelId>.obj         one model in its own coordinates
    <root>/metadata/ModelCategoryMapping.csv      model_id → fine/coarse class, nyuv2_40class

``house.json`` is read the way the SUNCG toolbox does (its README and GAPS
``R3Scene::ReadSUNCGFile``): ``levels[].nodes[]`` of type ``Room``, ``Object``, ``Ground``
or ``Box``.

- Levels and nodes with ``valid: 0`` are skipped.
- ``transform`` is a **column-major** 4×4 from model to scene coordinates. A mirrored
  transform (negative determinant) reverses the face winding so that normals stay outward.
- Room nodes load ``<modelId>f/c/w.obj`` untransformed (they are in scene space), each
  unless ``hideFloor`` / ``hideCeiling`` / ``hideWalls`` is 1. A missing room file is
  skipped with a warning, as the toolbox skips it. ``nodeIndices`` (indices into the
  level's ``nodes``) give the room of the other nodes.
- Ground nodes load ``<modelId>f.obj`` with their transform: floor outside any room.
- Box nodes are boxes of size ``dimensions`` centred on their origin, then transformed.
  They have no model id, hence no category: void, as in the toolbox.
- Object nodes load ``object/<modelId>/<modelId>.obj`` (``<modelId>_0.obj`` when ``state``
  is 1). A missing model file is an error.
- Everything is scaled by ``scaleToMeters``.

In sceneforge terms: an object's NYU40 class is its model's ``nyuv2_40class`` and its label
the ``fine_grained_class`` (so the fireplace/person/plant rules of
:mod:`sceneforge.conventions` apply); persons and plants are dropped. A room's id is its
``modelId`` (``fr_0rm_3``, unique in a house), its type the ``roomTypes`` joined by commas,
its level the level listing it. A level's floor height is the bottom of its ``bbox``.
OBJ files are read and written by :mod:`sceneforge.houses.formats.obj`.
"""

from __future__ import annotations

import csv
import json
import re
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_IDS, NYU40_NAMES, is_dropped, nyu40_id
from ...errors import HouseError
from ..categories import resolve
from ..model import House, Instance, Level, Material, Room, make_instance
from .meshio import Mesh, place
from .obj import read_obj, write_obj

if TYPE_CHECKING:
    from .. import LoadOptions

VERSION = "suncg@1.0.0"
CATEGORY_CSV = Path("metadata") / "ModelCategoryMapping.csv"
CSV_FIELDS = (
    "index", "model_id", "fine_grained_class", "coarse_grained_class", "empty_struct_obj",
    "nyuv2_40class", "wnsynsetid", "wnsynsetkey",
)
#: Room envelope files: file suffix, NYU40 class (also the label) and the flag hiding it.
ROOM_PARTS = (("f", "floor", "hideFloor"), ("c", "ceiling", "hideCeiling"), ("w", "wall", "hideWalls"))


# --------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------


def _flag(value) -> bool:
    """A SUNCG boolean: 1, "1", true. The toolbox compares the value's text with "1"."""
    return str(value).strip().lower() in ("1", "true")


def _invalid(item: dict) -> bool:
    return "valid" in item and str(item["valid"]).strip().lower() in ("0", "false")


@lru_cache(maxsize=4)
def _category_rows(path: str, mtime_ns: int) -> dict[str, tuple[str, str, str]]:
    """model_id → (fine_grained_class, coarse_grained_class, nyuv2_40class)."""
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = {"model_id", "fine_grained_class", "coarse_grained_class", "nyuv2_40class"} - set(
            reader.fieldnames or ()
        )
        if missing:
            raise ValueError(f"missing column(s) {', '.join(sorted(missing))}")
        return {
            r["model_id"].strip(): (
                (r["fine_grained_class"] or "").strip(),
                (r["coarse_grained_class"] or "").strip(),
                (r["nyuv2_40class"] or "").strip(),
            )
            for r in reader
            if r.get("model_id")
        }


class _Reader:
    """State of one house being read: paths, category table, OBJ cache, the house."""

    def __init__(self, path: Path, options: LoadOptions):
        self.path = path
        self.strict = options.strict
        self.house = House(id=path.parent.name, instances=[], rooms=[], levels=[],
                           source_format="suncg", source_path=str(path))
        parents = path.resolve().parents
        if len(parents) < 3:
            raise self.error("a SUNCG house.json lies in <root>/house/<id>/")
        self.root = parents[2]
        self.csv_path = self.root / CATEGORY_CSV
        self._objs: dict[Path, Mesh] = {}

    def error(self, problem: str, file: Path | None = None) -> HouseError:
        return HouseError(self.house.id, file or self.path, problem)

    def read_doc(self) -> dict:
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise self.error(f"cannot read house.json: {e}") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("levels"), list):
            raise self.error("not a SUNCG house.json: no 'levels' list")
        up = doc.get("up", [0, 1, 0])
        try:
            up_ok = np.allclose(np.asarray(up, dtype=float) / np.linalg.norm(up), [0, 1, 0], atol=1e-6)
        except (TypeError, ValueError):
            up_ok = False
        if not up_ok:
            raise self.error(f"'up' is {up}; only +Y-up SUNCG houses ([0, 1, 0]) are supported")
        try:
            self.scale = float(doc.get("scaleToMeters", 1.0))
        except (TypeError, ValueError):
            self.scale = float("nan")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise self.error(f"'scaleToMeters' must be a positive number, got {doc.get('scaleToMeters')!r}")
        try:
            stat = self.csv_path.stat()
            self.categories = _category_rows(str(self.csv_path), stat.st_mtime_ns)
        except OSError as e:
            raise self.error(f"cannot read the SUNCG category table: {e.strerror or e}",
                             self.csv_path) from None
        except (ValueError, KeyError, csv.Error) as e:
            raise self.error(f"cannot read the SUNCG category table: {e}", self.csv_path) from None
        self.room_dir = self.root / "room" / str(doc.get("id") or self.house.id)
        return doc

    def obj(self, file: Path) -> Mesh:
        if file not in self._objs:
            try:
                self._objs[file] = read_obj(file)
            except (OSError, ValueError) as e:
                raise self.error(f"cannot read OBJ: {e}", file) from None
        return self._objs[file]

    def matrix(self, node: dict, node_id: str) -> np.ndarray:
        """Model → world (metres): the node's column-major transform, then scaleToMeters."""
        m = np.eye(4)
        if "transform" in node:
            try:
                t = np.asarray(node["transform"], dtype=np.float64)
            except (TypeError, ValueError):
                t = np.empty(0)
            if t.shape != (16,) or not np.isfinite(t).all():
                raise self.error(f"node {node_id}: 'transform' must be 16 finite numbers")
            m = t.reshape(4, 4).T
        return np.diag([self.scale, self.scale, self.scale, 1.0]) @ m

    def add(self, name, category, label, room_id, mesh: Mesh, matrix, file, material=None):
        v, f = place(mesh.vertices, mesh.faces, matrix)
        make_instance(self.house, name=name, category=category, label=label, room_id=room_id,
                      vertices=v, faces=f, uv=mesh.uv, file=file, material=material or mesh.material)

    # ---- node types ----

    def room(self, node: dict, node_id: str, room_id: str) -> None:
        scale = np.diag([self.scale] * 3 + [1.0])
        for suffix, name, hide in ROOM_PARTS:
            if _flag(node.get(hide, 0)):
                continue
            file = self.room_dir / f"{node.get('modelId')}{suffix}.obj"
            if not file.is_file():
                self.house.warnings.append(f"room {room_id}: {file} is missing, its {name} skipped")
                continue
            self.add(f"{name.capitalize()}#{node_id}", NYU40_IDS[name], name, room_id,
                     self.obj(file), scale, file)

    def ground(self, node: dict, node_id: str, room_id: str | None) -> None:
        if _flag(node.get("hideFloor", 0)):
            return
        file = self.room_dir / f"{node.get('modelId')}f.obj"
        if not file.is_file():
            self.house.warnings.append(f"ground {node_id}: {file} is missing, skipped")
            return
        self.add(f"Ground#{node_id}", NYU40_IDS["floor"], "ground", room_id, self.obj(file),
                 self.matrix(node, node_id), file)

    def box(self, node: dict, node_id: str, room_id: str | None) -> None:
        import trimesh

        try:
            dims = np.asarray(node.get("dimensions", [1, 1, 1]), dtype=np.float64)
        except (TypeError, ValueError):
            dims = np.empty(0)
        if dims.shape != (3,) or not (np.isfinite(dims).all() and (dims > 0).all()):
            raise self.error(f"box node {node_id}: 'dimensions' must be 3 positive numbers")
        b = trimesh.creation.box(extents=dims)
        mesh = Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int64))
        self.add(f"Box#{node_id}", 0, "Box", room_id, mesh, self.matrix(node, node_id), self.path,
                 material=_node_material(node))

    def object(self, node: dict, node_id: str, room_id: str | None) -> None:
        model = str(node.get("modelId") or "")
        if not model:
            self.house.warnings.append(f"object node {node_id}: no modelId, skipped")
            return
        row = self.categories.get(model)
        if row is None:
            label = ""
            category = resolve(self.house, f"model {model} (not in ModelCategoryMapping.csv)", None,
                               strict=self.strict, file=self.csv_path)
        else:
            fine, coarse, nyu = row
            if any(is_dropped(0, name) for name in row):
                return
            label = fine or coarse or nyu
            category = resolve(self.house, nyu, nyu40_id(nyu), strict=self.strict, file=self.csv_path)
        stem = f"{model}_0" if _flag(node.get("state", 0)) else model
        file = self.root / "object" / model / f"{stem}.obj"
        if not file.is_file():
            raise self.error(f"object node {node_id}: model file is missing", file)
        self.add(f"Object#{node_id}", category, label, room_id, self.obj(file),
                 self.matrix(node, node_id), file)


def _node_material(node: dict) -> Material | None:
    """The first ``materials[].diffuse`` (``#rrggbb``) of a node, if any."""
    for mat in node.get("materials") or []:
        diffuse = str(mat.get("diffuse") or "") if isinstance(mat, dict) else ""
        if re.fullmatch(r"#[0-9a-fA-F]{6}", diffuse):
            return Material(base_color=(*(int(diffuse[i:i + 2], 16) / 255 for i in (1, 3, 5)), 1.0))
    return None


def load_house(path: Path, options: LoadOptions) -> House:
    """Read ``<root>/house/<id>/house.json`` (or its folder) of a SUNCG root."""
    path = Path(path)
    if path.is_dir():
        path = path / "house.json"
    r = _Reader(path, options)
    doc = r.read_doc()
    house = r.house
    for li, level in enumerate(doc["levels"]):
        if not isinstance(level, dict) or _invalid(level):
            continue
        try:
            level_id = int(level.get("id", li))
        except (TypeError, ValueError):
            level_id = li
        nodes = [n if isinstance(n, dict) else {} for n in level.get("nodes") or []]
        first = len(house.instances)
        room_of: dict[int, str] = {}
        rooms: list[tuple[int, str]] = []
        for ni, node in enumerate(nodes):
            if node.get("type") == "Room" and not _invalid(node):
                rid = str(node.get("modelId") or node.get("id") or f"{li}_{ni}")
                house.rooms.append(Room(rid, ",".join(map(str, node.get("roomTypes") or [])), level_id))
                rooms.append((ni, rid))
                for k in node.get("nodeIndices") or []:
                    if isinstance(k, (int, float)) and 0 <= int(k) < len(nodes):
                        room_of[int(k)] = rid
        room_ids = dict(rooms)
        for ni, node in enumerate(nodes):
            if _invalid(node):
                continue
            kind, node_id = node.get("type"), str(node.get("id", f"{li}_{ni}"))
            if kind == "Room":
                r.room(node, node_id, room_ids[ni])
            elif kind == "Ground":
                r.ground(node, node_id, room_of.get(ni))
            elif kind == "Box":
                r.box(node, node_id, room_of.get(ni))
            elif kind == "Object":
                r.object(node, node_id, room_of.get(ni))
            else:
                house.warnings.append(f"node {node_id}: unknown type {kind!r}, skipped")
        house.levels.append(Level(level_id, _floor_y(level, house.instances[first:], r.scale)))
    if not house.levels:
        house.levels.append(Level(0, 0.0))
    return house.check_not_empty()


def _floor_y(level: dict, instances: list[Instance], scale: float) -> float:
    """Bottom of the level's bbox; without one, the lowest floor (or anything) of the level."""
    try:
        return float(level["bbox"]["min"][1]) * scale
    except (KeyError, IndexError, TypeError, ValueError):
        pass
    floors = [i for i in instances if i.category == NYU40_IDS["floor"]] or instances
    return float(min(i.vertices[:, 1].min() for i in floors)) if floors else 0.0


# --------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------


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
