"""Generic scenes: glTF 2.0 (``.gltf``/``.glb``), Wavefront OBJ and PLY, read and written.

A generic scene has no rooms and no categories, only named meshes:

- **glTF/GLB**: one instance per node that has triangles, in depth-first node order, node
  transforms applied; the primitives of a node's mesh are merged into one instance.
- **OBJ**: one instance per object, in order of first appearance. Objects are the ``o``
  names when the file has several, else the ``g`` groups when it has several, else the
  whole file.
- **PLY**: one instance per value of a per-face (else per-vertex) ``instance``,
  ``instance_id``, ``object_id`` or ``obj_id`` property, in increasing order; without such a
  property, one instance. Names come from ``comment instance <value> <name>`` header lines.

The category of an instance comes from its name through a :class:`PatternMap` (the bundled
one or ``LoadOptions.name_map``); its ``label`` is the name without Blender-style copy
numbers (``Chair.001`` → ``Chair``), so that rules on source labels (fireplace, plant, ...)
see the object's kind. Persons and plants are dropped.

The writers name every instance ``<nyu40 name>__<name>``, or ``<nyu40 name>__<label>__<name>``
when the label is not the one the name gives (or the name holds ``__``): the bundled pattern
map sends the tag back to the same class, and the loader takes tag and label off the name.

glTF is read here rather than with ``trimesh.load``: trimesh renames the primitives of a
multi-primitive mesh with random suffixes and keeps textures only as decoded images, while
sceneforge needs the glTF node names, a deterministic order and the image file paths (with a
fallback when an image is missing, e.g. the ``.dds`` files of ``MSFT_texture_dds``).

Texture coordinates follow OBJ/OpenGL: ``v = 0`` is the bottom row of the image (glTF's
``v`` is flipped on the way in and out).
"""

from __future__ import annotations

import base64
import io
import json
import re
import struct
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import unquote

import numpy as np

from ..conventions import NYU40_NAMES, is_dropped
from ..errors import HouseError, SceneforgeError
from .categories import PatternMap, resolve
from .model import House, Instance, Material, make_instance

if TYPE_CHECKING:
    from . import LoadOptions

__all__ = ["SUFFIXES", "load_house", "tagged_name", "write_house"]

#: file suffix → source format name
SUFFIXES = {".gltf": "gltf", ".glb": "gltf", ".obj": "obj", ".ply": "ply"}

#: rotation taking a Z-up source to +Y up, right-handed: (x, y, z) → (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_TAG = re.compile(r"^(" + "|".join(map(re.escape, NYU40_NAMES)) + r")__(?=.)")
# Blender ".001", "_2", " 3": copies of one object, not different kinds of object.
_COPY_NUMBER = re.compile(r"(?:[._ -]\d+)+$")
# Image files tried, in order, in place of a missing texture image with the same stem.
_TWIN_SUFFIXES = (".png", ".jpg", ".jpeg")


# --------------------------------------------------------------------------- public API


def load_house(path: str | Path, options: LoadOptions | None = None) -> House:
    """Read a glTF/GLB, OBJ or PLY scene as a house (id = file stem, no rooms).

    ``options`` is a :class:`sceneforge.houses.LoadOptions`; ``scale``, ``up_axis``,
    ``name_map`` and ``strict`` apply. Raises :class:`HouseError` naming the house, the
    file and the problem for anything unreadable, and :class:`SceneforgeError` for a bad
    option.
    """
    from . import LoadOptions

    path = Path(path)
    options = options or LoadOptions()
    fmt = SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise SceneforgeError(f"{path}: not a generic scene (expected one of {', '.join(SUFFIXES)})")
    builder = _Builder(path, fmt, options)
    if not path.is_file():
        raise HouseError(builder.house.id, path, "no such file")
    {"gltf": _read_gltf, "obj": _read_obj, "ply": _read_ply}[fmt](builder)
    return builder.house.check_not_empty()


