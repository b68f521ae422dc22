"""Wavefront OBJ and MTL: the one reader (SUNCG and 3D-FUTURE models, OBJ scenes).

Reading keeps ``v``, ``vt``, ``f``, ``o``, ``g``, ``usemtl`` and ``mtllib`` and ignores the
rest (normals, lines, smoothing groups):

- Polygons are fanned into triangles around their first corner, in file order. Indices
  count from 1; negative ones count back from the last vertex (texture coordinate) defined
  so far. A texture index 0 or none (``f 1//1``) means the corner has no uv.
- Texture coordinates follow OBJ/OpenGL: ``v = 0`` is the bottom row of the image. A mesh
  has uv when any corner of its faces has one: models often give them only to the faces of
  their textured materials (SUNCG: ``f 1/1/1`` under a ``map_Kd`` material, ``f 1//1``
  under a plain one), and dropping the mesh's uv for that showed every texture of it as a
  flat colour (a wardrobe +2 stops too bright beside PBRS, issue 40). A corner without one
  gets (0, 0); in a mesh with uv, a face group whose material has a texture but none of
  whose corners has uv shows the material's colour without it (with a warning), as nothing
  says where its texels go (a mesh without any uv keeps its materials as they are: the
  renderers draw a texture only with uv). A vertex used with several texture coordinates
  keeps its first; every further (vertex, texture coordinate) pair becomes a new vertex
  after the others (a uv seam), so vertices keep their file order.
- Materials come from the ``mtllib`` files: ``Kd``, ``d`` (or ``Tr``) and ``map_Kd``
  (options before the image name are skipped; a missing image may be replaced by its
  ``.png``/``.jpg`` twin). A mesh keeps every material its faces name with ``usemtl``, as
  face groups in order of first use (``Mesh.face_material``); faces before any ``usemtl``
  get the default material. ``Kd`` multiplies ``map_Kd`` (SUNCG tints textures with it).
  Textures repeat outside [0, 1] (``-clamp on`` clamps them).
- Malformed content raises :class:`~sceneforge.houses.formats.meshio.MeshFileError` with the line.

trimesh is not used: it splits meshes per material, packs textures into one atlas and
merges vertices, which reorders vertices and rewrites uv. Lines are parsed in bulk by
numpy (all ``v`` lines at once, all ``f`` lines of one layout at once) rather than one at
a time in Python, which matters for models of millions of faces.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..model import Material
from .meshio import (
    Mesh,
    MeshFileError,
    Warn,
    compact,
    fan,
    find_image,
    ignore,
)

__all__ = ["read_mtl", "read_obj", "read_objects"]

# Texture corner of a face corner without texture coordinate (a bad index, even negative, is larger).
_NO_UV = np.iinfo(np.int64).min
_DEFAULT_KD = (0.8, 0.8, 0.8)


def read_obj(path: str | Path, warn: Warn = ignore) -> Mesh:
    """The whole file as one mesh (a model), named after the file.

    Its vertices are all the file's vertices in file order (uv seams appended), so that
    the file's face indices stay valid. Raises :class:`MeshFileError` for malformed
    content; ``warn`` receives what was tolerated (a missing library, material or texture).
    """
    path = Path(path)
    obj = _parse(path, warn)
    return _mesh(obj, np.arange(len(obj.tri_v)), path.stem, obj.vertices, obj.tri_v, warn)


def read_objects(path: str | Path, warn: Warn = ignore) -> Iterator[Mesh]:
    """Yield one mesh per object, in order of first appearance (none for a file without faces).

    Objects are the ``o`` names when the file has several, else the ``g`` groups when it
    has several, else the whole file (named after it); a face before any name of that kind
    goes by the other kind's name, else the file's. Each mesh has the vertices its faces
    use, in file order. Raises and warns as :func:`read_obj`.
    """
    path = Path(path)
    obj = _parse(path, warn)
    n_o, n_g = (len(np.unique(codes[codes >= 0])) for codes in (obj.line_o, obj.line_g))
    if n_o > 1 or (n_o == 1 and n_g <= 1):
        first, second, first_names, second_names = obj.line_o, obj.line_g, obj.o_names, obj.g_names
    else:
        first, second, first_names, second_names = obj.line_g, obj.line_o, obj.g_names, obj.o_names

    def name_of(pair: int) -> str:
        f, s = divmod(pair, len(second_names) + 1)
        return first_names[f - 1] if f else second_names[s - 1] if s else path.stem

    # each face line's (first, second) name pair, one code; objects by first face line
    pairs, first_line, line_pair = np.unique((first + 1) * (len(second_names) + 1) + (second + 1),
                                             return_index=True, return_inverse=True)
    pair_names = [name_of(int(p)) for p in pairs]
    objects = list(dict.fromkeys(pair_names[k] for k in np.argsort(first_line, kind="stable")))
    code = {name: k for k, name in enumerate(objects)}
    line_object = np.array([code[n] for n in pair_names], dtype=np.int64)[line_pair.reshape(-1)]
    tri_object = line_object[obj.tri_line]
    by_object = np.argsort(tri_object, kind="stable")
    starts = np.searchsorted(tri_object[by_object], np.arange(len(objects) + 1))
    for k, name in enumerate(objects):
        triangles = by_object[starts[k]:starts[k + 1]]
        used, faces = compact(obj.tri_v[triangles])
        yield _mesh(obj, triangles, name, obj.vertices[used], faces, warn)


def read_mtl(path: Path, warn: Warn = ignore) -> dict[str, Material]:
    """Materials of an MTL file by name (``{}`` with a warning when it cannot be read).

    ``Kd`` and ``d`` (or ``1 - Tr``) give the base colour, clipped to [0, 1] (default
    0.8 grey, opaque); ``map_Kd`` the texture; ``Ke`` the emission (default none).
    """
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        warn(f"material library {path.name} cannot be read ({e.strerror or e}); default colours")
        return {}
    found: dict[str, dict] = {}
    current = None
    for line in text.splitlines():
        parts = line.strip().split(None, 1)
        if not parts:
            continue
        key, rest = parts[0], parts[1].strip() if len(parts) > 1 else ""
        try:
            if key == "newmtl":
                current = found.setdefault(rest, {"kd": _DEFAULT_KD, "alpha": 1.0, "map": None,
                                                  "clamp": False, "ke": (0.0, 0.0, 0.0)})
            elif current is None:
                continue
            elif key == "Kd":
                kd = tuple(float(c) for c in rest.split()[:3])
                current["kd"] = kd if len(kd) == 3 else _DEFAULT_KD
            elif key == "Ke":
                ke = tuple(max(float(c), 0.0) for c in rest.split()[:3])
                current["ke"] = ke if len(ke) == 3 else current["ke"]
            elif key == "d":
                current["alpha"] = float(rest.split()[0])
            elif key == "Tr":
                current["alpha"] = 1.0 - float(rest.split()[0])
            elif key == "map_Kd" and rest:
                # Options (-s 1 1 1, -bm 0.5, ...) come first; the file name is the rest.
                whole = path.parent / rest
                words = rest.split()
                current["clamp"] = any(w == "-clamp" and words[k + 1:k + 2] == ["on"] for k, w in enumerate(words))
                current["map"] = whole if whole.is_file() else path.parent / rest.split()[-1]
        except (ValueError, IndexError):
            warn(f"{path.name}: cannot read line {line.strip()!r}")
    return {
        name: Material(
            base_color=tuple(float(c) for c in np.clip([*m["kd"], m["alpha"]], 0.0, 1.0)),
            texture=find_image(m["map"], warn, warn_missing=True) if m["map"] else None,
            wrap=("clamp", "clamp") if m["clamp"] else ("repeat", "repeat"),
            emission=m["ke"],
        )
        for name, m in found.items()
    }


# --------------------------------------------------------------------------- parsing


@dataclass
class _Obj:
    """An OBJ file's content, triangulated, before it is cut into meshes.

    vertices  : (n, 3) float64  every ``v``
    uvs       : (t, 2) float64  every ``vt``
    tri_v     : (m, 3) int64    each triangle corner's vertex, 0-based, in range
    tri_t     : (m, 3) int64    its texture coordinate, 0-based, ``_NO_UV`` for none, not range checked
    tri_line  : (m,) int64      the face line each triangle comes from (index into ``f_lines``)
    f_lines   : (k,) int64      the file line number of each ``f`` line
    line_o, line_g, line_mtl : (k,) int64  each face line's ``o`` / ``g`` / ``usemtl`` name
                as an index into ``o_names`` / ``g_names`` / ``mtl_names``, -1 for none
    materials : the material libraries' materials by name
    """

    vertices: np.ndarray
    uvs: np.ndarray
    tri_v: np.ndarray
    tri_t: np.ndarray
    tri_line: np.ndarray
    f_lines: np.ndarray
    line_o: np.ndarray
    line_g: np.ndarray
    line_mtl: np.ndarray
    o_names: list[str]
    g_names: list[str]
    mtl_names: list[str]
    materials: dict[str, Material]


def _parse(path: Path, warn: Warn) -> _Obj:
    """Read and triangulate an OBJ file and its material libraries."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise MeshFileError(f"cannot read: {e.strerror or e}") from None
    # a trailing backslash continues a line (line numbers after one are one too low)
    text = text.replace("\\\n", " ").replace("\t", " ")
    lines = text.splitlines()
    if text.startswith(" ") or "\n " in text:
        lines = [line.lstrip() for line in lines]
    head = np.array([line[:2] for line in lines], dtype="<U2")
    is_v, is_vt, is_f = head == "v ", head == "vt", head == "f "
    v_at, vt_at, f_at = np.flatnonzero(is_v), np.flatnonzero(is_vt), np.flatnonzero(is_f)

    # keyword → (its line indices, the name index of each or -1 for none, name → name index)
    names: dict[str, tuple[list[int], list[int], dict[str, int]]] = {
        k: ([], [], {}) for k in ("o", "g", "usemtl")}
    libraries = []
    for i in np.flatnonzero(~(is_v | is_vt | is_f | (head == "vn"))):  # few lines: one at a time
        key, _, rest = lines[i].partition(" ")
        rest = rest.strip()
        if key in names:
            at, index, table = names[key]
            at.append(i)
            index.append(table.setdefault(rest, len(table)) if rest else -1)
        elif key == "mtllib":
            libraries.append(rest)
        elif key == "v":
            raise MeshFileError(f"line {i + 1}: cannot read vertex ''")
        elif key == "f":
            raise MeshFileError(f"line {i + 1}: a face needs 3 vertices, got 0")

    vertices = _numbers([lines[i][2:] for i in v_at], v_at, 3, 3, "vertex")
    uvs = _numbers([lines[i][2:] for i in vt_at], vt_at, 2, 0, "texture coordinate")
    tri_v, tri_t, tri_line = _triangles([lines[i][2:] for i in f_at], np.cumsum(is_v)[f_at],
                                        np.cumsum(is_vt)[f_at], f_at + 1)
    bad = (tri_v < 0) | (tri_v >= len(vertices))
    if bad.any():
        row = np.flatnonzero(bad.any(axis=1))[0]
        n = len(vertices)
        raise MeshFileError(f"a face uses a vertex index outside the {n} vertices (line "
                            f"{f_at[tri_line[row]] + 1}: face index {int(tri_v[row][bad[row]][0]) + 1} "
                            f"is outside the {n} vertices)")

    def line_names(key: str) -> np.ndarray:
        at, index, _ = names[key]
        k = np.searchsorted(np.array(at, dtype=np.int64), f_at) - 1
        return np.array(index + [-1], dtype=np.int64)[k]  # k = -1: before the first, none

    materials: dict[str, Material] = {}
    for lib in libraries:
        whole = path.parent / lib
        for file in [whole] if whole.is_file() else [path.parent / n for n in lib.split()]:
            materials.update(read_mtl(file, warn))
    return _Obj(vertices, uvs, tri_v, tri_t, tri_line, f_at + 1, line_names("o"), line_names("g"),
                line_names("usemtl"), *(list(names[k][2]) for k in ("o", "g", "usemtl")), materials)


