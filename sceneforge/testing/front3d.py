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


# ---- a house shaped like the released files -----------------------------------------------
#
# What real 3D-FRONT scene JSONs hold that write_house never writes: furniture entries without
# ``valid`` (unreleased models, often only uid/jid/aid), ``super/sub`` titles, null fine
# categories, coarse entry categories, jamb-only Door/Window/Hole/Pocket meshes, exterior
# shells (WallOuter, SlabSide, SlabBottom), materials with an empty texture URL whose texture
# lives under the material's jid with a UVTransform, numeric strings, empty meshes, cabinet
# boards sharing a constructid, child references to no uid, duplicate uids, a model whose size
# is off its entry's bbox and a child scale of 7.16. The geometry is known exactly:

#: Room A (LivingRoom-1) spans x 0..4, room B (Bedroom-2) x 4.2..8.2, both z 0..4, y 0..2.8.
ROOM_A, ROOM_B, HEIGHT = (0.0, 4.0), (4.2, 8.2), 2.8
#: The door between them: through the wall x 4.0..4.2, z 1.5..2.4, y 0..2.1.
DOOR = {"wall": (4.0, 4.2), "span": (1.5, 2.4), "height": (0.0, 2.1)}
#: Room A's window: through the exterior wall z -0.24..0, x 1.5..2.7, y 0.9..2.1 (its Window
#: mesh is a sill and a lintel: 4 faces).
WINDOW = {"wall": (-0.24, 0.0), "span": (1.5, 2.7), "height": (0.9, 2.1)}
#: A Hole in room B's exterior wall: through x 8.2..8.44, z 1.0..2.0, y 0.8..2.0 (a window:
#: its sill is above the floor).
HOLE = {"wall": (8.2, 8.44), "span": (1.0, 2.0), "height": (0.8, 2.0)}
#: Row-major 3×3 UVTransforms of the floor and wall materials (none is the identity).
UV_TRANSFORMS = {"tex-floor": [0.5, 0.25, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0],
                 "tex-wall": [1.5, 0.0, 0.0, 0.0, 1.5, 0.0, 0.0, 0.0, 1.0]}
#: What loading the house counts (reason constants of :mod:`~sceneforge.houses.formats.front3d`).
EXPECTED_LOSSES = {
    "UNRELEASED": 4, "DANGLING": 2, "DUPLICATE": 1, "NO_MODEL": 1, "EXTERIOR": 3, "DROPPED": 1,
    "NO_TEXTURE": 1, "SCALE_FLAG": 1, "SIZE_FLAG": 1,
}
_WALL = 0.24
_IDENTITY = {"pos": [0.0, 0.0, 0.0], "rot": [0.0, 0.0, 0.0, 1.0], "scale": [1.0, 1.0, 1.0]}


def _quads(quads, facing) -> tuple[list, list]:
    """Flat xyz and faces of quads (k, 4, 3), each wound to face along its ``facing`` vector."""
    xyz, faces = [], []
    for corners, n in zip(np.asarray(quads, dtype=np.float64), np.asarray(facing, dtype=np.float64)):
        k = len(xyz)
        tri = [[k, k + 1, k + 2], [k, k + 2, k + 3]]
        if np.cross(corners[1] - corners[0], corners[2] - corners[0]) @ n < 0:
            tri = [t[::-1] for t in tri]
        xyz += corners.tolist()
        faces += tri
    return xyz, faces


def _plane_rects(axis: int, at: float, along: int, rects) -> list:
    """Quads in the plane ``coord[axis] = at`` from rectangles (a0, a1, b0, b1) in
    (coord[along], the third coordinate)."""
    other = 3 - axis - along
    out = []
    for a0, a1, b0, b1 in rects:
        if a1 - a0 <= 0 or b1 - b0 <= 0:
            continue
        quad = []
        for a, b in ((a0, b0), (a1, b0), (a1, b1), (a0, b1)):
            p = [0.0, 0.0, 0.0]
            p[axis], p[along], p[other] = at, a, b
            quad.append(p)
        out.append(quad)
    return out