def write_house(house: House, path: str | Path) -> Path:
    """Write ``house`` as ``.gltf``, ``.glb``, ``.obj`` (+ ``.mtl``) or ``.ply`` (by suffix).

    Every format keeps instances (one node / ``o`` object / PLY ``instance`` value each),
    categories (through :func:`tagged_name`) and geometry. glTF and OBJ keep base colours,
    textures and uv; PLY keeps base colours (as face colours) and uv, not textures. Rooms
    are not kept. glTF stores positions as float32, relative to each instance's centre
    (about 6e-8 × the instance's size of error). Returns ``path``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise SceneforgeError(
            f"{path}: cannot write a house as {suffix!r} (use one of {', '.join(SUFFIXES)})")
    path.parent.mkdir(parents=True, exist_ok=True)
    names = _unique_tagged_names(house.instances)
    if suffix in (".gltf", ".glb"):
        _write_gltf(house, names, path)
    elif suffix == ".obj":
        _write_obj(house, names, path)
    else:
        _write_ply(house, names, path)
    return path


def tagged_name(instance: Instance) -> str:
    """The name the writers give ``instance``: ``<nyu40 name>__[<label>__]<name>`` (module docs)."""
    name = re.sub(r"\s+", " ", instance.name).strip() or f"instance{instance.id}"
    label = re.sub(r"\s+", " ", re.sub(r"_{2,}", "_", instance.label)).strip() or _label_of(name)
    tag = NYU40_NAMES[instance.category]
    if "__" in name or label != _label_of(name):
        return f"{tag}__{label}__{name}"
    return f"{tag}__{name}"


def _label_of(name: str) -> str:
    """The kind of object a name stands for: the name without copy numbers (``Chair.001``)."""
    return _COPY_NUMBER.sub("", name) or name


def _split_name(node_name: str) -> tuple[str, str]:
    """(name, label) of a node/object name, taking off a :func:`tagged_name` tag and label."""
    tag = _TAG.match(node_name)
    if tag is None:
        return node_name, _label_of(node_name)
    label, sep, name = node_name[tag.end():].partition("__")
    if sep and label and name:
        return name, label
    rest = node_name[tag.end():]
    return rest, _label_of(rest)


# --------------------------------------------------------------------------- shared loading


class _Builder:
    """Turns named meshes of one file into instances: options, categories, checks."""

    def __init__(self, path: Path, fmt: str, options: LoadOptions):
        scale, up = options.scale, str(options.up_axis).lower()
        number = isinstance(scale, (int, float)) and not isinstance(scale, bool)
        if not number or not np.isfinite(scale) or scale <= 0:
            raise SceneforgeError(f"scale must be a finite number > 0, got {scale!r}")
        if up not in ("y", "z"):
            raise SceneforgeError(f"up_axis must be 'y' or 'z', got {options.up_axis!r}")
        self.path = path
        self.options = options
        self.patterns = PatternMap.from_file(options.name_map) if options.name_map else PatternMap.default()
        #: (3, 3) float64 source → world linear map (scale and up axis)
        self.to_world = float(scale) * (Z_UP_TO_Y_UP if up == "z" else np.eye(3))
        self.house = House(id=path.stem, instances=[], rooms=[], source_format=fmt, source_path=str(path))

    def error(self, problem: str, file: Path | None = None) -> HouseError:
        return HouseError(self.house.id, file or self.path, problem)

    def warn(self, message: str) -> None:
        if message not in self.house.warnings:
            self.house.warnings.append(message)

    def add(self, name: str, vertices, faces, *, material=None, uv=None, other_names=()) -> None:
        """Add one mesh (vertices (n, 3) float in source units/axes, faces (m, 3) int)."""
        clean, label = _split_name(name)
        category = self.patterns.lookup(name)
        for other in other_names:
            category = self.patterns.lookup(other) if category is None else category
        if is_dropped(category or 0, label):  # before resolve: plants have no NYU40 class
            self.warn(f"instance {clean!r} ({label}) dropped: persons and plants are not kept")
            return
        category = resolve(self.house, label, category, strict=self.options.strict, file=self.path)
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3) @ self.to_world.T
        make_instance(self.house, name=clean, category=category, label=label, room_id=None,
                      vertices=v, faces=faces, file=self.path, material=material, uv=uv)


def _find_image(builder: _Builder, path: Path, warn_missing: bool = False) -> Path | None:
    """``path`` if it exists, else a ``.png``/``.jpg`` twin beside it (with a warning), else None."""
    if path.is_file():
        return path
    for twin in (path.with_suffix(s) for s in _TWIN_SUFFIXES):
        if twin != path and twin.is_file():
            builder.warn(f"texture {path.name} is missing, using {twin.name}")
            return twin
    if warn_missing:
        builder.warn(f"texture {path.name} is missing; no texture")
    return None


def _decode_image(builder: _Builder, data: bytes, what: str):
    """A PIL image from encoded bytes, or None (with a warning) when they do not decode."""
    import PIL.Image

    try:
        image = PIL.Image.open(io.BytesIO(data))
        image.load()
    except (OSError, ValueError, PIL.Image.DecompressionBombError) as e:
        builder.warn(f"{what} cannot be decoded ({e}); no texture")
        return None
    return image


def _local_vertices(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Compact the vertices used by ``faces`` (m, 3) int: (used (n,) int64, local faces (m, 3) int64)."""
    used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
    return used, inverse.reshape(-1, 3).astype(np.int64)


def _fan(polygons: np.ndarray) -> np.ndarray:
    """Triangles (n * (k - 2), 3) of n convex k-gons (n, k) by fans around their first corners."""
    k = polygons.shape[1]
    fans = np.stack([np.repeat(polygons[:, :1], k - 2, axis=1), polygons[:, 1:-1], polygons[:, 2:]], axis=2)
    return fans.reshape(-1, 3)