def _numbers(rows: list[str], at: np.ndarray, width: int, least: int, what: str) -> np.ndarray:
    """(len(rows), width) float64: the first ``width`` numbers of each ``v``/``vt`` row.

    A row needs at least ``least`` numbers; missing ones up to ``width`` are 0. ``at`` holds
    the rows' 0-based line indices, for errors.
    """
    if not rows:
        return np.zeros((0, width))
    try:  # one parse for the whole file when every row has as many numbers
        values = _table(rows, np.float64)
        if values.shape[0] == len(rows) and values.shape[1] >= width:
            return values[:, :width]
    except ValueError:
        pass
    out = np.zeros((len(rows), width))
    for k, row in enumerate(rows):
        tokens = row.split("#", 1)[0].split()[:width]
        try:
            if len(tokens) < least:
                raise ValueError
            out[k, :len(tokens)] = [float(t) for t in tokens]
        except ValueError:
            raise MeshFileError(f"line {at[k] + 1}: cannot read {what} {row.strip()!r}") from None
    return out


def _triangles(rests: list[str], nv: np.ndarray, nvt: np.ndarray, line_no: np.ndarray):
    """Fan-triangulate face lines (their text after ``f``) into 0-based corners.

    nv, nvt : (k,) int  vertices and texture coordinates defined before each line, for
              negative (relative) indices
    line_no : (k,) int  file line numbers, for errors
    Returns corners (m, 3) int64 (unchecked), texture corners (m, 3) int64 (``_NO_UV`` where
    none) and the face line of each triangle (m,) int64, in file order. Lines with the same
    spaces and slashes are parsed together; lines that do not have their group's layout
    (the first line's corners and ``v/vt/vn`` form) one at a time.
    """
    # layout of each line in C-speed counts: ``v/vt/vn`` form and corners when single-spaced
    layout = np.array([r.count(" ") for r in rests], dtype=np.int64) * (1 << 32) + np.array(
        [r.count("/") for r in rests], dtype=np.int64)
    keys, group_of = np.unique(layout, return_inverse=True)
    parts = [(np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int64))]
    for g in range(len(keys)):
        idx = np.flatnonzero(group_of == g) if len(keys) > 1 else np.arange(len(rests))
        lines = [rests[i] for i in idx] if len(keys) > 1 else rests
        tokens = lines[0].split()
        corners, fields = len(tokens), (tokens[0].count("/") + 1 if tokens else 1)
        numbers = None
        if corners >= 3:
            text = "\n".join(lines).replace("//", "/0/").replace("/", " ")
            try:
                numbers = _table(text.splitlines(), np.int64)
            except ValueError:
                pass
        if numbers is None or numbers.shape != (len(idx), corners * fields):
            parts += [_face(rests[i], nv[i], nvt[i], line_no[i], i) for i in idx]
            continue
        numbers = numbers.reshape(len(idx), corners, fields)
        v = _resolve(numbers[:, :, 0], nv[idx, None], -1)
        t = _resolve(numbers[:, :, 1], nvt[idx, None], _NO_UV) if fields > 1 else np.full_like(v, _NO_UV)
        parts.append((fan(v), fan(t), np.repeat(idx, corners - 2)))
    tri_v, tri_t, src = (np.concatenate(p) for p in zip(*parts, strict=True))
    order = np.argsort(src, kind="stable")
    return tri_v[order], tri_t[order], src[order]


