"""SUNCG houses: ``house.json`` with its ``room/``, ``object/`` and ``metadata/`` folders.

A SUNCG root, as released and as :func:`sceneforge.testing.suncg.write_house` writes it::

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
  is 1). A missing model file is an error. Their ``materials`` list overrides the model's
  own materials as the toolbox's ``ParseSUNCGMaterials`` does (:func:`_overrides`): entry
  *i* replaces the model's *i*-th material (the *i*-th ``newmtl`` of its ``.mtl``), its
  ``diffuse`` (``#rrggbb``) the colour and its ``texture`` the image
  (``<root>/texture/<name>.png``, else ``.jpg``); an entry with neither, or past the
  model's materials, changes nothing.
- Everything is scaled by ``scaleToMeters``.

Textured materials. A SUNCG ``.mtl`` material usually has both ``Kd`` and ``map_Kd``, and
``Kd`` is often a saturated colour under a plain texture (walls: ``Kd 1 0.07 0.40`` over
the pure white ``wallp_0.jpg``). ``LoadOptions.suncg_textures`` decides what the material
shows: ``replace`` (default) the texture alone, ``multiply`` ``Kd`` × the texture. PBRS,
the paper's RGB, rendered SUNCG with Mitsuba, whose OBJ importer takes ``map_Kd`` in place of
``Kd`` (mitsuba-renderer/mitsuba ``src/shapes/obj.cpp``, ``loadMaterialLibrary``: both set
the one ``diffuse`` reflectance, ``map_Kd`` last), and shows those walls white; OpenGL's
modulate (the toolbox's viewer) would show them magenta. A node's ``diffuse`` override is a
``Kd`` like the others: under ``replace`` it shows only on materials without a texture.

In sceneforge terms: an object's NYU40 class is its model's ``nyuv2_40class`` and its label
the ``fine_grained_class`` (so the fireplace/person/plant rules of
:mod:`sceneforge.conventions` apply); persons and plants are dropped. A room's id is its
``modelId`` (``fr_0rm_3``, unique in a house), its type the ``roomTypes`` joined by commas,
its level the level listing it. A level's floor height is the bottom of its ``bbox``.
OBJ files are read by :mod:`sceneforge.houses.formats.obj`.
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_IDS, is_dropped, nyu40_id
from ...errors import HouseError
from ..categories import resolve
from ..model import House, Instance, Level, Material, Room, make_instance
from .base import Format, HouseSource, json_document
from .meshio import Mesh, place
from .obj import read_obj

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


def root_of(path: Path) -> Path | None:
    """The SUNCG root of ``path`` (root, ``house/<id>/`` or its ``house.json``), if it is one."""
    for cand in (path, *path.parents[:3]):
        if (cand / "house").is_dir() and (cand / "object").is_dir():
            return cand
    return None


def detect(path: Path) -> bool:
    """True for a SUNCG root (``house/`` and ``object/`` folders), a house folder inside one,
    or a SUNCG ``house.json`` (``levels``, and ``version`` or ``up``)."""
    if path.is_dir():
        root = root_of(path)
        return root is not None and (root == path or (path / "house.json").is_file())
    doc = json_document(path)
    return isinstance(doc, dict) and "levels" in doc and ("version" in doc or "up" in doc)


def list_houses(path: Path) -> list[HouseSource]:
    """Every house of a SUNCG root (by id), or the one house of a house folder or ``house.json``."""
    if path.is_dir() and root_of(path) == path:
        return [
            HouseSource(d.name, FORMAT.name, d / "house.json")
            for d in sorted((path / "house").iterdir())
            if (d / "house.json").is_file()
        ]
    house_dir = path.parent if path.is_file() else path
    return [HouseSource(house_dir.name, FORMAT.name, house_dir / "house.json")]


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
        self.textures = options.suncg_textures
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
        args = {"material": material} if material is not None else mesh.instance_args()
        given = args["material"]
        if given is not None and (self.textures == "replace" or mesh.uv is None):
            # without uv no texture shows (the raster and path tracer would draw a textured
            # material's colour alone: white under ``replace``), so such a material keeps Kd
            alone = _texture_alone if mesh.uv is not None else _without_texture
            args["material"] = tuple(map(alone, given)) if isinstance(given, tuple) else alone(given)
        make_instance(self.house, name=name, category=category, label=label, room_id=room_id,
                      vertices=v, faces=f, uv=mesh.uv, file=file, **args)

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
        mesh = self.obj(file)
        if isinstance(node.get("materials"), list):
            mesh = self.overrides(mesh, node["materials"], node_id)
        self.add(f"Object#{node_id}", category, label, room_id, mesh, self.matrix(node, node_id), file)

    def overrides(self, mesh: Mesh, entries: list, node_id: str) -> Mesh:
        """``mesh`` with an Object node's ``materials`` applied (module docs).

        As SUNCGtoolbox's ``ParseSUNCGMaterials`` (gaps/pkgs/R3Graphics/R3Scene.cpp): entry
        ``index`` pairs with ``input_materials.Kth(index)``, the model's materials in the
        order its ``.mtl`` defines them (``ReadObjMtlFile`` inserts one per ``newmtl``); a
        ``diffuse`` string ``#rrggbb`` is read as three hex bytes / 255 into the copied BRDF's
        diffuse; a ``texture`` name is ``../../texture/<name>.png`` from the house folder,
        else ``.jpg``, and replaces the texture (else the input's is kept). The toolbox
        fails the house on an unreadable texture; here it is a warning and the model's own
        texture stays (the geometry is right either way).
        """
        by_name: dict[str, Material] = {}
        own = dict(zip(mesh.material_names, mesh.materials, strict=True))
        for index, entry in enumerate(entries):
            if not isinstance(entry, dict) or index >= len(mesh.library) or mesh.library[index] not in own:
                continue  # not a material entry, past the model's materials, or one no face uses
            name = mesh.library[index]
            material = by_name.get(name, own[name])
            diffuse = str(entry.get("diffuse") or "")
            if diffuse:
                if re.fullmatch(r"#[0-9a-fA-F]{6}", diffuse):
                    rgb = tuple(int(diffuse[i:i + 2], 16) / 255 for i in (1, 3, 5))
                    material = replace(material, base_color=(*rgb, material.base_color[3]))
                else:
                    self.house.warnings.append(f"object node {node_id}: material {index} diffuse {diffuse!r} "
                                               "is not #rrggbb, ignored")
            texture = str(entry.get("texture") or "")
            if texture:
                image = next((p for p in (self.root / "texture" / f"{texture}{ext}" for ext in (".png", ".jpg"))
                              if p.is_file()), None)
                if image is None:
                    self.house.warnings.append(f"object node {node_id}: texture {texture!r} not found in "
                                               f"{self.root / 'texture'}, the model's own kept")
                else:
                    material = replace(material, texture=image)
            by_name[name] = material
        if not by_name:
            return mesh
        materials = tuple(by_name.get(n, m) for n, m in zip(mesh.material_names, mesh.materials, strict=True))
        return replace(mesh, material=materials if isinstance(mesh.material, tuple) else materials[0])


def _texture_alone(material: Material) -> Material:
    """``material`` showing its texture alone (``suncg_textures`` ``replace``): its colour
    white, its opacity kept; a material without a texture as it is."""
    if material.texture is None:
        return material
    return replace(material, base_color=(1.0, 1.0, 1.0, material.base_color[3]))


def _without_texture(material: Material) -> Material:
    """``material`` showing its colour (``Kd``, or a node's ``diffuse``): for a mesh without uv."""
    return material if material.texture is None else replace(material, texture=None)


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


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, options)


FORMAT = Format("suncg", detect=detect, list=list_houses, load=_load)