def _face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) float64 areas of faces (m, 3) int over vertices (n, 3) float."""
    v = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


# --------------------------------------------------------------------------- glTF reading

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = b"glTF", 0x4E4F534A, 0x004E4942
_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6
_UNSUPPORTED_REQUIRED = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression"}


class _Gltf:
    """The JSON of a glTF 2.0 file and its buffers, with accessor and material decoding."""

    def __init__(self, builder: _Builder):
        self.b = builder
        try:
            data = builder.path.read_bytes()
        except OSError as e:
            raise builder.error(f"cannot read: {e.strerror or e}") from None
        self.bin_chunk: bytes | None = None
        if data[:4] == _GLB_MAGIC:
            text = self._split_glb(data)
        else:
            text = data
        try:
            self.doc = json.loads(text)
        except (UnicodeDecodeError, ValueError) as e:
            raise builder.error(f"not a glTF file: its JSON does not parse ({e})") from None
        version = self.doc.get("asset", {}).get("version", "") if isinstance(self.doc, dict) else ""
        if not str(version).startswith("2"):
            raise builder.error("not a glTF 2.0 file (asset.version is not 2.x)")
        required = set(self.doc.get("extensionsRequired", [])) & _UNSUPPORTED_REQUIRED
        if required:
            raise builder.error(f"needs {', '.join(sorted(required))}, which sceneforge cannot decode; "
                                "export the scene without mesh compression")
        self.buffers: dict[int, bytes] = {}
        self.materials: dict[int | None, Material] = {}
        self.images: dict[int, object] = {}

    def _split_glb(self, data: bytes) -> bytes:
        if len(data) < 12:
            raise self.b.error(f"GLB is truncated: {len(data)} bytes, not even a header")
        _, version, length = struct.unpack_from("<4sII", data)
        if version != 2:
            raise self.b.error(f"GLB version {version} is not supported (only glTF 2.0)")
        if length > len(data):
            raise self.b.error(f"GLB is truncated: its header says {length} bytes, the file has {len(data)}")
        json_chunk, offset = None, 12
        while offset + 8 <= length:
            size, kind = struct.unpack_from("<II", data, offset)
            offset += 8
            if offset + size > length:
                raise self.b.error(
                    f"GLB is truncated: a chunk of {size} bytes at {offset} ends past {length}")
            chunk = data[offset:offset + size]
            offset += size
            if kind == _GLB_JSON and json_chunk is None:
                json_chunk = chunk
            elif kind == _GLB_BIN and self.bin_chunk is None:
                self.bin_chunk = chunk
        if json_chunk is None:
            raise self.b.error("GLB has no JSON chunk")
        return json_chunk

    def item(self, kind: str, index) -> dict:
        """``doc[kind][index]``, or a HouseError saying which reference is broken."""
        items = self.doc.get(kind, [])
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise self.b.error(f"{kind}[{index}] is referenced but the file has {len(items)} {kind}")
        return items[index]

    def buffer(self, index: int) -> bytes:
        if index not in self.buffers:
            spec = self.item("buffers", index)
            uri = spec.get("uri")
            if uri is None:
                data = self.bin_chunk
                if data is None:
                    raise self.b.error(f"buffers[{index}] has no uri and the file has no GLB binary chunk")
            elif uri.startswith("data:"):
                data = self._data_uri(uri, f"buffers[{index}]")
            else:
                file = self.b.path.parent / unquote(uri)
                try:
                    data = file.read_bytes()
                except OSError as e:
                    raise self.b.error(f"cannot read buffer {uri!r}: {e.strerror or e}", file) from None
            if len(data) < spec.get("byteLength", 0):
                raise self.b.error(
                    f"buffers[{index}] is truncated: {len(data)} of {spec['byteLength']} bytes")
            self.buffers[index] = data
        return self.buffers[index]

    def _data_uri(self, uri: str, what: str) -> bytes:
        head, _, payload = uri.partition(",")
        try:
            if head.endswith(";base64"):
                return base64.b64decode(payload, validate=True)
            return unquote(payload).encode()
        except ValueError as e:
            raise self.b.error(f"{what}: bad data URI ({e})") from None

    def view_bytes(self, index: int) -> bytes:
        view = self.item("bufferViews", index)
        data, start = self.buffer(view["buffer"]), view.get("byteOffset", 0)
        if start + view["byteLength"] > len(data):
            raise self.b.error(f"bufferViews[{index}] ends at byte {start + view['byteLength']} "
                               f"but its buffer has {len(data)} (truncated file?)")
        return data[start:start + view["byteLength"]]

    def _view_array(self, view_index: int, offset: int, dtype: np.dtype, count: int, width: int,
                    stride: int | None = None) -> np.ndarray:
        data = self.view_bytes(view_index)
        stride = stride or dtype.itemsize * width
        end = offset + (count - 1) * stride + dtype.itemsize * width if count else offset
        if end > len(data):
            raise self.b.error(
                f"an accessor reads {end} bytes of bufferViews[{view_index}], which has {len(data)}")
        return np.ndarray((count, width), dtype, buffer=data, offset=offset,
                          strides=(stride, dtype.itemsize)).copy()

    def accessor(self, index: int) -> np.ndarray:
        """(count, width) array of accessor ``index`` (sparse and normalised values applied)."""
        acc = self.item("accessors", index)
        if acc.get("componentType") not in _COMPONENTS or acc.get("type") not in _WIDTHS:
            raise self.b.error(
                f"accessors[{index}] has an unknown type {acc.get('componentType')}/{acc.get('type')}")
        dtype, width, count = np.dtype(_COMPONENTS[acc["componentType"]]), _WIDTHS[acc["type"]], acc["count"]
        if "bufferView" in acc:
            stride = self.item("bufferViews", acc["bufferView"]).get("byteStride")
            out = self._view_array(acc["bufferView"], acc.get("byteOffset", 0), dtype, count, width, stride)
        else:
            out = np.zeros((count, width), dtype)
        sparse = acc.get("sparse")
        if sparse:
            n, ind, val = sparse["count"], sparse["indices"], sparse["values"]
            where = self._view_array(ind["bufferView"], ind.get("byteOffset", 0),
                                     np.dtype(_COMPONENTS[ind["componentType"]]), n, 1).ravel()
            if len(where) and where.max() >= count:
                raise self.b.error(
                    f"accessors[{index}]: sparse index {int(where.max())} is past its {count} elements")
            out[where] = self._view_array(val["bufferView"], val.get("byteOffset", 0), dtype, n, width)
        if acc.get("normalized") and dtype.kind in "iu":
            out = np.maximum(out / np.iinfo(dtype).max, -1.0)
        return out

    def material(self, index: int | None) -> Material:
        """The :class:`Material` of glTF material ``index`` (None: glTF's default, white)."""
        if index not in self.materials:
            if index is None:
                self.materials[index] = Material(base_color=(1.0, 1.0, 1.0, 1.0))
            else:
                spec = self.item("materials", index)
                pbr = spec.get("pbrMetallicRoughness")
                if pbr is None:  # the retired spec-gloss workflow has the same two fields, renamed
                    sg = spec.get("extensions", {}).get("KHR_materials_pbrSpecularGlossiness", {})
                    pbr = {"baseColorFactor": sg.get("diffuseFactor"),
                           "baseColorTexture": sg.get("diffuseTexture")}
                color = pbr.get("baseColorFactor") or (1.0, 1.0, 1.0, 1.0)
                tex = pbr.get("baseColorTexture")
                self.materials[index] = Material(
                    base_color=tuple(float(c) for c in color),
                    texture=self.texture(tex["index"]) if tex else None,
                )
        return self.materials[index]

    def texture(self, index: int):
        """Image of texture ``index``: a Path, a PIL image (embedded), or None (with a warning).

        The core ``source`` is tried first, then the sources of extensions such as
        ``MSFT_texture_dds``; a missing image file may be replaced by its ``.png``/``.jpg`` twin.
        """
        spec = self.item("textures", index)
        sources = [spec.get("source")] + [e.get("source") for e in spec.get("extensions", {}).values()
                                          if isinstance(e, dict)]
        tried = []
        for source in (s for s in sources if s is not None):
            image = self.image(source)
            if image is not None:
                return image
            tried.append(self.item("images", source).get("uri", f"images[{source}]"))
        self.b.warn(f"textures[{index}]: no readable image ({', '.join(tried) or 'none given'}); no texture")
        return None

    def image(self, index: int):
        if index not in self.images:
            spec = self.item("images", index)
            uri = spec.get("uri")
            if "bufferView" in spec:
                image = _decode_image(self.b, self.view_bytes(spec["bufferView"]), f"images[{index}]")
            elif uri is None:
                image = None
            elif uri.startswith("data:"):
                image = _decode_image(self.b, self._data_uri(uri, f"images[{index}]"), f"images[{index}]")
            else:
                image = _find_image(self.b, self.b.path.parent / unquote(uri))
            self.images[index] = image
        return self.images[index]

    def primitive(self, mesh_name: str, k: int, prim: dict):
        """Vertices (n, 3) float64, faces (m, 3) int64, uv (n, 2) or None of one primitive."""
        mode = prim.get("mode", _TRIANGLES)
        if mode not in (_TRIANGLES, _STRIP, _FAN):
            return None
        if "POSITION" not in prim.get("attributes", {}):
            raise self.b.error(f"mesh {mesh_name!r} primitive {k} has no POSITION attribute")
        vertices = self.accessor(prim["attributes"]["POSITION"]).astype(np.float64)
        if len(vertices) and vertices.shape[1] != 3:
            raise self.b.error(f"mesh {mesh_name!r} primitive {k}: POSITION is not VEC3")
        if "indices" in prim:
            idx = self.accessor(prim["indices"]).ravel().astype(np.int64)
        else:
            idx = np.arange(len(vertices), dtype=np.int64)
        if len(idx) and (idx.max() >= len(vertices) or idx.min() < 0):
            raise self.b.error(f"mesh {mesh_name!r} primitive {k}: index {int(idx.max())} is outside "
                               f"its {len(vertices)} vertices")
        if mode == _TRIANGLES:
            if len(idx) % 3:
                raise self.b.error(
                    f"mesh {mesh_name!r} primitive {k}: {len(idx)} indices is not a multiple of 3")
            faces = idx.reshape(-1, 3)
        elif len(idx) < 3:
            faces = np.zeros((0, 3), np.int64)
        elif mode == _FAN:
            faces = _fan(idx[None])
        else:
            faces = np.stack([idx[:-2], idx[1:-1], idx[2:]], axis=1)
            faces[1::2, :2] = faces[1::2, 1::-1]  # odd triangles of a strip are wound the other way
        uv = None
        if "TEXCOORD_0" in prim["attributes"]:
            uv = self.accessor(prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
            uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]) if uv.shape == (len(vertices), 2) else None
        return vertices, faces, uv

    def node_meshes(self):
        """Yield (node name, mesh name, world matrix (4, 4) float64, mesh dict), depth-first."""
        scenes = self.doc.get("scenes", [])
        nodes = self.doc.get("nodes", [])
        if scenes:
            roots = self.item("scenes", self.doc.get("scene", 0)).get("nodes", [])
        else:  # no scene: every node that is nobody's child is a root
            children = {c for n in nodes for c in n.get("children", [])}
            roots = [i for i in range(len(nodes)) if i not in children]
        stack = [(i, np.eye(4), ()) for i in reversed(roots)]
        while stack:
            index, parent, ancestors = stack.pop()
            if index in ancestors:
                raise self.b.error(f"nodes[{index}] is its own ancestor (cyclic node hierarchy)")
            node = self.item("nodes", index)
            world = parent @ _node_matrix(node)
            if "mesh" in node:
                mesh = self.item("meshes", node["mesh"])
                mesh_name = mesh.get("name") or f"mesh{node['mesh']}"
                yield node.get("name") or mesh.get("name") or f"node{index}", mesh_name, world, mesh
            stack += [(c, world, (*ancestors, index)) for c in reversed(node.get("children", []))]


