"""Materials and textures as the mesh writers put them into files."""

from __future__ import annotations

import io
from pathlib import Path

from ..houses.formats.meshio import Mesh
from ..houses.model import Instance, Material


def distinct_materials(materials: list[Material | None]) -> tuple[list[Material], list[int], list]:
    """Equal materials (same colour, texture object, wrapping and emission) written once.

    Returns the distinct materials, the index of each input among them (-1 for None) and the
    distinct textures in order of first use.
    """
    keys: dict = {}
    textures: dict[int, object] = {}
    index = []
    for m in materials:
        if m is None:
            index.append(-1)
            continue
        if m.texture is not None:
            textures.setdefault(id(m.texture), m.texture)
        key = (tuple(float(c) for c in m.base_color), id(m.texture) if m.texture is not None else None,
               tuple(m.wrap), tuple(float(c) for c in m.emission))
        index.append(keys.setdefault(key, len(keys)))
    distinct = [Material(base_color=color, texture=textures.get(tex_id), wrap=wrap, emission=emission)
                for color, tex_id, wrap, emission in keys]
    return distinct, index, list(textures.values())


def mesh_of(inst: Instance, vertices=None, name: str = "") -> Mesh:
    """The :class:`Mesh` a writer writes for ``inst`` (its vertices or ``vertices`` (n, 3)):
    its uv and every face group's material."""
    material = inst.materials if inst.face_material is not None else inst.materials[0]
    return Mesh(inst.vertices if vertices is None else vertices, inst.faces, inst.uv, material, name,
                face_material=inst.face_material)


def texture_suffix(texture) -> str:
    """The file suffix a texture keeps when written: its file's, ``.png`` for an image in memory."""
    return Path(texture).suffix.lower() if isinstance(texture, (str, Path)) else ".png"


def encode_texture(texture, suffix: str) -> bytes:
    """A :class:`Material` texture (an image file path or a PIL image) as an image file of type
    ``suffix``: a file of that type as it is, anything else re-encoded."""
    if isinstance(texture, (str, Path)) and texture_suffix(texture) == suffix.lower():
        return Path(texture).read_bytes()
    from PIL import Image

    image = Image.open(texture) if isinstance(texture, (str, Path)) else texture
    buf = io.BytesIO()
    image.save(buf, format=Image.registered_extensions()[suffix.lower()])
    return buf.getvalue()


def save_texture(texture, dst: Path) -> None:
    """Write a :class:`Material` texture to ``dst`` as the image type its suffix names."""
    dst.write_bytes(encode_texture(texture, dst.suffix))
