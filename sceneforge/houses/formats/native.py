"""sceneforge's own house format: ``house.json`` + one little-endian binary buffer.

The JSON is described by ``schemas/house.schema.json``; each instance points at byte
ranges of the buffer: vertices ``(n, 3) float64``, faces ``(m, 3) uint32`` and optional
uv ``(n, 2) float32``; an instance of several materials has ``materials`` and face
materials ``(m,) uint32`` instead of one ``material``, and vertex colours ``(n, 4) float32``
when it has them. A one-material instance is written as before the face groups existed, so
old files and new ones of such houses are the same. Writing is deterministic: the same
house gives the same bytes.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_NAMES, nyu40_id
from ...errors import HouseError
from ..model import House, Level, Material, Room, make_instance
from .base import Format, HouseSource

if TYPE_CHECKING:
    from .. import LoadOptions

FORMAT_TAG = "sceneforge-house"
SCHEMA_VERSION = 1
HOUSE_FILE = "house.json"
BUFFER_FILE = "house.bin"


def is_native(path: Path) -> bool:
    """True for a ``house.json`` (or a folder holding one) in sceneforge's format."""
    path = Path(path)
    if path.is_dir():
        path = path / HOUSE_FILE
    if not (path.is_file() and path.suffix == ".json"):
        return False
    try:
        with open(path, "rb") as fh:
            head = fh.read(256)
    except OSError:
        return False
    return FORMAT_TAG.encode() in head


def list_houses(path: Path) -> list[HouseSource]:
    """The house of a ``house.json`` or its folder; its id is the folder's name."""
    house_dir = path.parent if path.is_file() else path
    return [HouseSource(house_dir.name, FORMAT.name, house_dir)]


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, strict=options.strict)


def write_house(house: House, out_dir: str | Path) -> Path:
    """Write ``house`` into ``out_dir`` (created) and return the path of its ``house.json``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    chunks: list[bytes] = []
    offset = 0

    def put(arr: np.ndarray, dtype: str) -> dict:
        nonlocal offset
        data = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()
        ref = {"offset": offset, "count": int(len(arr))}
        chunks.append(data)
        offset += len(data)
        return ref

    textures: dict[int, str] = {}

    def material(m: Material) -> dict:
        tex = m.texture
        if tex is not None and id(tex) not in textures:
            name = Path(tex).name if isinstance(tex, (str, Path)) else "embedded.png"
            textures[id(tex)] = f"textures/{len(textures):04d}_{name}"
            (out / "textures").mkdir(exist_ok=True)
            if isinstance(tex, (str, Path)):
                shutil.copyfile(tex, out / textures[id(tex)])
            else:
                tex.save(out / textures[id(tex)])
        record = {"base_color": [float(c) for c in m.base_color],
                  "texture": textures[id(tex)] if tex is not None else None}
        if tuple(m.wrap) != Material().wrap:
            record["wrap"] = list(m.wrap)
        return record

    records = []
    for inst in house.instances:
        record = {
            "name": inst.name,
            "category": NYU40_NAMES[inst.category],
            "label": inst.label,
            "room": inst.room_id,
            "vertices": put(inst.vertices, "float64"),
            "faces": put(inst.faces, "uint32"),
            "uv": None if inst.uv is None else put(inst.uv, "float32"),
        }
        if inst.face_material is None:
            record["material"] = material(inst.materials[0])
        else:
            record["materials"] = [material(m) for m in inst.materials]
            record["face_material"] = put(inst.face_material, "uint32")
        if inst.colors is not None:
            record["colors"] = put(inst.colors, "float32")
        records.append(record)
    doc = {
        "format": FORMAT_TAG,
        "schema_version": SCHEMA_VERSION,
        "id": house.id,
        "buffer": BUFFER_FILE,
        "units": "metres",
        "up": "+y",
        "levels": [{"id": lv.id, "floor_y": float(lv.floor_y)} for lv in house.levels],
        "rooms": [{"id": r.id, "type": r.type, "level": r.level} for r in house.rooms],
        "instances": records,
    }
    (out / BUFFER_FILE).write_bytes(b"".join(chunks))
    path = out / HOUSE_FILE
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def load_house(path: str | Path, *, strict: bool = False) -> House:
    """Read a house written by :func:`write_house` (``path``: the JSON or its folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / HOUSE_FILE
    house_id = path.parent.name
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise HouseError(house_id, path, f"cannot read house file: {e}") from None
    from sceneforge.schemas import validate_or_raise

    validate_or_raise(doc, "house", what=f"house {doc.get('id', house_id)}: {path}")
    house = House(
        id=doc["id"],
        instances=[],
        rooms=[Room(r["id"], r["type"], r["level"]) for r in doc["rooms"]],
        levels=[Level(lv["id"], lv["floor_y"]) for lv in doc["levels"]],
        source_format="sceneforge",
        source_path=str(path),
    )
    buf_path = path.parent / doc["buffer"]
    try:
        buf = buf_path.read_bytes()
    except OSError as e:
        raise HouseError(house.id, buf_path, f"cannot read buffer: {e.strerror or e}") from None

    def get(ref: dict | None, dtype: str, width: int):
        if ref is None:
            return None
        dt = np.dtype(dtype).newbyteorder("<")
        end = ref["offset"] + ref["count"] * width * dt.itemsize
        if end > len(buf):
            raise HouseError(house.id, buf_path, f"buffer is {len(buf)} bytes, a range ends at {end}")
        return np.frombuffer(buf, dt, ref["count"] * width, ref["offset"]).reshape(-1, width)

    for rec in doc["instances"]:
        cid = nyu40_id(rec["category"])
        if cid is None:
            raise HouseError(house.id, path, f"instance {rec['name']!r}: unknown NYU40 class {rec['category']!r}")
        materials = [_material(m, path) for m in rec.get("materials") or [rec.get("material") or {}]]
        make_instance(
            house,
            name=rec["name"],
            category=cid,
            label=rec.get("label", rec["category"]),
            room_id=rec.get("room"),
            vertices=get(rec["vertices"], "float64", 3),
            faces=get(rec["faces"], "uint32", 3),
            uv=get(rec.get("uv"), "float32", 2),
            file=path,
            material=materials if len(materials) > 1 else materials[0],
            face_material=get(rec.get("face_material"), "uint32", 1),
            colors=get(rec.get("colors"), "float32", 4),
        )
    return house.check_not_empty()


def _material(record: dict, path: Path) -> Material:
    """The :class:`Material` of a material record of the house file at ``path``."""
    tex = record.get("texture")
    return Material(base_color=tuple(record.get("base_color", (0.8, 0.8, 0.8, 1.0))),
                    texture=(path.parent / tex) if tex else None,
                    wrap=tuple(record.get("wrap", Material().wrap)))


FORMAT = Format("sceneforge", detect=is_native, list=list_houses, load=_load)
