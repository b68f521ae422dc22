"""Every material of every mesh: face groups through the model, the native format and the
OBJ, glTF and PLY writers and readers; old one-material files unchanged."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sceneforge import schemas
from sceneforge.errors import HouseError
from sceneforge.houses import BUNDLED_TOY, House, LoadOptions, Material, discover, load, make_instance
from sceneforge.houses.formats.generic import load_house as load_generic
from sceneforge.houses.formats.native import write_house
from sceneforge.testing.generic import write_house as write_generic

from .conftest import box_instance, box_room


def two_material_house(texture=None) -> House:
    """A room with a box whose top faces are red (textured, clamped) and the rest blue."""
    house = box_room("two", size=4.0, height=3.0)
    box = box_instance(house, "table", 7, (0.6, 0.5, 0.4), (0.3, 0.25, 0.7))
    normals = np.cross(*(box.vertices[box.faces[:, k]] - box.vertices[box.faces[:, 0]] for k in (1, 2)))
    box.materials = (Material((1.0, 0.0, 0.0, 1.0), texture, ("clamp", "clamp")), Material((0.0, 0.0, 1.0, 0.5)))
    box.face_material = (normals[:, 1] <= 0).astype(np.int32)
    box.uv = (box.vertices[:, [0, 2]] - box.vertices[:, [0, 2]].min(0)).astype(np.float32)
    return house


def test_make_instance_keeps_groups_drops_unused_and_checks():
    house = House(id="h", instances=[])
    quad = dict(vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 2, 0]], category=0, label="x",
                room_id=None)
    a, b, c = (Material((k / 3, 0, 0, 1)) for k in range(3))
    # the third face is degenerate: dropped, and material c with it
    inst = make_instance(house, name="q", faces=[[0, 1, 2], [0, 2, 3], [4, 4, 4]], material=[a, b, c],
                         face_material=[1, 0, 2], **quad)
    assert inst.materials == (a, b) and inst.face_material.tolist() == [1, 0]
    one = make_instance(house, name="q1", faces=[[0, 1, 2]], material=[a, b], face_material=[1], **quad)
    assert one.materials == (b,) and one.face_material is None and one.material == b
    with pytest.raises(HouseError, match="face materials must be 1 indices into its 2 materials"):
        make_instance(house, name="bad", faces=[[0, 1, 2]], material=[a, b], face_material=[2], **quad)
    with pytest.raises(HouseError, match="2 materials but no face materials"):
        make_instance(house, name="bad", faces=[[0, 1, 2]], material=[a, b], **quad)


def test_material_is_the_one_covering_the_most_area_and_setting_it_sets_all():
    house = two_material_house()
    box = house.instances[-1]
    assert box.material.base_color == (0.0, 0.0, 1.0, 0.5)  # sides and bottom: 5 of 6 box faces
    box.material = Material((0.5, 0.5, 0.5, 1.0))
    assert box.materials == (Material((0.5, 0.5, 0.5, 1.0)),) and box.face_material is None


def test_native_round_trip_keeps_groups_wrapping_and_vertex_colours(tmp_path):
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(tmp_path / "t.png")
    house = two_material_house(tmp_path / "t.png")
    box = house.instances[-1]
    box.colors = np.linspace(0, 1, 4 * len(box.vertices), dtype=np.float32).reshape(-1, 4)
    path = write_house(house, tmp_path / "out")
    doc = json.loads(path.read_text())
    assert schemas.errors(doc, "house") == []
    record = doc["instances"][-1]
    assert "material" not in record and len(record["materials"]) == 2
    assert record["materials"][0]["wrap"] == ["clamp", "clamp"]
    assert "materials" not in doc["instances"][0] and "wrap" not in doc["instances"][0]["material"]
    back = load(tmp_path / "out").instances[-1]
    np.testing.assert_array_equal(back.face_material, box.face_material)
    np.testing.assert_array_equal(back.colors, box.colors)
    assert [m.base_color for m in back.materials] == [m.base_color for m in box.materials]
    assert [m.wrap for m in back.materials] == [("clamp", "clamp"), ("repeat", "repeat")]
    assert back.materials[0].texture.read_bytes() == (tmp_path / "t.png").read_bytes()


def test_bundled_toy_houses_still_load_and_write_the_same_bytes(tmp_path):
    """The bundled houses (one material per instance) load as before and are written back byte
    for byte as the files they came from: the one-material layout is unchanged."""
    for source in discover(BUNDLED_TOY)[:2]:
        house = load(source)
        assert all(i.face_material is None and len(i.materials) == 1 for i in house.instances)
        path = write_house(house, tmp_path / house.id)
        original = source.path / "house.json" if source.path.is_dir() else source.path
        assert json.loads(path.read_text())["instances"] == json.loads(original.read_text())["instances"]


@pytest.mark.parametrize("suffix", [".obj", ".gltf", ".glb", ".ply"])
def test_writers_and_readers_keep_face_groups(suffix, tmp_path):
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(tmp_path / "t.png")
    house = two_material_house(None if suffix == ".ply" else tmp_path / "t.png")
    box = house.instances[-1]
    back = load_generic(write_generic(house, tmp_path / f"scene{suffix}"), LoadOptions())
    (table,) = [i for i in back.instances if i.category_name == "table"]
    assert len(table.materials) == 2 and not any("materials" in w for w in back.warnings)
    # every face has its material back, faces found by their centres (glTF writes a primitive
    # per material, so faces come back grouped; materials come back in order of first use)
    def per_face(inst):
        centres = np.round(inst.vertices[inst.faces].mean(1), 4)
        return {tuple(c): (tuple(np.round(np.array(inst.materials[g].base_color) * 255)), inst.materials[g].wrap,
                           inst.materials[g].texture is not None)
                for c, g in zip(centres, inst.face_materials(), strict=True)}

    got, want = per_face(table), per_face(box)
    if suffix == ".ply":  # no textures, no wrapping
        got, want = ({c: v[0] for c, v in d.items()} for d in (got, want))
    assert got == want


def test_ply_vertex_colours_become_the_instance_colours(tmp_path):
    path = tmp_path / "c.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\n"
                    "property list uchar int vertex_indices\nend_header\n"
                    "0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n3 0 1 2\n")
    (inst,) = load_generic(path, LoadOptions(up_axis="y")).instances  # one triangle: no up axis to tell
    np.testing.assert_allclose(inst.colors, [[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1]])
    assert inst.material.base_color == (1.0, 1.0, 1.0, 1.0)


@pytest.mark.parametrize("element", ["vertex", "face"])
def test_ply_colours_are_srgb_decoded_to_linear(element, tmp_path):
    """PLY colours are display (sRGB) values: byte 128 is linear 0.2158, not 0.502; alpha stays linear."""
    colour = " 128 64 255 128"
    vertex_props = "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
    path = tmp_path / "c.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    + (vertex_props if element == "vertex" else "") + "element face 1\n"
                    "property list uchar int vertex_indices\n" + (vertex_props if element == "face" else "")
                    + "end_header\n" + "".join(f"{v}{colour if element == 'vertex' else ''}\n"
                                                for v in ("0 0 0", "1 0 0", "0 1 0"))
                    + "3 0 1 2" + (colour if element == "face" else "") + "\n")
    (inst,) = load_generic(path, LoadOptions(up_axis="y")).instances  # one triangle: no up axis to tell
    expected = [((128 / 255 + 0.055) / 1.055) ** 2.4, ((64 / 255 + 0.055) / 1.055) ** 2.4, 1.0, 128 / 255]
    got = inst.colors[0] if element == "vertex" else inst.material.base_color
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    assert abs(expected[0] - 0.2158) < 1e-4


def _gltf_two_primitives(tmp_path, second_material: int) -> "Path":
    """A glTF mesh of two quads: primitive 0 with TEXCOORD_0 and material 0 (a texture),
    primitive 1 without texture coordinates and material ``second_material``."""
    import base64
    import io

    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = quad.tobytes() + uv.tobytes() + idx.tobytes() + (quad + [0, 0, 1]).astype(np.float32).tobytes()
    png = io.BytesIO()
    Image.fromarray(np.full((2, 2, 3), (200, 100, 50), np.uint8)).save(png, format="PNG")
    views = [(0, 48), (48, 32), (80, 12), (92, 48)]
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "table", "mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0},
                                   {"attributes": {"POSITION": 3}, "indices": 2, "material": second_material}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
                      {"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.3, 0.4, 1.0]}}],
        "textures": [{"source": 0}],
        "images": [{"uri": "data:image/png;base64," + base64.b64encode(png.getvalue()).decode()}],
        "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": n} for o, n in views],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 1], "max": [1, 1, 1]},
        ],
    }
    path = tmp_path / "scene.gltf"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("second", [1, 0])
def test_gltf_primitive_without_uv_keeps_the_others_textures(tmp_path, second):
    """One primitive without TEXCOORD_0 no longer takes the mesh's uv (and with them every
    texture of it) away (issue 40); its own material shows without a texture, even one it
    shares with a primitive that has uv."""
    from sceneforge.houses.formats.gltf import read_gltf

    (mesh,) = read_gltf(_gltf_two_primitives(tmp_path, second))
    assert mesh.uv is not None and len(mesh.uv) == 8
    np.testing.assert_array_equal(mesh.uv[4:], 0)
    textured, other = mesh.materials
    assert textured.texture is not None
    assert other.texture is None
    np.testing.assert_array_equal(mesh.face_material, [0, 0, 1, 1])
    if second == 1:
        assert other.base_color == (0.2, 0.3, 0.4, 1.0)


def test_front3d_merged_pieces_keep_uv_of_the_pieces_that_have_them():
    """3D-FRONT pieces merged into one instance (a room's wall pieces): uv where any piece has
    them, the others' corners (0, 0) and their textures dropped (issue 40)."""
    from pathlib import Path as _Path

    from sceneforge.houses.formats.front3d import _merge, _Piece

    wood = Material((1.0, 1.0, 1.0, 1.0), texture=_Path("wood.png"))
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    a = _Piece("wall", 1, "wall", "r", tri, np.array([[0, 1, 2]]), np.array([[0, 0], [1, 0], [0, 1]], float),
               wood, _Path("x.json"), group=("r", "w"))
    b = _Piece("wall", 1, "wall", "r", tri + 2, np.array([[0, 1, 2]]), None, wood, _Path("x.json"), group=("r", "w"))
    merged = _merge([a, b])
    assert merged.uv is not None and len(merged.uv) == 6
    np.testing.assert_array_equal(merged.uv[3:], 0)
    assert merged.material[0].texture == _Path("wood.png") and merged.material[1].texture is None
    np.testing.assert_array_equal(merged.face_material, [0, 1])
