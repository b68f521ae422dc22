"""glTF 2.0 scenes (``.gltf``/``.glb``), read into meshes.

Reading: one mesh per node that has triangles, in depth-first node order, node transforms
applied (a mirroring transform reverses the winding); the primitives of a node's mesh are
merged into one mesh whose face groups keep each primitive's material (base-colour factor
× base-colour texture, with the texture's sampler wrapping; one group per distinct
material, in primitive order); ``COLOR_0`` vertex colours (linear) multiply it. Triangle
lists, strips and fans are read; points and lines are skipped.

glTF is read here rather than with ``trimesh.load``: trimesh renames the primitives of a
multi-primitive mesh with random suffixes and keeps textures only as decoded images, while
sceneforge needs the glTF node names, a deterministic order and the image file paths (with a
fallback when an image is missing, e.g. the ``.dds`` files of ``MSFT_texture_dds``).

glTF's ``v`` runs down the image; sceneforge's uv follow OBJ/OpenGL (``v = 0`` at the
bottom row), so ``v`` is flipped on the way in (and out, in :mod:`sceneforge.testing.gltf`).
A merged mesh has uv when any of its primitives has ``TEXCOORD_0``; the corners of the
others get (0, 0) and their materials show without a texture (nothing places one there).
"""

from __future__ import annotations

import base64
import io
import json
import struct
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..model import Material
from .meshio import (
    Mesh,
    MeshFileError,
    Warn,
    fan,
    find_image,
    ignore,
    place,
    quaternion_matrix,
)

__all__ = ["read_gltf"]

# --------------------------------------------------------------------------- glTF reading

#: a GLB file's magic and its JSON and BIN chunk types
GLB_MAGIC, GLB_JSON, GLB_BIN = b"glTF", 0x4E4F534A, 0x004E4942
_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6
_WRAPS = {10497: "repeat", 33071: "clamp", 33648: "mirror"}
_UNSUPPORTED_REQUIRED = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression"}


