"""PLY writer: binary little-endian, one ``instance`` value per instance; the reader is
:mod:`sceneforge.houses.formats.ply`.

It keeps instances (the face property ``instance`` and its comment line), geometry, base
colours (as face colours) and uv, not textures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..colour import linear_to_srgb
from ..houses.model import House


def write_ply(path: Path, house: House, names: list[str]) -> None:
    """Write ``house`` as a binary little-endian PLY, instance ``k`` named ``names[k]``.

    Vertices are float64 (exact), uv float32 (only when every instance has uv), colours
    each face's material's base colour sRGB-encoded and rounded to bytes (alpha as it is).
    """
    with_uv = bool(house.instances) and all(i.uv is not None for i in house.instances)
    vertex_fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    vertex_fields += [("s", "<f4"), ("t", "<f4")] if with_uv else []
    face_dtype = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("instance", "<i4"),
                           ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
    vertex_blocks, face_blocks, offset = [], [], 0
    for inst in house.instances:
        block = np.zeros(len(inst.vertices), vertex_fields)
        block["x"], block["y"], block["z"] = inst.vertices.T
        if with_uv:
            block["s"], block["t"] = inst.uv.T
        vertex_blocks.append(block)
        faces = np.zeros(len(inst.faces), face_dtype)
        faces["n"], faces["v"], faces["instance"] = 3, inst.faces + offset, inst.id
        linear = np.array([m.base_color for m in inst.materials], dtype=np.float64).reshape(-1, 4)
        palette = np.clip(np.round(np.column_stack([linear_to_srgb(linear[:, :3]), linear[:, 3]]) * 255), 0, 255)
        rgba = palette[inst.face_materials()]
        for k, channel in enumerate(("red", "green", "blue", "alpha")):
            faces[channel] = rgba[:, k]
        face_blocks.append(faces)
        offset += len(inst.vertices)
    vertices = np.concatenate(vertex_blocks) if vertex_blocks else np.zeros(0, vertex_fields)
    faces = np.concatenate(face_blocks) if face_blocks else np.zeros(0, face_dtype)
    ply_type = {"<f8": "double", "<f4": "float"}
    lines = ["ply", "format binary_little_endian 1.0",
             f"comment sceneforge house {house.id}: instance <value> <nyu40 class>__<name>"]
    lines += [f"comment instance {i.id} {name}" for i, name in zip(house.instances, names, strict=True)]
    lines += [f"element vertex {len(vertices)}"]
    lines += [f"property {ply_type[t]} {n}" for n, t in vertex_fields]
    lines += [f"element face {len(faces)}", "property list uchar int vertex_indices", "property int instance",
              "property uchar red", "property uchar green", "property uchar blue", "property uchar alpha",
              "end_header"]
    path.write_bytes(("\n".join(lines) + "\n").encode() + vertices.tobytes() + faces.tobytes())