def _node_matrix(node: dict) -> np.ndarray:
    """(4, 4) float64 local transform of a glTF node: ``matrix`` or T · R · S."""
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    x, y, z, w = np.asarray(node.get("rotation", (0, 0, 0, 1)), dtype=np.float64) / np.linalg.norm(
        node.get("rotation", (0, 0, 0, 1)))
    rot = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = rot * np.asarray(node.get("scale", (1, 1, 1)), dtype=np.float64)
    m[:3, 3] = node.get("translation", (0, 0, 0))
    return m


def _read_gltf(b: _Builder) -> None:
    try:
        gltf = _Gltf(b)
        for node_name, mesh_name, world, mesh in gltf.node_meshes():
            parts = [(p, gltf.primitive(mesh_name, k, p)) for k, p in enumerate(mesh.get("primitives", []))]
            parts = [(p, g) for p, g in parts if g is not None and len(g[1])]
            if not parts:
                continue
            offsets = np.cumsum([0] + [len(g[0]) for _, g in parts])
            vertices = np.concatenate([g[0] for _, g in parts])
            faces = np.concatenate([g[1] + o for (_, g), o in zip(parts, offsets[:-1], strict=True)])
            uv = np.concatenate([g[2] for _, g in parts]) if all(g[2] is not None for _, g in parts) else None
            # An instance has one material: keep the one that covers the most surface.
            areas = [_face_areas(g[0], g[1]).sum() for _, g in parts]
            materials = {p.get("material") for p, _ in parts}
            if len(materials) > 1:
                b.warn(f"mesh {mesh_name!r}: {len(materials)} materials, kept the one covering the most area")
            material = gltf.material(parts[int(np.argmax(areas))][0].get("material"))
            vertices = vertices @ world[:3, :3].T + world[:3, 3]
            if np.linalg.det(world[:3, :3]) < 0:  # a mirroring transform turns the winding around
                faces = faces[:, ::-1]
            b.add(node_name, vertices, faces, material=material, uv=uv, other_names=(mesh_name,))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        raise b.error(f"malformed glTF ({type(e).__name__}: {e})") from None