def _table(rows: list[str], dtype) -> np.ndarray:
    """(rows, columns) array of whitespace-separated numbers; ValueError unless every row has
    as many. Blank and ``#`` rows are skipped (the caller compares the row count)."""
    with warnings.catch_warnings():  # all rows blank: an empty table, not a warning
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(rows, dtype=dtype, ndmin=2)


def _resolve(index: np.ndarray, count, zero: int) -> np.ndarray:
    """0-based indices of OBJ indices (1-based, or negative: back from ``count`` defined so far);
    ``zero`` for index 0."""
    return np.where(index > 0, index - 1, np.where(index < 0, index + count, zero))


def _face(rest: str, nv: int, nvt: int, line: int, i: int):
    """One face line the slow way: (corners, texture corners, face line) of its triangles."""
    refs = [token.split("/") for token in rest.split("#", 1)[0].split()]
    try:
        v = [int(r[0]) for r in refs]
        t = [int(r[1]) if len(r) > 1 and r[1] else 0 for r in refs]
    except ValueError:
        raise MeshFileError(f"line {line}: cannot read face {rest.strip()!r}") from None
    if len(v) < 3:
        raise MeshFileError(f"line {line}: a face needs 3 vertices, got {len(v)}")
    v = fan(_resolve(np.array([v], dtype=np.int64), nv, -1))
    return v, fan(_resolve(np.array([t], dtype=np.int64), nvt, _NO_UV)), np.full(len(v), i)