def _wall(axis: int, at: float, span, hole=None) -> list:
    """The quads of a full-height wall face, less a hole (span, height) when given."""
    a0, a1 = span
    if hole is None:
        return _plane_rects(axis, at, 2 - axis, [(a0, a1, 0.0, HEIGHT)])
    (h0, h1), (v0, v1) = hole["span"], hole["height"]
    return _plane_rects(axis, at, 2 - axis, [(a0, h0, 0.0, HEIGHT), (h1, a1, 0.0, HEIGHT),
                                             (h0, h1, 0.0, v0), (h0, h1, v1, HEIGHT)])


def _jamb(axis: int, opening, sides: bool = True, sill: bool = True, top: bool = True) -> list:
    """Reveal quads of an opening through a wall normal to ``axis`` (0: x, 2: z), each facing
    into the opening."""
    (w0, w1), (s0, s1), (y0, y1) = opening["wall"], opening["span"], opening["height"]
    along = 2 - axis
    quads, facing = [], []
    for s, n in ((s0, 1.0), (s1, -1.0)) if sides else ():
        quads += _plane_rects(along, s, axis, [(w0, w1, y0, y1)])
        facing.append([n if along == 0 else 0.0, 0.0, n if along == 2 else 0.0])
    for y, n, keep in ((y0, 1.0, sill), (y1, -1.0, top)):
        if keep:
            corners = []
            for w, s in ((w0, s0), (w1, s0), (w1, s1), (w0, s1)):
                p = [0.0, y, 0.0]
                p[axis], p[along] = w, s
                corners.append(p)
            quads.append(corners)
            facing.append([0.0, n, 0.0])
    return _quads(quads, facing)