# --------------------------------------------------------------------------- OBJ reading


def _read_mtl(b: _Builder, file: Path) -> dict[str, Material]:
    """Materials of an MTL file by name: ``Kd``, ``d``/``Tr`` and ``map_Kd``."""
    try:
        text = file.read_text(errors="replace")
    except OSError as e:
        b.warn(f"material library {file.name} cannot be read ({e.strerror or e}); default colours")
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
                current = found.setdefault(rest, {"kd": (0.8, 0.8, 0.8), "alpha": 1.0, "map": None})
            elif current is None:
                continue
            elif key == "Kd":
                current["kd"] = tuple(float(c) for c in rest.split()[:3])
            elif key == "d":
                current["alpha"] = float(rest.split()[0])
            elif key == "Tr":
                current["alpha"] = 1.0 - float(rest.split()[0])
            elif key == "map_Kd" and rest:
                # Options (-s 1 1 1, -bm 0.5, ...) come first; the file name is the rest.
                whole = file.parent / rest
                current["map"] = whole if whole.is_file() else file.parent / rest.split()[-1]
        except (ValueError, IndexError):
            b.warn(f"{file.name}: cannot read line {line.strip()!r}")
    return {
        name: Material(
            base_color=(*m["kd"], m["alpha"]) if len(m["kd"]) == 3 else (0.8, 0.8, 0.8, m["alpha"]),
            texture=_find_image(b, m["map"], warn_missing=True) if m["map"] else None,
        )
        for name, m in found.items()
    }


def _read_obj(b: _Builder) -> None:
    try:
        text = b.path.read_text(errors="replace").replace("\\\n", " ")
    except OSError as e:
        raise b.error(f"cannot read: {e.strerror or e}") from None
    v_rows, v_lines, vt_rows, libraries = [], [], [], []
    # face lines: text after "f", vertices and texture coordinates defined before it, line number
    f_rest, f_nv, f_nvt, f_line = [], [], [], []
    runs: list[tuple[int, str | None, str | None, str | None]] = []  # (first face line, o, g, material)
    state, changed = (None, None, None), True
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split(None, 1)
        if not parts:
            continue
        key, rest = parts[0], parts[1] if len(parts) > 1 else ""
        if key == "f":
            if changed:
                runs.append((len(f_rest), *state))
                changed = False
            f_rest.append(rest)
            f_nv.append(len(v_rows))
            f_nvt.append(len(vt_rows))
            f_line.append(number)
        elif key == "v":
            v_rows.append(rest)
            v_lines.append(number)
        elif key == "vt":
            vt_rows.append((rest.split() + ["0", "0"])[:2])
        elif key in ("o", "g", "usemtl"):
            name = rest.strip() or None
            state = (name, state[1], state[2]) if key == "o" else (
                (state[0], name, state[2]) if key == "g" else (state[0], state[1], name))
            changed = True
        elif key == "mtllib":
            libraries.append(rest.strip())
    if not f_rest:
        raise b.error("no faces")
    vertices = _obj_vertices(b, v_rows, v_lines)
    try:
        uvs = np.array(vt_rows, dtype=np.float64).reshape(-1, 2)
    except ValueError:
        raise b.error("cannot read a texture coordinate (vt line)") from None
    tri_v, tri_t, tri_src = _obj_triangles(b, f_rest, np.array(f_nv), np.array(f_nvt), f_line)
    bad = np.flatnonzero(((tri_v < 0) | (tri_v >= len(vertices))).any(axis=1))
    if len(bad):
        row = tri_v[bad[0]]
        index = int(row[(row < 0) | (row >= len(vertices))][0])
        raise b.error(f"line {f_line[tri_src[bad[0]]]}: face index {index + 1} is outside the "
                      f"{len(vertices)} vertices")
    materials: dict[str, Material] = {}
    for lib in libraries:
        whole = b.path.parent / lib
        for file in [whole] if whole.is_file() else [b.path.parent / n for n in lib.split()]:
            materials.update(_read_mtl(b, file))
    # Objects: `o` names when there are several, else `g` groups when there are several.
    n_o, n_g = (len({r[k] for r in runs} - {None}) for k in (1, 2))
    first, second = (1, 2) if n_o > 1 or (n_o == 1 and n_g <= 1) else (2, 1)
    run_key = [r[first] or r[second] or b.path.stem for r in runs]
    codes = {k: i for i, k in enumerate(dict.fromkeys(run_key))}
    run_of_tri = np.searchsorted([r[0] for r in runs], tri_src, side="right") - 1
    object_of_tri = np.array([codes[k] for k in run_key])[run_of_tri]
    for name, code in codes.items():
        sel = np.flatnonzero(object_of_tri == code)
        corners, tex = tri_v[sel], tri_t[sel]
        if len(uvs) and not (tex == _NO_UV).any():
            if (tex < 0).any() or (tex >= len(uvs)).any():
                raise b.error(
                    f"object {name!r}: a texture index is outside the {len(uvs)} texture coordinates")
            # A vertex with two different uv in one object becomes two vertices.
            pairs, inverse = np.unique(np.stack([corners.ravel(), tex.ravel()], axis=1), axis=0,
                                       return_inverse=True)
            v, uv, faces = vertices[pairs[:, 0]], uvs[pairs[:, 1]], inverse.reshape(-1, 3)
        else:
            used, faces = _local_vertices(corners)
            v, uv = vertices[used], None
        run_area = np.bincount(run_of_tri[sel], weights=_face_areas(v, faces), minlength=len(runs))
        area_of: dict[str | None, float] = {}
        for run, area in zip(runs, run_area, strict=True):
            if area > 0:
                area_of[run[3]] = area_of.get(run[3], 0.0) + area
        material = _dominant_material(b, name, area_of, materials)
        b.add(name, v, faces, material=material, uv=uv)


