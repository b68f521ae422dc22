"""3D-FRONT writer: a house as a 3D-FRONT root (scene JSON, 3D-FUTURE models, textures);
the reader and the layout are in :mod:`sceneforge.houses.formats.front3d`."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import numpy as np

from ..conventions import NYU40_NAMES
from ..houses.formats.front3d import MODEL_DIR, MODEL_INFO, SCENE_DIR, TEXTURE_DIR, lookup
from ..houses.formats.meshio import Mesh
from ..houses.model import House, Instance
from .obj import write_obj
from .textures import save_texture


def _source_name(inst: Instance, fallback: str | None) -> str:
    """The instance's label when it maps back to its class (given ``fallback``), else the NYU40 name."""
    name = NYU40_NAMES[inst.category]
    return inst.label if inst.label and lookup([inst.label, fallback])[1] == inst.category else name


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(n, 3) float64 area-weighted vertex normals (zero for unused vertices)."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def write_house(house: House, root: str | Path) -> Path:
    """Write ``house`` into the 3D-FRONT root ``root`` and return the path of its scene JSON.

    - Envelope instances become inline ``mesh`` entries (world coordinates, identity child
      placement) with a ``material`` entry (colour rounded to 0–255; a texture is copied to
      ``3D-FRONT-texture/<id>/texture.png``). Their ``type`` is the label when it maps back
      to the same class, else the NYU40 name.
    - Every other instance becomes a 3D-FUTURE model ``3D-FUTURE-model/<jid>/raw_model.obj``
      (+ ``model.mtl``, ``texture.png``) in coordinates relative to the centre of its base,
      placed by ``pos``; its ``category`` is its label when that maps back to the same class
      (``model_info.json`` gets the NYU40 name as ``super-category``, merged with the entries
      already there), else the NYU40 name. jids are UUIDs derived from house id and index.
    - Rooms keep their ids (``instanceid``) and types; instances outside any room go into a
      last room without ``instanceid``, which the loader reads as "no room".

    Read back, instances come room by room (rooms in ``house.rooms`` order, then rooms known
    only from instances, then the room-less instances), in house order within a room.
    """
    root = Path(root)
    scene_dir, future, textures = root / SCENE_DIR, root / MODEL_DIR, root / TEXTURE_DIR
    scene_dir.mkdir(parents=True, exist_ok=True)
    future.mkdir(parents=True, exist_ok=True)
    order = [r.id for r in house.rooms]
    for inst in house.instances:
        if inst.room_id not in order:
            order.append(inst.room_id)
    types = {r.id: r.type for r in house.rooms}
    children: dict[str | None, list[dict]] = {rid: [] for rid in order}
    furniture, meshes, materials, infos = [], [], [], []
    identity = {"pos": [0.0, 0.0, 0.0], "rot": [0.0, 0.0, 0.0, 1.0], "scale": [1.0, 1.0, 1.0]}
    for k, inst in enumerate(house.instances):
        jid = str(uuid.uuid5(uuid.NAMESPACE_URL, f"sceneforge:{house.id}:{k}"))
        if inst.envelope:
            uid = f"{k}/mesh"
            texture = ""
            if inst.material.texture is not None:
                (textures / jid).mkdir(parents=True, exist_ok=True)
                save_texture(inst.material.texture, textures / jid / "texture.png")
                texture = f"{TEXTURE_DIR}/{jid}/texture.png"
            materials.append({"uid": f"{k}/material", "jid": jid, "texture": texture, "normaltexture": "",
                              "color": [round(c * 255) for c in inst.material.base_color],
                              "colorMode": "texture" if texture else "color"})
            meshes.append({
                "uid": uid, "jid": jid, "instanceid": f"mesh{k}", "type": _source_name(inst, None),
                "xyz": inst.vertices.reshape(-1).tolist(),
                "normal": _vertex_normals(inst.vertices, inst.faces).reshape(-1).tolist(),
                "uv": [] if inst.uv is None else inst.uv.astype(np.float64).reshape(-1).tolist(),
                "faces": inst.faces.reshape(-1).tolist(), "material": f"{k}/material",
            })
            children[inst.room_id].append({"ref": uid, "instanceid": f"mesh/{k}", **identity})
        else:
            uid = f"{k}/model"
            name = _source_name(inst, NYU40_NAMES[inst.category])
            lo, hi = inst.vertices.min(0), inst.vertices.max(0)
            origin = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
            model = Mesh(inst.vertices - origin, inst.faces, inst.uv, inst.material)
            write_obj(future / jid / "raw_model.obj", [model], mtl_name="model.mtl",
                      texture_name="texture.png")
            furniture.append({"uid": uid, "jid": jid, "title": inst.label, "category": name,
                              "size": (hi - lo).tolist(), "valid": True})
            infos.append({"model_id": jid, "category": name, "super-category": NYU40_NAMES[inst.category]})
            children[inst.room_id].append({"ref": uid, "instanceid": f"furniture/{k}",
                                           **identity, "pos": origin.tolist()})
    rooms = [{"type": types.get(rid, ""), "instanceid": rid or "", **identity, "children": children[rid]}
             for rid in order if rid is not None]
    if None in children:
        rooms.append({"type": "", "instanceid": "", **identity, "children": children[None]})
    _merge_model_info(future / MODEL_INFO, infos)
    doc = {"uid": house.id, "north_vector": [0, 1, 0], "furniture": furniture, "mesh": meshes,
           "material": materials, "scene": {"ref": "-1", **identity, "room": rooms}}
    path = scene_dir / f"{house.id}.json"
    path.write_text(json.dumps(doc) + "\n")
    return path


def _merge_model_info(path: Path, entries: list[dict]) -> None:
    old = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else []
    ids = {e["model_id"] for e in entries}
    path.write_text(json.dumps([e for e in old if e.get("model_id") not in ids] + entries, indent=1) + "\n")
