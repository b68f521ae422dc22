"""PLY scenes (ASCII or binary, either byte order), read into meshes.

Reading: one mesh per value of a per-face (else per-vertex: a face takes its first
corner's) ``instance``, ``instance_id``, ``object_id`` or ``obj_id`` property, in
increasing order; without such a property, one mesh. Names come from ``comment instance
<value> <name>`` header lines, else the file stem (with ``_<value>`` when there are
several). Polygons are fanned; per-face colours give face groups (one material per
distinct colour, in order of first use), per-vertex colours the mesh's vertex colours (on a
white material); both are sRGB-encoded (what every PLY writer stores, bytes or floats in
[0, 1]) and decoded to linear RGB, alpha kept as it is (bytes / 255). ``s``/``t`` (or ``u``/``v``)
give the uv, a ``comment TextureFile`` the texture.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ...colour import srgb_to_linear
from ..model import Material
from .meshio import Mesh, MeshFileError, Warn, compact, fan, find_image, ignore

__all__ = ["read_ply"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_INSTANCE_PROPERTIES = ("instance", "instance_id", "object_id", "obj_id")
_UV_PROPERTIES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"))

# (property name, value type, list item type or None for a scalar)
_PlyProperty = tuple[str, str, "str | None"]


def _parse_ply(path: Path) -> tuple[list[str], dict[str, dict[str, np.ndarray]]]:
    """Header comments and element data of a PLY file (ASCII or binary, either byte order).

    A scalar property is an (n,) array; a list property an (n, k) array when every list
    has k items, else an (n,) object array of (k_i,) arrays.
    """
    try:
        data = path.read_bytes()
    except OSError as e:
        raise MeshFileError(f"cannot read: {e.strerror or e}") from None
    end = data.find(b"end_header")
    body = data.find(b"\n", end) + 1
    if not data.startswith(b"ply") or end < 0 or body == 0:
        raise MeshFileError("not a PLY file (no 'ply' ... 'end_header' header)")
    fmt, comments = None, []
    layout: list[tuple[str, int, list[_PlyProperty]]] = []
    for line in data[:end].decode("latin-1").splitlines()[1:]:
        p = line.split()
        try:
            if not p:
                continue
            if p[0] == "format":
                fmt = p[1]
            elif p[0] in ("comment", "obj_info"):
                comments.append(line.strip().split(None, 1)[1] if len(p) > 1 else "")
            elif p[0] == "element":
                layout.append((p[1], int(p[2]), []))
            elif p[0] == "property" and p[1] == "list":
                layout[-1][2].append((p[4], _PLY_TYPES[p[2]], _PLY_TYPES[p[3]]))
            elif p[0] == "property":
                layout[-1][2].append((p[2], _PLY_TYPES[p[1]], None))
        except (IndexError, ValueError, KeyError):
            raise MeshFileError(f"bad PLY header line {line.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFileError(f"unknown PLY format {fmt!r}")
    elements = {}
    if fmt == "ascii":
        tokens, cursor = data[body:].decode("latin-1").split(), 0
        for name, count, props in layout:
            elements[name], cursor = _ply_ascii_element(tokens, cursor, name, count, props)
    else:
        endian, cursor = "<" if fmt == "binary_little_endian" else ">", body
        for name, count, props in layout:
            elements[name], cursor = _ply_binary_element(data, cursor, name, count, props, endian)
    return comments, elements


def _ply_columns(rows: np.ndarray, props: list[_PlyProperty], lengths: list[int]) -> dict | None:
    """Split (n, width) values into properties when every list has its first row's length."""
    out, col = {}, 0
    for (name, kind, item), k in zip(props, lengths, strict=True):
        if item is None:
            out[name] = rows[:, col].astype(kind)
            col += 1
        else:
            if (rows[:, col] != k).any():
                return None
            out[name] = rows[:, col + 1:col + 1 + k].astype(item)
            col += 1 + k
    return out