# Texture corner of a face without texture coordinates (a real index, even a bad one, is larger).
_NO_UV = np.iinfo(np.int64).min


def _obj_triangles(b: _Builder, rests: list[str], nv: np.ndarray, nvt: np.ndarray, lines: list[int]):
    """Fan-triangulate OBJ face lines into 0-based corners.

    rests : text after ``f`` of each face line; nv, nvt (k,) int: vertices and texture
    coordinates defined before each line (for negative, relative indices).
    Returns corners (m, 3) int64, texture corners (m, 3) int64 (``_NO_UV`` where absent) and
    the face line of each triangle (m,) int64, in file order. Lines that share a layout (corner
    count, ``v/vt/vn`` form) are parsed together with numpy; any other line one at a time.
    """
    groups: dict[tuple, list[int]] = {}
    for i, rest in enumerate(rests):  # cheap string counts; a group's first line is checked below
        groups.setdefault((rest.count(" "), rest.count("/"), "//" in rest), []).append(i)
    parts = []
    for (_, _, no_vt), idx in groups.items():
        idx = np.array(idx)
        tokens = rests[idx[0]].split()
        corners, slashes = len(tokens), tokens[0].count("/") if tokens else 0
        if corners < 3:
            raise b.error(f"line {lines[idx[0]]}: a face needs 3 vertices, got {corners}")
        fields = slashes + 1
        joined = " ".join(rests[i] for i in idx).replace("//", "/0/").replace("/", " ").split()
        try:
            numbers = np.array(joined, dtype=np.int64)
        except ValueError:
            numbers = np.zeros(0, np.int64)
        if numbers.size != len(idx) * corners * fields:  # lines that are not what the first one promised
            parts += [_obj_triangles_slow(b, rests[i], nv[i], nvt[i], lines[i], i) for i in idx]
            continue
        numbers = numbers.reshape(len(idx), corners, fields)
        v = np.where(numbers[:, :, 0] < 0, numbers[:, :, 0] + nv[idx, None], numbers[:, :, 0] - 1)
        if fields > 1 and not no_vt:
            t = np.where(numbers[:, :, 1] < 0, numbers[:, :, 1] + nvt[idx, None], numbers[:, :, 1] - 1)
        else:
            t = np.full_like(v, _NO_UV)
        parts.append((_fan(v), _fan(t), np.repeat(idx, corners - 2)))
    tri_v, tri_t, src = (np.concatenate(p) for p in zip(*parts, strict=True))
    order = np.argsort(src, kind="stable")
    return tri_v[order], tri_t[order], src[order]


def _obj_triangles_slow(b: _Builder, rest: str, nv: int, nvt: int, line: int, i: int):
    refs = [t.split("/") for t in rest.split()]
    try:
        vs = [_obj_index(r[0], nv) for r in refs]
        ts = [_obj_index(r[1], nvt) for r in refs] if all(len(r) > 1 and r[1] for r in refs) else None
    except ValueError:
        raise b.error(f"line {line}: cannot read face {rest.strip()!r}") from None
    if len(vs) < 3:
        raise b.error(f"line {line}: a face needs 3 vertices, got {len(vs)}")
    v = _fan(np.array([vs]))
    t = _fan(np.array([ts])) if ts is not None else np.full_like(v, _NO_UV)
    return v, t, np.full(len(v), i)


def _obj_vertices(b: _Builder, rows: list[str], lines: list[int]) -> np.ndarray:
    """(n, 3) float64 positions of ``v`` lines (a w or a colour after x y z is ignored)."""
    try:  # all lines "x y z": one conversion for the whole file
        values = np.array(" ".join(rows).split(), dtype=np.float64)
        if values.size == 3 * len(rows):
            return values.reshape(-1, 3)
    except ValueError:
        pass
    for row, line in zip(rows, lines, strict=True):
        if len(row.split()) < 3 or not _all_floats(row.split()[:3]):
            raise b.error(f"line {line}: cannot read vertex {row.strip()!r}")
    return np.array([row.split()[:3] for row in rows], dtype=np.float64).reshape(-1, 3)


def _obj_index(token: str, count: int) -> int:
    """0-based index of a 1-based (or negative, relative) OBJ index among ``count`` so far."""
    i = int(token)
    return count + i if i < 0 else i - 1


def _all_floats(row) -> bool:
    try:
        [float(x) for x in row]
    except ValueError:
        return False
    return True