def _mesh(obj: _Obj, triangles: np.ndarray, name: str, vertices: np.ndarray, faces: np.ndarray,
          warn: Warn) -> Mesh:
    """The mesh of some of ``obj``'s triangles (indices (m,)), given as ``faces`` (m, 3) into
    ``vertices`` (n, 3): uv when any corner has one, a face group per material."""
    tex = obj.tri_t[triangles]
    uv = None
    has_uv = (tex != _NO_UV).any(axis=1) if len(tex) else np.zeros(0, dtype=bool)
    if len(obj.uvs) and has_uv.any():
        bad = ((tex < 0) | (tex >= len(obj.uvs))) & (tex != _NO_UV)
        if bad.any():
            row = np.flatnonzero(bad.any(axis=1))[0]
            raise MeshFileError(
                f"line {obj.f_lines[obj.tri_line[triangles[row]]]}: texture index "
                f"{int(tex[row][bad[row]][0]) + 1} is outside the {len(obj.uvs)} texture coordinates")
        uvs = obj.uvs
        if (tex == _NO_UV).any():  # corners without uv: (0, 0), one extra texture coordinate
            uvs = np.concatenate([obj.uvs, np.zeros((1, 2))])
            tex = np.where(tex == _NO_UV, len(obj.uvs), tex)
        vertices, faces, uv = _split_seams(vertices, faces, tex, uvs)
    else:
        has_uv[:] = False
    # one face group per usemtl name its faces use, in order of first use; faces before any
    # usemtl (or naming a material no library has) get the default material
    named = obj.line_mtl[obj.tri_line[triangles]]
    library = tuple(obj.materials)
    if not len(named) or (named < 0).all():
        return Mesh(vertices, faces, uv, None, name, material_names=("",), library=library)
    used, first, group = np.unique(named, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    materials, names = [], []
    for code in used[order]:
        material = obj.materials.get(obj.mtl_names[code]) if code >= 0 else None
        if code >= 0 and material is None:
            warn(f"material {obj.mtl_names[code]!r} is not in any material library; default colour")
        if material is not None and material.texture is not None and uv is not None \
                and not has_uv[named == code].any():
            warn(f"material {obj.mtl_names[code]!r} has a texture but its faces no texture "
                 "coordinates; its colour without the texture")
            material = replace(material, texture=None)
        materials.append(material or Material())
        names.append(obj.mtl_names[code] if code >= 0 else "")
    if len(materials) == 1:
        return Mesh(vertices, faces, uv, materials[0], name, material_names=tuple(names), library=library)
    return Mesh(vertices, faces, uv, tuple(materials), name, face_material=rank[group.reshape(-1)].astype(np.int32),
                material_names=tuple(names), library=library)


def _split_seams(vertices: np.ndarray, faces: np.ndarray, tex: np.ndarray, uvs: np.ndarray):
    """Per-vertex uv: a vertex keeps the texture coordinate of its first use; each further
    (vertex, texture coordinate) pair becomes a new vertex appended at the end.

    vertices (n, 3), faces (m, 3), tex (m, 3) texture corners into uvs (t, 2) →
    vertices (n', 3), faces (m, 3), uv (n', 2) float32 (0 for vertices no face uses)
    """
    key = faces.reshape(-1) * (len(uvs) + 1) + tex.reshape(-1)
    uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    pv, pt = (uniq // (len(uvs) + 1))[order], (uniq % (len(uvs) + 1))[order]
    primary = np.zeros(len(pv), dtype=bool)
    primary[np.unique(pv, return_index=True)[1]] = True
    new = np.where(primary, pv, 0)
    new[~primary] = len(vertices) + np.arange((~primary).sum())
    vertices = np.concatenate([vertices, vertices[pv[~primary]]])
    uv = np.zeros((len(vertices), 2), dtype=np.float32)
    uv[new] = uvs[pt]
    pair_index = np.empty(len(uniq), dtype=np.int64)
    pair_index[order] = new
    return vertices, pair_index[inverse.reshape(-1)].reshape(-1, 3), uv