def _ply_ascii_element(tokens, cursor, name, count, props):
    lengths, c = [], cursor
    try:
        for _, _, item in props:  # the first row fixes the list lengths of the fast path
            lengths.append(int(float(tokens[c])) if item is not None else 1)
            c += 1 + lengths[-1] if item is not None else 1
        width = c - cursor
        block = tokens[cursor:cursor + count * width]
        if count and len(block) == count * width:
            out = _ply_columns(np.array(block, dtype=np.float64).reshape(count, width), props, lengths)
            if out is not None:
                return out, cursor + count * width
        cols = {p[0]: [] for p in props}
        for _ in range(count):  # lists of varying length: one row at a time
            for pname, _, item in props:
                if item is None:
                    cols[pname].append(float(tokens[cursor]))
                    cursor += 1
                else:
                    k = int(float(tokens[cursor]))
                    values = np.array(tokens[cursor + 1:cursor + 1 + k], dtype=np.float64)
                    cols[pname].append(values.astype(item))
                    cursor += 1 + k
    except IndexError:
        raise MeshFileError(
            f"PLY is truncated: element {name!r} has fewer values than its {count} rows") from None
    except ValueError as e:
        raise MeshFileError(f"PLY element {name!r}: cannot read a value ({e})") from None
    columns = zip(props, cols.values(), strict=True)
    return {p: _ply_list_or_array(v, kind, item) for (p, kind, item), v in columns}, cursor


def _ply_binary_element(data, cursor, name, count, props, endian):
    fields, lengths, c = [], [], cursor
    try:
        for pname, kind, item in props:  # the first row fixes the list lengths of the fast path
            size = np.dtype(kind).itemsize
            if item is None:
                fields.append((pname, endian + kind))
                lengths.append(1)
                c += size
            else:
                k = int(np.frombuffer(data, endian + kind, 1, c)[0]) if count else 0
                fields += [(pname + "#count", endian + kind), (pname, endian + item, (k,))]
                lengths.append(k)
                c += size + k * np.dtype(item).itemsize
        dtype = np.dtype(fields)
        if cursor + count * dtype.itemsize <= len(data):
            rows = np.frombuffer(data, dtype, count, cursor)
            lists = [(p, k) for (p, _, item), k in zip(props, lengths, strict=True) if item is not None]
            if all((rows[p + "#count"] == k).all() for p, k in lists):
                out = {p: rows[p].astype(item or kind) for p, kind, item in props}
                return out, cursor + count * dtype.itemsize
        cols = {p[0]: [] for p in props}
        for _ in range(count):  # lists of varying length: one row at a time
            for pname, kind, item in props:
                value = np.frombuffer(data, endian + kind, 1, cursor)[0]
                cursor += np.dtype(kind).itemsize
                if item is None:
                    cols[pname].append(value)
                else:
                    cols[pname].append(np.frombuffer(data, endian + item, int(value), cursor).astype(item))
                    cursor += int(value) * np.dtype(item).itemsize
    except ValueError:
        raise MeshFileError(f"PLY is truncated: element {name!r} ends past the end of the file") from None
    columns = zip(props, cols.values(), strict=True)
    return {p: _ply_list_or_array(v, kind, item) for (p, kind, item), v in columns}, cursor


def _ply_list_or_array(values: list, kind: str, item: str | None) -> np.ndarray:
    if item is None:
        return np.array(values, dtype=kind)
    out = np.empty(len(values), dtype=object)
    out[:] = values
    return out