def _dominant_material(b: _Builder, name: str, area_of: dict[str | None, float],
                       materials: dict[str, Material]) -> Material | None:
    """Of the materials of object ``name`` (name → area covered), the one covering the most."""
    if len(area_of) > 1:
        b.warn(f"object {name!r}: {len(area_of)} materials, kept the one covering the most area")
    best = max(area_of, key=area_of.get, default=None)
    if best is not None and best not in materials:
        b.warn(f"material {best!r} is not in any material library; default colour")
    return materials.get(best)


# --------------------------------------------------------------------------- PLY reading

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_INSTANCE_PROPERTIES = ("instance", "instance_id", "object_id", "obj_id")
_UV_PROPERTIES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"))

# (property name, value type, list item type or None for a scalar)
_PlyProperty = tuple[str, str, "str | None"]


def _parse_ply(b: _Builder) -> tuple[list[str], dict[str, dict[str, np.ndarray]]]:
    """Header comments and element data of a PLY file (ASCII or binary, either byte order).

    A scalar property is an (n,) array; a list property an (n, k) array when every list
    has k items, else an (n,) object array of (k_i,) arrays.
    """
    try:
        data = b.path.read_bytes()
    except OSError as e:
        raise b.error(f"cannot read: {e.strerror or e}") from None
    end = data.find(b"end_header")
    body = data.find(b"\n", end) + 1
    if not data.startswith(b"ply") or end < 0 or body == 0:
        raise b.error("not a PLY file (no 'ply' ... 'end_header' header)")
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
            raise b.error(f"bad PLY header line {line.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise b.error(f"unknown PLY format {fmt!r}")
    elements = {}
    if fmt == "ascii":
        tokens, cursor = data[body:].decode("latin-1").split(), 0
        for name, count, props in layout:
            elements[name], cursor = _ply_ascii_element(b, tokens, cursor, name, count, props)
    else:
        endian, cursor = "<" if fmt == "binary_little_endian" else ">", body
        for name, count, props in layout:
            elements[name], cursor = _ply_binary_element(b, data, cursor, name, count, props, endian)
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


def _ply_ascii_element(b, tokens, cursor, name, count, props):
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
        raise b.error(f"PLY is truncated: element {name!r} has fewer values than its {count} rows") from None
    except ValueError as e:
        raise b.error(f"PLY element {name!r}: cannot read a value ({e})") from None
    columns = zip(props, cols.values(), strict=True)
    return {p: _ply_list_or_array(v, kind, item) for (p, kind, item), v in columns}, cursor


def _ply_binary_element(b, data, cursor, name, count, props, endian):
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
        raise b.error(f"PLY is truncated: element {name!r} ends past the end of the file") from None
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
        tris = [_fan(np.asarray(p, dtype=np.int64)[None]) if len(p) >= 3 else np.zeros((0, 3), np.int64)
                for p in polygons]
        return np.concatenate(tris), np.repeat(np.arange(len(tris)), [len(t) for t in tris])
    k = polygons.shape[1]
    if k < 3:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return _fan(polygons.astype(np.int64)), np.repeat(np.arange(len(polygons)), k - 2)


def _read_ply(b: _Builder) -> None:
    comments, elements = _parse_ply(b)
    vertex, face = elements.get("vertex", {}), elements.get("face", {})
    if not all(c in vertex for c in "xyz"):
        raise b.error("PLY vertices have no x, y, z properties")
    polygons = face.get("vertex_indices", face.get("vertex_index"))
    if polygons is None or not len(polygons):
        raise b.error("no faces (a point cloud is not a scene)")
    vertices = np.column_stack([vertex[c] for c in "xyz"]).astype(np.float64)
    faces, source = _ply_triangles(polygons)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        bad = int(faces.max() if faces.max() >= len(vertices) else faces.min())
        raise b.error(f"face index {bad} is outside the {len(vertices)} vertices")

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
            texture = _find_image(b, b.path.parent / comment.split(None, 1)[1].strip(), warn_missing=True)
    values = np.unique(ids)
    for value in values:
        sel = np.flatnonzero(ids == value)
        key = f"{value:g}" if values.dtype.kind == "f" else str(value)
        name = names.get(key) or (b.path.stem if len(values) == 1 else f"{b.path.stem}_{key}")
        used, local = _local_vertices(faces[sel])
        material = None
        if colors is not None:
            rows = colors[source[sel]] if per_face else colors[used]
            if not (rows == rows[0]).all():  # several colours: the most frequent one
                unique, counts = np.unique(rows, axis=0, return_counts=True)
                rows = unique[np.argmax(counts)][None]
            material = Material(base_color=tuple(float(c) for c in rows[0]), texture=texture)
        elif texture is not None:
            material = Material(texture=texture)
        b.add(name, vertices[used], local, material=material, uv=None if uv is None else uv[used])


def _ply_colors(face: dict, vertex: dict) -> tuple[np.ndarray | None, bool]:
    """RGBA in [0, 1], (faces, 4) or (vertices, 4), and whether they are per face."""
    for element, per_face in ((face, True), (vertex, False)):
        if all(c in element for c in ("red", "green", "blue")):
            is_byte = element["red"].dtype.kind in "iu"
            full = 255.0 if is_byte else 1.0
            alpha = element.get("alpha", np.full(len(element["red"]), full))
            rgb = [element[c] for c in ("red", "green", "blue")]
            rgba = np.column_stack([*rgb, alpha]).astype(np.float64)
            return rgba / full, per_face
    return None, False


# --------------------------------------------------------------------------- writing


def _unique_tagged_names(instances: list[Instance]) -> list[str]:
    """Tagged names, made unique with ``.2``, ``.3``... (OBJ would merge equal names)."""
    seen: dict[str, int] = {}
    out = []
    for inst in instances:
        name = tagged_name(inst)
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name}.{seen[name]}")
    return out


