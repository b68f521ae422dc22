"""glTF 2.0 writer (``.gltf`` + ``.bin`` + images, or one ``.glb``); the reader is
:mod:`sceneforge.houses.formats.gltf`."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from ..houses.formats.gltf import GLB_BIN, GLB_JSON, GLB_MAGIC
from ..houses.model import House
from .textures import distinct_materials, encode_texture, texture_suffix

_MIME_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


def write_gltf(path: Path, house: House, names: list[str]) -> None:
    """Write ``house`` as ``.gltf`` (+ ``.bin`` and image files) or ``.glb`` (by suffix).

    One node and mesh per instance, named ``names[k]``, with one primitive per material of
    the instance (its faces in order); positions are float32 relative to the instance's
    centre, which is the node's translation. Texture wrapping goes into samplers. Textures other than PNG and JPEG
    (the two types core glTF allows) are re-encoded as PNG.
    """
    binary = path.suffix.lower() == ".glb"
    starts = np.cumsum([0] + [len(i.materials) for i in house.instances])
    materials, flat_index, textures = distinct_materials([m for i in house.instances for m in i.materials])
    chunks: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []

    def view(data: bytes, target: int | None = None) -> int:
        offset = sum(len(c) for c in chunks)
        chunks.append(data + b"\0" * (-len(data) % 4))  # 4-byte alignment for float32/uint32
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
                     | ({"target": target} if target else {}))
        return len(views) - 1

    def accessor(array: np.ndarray, component: int, kind: str, target: int, bounds: bool = False) -> int:
        acc = {"bufferView": view(np.ascontiguousarray(array).tobytes(), target), "componentType": component,
               "count": int(len(array)), "type": kind}
        if bounds:
            acc |= {"min": array.min(axis=0).tolist(), "max": array.max(axis=0).tolist()}
        accessors.append(acc)
        return len(accessors) - 1

    images = []
    for k, tex in enumerate(textures):
        suffix = texture_suffix(tex) if texture_suffix(tex) in _MIME_TYPES else ".png"
        data = encode_texture(tex, suffix)
        if binary:
            images.append({"bufferView": view(data), "mimeType": _MIME_TYPES[suffix]})
        else:
            file = f"{path.stem}_texture{k}{suffix}"
            (path.parent / file).write_bytes(data)
            images.append({"uri": file})
    gl_textures: dict[tuple, int] = {}  # (texture, wrap) → index of its glTF texture
    samplers: dict[tuple, int] = {}
    texture_index = {id(t): k for k, t in enumerate(textures)}
    gl_materials = []
    for m in materials:
        pbr = {"baseColorFactor": list(m.base_color), "metallicFactor": 0.0, "roughnessFactor": 1.0}
        if m.texture is not None:
            sampler = samplers.setdefault(tuple(m.wrap), len(samplers))
            pbr["baseColorTexture"] = {"index": gl_textures.setdefault((texture_index[id(m.texture)], sampler),
                                                                       len(gl_textures))}
        material = {"pbrMetallicRoughness": pbr}
        strength = max(1.0, *m.emission)  # a factor is at most 1: the rest goes to the strength
        if any(m.emission):
            material["emissiveFactor"] = [float(c) / strength for c in m.emission]
        if strength > 1:
            material["extensions"] = {"KHR_materials_emissive_strength": {"emissiveStrength": strength}}
        gl_materials.append(material)

    meshes, nodes = [], []
    for k, (inst, name) in enumerate(zip(house.instances, names, strict=True)):
        # float32 positions relative to the instance's centre (kept in float64 as the node's
        # translation) lose far less than world coordinates would
        center = (inst.vertices.min(axis=0) + inst.vertices.max(axis=0)) / 2
        local = (inst.vertices - center).astype("<f4")
        attributes = {"POSITION": accessor(local, 5126, "VEC3", 34962, bounds=True)}
        if inst.uv is not None:
            uv = np.column_stack([inst.uv[:, 0], 1.0 - inst.uv[:, 1]]).astype("<f4")
            attributes["TEXCOORD_0"] = accessor(uv, 5126, "VEC2", 34962)
        group = inst.face_materials()
        primitives = []
        for g in range(len(inst.materials)):
            indices = accessor(inst.faces[group == g].astype("<u4").ravel(), 5125, "SCALAR", 34963)
            primitives.append({"attributes": attributes, "indices": indices, "material": flat_index[starts[k] + g]})
        meshes.append({"name": name, "primitives": primitives})
        nodes.append({"name": name, "mesh": len(meshes) - 1, "translation": center.tolist()})

    blob = b"".join(chunks)
    buffer = {"byteLength": len(blob)}
    if not binary:
        buffer["uri"] = f"{path.stem}.bin"
        (path.parent / buffer["uri"]).write_bytes(blob)
    doc = {
        "asset": {"version": "2.0", "generator": "sceneforge"},
        "extras": {"sceneforge_house": house.id},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": gl_materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [buffer] if blob else [],
    }
    if any("extensions" in m for m in gl_materials):
        doc["extensionsUsed"] = ["KHR_materials_emissive_strength"]
    if textures:
        codes = {"repeat": 10497, "clamp": 33071, "mirror": 33648}
        doc |= {"images": images, "textures": [{"source": t, "sampler": s} for t, s in gl_textures],
                "samplers": [{"wrapS": codes[s], "wrapT": codes[t]} for s, t in samplers]}
    text = json.dumps(doc, separators=(",", ":")).encode()
    if not binary:
        path.write_bytes(text)
        return
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), GLB_JSON) + text
    if blob:
        body += struct.pack("<II", len(blob), GLB_BIN) + blob
    path.write_bytes(struct.pack("<4sII", GLB_MAGIC, 2, 12 + len(body)) + body)