class _Gltf:
    """The JSON of a glTF 2.0 file and its buffers, with accessor and material decoding."""

    def __init__(self, path: Path, warn: Warn):
        self.path, self.warn = path, warn
        try:
            data = path.read_bytes()
        except OSError as e:
            raise MeshFileError(f"cannot read: {e.strerror or e}") from None
        self.bin_chunk: bytes | None = None
        if data[:4] == GLB_MAGIC:
            text = self._split_glb(data)
        else:
            text = data
        try:
            self.doc = json.loads(text)
        except (UnicodeDecodeError, ValueError) as e:
            raise MeshFileError(f"not a glTF file: its JSON does not parse ({e})") from None
        version = self.doc.get("asset", {}).get("version", "") if isinstance(self.doc, dict) else ""
        if not str(version).startswith("2"):
            raise MeshFileError("not a glTF 2.0 file (asset.version is not 2.x)")
        required = set(self.doc.get("extensionsRequired", [])) & _UNSUPPORTED_REQUIRED
        if required:
            raise MeshFileError(f"needs {', '.join(sorted(required))}, which sceneforge cannot decode; "
                                "export the scene without mesh compression")
        self.buffers: dict[int, bytes] = {}
        self.materials: dict[int | None, Material] = {}
        self.images: dict[int, object] = {}

    def _split_glb(self, data: bytes) -> bytes:
        if len(data) < 12:
            raise MeshFileError(f"GLB is truncated: {len(data)} bytes, not even a header")
        _, version, length = struct.unpack_from("<4sII", data)
        if version != 2:
            raise MeshFileError(f"GLB version {version} is not supported (only glTF 2.0)")
        if length > len(data):
            raise MeshFileError(f"GLB is truncated: its header says {length} bytes, the file has {len(data)}")
        json_chunk, offset = None, 12
        while offset + 8 <= length:
            size, kind = struct.unpack_from("<II", data, offset)
            offset += 8
            if offset + size > length:
                raise MeshFileError(
                    f"GLB is truncated: a chunk of {size} bytes at {offset} ends past {length}")
            chunk = data[offset:offset + size]
            offset += size
            if kind == GLB_JSON and json_chunk is None:
                json_chunk = chunk
            elif kind == GLB_BIN and self.bin_chunk is None:
                self.bin_chunk = chunk
        if json_chunk is None:
            raise MeshFileError("GLB has no JSON chunk")
        return json_chunk

    def item(self, kind: str, index) -> dict:
        """``doc[kind][index]``, or a HouseError saying which reference is broken."""
        items = self.doc.get(kind, [])
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise MeshFileError(f"{kind}[{index}] is referenced but the file has {len(items)} {kind}")
        return items[index]

    def buffer(self, index: int) -> bytes:
        if index not in self.buffers:
            spec = self.item("buffers", index)
            uri = spec.get("uri")
            if uri is None:
                data = self.bin_chunk
                if data is None:
                    raise MeshFileError(f"buffers[{index}] has no uri and the file has no GLB binary chunk")
            elif uri.startswith("data:"):
                data = self._data_uri(uri, f"buffers[{index}]")
            else:
                file = self.path.parent / unquote(uri)
                try:
                    data = file.read_bytes()
                except OSError as e:
                    raise MeshFileError(f"cannot read buffer {uri!r}: {e.strerror or e}", file) from None
            if len(data) < spec.get("byteLength", 0):
                raise MeshFileError(
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
            raise MeshFileError(f"{what}: bad data URI ({e})") from None

    def view_bytes(self, index: int) -> bytes:
        view = self.item("bufferViews", index)
        data, start = self.buffer(view["buffer"]), view.get("byteOffset", 0)
        if start + view["byteLength"] > len(data):
            raise MeshFileError(f"bufferViews[{index}] ends at byte {start + view['byteLength']} "
                               f"but its buffer has {len(data)} (truncated file?)")
        return data[start:start + view["byteLength"]]

    def _view_array(self, view_index: int, offset: int, dtype: np.dtype, count: int, width: int,
                    stride: int | None = None) -> np.ndarray:
        data = self.view_bytes(view_index)
        stride = stride or dtype.itemsize * width
        end = offset + (count - 1) * stride + dtype.itemsize * width if count else offset
        if end > len(data):
            raise MeshFileError(
                f"an accessor reads {end} bytes of bufferViews[{view_index}], which has {len(data)}")
        return np.ndarray((count, width), dtype, buffer=data, offset=offset,
                          strides=(stride, dtype.itemsize)).copy()

    def accessor(self, index: int) -> np.ndarray:
        """(count, width) array of accessor ``index`` (sparse and normalised values applied)."""
        acc = self.item("accessors", index)
        if acc.get("componentType") not in _COMPONENTS or acc.get("type") not in _WIDTHS:
            raise MeshFileError(
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
                raise MeshFileError(
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
                strength = spec.get("extensions", {}).get("KHR_materials_emissive_strength", {})
                self.materials[index] = Material(
                    base_color=tuple(float(c) for c in color),
                    texture=self.texture(tex["index"]) if tex else None,
                    wrap=self.wrap(tex["index"]) if tex else ("repeat", "repeat"),
                    emission=tuple(float(c) * float(strength.get("emissiveStrength", 1.0))
                                   for c in spec.get("emissiveFactor") or (0.0, 0.0, 0.0)),
                )
        return self.materials[index]

    def wrap(self, index: int) -> tuple[str, str]:
        """(s, t) wrapping of texture ``index`` from its sampler (glTF's default: repeat)."""
        sampler = self.item("textures", index).get("sampler")
        spec = self.item("samplers", sampler) if sampler is not None else {}
        return tuple(_WRAPS.get(spec.get(k, 10497), "repeat") for k in ("wrapS", "wrapT"))

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
        self.warn(f"textures[{index}]: no readable image ({', '.join(tried) or 'none given'}); no texture")
        return None

    def image(self, index: int):
        if index not in self.images:
            spec = self.item("images", index)
            uri = spec.get("uri")
            if "bufferView" in spec:
                image = _decode_image(self.view_bytes(spec["bufferView"]), f"images[{index}]", self.warn)
            elif uri is None:
                image = None
            elif uri.startswith("data:"):
                image = _decode_image(self._data_uri(uri, f"images[{index}]"), f"images[{index}]", self.warn)
            else:
                image = find_image(self.path.parent / unquote(uri), self.warn)
            self.images[index] = image
        return self.images[index]

    def primitive(self, mesh_name: str, k: int, prim: dict):
        """Vertices (n, 3) float64, faces (m, 3) int64, uv (n, 2) or None and linear RGBA
        vertex colours (n, 4) or None of one primitive."""
        mode = prim.get("mode", _TRIANGLES)
        if mode not in (_TRIANGLES, _STRIP, _FAN):
            return None
        if "POSITION" not in prim.get("attributes", {}):
            raise MeshFileError(f"mesh {mesh_name!r} primitive {k} has no POSITION attribute")
        vertices = self.accessor(prim["attributes"]["POSITION"]).astype(np.float64)
        if len(vertices) and vertices.shape[1] != 3:
            raise MeshFileError(f"mesh {mesh_name!r} primitive {k}: POSITION is not VEC3")
        if "indices" in prim:
            idx = self.accessor(prim["indices"]).ravel().astype(np.int64)
        else:
            idx = np.arange(len(vertices), dtype=np.int64)
        if len(idx) and (idx.max() >= len(vertices) or idx.min() < 0):
            raise MeshFileError(f"mesh {mesh_name!r} primitive {k}: index {int(idx.max())} is outside "
                               f"its {len(vertices)} vertices")
        if mode == _TRIANGLES:
            if len(idx) % 3:
                raise MeshFileError(
                    f"mesh {mesh_name!r} primitive {k}: {len(idx)} indices is not a multiple of 3")
            faces = idx.reshape(-1, 3)
        elif len(idx) < 3:
            faces = np.zeros((0, 3), np.int64)
        elif mode == _FAN:
            faces = fan(idx[None])
        else:
            faces = np.stack([idx[:-2], idx[1:-1], idx[2:]], axis=1)
            faces[1::2, :2] = faces[1::2, 1::-1]  # odd triangles of a strip are wound the other way
        uv = None
        if "TEXCOORD_0" in prim["attributes"]:
            uv = self.accessor(prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
            uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]) if uv.shape == (len(vertices), 2) else None
        colors = None
        if "COLOR_0" in prim["attributes"]:
            colors = self.accessor(prim["attributes"]["COLOR_0"]).astype(np.float64)
            if colors.shape == (len(vertices), 3):
                colors = np.column_stack([colors, np.ones(len(colors))])
            if colors.shape != (len(vertices), 4):
                colors = None
        return vertices, faces, uv, colors

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
                raise MeshFileError(f"nodes[{index}] is its own ancestor (cyclic node hierarchy)")
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
    m = np.eye(4)
    m[:3, :3] = quaternion_matrix(node.get("rotation", (0, 0, 0, 1))) * np.asarray(
        node.get("scale", (1, 1, 1)), dtype=np.float64)
    m[:3, 3] = node.get("translation", (0, 0, 0))
    return m


def _decode_image(data: bytes, what: str, warn: Warn):
    """A PIL image from encoded bytes, or None (with a warning) when they do not decode."""
    import PIL.Image

    try:
        image = PIL.Image.open(io.BytesIO(data))
        image.load()
    except (OSError, ValueError, PIL.Image.DecompressionBombError) as e:
        warn(f"{what} cannot be decoded ({e}); no texture")
        return None
    return image


def read_gltf(path: Path, warn: Warn = ignore) -> Iterator[Mesh]:
    """Yield the meshes of a glTF/GLB scene (module docs), named after their nodes.

    Raises :class:`MeshFileError` for anything unreadable; ``warn`` receives what was
    tolerated (a missing texture image).
    """
    try:
        gltf = _Gltf(Path(path), warn)
        for node_name, mesh_name, world, mesh in gltf.node_meshes():
            parts = [(p, gltf.primitive(mesh_name, k, p)) for k, p in enumerate(mesh.get("primitives", []))]
            parts = [(p, g) for p, g in parts if g is not None and len(g[1])]
            if not parts:
                continue
            offsets = np.cumsum([0] + [len(g[0]) for _, g in parts])
            vertices = np.concatenate([g[0] for _, g in parts])
            faces = np.concatenate([g[1] + o for (_, g), o in zip(parts, offsets[:-1], strict=True)])
            # uv when any primitive has them (the others' corners (0, 0)): a primitive without
            # TEXCOORD_0 does not take the other primitives' textures away (issue 40); its own
            # material shows without its texture, which nothing places
            uv = None
            if any(g[2] is not None for _, g in parts):
                uv = np.concatenate([g[2] if g[2] is not None else np.zeros((len(g[0]), 2)) for _, g in parts])
            colors = None
            if any(g[3] is not None for _, g in parts):
                colors = np.concatenate([g[3] if g[3] is not None else np.ones((len(g[0]), 4)) for _, g in parts])

            def key_of(p, g, textured=uv is not None):
                return p.get("material"), textured and g[2] is None

            keys = list(dict.fromkeys(key_of(p, g) for p, g in parts))
            materials = tuple(_untextured(gltf.material(key)) if bare else gltf.material(key) for key, bare in keys)
            face_material = np.concatenate([np.full(len(g[1]), keys.index(key_of(p, g)), np.int32)
                                            for p, g in parts])
            vertices, faces = place(vertices, faces, world)
            yield Mesh(vertices, faces, uv, materials[0] if len(materials) == 1 else materials, node_name,
                       (mesh_name,), face_material if len(materials) > 1 else None, colors)
    except MeshFileError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        raise MeshFileError(f"malformed glTF ({type(e).__name__}: {e})") from None


def _untextured(material: Material) -> Material:
    """``material`` without its texture (faces without texture coordinates)."""
    return material if material.texture is None else replace(material, texture=None)