def _texture_bytes(texture) -> tuple[bytes, str]:
    """Encoded bytes and file suffix of a texture (a path is copied as is, a PIL image as PNG)."""
    if isinstance(texture, (str, Path)):
        return Path(texture).read_bytes(), Path(texture).suffix.lower()
    buf = io.BytesIO()
    texture.save(buf, format="PNG")
    return buf.getvalue(), ".png"


def _materials_of(house: House) -> tuple[list[Material], list[int], list]:
    """Distinct materials, each instance's material index, and the distinct textures."""
    keys: dict = {}
    textures: dict[int, object] = {}
    index = []
    for inst in house.instances:
        m = inst.material
        if m.texture is not None:
            textures.setdefault(id(m.texture), m.texture)
        key = (tuple(float(c) for c in m.base_color), id(m.texture) if m.texture is not None else None)
        index.append(keys.setdefault(key, len(keys)))
    materials = [None] * len(keys)
    for (color, tex_id), i in keys.items():
        materials[i] = Material(base_color=color, texture=textures.get(tex_id))
    return materials, index, list(textures.values())


def _write_gltf(house: House, names: list[str], path: Path) -> None:
    binary = path.suffix.lower() == ".glb"
    materials, material_index, textures = _materials_of(house)
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
        data, suffix = _texture_bytes(tex)
        mime = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}.get(suffix, "image/png")
        if binary:
            images.append({"bufferView": view(data), "mimeType": mime})
        else:
            file = f"{path.stem}_texture{k}{suffix}"
            (path.parent / file).write_bytes(data)
            images.append({"uri": file})
    texture_index = {id(t): k for k, t in enumerate(textures)}
    gl_materials = []
    for m in materials:
        pbr = {"baseColorFactor": list(m.base_color), "metallicFactor": 0.0, "roughnessFactor": 1.0}
        if m.texture is not None:
            pbr["baseColorTexture"] = {"index": texture_index[id(m.texture)]}
        gl_materials.append({"pbrMetallicRoughness": pbr})

    meshes, nodes = [], []
    for inst, name, mat in zip(house.instances, names, material_index, strict=True):
        # float32 positions relative to the instance's centre (kept in float64 as the node's
        # translation) lose far less than world coordinates would
        center = (inst.vertices.min(axis=0) + inst.vertices.max(axis=0)) / 2
        local = (inst.vertices - center).astype("<f4")
        attributes = {"POSITION": accessor(local, 5126, "VEC3", 34962, bounds=True)}
        if inst.uv is not None:
            uv = np.column_stack([inst.uv[:, 0], 1.0 - inst.uv[:, 1]]).astype("<f4")
            attributes["TEXCOORD_0"] = accessor(uv, 5126, "VEC2", 34962)
        indices = accessor(inst.faces.astype("<u4").ravel(), 5125, "SCALAR", 34963)
        primitive = {"attributes": attributes, "indices": indices, "material": mat}
        meshes.append({"name": name, "primitives": [primitive]})
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
    if textures:
        doc |= {"images": images, "textures": [{"source": k} for k in range(len(textures))]}
    text = json.dumps(doc, separators=(",", ":")).encode()
    if not binary:
        path.write_bytes(text)
        return
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), _GLB_JSON) + text
    if blob:
        body += struct.pack("<II", len(blob), _GLB_BIN) + blob
    path.write_bytes(struct.pack("<4sII", _GLB_MAGIC, 2, 12 + len(body)) + body)


def _write_obj(house: House, names: list[str], path: Path) -> None:
    materials, material_index, textures = _materials_of(house)
    texture_files = {}
    for k, tex in enumerate(textures):
        data, suffix = _texture_bytes(tex)
        texture_files[id(tex)] = f"{path.stem}_texture{k}{suffix}"
        (path.parent / texture_files[id(tex)]).write_bytes(data)
    mtl = io.StringIO()
    for k, m in enumerate(materials):
        r, g, b_, a = m.base_color
        mtl.write(f"newmtl material{k}\nKd {r:.9g} {g:.9g} {b_:.9g}\nd {a:.9g}\n")
        if m.texture is not None:
            mtl.write(f"map_Kd {texture_files[id(m.texture)]}\n")
    path.with_suffix(".mtl").write_text(mtl.getvalue())

    with open(path, "w") as fh:
        fh.write(f"# sceneforge house {house.id}: objects are named <nyu40 class>__<name>\n")
        fh.write(f"mtllib {path.with_suffix('.mtl').name}\n")
        nv = nt = 0
        for inst, name, mat in zip(house.instances, names, material_index, strict=True):
            fh.write(f"o {name}\nusemtl material{mat}\n")
            np.savetxt(fh, inst.vertices, fmt="v %.17g %.17g %.17g")
            f = inst.faces + nv + 1
            if inst.uv is not None:
                np.savetxt(fh, inst.uv, fmt="vt %.9g %.9g")
                t = inst.faces + nt + 1
                np.savetxt(fh, np.stack([f, t], axis=2).reshape(-1, 6), fmt="f %d/%d %d/%d %d/%d")
                nt += len(inst.uv)
            else:
                np.savetxt(fh, f, fmt="f %d %d %d")
            nv += len(inst.vertices)


def _write_ply(house: House, names: list[str], path: Path) -> None:
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
        rgba = np.clip(np.round(np.asarray(inst.material.base_color) * 255), 0, 255)
        for channel, value in zip(("red", "green", "blue", "alpha"), rgba, strict=True):
            faces[channel] = value
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
