"""3D-FRONT houses: one scene JSON plus 3D-FUTURE furniture models.

A 3D-FRONT root, as released and as :func:`sceneforge.testing.front3d.write_house` writes it::

    <root>/3D-FRONT/<uid>.json                    one house
    <root>/3D-FUTURE-model/<jid>/raw_model.obj    a furniture model (+ its .mtl, texture.png)
    <root>/3D-FUTURE-model/model_info.json        [{model_id, category, super-category, ...}]
    <root>/3D-FRONT-texture/<id>/texture.png      textures of the architecture meshes

The scene JSON is read as the 3D-FRONT-ToolBox reads it (``scripts/scene.py``, ``utils.py``):

- ``furniture[]``: ``uid``, ``jid`` (the 3D-FUTURE model), ``title``, ``category``, ``valid``;
  entries with ``valid: false`` are unreleased models and are skipped;
- ``mesh[]``: architecture inline, in world coordinates: ``uid``, ``type`` (Floor, WallInner,
  Ceiling, Door, ...), flat ``xyz``, ``faces``, ``uv``, ``normal`` and a ``material`` uid;
- ``material[]``: ``uid``, ``color`` (RGBA 0–255), ``texture`` (a URL whose last folder
  names the texture in ``3D-FRONT-texture``);
- ``scene.room[]``: ``type``, ``instanceid`` and ``children[]`` of
  ``{ref, instanceid, pos, rot, scale}``. Each child places the furniture or mesh whose uid
  is ``ref`` at ``R(rot) · (scale ⊙ v) + pos`` with ``rot`` a unit quaternion
  **(x, y, z, w)**; a mirroring (negative) scale reverses the face winding. Mesh children
  carry the identity in the released data.

Units are metres and +Y is up, as in sceneforge. A furniture model whose ``raw_model.obj``
is missing is skipped with a warning (3D-FRONT references models that were never
released, so an error would reject most houses); a missing model folder is an error.

Categories go through ``sceneforge/data/front3d_categories.json``: furniture tries its
``category``, then its model's ``category`` and ``super-category`` in ``model_info.json``,
then its ``title``; a mesh its ``type``. The first name found in the table (or that is an
NYU40 class name) decides; the instance label is the first name given. Plants are dropped.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import is_dropped, nyu40_id
from ...errors import HouseError, SceneforgeError
from ..categories import data_file, resolve
from ..model import House, Material, Room, make_instance
from .base import Format, HouseSource, json_document
from .meshio import Mesh, place, quaternion_matrix
from .obj import read_obj

if TYPE_CHECKING:
    from .. import LoadOptions

SCENE_DIR = "3D-FRONT"
MODEL_DIR = "3D-FUTURE-model"
TEXTURE_DIR = "3D-FRONT-texture"
MODEL_INFO = "model_info.json"
CATEGORY_FILE = "front3d_categories.json"


def detect(path: Path) -> bool:
    """True for a 3D-FRONT root (a folder holding ``3D-FRONT/``) or a scene JSON (``furniture``
    and ``scene``)."""
    if path.is_dir():
        return (path / SCENE_DIR).is_dir()
    doc = json_document(path)
    return isinstance(doc, dict) and "furniture" in doc and "scene" in doc


def list_houses(path: Path) -> list[HouseSource]:
    """Every scene of a root's ``3D-FRONT/`` folder, or the one scene of a scene JSON."""
    if path.is_dir():
        from . import find  # the registry, which imports this module

        return find(path / SCENE_DIR, FORMAT)
    return [HouseSource(path.stem, FORMAT.name, path)]


def _key(name: str) -> str:
    return " ".join(str(name).split()).lower()