def _box_quads(lo, hi) -> tuple[np.ndarray, list[list[int]]]:
    """The 8 corners (8, 3) of an axis-aligned box and its 6 outward quads (1-based, OBJ)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    quads = [[1, 4, 3, 2], [5, 6, 7, 8], [1, 2, 6, 5], [4, 8, 7, 3], [1, 5, 8, 4], [2, 3, 7, 6]]
    return v, quads


def _box_mesh(lo, hi) -> tuple[list, list]:
    """Flat xyz and faces of an axis-aligned box (outward)."""
    v, quads = _box_quads(lo, hi)
    centre = v.mean(axis=0)
    corners = [v[np.array(q) - 1] for q in quads]
    return _quads(corners, [c.mean(axis=0) - centre for c in corners])


def _write_model(folder: Path, size, texture: bool = False, broken: bool = False) -> None:
    """raw_model.obj of a box ``size`` (x, y, z) centred on its base, as quads."""
    folder.mkdir(parents=True, exist_ok=True)
    w, h, d = size
    v, quads = _box_quads((-w / 2, 0.0, -d / 2), (w / 2, h, d / 2))
    lines = ["# 3D-FUTURE-like model: quads, no normals", "mtllib model.mtl"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += ["f " + " ".join(map(str, q)) for q in quads]
    if broken:
        lines[-1] = "f 1 2 x"
    (folder / "raw_model.obj").write_text("\n".join(lines) + "\n")
    if texture:
        from PIL import Image

        Image.new("RGB", (4, 4), (200, 120, 40)).save(folder / "texture.png")


def _mesh_entry(uid: str, kind: str, xyz, faces, material: str, uv=None, **extra) -> dict:
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if uv is None:  # planar: metres along the two axes the face spreads over most
        spread = np.ptp(xyz, axis=0) if len(xyz) else np.zeros(3)
        a, b = sorted(np.argsort(spread)[1:])
        uv = xyz[:, [a, b]]
    return {"uid": uid, "jid": "", "aid": [], "type": kind, "xyz": xyz.reshape(-1).tolist(),
            "normal": [0.0, 1.0, 0.0] * len(xyz), "uv": np.asarray(uv).reshape(-1).tolist(),
            "faces": np.asarray(faces, dtype=np.int64).reshape(-1).tolist(), "material": material, **extra}


def write_real_shaped(root: str | Path, uid: str = "real-shaped", *, broken_model: bool = False,
                      nested_models: bool = False, model_info: bool = True) -> Path:
    """Write a two-room house shaped like the released 3D-FRONT files into ``root``; return
    the path of its scene JSON. Geometry, transforms and what loading counts are this module's
    constants (:data:`DOOR`, :data:`WINDOW`, :data:`HOLE`, :data:`UV_TRANSFORMS`,
    :data:`EXPECTED_LOSSES`).

    broken_model  : the nightstand's raw_model.obj has an unreadable face line
    nested_models : the models (and model_info.json) go one folder too deep, into
                    ``3D-FUTURE-model/3D-FUTURE-model``, as a careless unzip leaves them
    model_info    : write ``model_info.json``
    """
    from PIL import Image

    root = Path(root)
    future = root / MODEL_DIR / (MODEL_DIR if nested_models else "")
    (ax0, ax1), (bx0, bx1), z1 = ROOM_A, ROOM_B, 4.0
    meshes, a_children, b_children = [], [], []

    def mesh(room: list, ref: str, kind: str, built, material: str, **extra) -> None:
        xyz, faces = built
        meshes.append(_mesh_entry(ref, kind, xyz, faces, material, **extra))
        room.append({"ref": ref, "instanceid": f"mesh/{len(meshes)}", **_IDENTITY})

    # envelope of room A and room B
    floor_a = _quads(_plane_rects(1, 0.0, 0, [(ax0, ax1, 0.0, z1)]), [[0, 1, 0]])
    mesh(a_children, "1001/0", "Floor", floor_a, "mat-floor")
    xyz_b, faces_b = _quads(_plane_rects(1, 0.0, 0, [(bx0, bx1, 0.0, z1)]), [[0, 1, 0]])
    floor_b = _mesh_entry("1002/0", "Floor", xyz_b, faces_b, "mat-floor")
    floor_b["xyz"] = [repr(float(c)) for c in floor_b["xyz"]]  # real files hold numeric strings too
    floor_b["uv"] = [repr(float(c)) for c in floor_b["uv"]]
    meshes.append(floor_b)
    b_children.append({"ref": "1002/0", "instanceid": f"mesh/{len(meshes)}", **_IDENTITY})
    for room, (x0, x1), ref in ((a_children, ROOM_A, "1003/0"), (b_children, ROOM_B, "1004/0")):
        mesh(room, ref, "Ceiling", _quads(_plane_rects(1, HEIGHT, 0, [(x0, x1, 0.0, z1)]), [[0, -1, 0]]),
             "mat-wall")
    walls_a = [_wall(0, ax0, (0.0, z1)), _wall(0, ax1, (0.0, z1), DOOR), _wall(2, 0.0, ROOM_A, WINDOW),
               _wall(2, z1, ROOM_A)]
    walls_b = [_wall(0, bx0, (0.0, z1), DOOR), _wall(0, bx1, (0.0, z1), HOLE), _wall(2, 0.0, ROOM_B),
               _wall(2, z1, ROOM_B)]
    for room, walls, normals, ref in ((a_children, walls_a, ([1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1]), "1005/0"),
                                      (b_children, walls_b, ([1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1]), "1006/0")):
        quads = [q for w in walls for q in w]
        facing = [n for w, n in zip(walls, normals) for _ in w]
        mesh(room, ref, "WallInner", _quads(quads, facing), "mat-wall")
    # exterior shells: outer wall faces, slab sides, the slab's underside at y = -0.1
    ox0, ox1, oz0, oz1 = ax0 - _WALL, bx1 + _WALL, -_WALL, z1 + _WALL
    outer_window = {**WINDOW, "span": WINDOW["span"]}
    outer = [_wall(2, oz0, (ox0, ox1), outer_window), _wall(2, oz1, (ox0, ox1)), _wall(0, ox0, (oz0, oz1)),
             _wall(0, ox1, (oz0, oz1), HOLE)]
    mesh(a_children, "1007/0", "WallOuter",
         _quads([q for w in outer for q in w], [n for w, n in zip(outer, ([0, 0, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0]))
                                               for _ in w]), "mat-wall")
    sides = [_plane_rects(2, oz0, 0, [(ox0, ox1, -0.1, 0.0)]), _plane_rects(2, oz1, 0, [(ox0, ox1, -0.1, 0.0)]),
             _plane_rects(0, ox0, 2, [(oz0, oz1, -0.1, 0.0)]), _plane_rects(0, ox1, 2, [(oz0, oz1, -0.1, 0.0)])]
    mesh(a_children, "1008/0", "SlabSide", _quads([q for s in sides for q in s],
                                                  [[0, 0, -1], [0, 0, 1], [-1, 0, 0], [1, 0, 0]]), "mat-wall")
    mesh(a_children, "1009/0", "SlabBottom", _quads(_plane_rects(1, -0.1, 0, [(ox0, ox1, oz0, oz1)]), [[0, -1, 0]]),
         "mat-wall")
    # the openings: jambs only
    mesh(a_children, "1010/0", "Door", _jamb(0, DOOR, sill=False), "mat-door")
    mesh(a_children, "1011/0", "Window", _jamb(2, WINDOW, sides=False), "mat-wall")
    mesh(b_children, "1012/0", "Pocket", _jamb(0, DOOR, sill=False, top=False), "mat-wall")
    mesh(b_children, "1013/0", "Hole", _jamb(0, HOLE), "mat-wall")
    # a kitchen unit: four 2 cm boards of one construct, its light band, and a loose shelf board
    boards = [((0.0, 0.0, 2.8), (0.6, 0.85, 2.82)), ((0.0, 0.0, 3.78), (0.6, 0.85, 3.8)),
              ((0.0, 0.83, 2.8), (0.6, 0.85, 3.8)), ((0.0, 0.0, 2.8), (0.6, 0.02, 3.8))]
    for k, (lo, hi) in enumerate(boards):
        mesh(a_children, f"1020/{k}", "Cabinet", _box_mesh(lo, hi), "mat-wall", constructid="kitchen-1")
    mesh(a_children, "1020/9", "Cabinet/LightBand", _box_mesh((0.0, 2.7, 2.8), (0.3, 2.72, 3.8)), "mat-wall",
         constructid="kitchen-1")
    mesh(a_children, "1021/0", "Cabinet", _box_mesh((0.0, 1.5, 0.5), (0.3, 1.52, 1.5)), "mat-wall")
    mesh(a_children, "1022/0", "", ([], []), "mat-wall")  # an empty mesh with no type

    materials = [
        {"uid": "mat-floor", "jid": "tex-floor", "texture": "", "normaltexture": "", "color": [255, 255, 255, 255],
         "colorMode": "texture", "UVTransform": UV_TRANSFORMS["tex-floor"]},
        {"uid": "mat-wall", "jid": "tex-wall", "texture": "", "normaltexture": "", "color": [255, 255, 255, 255],
         "colorMode": "texture", "UVTransform": UV_TRANSFORMS["tex-wall"]},
        # its texture image was never downloaded
        {"uid": "mat-door", "jid": "tex-missing", "texture": "", "normaltexture": "", "color": [255, 255, 255, 255],
         "colorMode": "texture", "UVTransform": [1, 0, 0, 0, 1, 0, 0, 0, 1]},
    ]
    for jid, rgb in (("tex-floor", (180, 150, 110)), ("tex-wall", (230, 230, 225))):
        (root / TEXTURE_DIR / jid).mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (4, 4), rgb).save(root / TEXTURE_DIR / jid / "texture.png")

    # furniture: (entry, model size or None, room, child placement)
    s, c = float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))
    pieces = [
        ({"uid": "2001/model", "jid": "m-bed", "title": "bed/king-size bed", "category": "Bed",
          "bbox": [2.0, 0.5, 1.8], "valid": True}, (2.0, 0.5, 1.8), b_children, {"pos": [6.5, 0.0, 3.0]}),
        ({"uid": "2002/model", "jid": "m-nightstand", "title": "cabinet/nightstand", "category": "Cabinet/Shelf/Desk",
          "bbox": [0.4, 0.5, 0.4], "valid": True}, (0.4, 0.5, 0.4), b_children,
         {"pos": [7.8, 0.0, 3.6], "rot": [0.0, s, 0.0, c]}),
        ({"uid": "2003/model", "jid": "m-plant", "title": "plants/plants - on top of others", "valid": True},
         (0.3, 0.6, 0.3), a_children, {"pos": [3.5, 0.0, 0.5]}),
        ({"uid": "2004/model", "jid": "m-vase", "category": "300 - On top of others", "valid": True},
         (0.2, 0.3, 0.2), a_children, {"pos": [3.5, 0.0, 3.5]}),
        ({"uid": "2005/model", "jid": "m-beam", "title": "build element/beam", "valid": True},
         (0.2, 0.3, 3.0), a_children, {"pos": [1.0, 2.5, 2.0]}),
        ({"uid": "2006/model", "jid": "m-lamp", "title": "lighting/pendant lamp", "valid": True,
          "bbox": [0.3, 0.1, 0.3]}, (0.3, 0.1, 0.3), a_children, {"pos": [1.0, 2.0, 1.0], "scale": [1.0, 7.16, 1.0]}),
        ({"uid": "2007/model", "jid": "m-gone"}, None, a_children, None),  # overwritten by the next entry
        ({"uid": "2007/model", "jid": "m-stool", "valid": True}, (0.4, 0.45, 0.4), a_children, {"pos": [3.0, 0.0, 3.0]}),
        # its model is 2.5 times the size its entry declares
        ({"uid": "2008/model", "jid": "m-chair", "title": "chair/dining chair", "bbox": [0.45, 0.9, 0.5],
          "valid": True}, (1.125, 2.25, 1.25), b_children, {"pos": [5.0, 0.0, 0.8]}),
        ({"uid": "2009/model", "jid": "m-never-released", "title": "sofa/three-seat sofa", "valid": True}, None,
         b_children, {"pos": [6.0, 0.0, 1.0]}),
        # unreleased: no valid key (often only uid/jid/aid), or valid: false
        ({"uid": "2010/model", "jid": "j-window", "aid": [], "title": "window/floor-based window"}, None, a_children,
         {}),
        ({"uid": "2011/model", "jid": "j-door", "aid": [], "title": "door/single swing door"}, None, a_children, {}),
        ({"uid": "2012/model", "jid": "j-curtain", "title": "curtain/curtain", "valid": False}, None, b_children, {}),
        ({"uid": "2013/model", "jid": "j-kitchen", "aid": []}, None, b_children, {}),
    ]
    furniture = []
    for entry, size, room, child in pieces:
        furniture.append(entry)
        if size is not None:
            _write_model(future / entry["jid"], size, texture=entry["jid"] == "m-bed",
                         broken=broken_model and entry["jid"] == "m-nightstand")
        if child is not None:
            room.append({"ref": entry["uid"], "instanceid": f"furniture/{len(furniture)}", **_IDENTITY, **child})
    info = [
        {"model_id": "m-bed", "category": "King-size Bed", "super-category": "Bed", "style": None, "theme": None},
        {"model_id": "m-nightstand", "category": "Nightstand", "super-category": "Cabinet/Shelf/Desk"},
        {"model_id": "m-plant", "category": None, "super-category": "Others"},
        {"model_id": "m-vase", "category": None, "super-category": None},
        {"model_id": "m-lamp", "category": "Pendant Lamp", "super-category": "Lighting"},
        {"model_id": "m-stool", "category": "Footstool/Sofastool/Bed End Stool/Stool", "super-category": "Pier/Stool"},
        {"model_id": "m-chair", "category": "Dining Chair", "super-category": "Chair"},
    ]
    future.mkdir(parents=True, exist_ok=True)
    if model_info:
        (future / MODEL_INFO).write_text(json.dumps(info, indent=1) + "\n")
    # lights and other children whose ref names no entry
    a_children.append({"ref": "light/0", "instanceid": "light/0", **_IDENTITY})
    b_children.append({"ref": "sdf-gone", "instanceid": "furniture/99", **_IDENTITY})
    rooms = [{"type": "LivingRoom", "instanceid": "LivingRoom-1", "size": 16.0, **_IDENTITY, "children": a_children,
              "empty": 0},
             {"type": "Bedroom", "instanceid": "Bedroom-2", "size": 16.0, **_IDENTITY, "children": b_children,
              "empty": 0}]
    doc = {"uid": uid, "jobid": uid, "design_version": "0.1", "north_vector": [0, 1, 0], "furniture": furniture,
           "mesh": meshes, "material": materials, "extension": {}, "scene": {"ref": "-1", **_IDENTITY, "room": rooms}}
    path = root / SCENE_DIR / f"{uid}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc) + "\n")
    return path