def _ply_triangles(polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate PLY faces: triangles (m, 3) int64 and the face each came from (m,) int64."""
    if polygons.dtype == object:
        tris = [fan(np.asarray(p, dtype=np.int64)[None]) if len(p) >= 3 else np.zeros((0, 3), np.int64)
                for p in polygons]
        return np.concatenate(tris), np.repeat(np.arange(len(tris)), [len(t) for t in tris])
    k = polygons.shape[1]
    if k < 3:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return fan(polygons.astype(np.int64)), np.repeat(np.arange(len(polygons)), k - 2)


def read_ply(path: Path, warn: Warn = ignore) -> Iterator[Mesh]:
    """Yield the meshes of a PLY scene (module docs). Raises :class:`MeshFileError` for
    anything unreadable; ``warn`` receives what was tolerated (a missing texture)."""
    path = Path(path)
    comments, elements = _parse_ply(path)
    vertex, face = elements.get("vertex", {}), elements.get("face", {})
    if not all(c in vertex for c in "xyz"):
        raise MeshFileError("PLY vertices have no x, y, z properties")
    polygons = face.get("vertex_indices", face.get("vertex_index"))
    if polygons is None or not len(polygons):
        raise MeshFileError("no faces (a point cloud is not a scene)")
    vertices = np.column_stack([vertex[c] for c in "xyz"]).astype(np.float64)
    faces, source = _ply_triangles(polygons)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        bad = int(faces.max() if faces.max() >= len(vertices) else faces.min())
        raise MeshFileError(f"face index {bad} is outside the {len(vertices)} vertices")

    ids = next((face[n][source] for n in _INSTANCE_PROPERTIES if n in face), None)
    if ids is None:  # a face belongs to the instance of its first corner
        ids = next((vertex[n][faces[:, 0]] for n in _INSTANCE_PROPERTIES if n in vertex),
                   np.zeros(len(faces), np.int64))
    colors, per_face = _ply_colors(face, vertex)
    uv = next((np.column_stack([vertex[u], vertex[v]])
               for u, v in _UV_PROPERTIES if u in vertex and v in vertex), None)
    names, texture = {}, None
    for comment in comments:
        parts = comment.split(None, 2)
        if len(parts) == 3 and parts[0] == "instance":
            names[parts[1]] = parts[2].strip()
        elif len(parts) >= 2 and parts[0].lower() == "texturefile":
            texture = find_image(path.parent / comment.split(None, 1)[1].strip(), warn, warn_missing=True)
    values = np.unique(ids)
    for value in values:
        sel = np.flatnonzero(ids == value)
        key = f"{value:g}" if values.dtype.kind == "f" else str(value)
        name = names.get(key) or (path.stem if len(values) == 1 else f"{path.stem}_{key}")
        used, local = compact(faces[sel])
        material, face_material, vertex_colors = None, None, None
        if colors is not None and per_face:
            unique, first, group = np.unique(colors[source[sel]], axis=0, return_index=True, return_inverse=True)
            order = np.argsort(first, kind="stable")
            rank = np.empty_like(order)
            rank[order] = np.arange(len(order))
            material = tuple(Material(base_color=tuple(float(c) for c in unique[k]), texture=texture) for k in order)
            if len(material) == 1:
                material = material[0]
            else:
                face_material = rank[group.reshape(-1)].astype(np.int32)
        elif colors is not None:
            material, vertex_colors = Material(base_color=(1.0, 1.0, 1.0, 1.0), texture=texture), colors[used]
        elif texture is not None:
            material = Material(texture=texture)
        yield Mesh(vertices[used], local, None if uv is None else uv[used], material, name,
                   face_material=face_material, colors=vertex_colors)


def _ply_colors(face: dict, vertex: dict) -> tuple[np.ndarray | None, bool]:
    """Linear RGBA in [0, 1] (RGB decoded from sRGB), (faces, 4) or (vertices, 4), and
    whether they are per face."""
    for element, per_face in ((face, True), (vertex, False)):
        if all(c in element for c in ("red", "green", "blue")):
            is_byte = element["red"].dtype.kind in "iu"
            full = 255.0 if is_byte else 1.0
            alpha = element.get("alpha", np.full(len(element["red"]), full))
            rgb = [element[c] for c in ("red", "green", "blue")]
            rgba = np.column_stack([*rgb, alpha]).astype(np.float64) / full
            rgba[:, :3] = srgb_to_linear(np.clip(rgba[:, :3], 0.0, 1.0))
            return rgba, per_face
    return None, False