@lru_cache(maxsize=1)
def category_table() -> dict[str, str]:
    """Normalised 3D-FRONT name → NYU40 class name (or a dropped name: plant, person)."""
    path = data_file(CATEGORY_FILE)
    try:
        raw = json.loads(path.read_text())["categories"]
        table = {_key(k): str(v) for k, v in raw.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise SceneforgeError(f"cannot read the 3D-FRONT category table {path}: {e}") from None
    bad = sorted(v for v in set(table.values()) if nyu40_id(v) is None and not is_dropped(0, v))
    if bad:
        raise SceneforgeError(f"{path}: {', '.join(bad)} are not NYU40 class names")
    return table


def lookup(names) -> tuple[str, int | None, bool]:
    """``(label, NYU40 id or None, dropped)`` for the candidate names of one piece, best first."""
    names = [str(n).strip() for n in names if n and str(n).strip()]
    label = names[0] if names else ""
    table = category_table()
    for name in names:
        target = table.get(_key(name))
        if target is None and nyu40_id(name) is not None:
            target = name
        if target is not None:
            return label, nyu40_id(target), is_dropped(0, target) or is_dropped(0, label)
    return label, None, is_dropped(0, label)


def _future_dir(path: Path, options: LoadOptions) -> Path:
    if options.future_dir:
        return Path(options.future_dir)
    for cand in (path.parent.parent / MODEL_DIR, path.parent / MODEL_DIR):
        if cand.is_dir():
            return cand
    return path.parent.parent / MODEL_DIR


class _Reader:
    """State of one scene being read: paths, tables, model cache, the house."""

    def __init__(self, path: Path, options: LoadOptions):
        self.path = path
        self.strict = options.strict
        self.future = _future_dir(path, options)
        self.textures = path.parent.parent / TEXTURE_DIR
        self.house = House(id=path.stem, instances=[], rooms=[], source_format="front3d",
                           source_path=str(path))
        self._models: dict[str, Mesh | None] = {}

    def error(self, problem: str, file: Path | None = None) -> HouseError:
        return HouseError(self.house.id, file or self.path, problem)

    def read_doc(self) -> dict:
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise self.error(f"cannot read scene JSON: {e}") from None
        scene = doc.get("scene") if isinstance(doc, dict) else None
        if not (isinstance(scene, dict) and isinstance(scene.get("room"), list)):
            raise self.error("not a 3D-FRONT scene: no 'scene.room' list")
        self.info: dict[str, tuple[str, str]] = {}
        info_path = self.future / MODEL_INFO
        if info_path.is_file():
            try:
                self.info = {
                    str(m["model_id"]): (m.get("category") or "", m.get("super-category") or "")
                    for m in json.loads(info_path.read_text(encoding="utf-8"))
                }
            except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
                raise self.error(f"cannot read 3D-FUTURE model info: {e}", info_path) from None
        return doc

    def matrix(self, child: dict) -> np.ndarray:
        """Child placement ``pos + R(rot) · (scale ⊙ v)`` as a 4×4."""
        try:
            pos = np.asarray(child.get("pos", [0, 0, 0]), dtype=np.float64)
            rot = np.asarray(child.get("rot", [0, 0, 0, 1]), dtype=np.float64)
            scale = np.asarray(child.get("scale", [1, 1, 1]), dtype=np.float64)
            ok = pos.shape == (3,) and rot.shape == (4,) and scale.shape == (3,)
            ok = ok and all(np.isfinite(a).all() for a in (pos, rot, scale)) and np.linalg.norm(rot) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise self.error(f"child {child.get('instanceid', child.get('ref'))!r}: pos/rot/scale must be "
                             "3, 4 (a non-zero quaternion x, y, z, w) and 3 finite numbers")
        m = np.eye(4)
        m[:3, :3] = quaternion_matrix(rot) * scale
        m[:3, 3] = pos
        return m

    def model(self, jid: str) -> Mesh | None:
        """The 3D-FUTURE model ``jid`` (its texture.png as texture), None when missing."""
        if jid not in self._models:
            file = self.future / jid / "raw_model.obj"
            if not file.is_file():
                self.house.warnings.append(f"furniture model {jid}: {file} is missing, skipped")
                self._models[jid] = None
            else:
                try:
                    mesh = read_obj(file)
                except (OSError, ValueError) as e:
                    raise self.error(f"cannot read OBJ: {e}", file) from None
                texture = file.parent / "texture.png"
                if texture.is_file():
                    base = (mesh.material or Material()).base_color
                    mesh = replace(mesh, material=Material(base_color=base, texture=texture))
                self._models[jid] = mesh
        return self._models[jid]

    def category(self, names, what: str) -> tuple[str, int] | None:
        """(label, NYU40 id) of a piece, or None when it is dropped."""
        label, cid, dropped = lookup(names)
        if dropped:
            return None
        return label, resolve(self.house, label or f"{what} without a category", cid,
                              strict=self.strict, file=self.path)

    def furniture(self, entry: dict, child: dict, room_id: str | None) -> None:
        jid = str(entry.get("jid") or "")
        info = self.info.get(jid, ("", ""))
        cat = self.category([entry.get("category"), *info, entry.get("title")], "furniture")
        if cat is None:
            return
        mesh = self.model(jid)
        if mesh is None:
            return
        label, cid = cat
        v, f = place(mesh.vertices, mesh.faces, self.matrix(child))
        make_instance(self.house, name=f"{label or 'furniture'}#{child.get('instanceid', entry.get('uid'))}",
                      category=cid, label=label, room_id=room_id, vertices=v, faces=f, uv=mesh.uv,
                      file=self.future / jid / "raw_model.obj", material=mesh.material)

    def mesh(self, entry: dict, child: dict, room_id: str | None, materials: dict) -> None:
        cat = self.category([entry.get("type")], "mesh")
        if cat is None:
            return
        label, cid = cat
        uid = entry.get("uid")
        try:
            xyz = np.asarray(entry.get("xyz", []), dtype=np.float64).reshape(-1, 3)
            faces = np.asarray(entry.get("faces", []), dtype=np.int64).reshape(-1, 3)
        except (TypeError, ValueError) as e:
            raise self.error(f"mesh {uid!r}: 'xyz' and 'faces' must be flat lists of 3k numbers ({e})"
                             ) from None
        uv = entry.get("uv") or None
        if uv is not None:
            try:
                uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
            except (TypeError, ValueError):
                uv = None
            if uv is not None and (len(uv) != len(xyz) or not np.isfinite(uv).all()):
                uv = None
        v, f = place(xyz, faces, self.matrix(child))
        make_instance(self.house, name=f"{label or 'mesh'}#{child.get('instanceid', uid)}", category=cid,
                      label=label, room_id=room_id, vertices=v, faces=f, uv=uv, file=self.path,
                      material=self.material(materials.get(entry.get("material"))))

    def material(self, entry: dict | None) -> Material:
        """A mesh material: ``color`` (RGB or RGBA, 0–255) and the texture its URL names."""
        if not isinstance(entry, dict):
            return Material()
        try:
            c = np.asarray(entry.get("color") or [], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            c = np.empty(0)
        base = Material().base_color
        if 3 <= len(c) <= 4 and np.isfinite(c).all():
            base = tuple(float(x) for x in np.clip(np.append(c / 255, 1.0)[:4], 0, 1))
        texture = None
        url = str(entry.get("texture") or "").rstrip("/")
        if "/" in url:
            cand = self.textures / url.split("/")[-2] / "texture.png"
            texture = cand if cand.is_file() else None
        return Material(base_color=base, texture=texture)


def load_house(path: Path, options: LoadOptions) -> House:
    """Read one 3D-FRONT scene JSON (its furniture from the 3D-FUTURE model folder)."""
    r = _Reader(Path(path), options)
    doc = r.read_doc()
    furniture = {f.get("uid"): f for f in doc.get("furniture") or [] if isinstance(f, dict)}
    meshes = {m.get("uid"): m for m in doc.get("mesh") or [] if isinstance(m, dict)}
    materials = {m.get("uid"): m for m in doc.get("material") or [] if isinstance(m, dict)}
    if furniture and not r.future.is_dir():
        raise r.error("3D-FUTURE model folder not found (pass --future-dir)", r.future)
    invalid = 0
    for room in doc["scene"]["room"]:
        if not isinstance(room, dict):
            continue
        # the writer's convention for pieces outside any room: a room without an instanceid
        room_id = str(room.get("instanceid") or "") or None
        if room_id is not None:
            r.house.rooms.append(Room(room_id, str(room.get("type") or ""), 0))
        for child in room.get("children") or []:
            ref = child.get("ref") if isinstance(child, dict) else None
            if ref in furniture:
                if furniture[ref].get("valid", True) is False:
                    invalid += 1
                    continue
                r.furniture(furniture[ref], child, room_id)
            elif ref in meshes:
                r.mesh(meshes[ref], child, room_id, materials)
    if invalid:
        r.house.warnings.append(f"{invalid} placed furniture pieces are marked invalid (unreleased), skipped")
    return r.house.check_not_empty()


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, options)


FORMAT = Format(
    "front3d", detect=detect, list=list_houses, load=_load,
    # scene files vary: inside a root, or when 3D-FRONT is asked for, any other JSON is one
    fallback=lambda path: path.suffix.lower() == ".json",
)
