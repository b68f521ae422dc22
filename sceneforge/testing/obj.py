"""Wavefront OBJ + MTL writer (OBJ scenes, SUNCG and 3D-FUTURE models); the reader is
:mod:`sceneforge.houses.formats.obj`."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..houses.formats.meshio import Mesh
from .textures import distinct_materials, save_texture, texture_suffix


def write_obj(
    path: str | Path,
    meshes: Sequence[Mesh],
    *,
    mtl_name: str | None = None,
    texture_name: str | None = None,
    comment: str | None = None,
) -> Path:
    """Write meshes as one OBJ (an ``o`` object each, when named) with its MTL and textures.

    Vertices are written with 17 significant digits and uv with 9 (float32), so both read
    back exactly. A mesh of several materials (``Mesh.face_material``) gets a ``usemtl``
    line before each run of faces of one material. Equal materials are written once
    (``material<k>``); a texture file keeps its image type and goes to
    ``<stem>_texture<k><suffix>`` beside the OBJ.

    mtl_name     : the MTL's file name (default ``<stem>.mtl``); no MTL without materials
    texture_name : the file name of the one texture (3D-FUTURE's ``texture.png``)
    comment      : a first ``#`` line
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    groups = [m.materials if m.material is not None else (None,) for m in meshes]
    materials, flat_index, textures = distinct_materials([g for group in groups for g in group])
    starts = np.cumsum([0] + [len(g) for g in groups])
    if texture_name is not None and len(textures) > 1:
        raise ValueError(f"{path}: one texture_name for {len(textures)} textures")
    mtl_name = mtl_name or path.with_suffix(".mtl").name
    with open(path, "w", encoding="utf-8") as fh:
        if comment is not None:
            fh.write(f"# {comment}\n")
        if materials:
            fh.write(f"mtllib {mtl_name}\n")
        nv = nt = 0
        for k, mesh in enumerate(meshes):
            if mesh.name:
                fh.write(f"o {mesh.name}\n")
            vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
            f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
            np.savetxt(fh, vertices, fmt="v %.17g %.17g %.17g")
            if mesh.uv is not None:
                np.savetxt(fh, np.asarray(mesh.uv).reshape(-1, 2), fmt="vt %.9g %.9g")
                lines = np.stack([f + nv + 1, f + nt + 1], axis=2).reshape(-1, 6)
                fmt = "f %d/%d %d/%d %d/%d"
                nt += len(mesh.uv)
            else:
                lines, fmt = f + nv + 1, "f %d %d %d"
            group = mesh.face_materials()
            runs = np.flatnonzero(np.diff(group, prepend=-1, append=-1)) if len(group) else [0, 0]
            for a, b in zip(runs[:-1], runs[1:], strict=True):
                mat = flat_index[starts[k] + group[a]]
                if mat >= 0:
                    fh.write(f"usemtl material{mat}\n")
                np.savetxt(fh, lines[a:b], fmt=fmt)
            nv += len(vertices)
    if materials:
        texture_files = {}
        for k, tex in enumerate(textures):
            texture_files[id(tex)] = texture_name or f"{path.stem}_texture{k}{texture_suffix(tex)}"
            save_texture(tex, path.parent / texture_files[id(tex)])
        lines = []
        for k, m in enumerate(materials):
            r, g, b, a = (float(c) for c in m.base_color)  # repr: the shortest text that reads back exactly
            lines += [f"newmtl material{k}", f"Kd {r!r} {g!r} {b!r}", f"d {a!r}"]
            if any(m.emission):
                lines.append("Ke " + " ".join(repr(float(c)) for c in m.emission))
            if m.texture is not None:
                clamp = "-clamp on " if tuple(m.wrap) == ("clamp", "clamp") else ""
                lines.append(f"map_Kd {clamp}{texture_files[id(m.texture)]}")
        (path.parent / mtl_name).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
