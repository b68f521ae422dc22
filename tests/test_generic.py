"""Generic glTF/GLB, OBJ and PLY scenes: round trips, options, hand-made files with known
answers, trimesh as an independent reference reader, bad input, and the real breakfast room."""

from __future__ import annotations

import base64
import json
import struct

import numpy as np
import PIL.Image
import pytest
import trimesh

from sceneforge.conventions import NYU40_IDS
from sceneforge.errors import HouseError, SceneforgeError
from sceneforge.houses import House, LoadOptions, Material, load, make_instance
from sceneforge.houses.formats.generic import load_house, tagged_name
from sceneforge.testing.generic import write_house

from .conftest import BREAKFAST_ROOM, needs_shared

FORMATS = (".glb", ".gltf", ".obj", ".ply")


def _box(house, name, category, extents, center, material=None, with_uv=False, label=None):
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(center)
    uv = None
    if with_uv:  # any per-vertex uv will do; (x, z) spread over [0, 1]
        lo, hi = b.bounds
        uv = (b.vertices[:, [0, 2]] - lo[[0, 2]]) / (hi - lo)[[0, 2]]
    return make_instance(house, name=name, category=category, label=label or name, room_id=None,
                         vertices=b.vertices, faces=b.faces, material=material, uv=uv)


@pytest.fixture
def house() -> House:
    """Floor, chair, a textured table, an 'otherprop' named like a lamp, a void thing and a
    fireplace (envelope by its label only) whose name says nothing."""
    h = House(id="rt", instances=[])
    texture = PIL.Image.fromarray(np.arange(4 * 4 * 3, dtype=np.uint8).reshape(4, 4, 3) * 5)
    _box(h, "Floor", NYU40_IDS["floor"], (4, 0.1, 4), (0, -0.05, 0), Material((0.5, 0.4, 0.3, 1.0)))
    _box(h, "chair_1", NYU40_IDS["chair"], (0.45, 0.45, 0.45), (0.3, 0.225, 0.7),
         Material((0.9, 0.1, 0.2, 1.0)))
    _box(h, "table", NYU40_IDS["table"], (1.2, 0.05, 0.8), (0, 0.725, 0), Material((1, 1, 1, 1), texture),
         with_uv=True)
    # Named like a lamp but an otherprop: the written tag, not the name pattern, must decide.
    _box(h, "Lamp", NYU40_IDS["otherprop"], (0.1, 0.3, 0.1), (0.2, 0.9, 0.1), Material((0.2, 0.8, 0.4, 0.5)))
    _box(h, "mystery", 0, (0.2, 0.2, 0.2), (-1, 0.1, -1))
    _box(h, "obj__7", NYU40_IDS["otherfurniture"], (1, 1, 0.3), (0, 0.5, -1.9), label="fireplace")
    return h


def _triangles(inst) -> np.ndarray:
    """(m, 9) the instance's triangles by corner coordinates, each rolled to start at its
    smallest corner (winding kept), rows sorted: equal for equal surfaces, whatever the indexing."""
    tri = inst.vertices[inst.faces]
    first = np.array([min(range(3), key=lambda k: tuple(t[k])) for t in tri])
    rolled = np.stack([np.roll(t, -f, axis=0) for t, f in zip(tri, first, strict=True)]).reshape(-1, 9)
    return rolled[np.lexsort(rolled.T[::-1])]


def _image_array(texture) -> np.ndarray:
    return np.asarray(PIL.Image.open(texture) if not isinstance(texture, PIL.Image.Image) else texture)


@pytest.mark.parametrize("suffix", FORMATS)
def test_round_trip_keeps_instances_categories_geometry(house, tmp_path, suffix):
    back = load_house(write_house(house, tmp_path / f"scene{suffix}"), LoadOptions())
    assert [i.name for i in back.instances] == [i.name for i in house.instances]
    assert [i.category for i in back.instances] == [i.category for i in house.instances]
    assert [i.label for i in back.instances] == [i.label for i in house.instances]
    assert [i.envelope for i in back.instances] == [True, False, False, False, False, True]
    assert back.warnings == []  # the void instance is tagged void, not "unknown"
    atol = 1e-6 if suffix in (".glb", ".gltf") else 1e-12  # glTF positions are float32
    # PLY stores sRGB bytes: half a level of sRGB is up to 2.4 / 1.055 × 0.5 / 255 in linear (near white)
    color_tol = 1.14 / 255 if suffix == ".ply" else 1e-6
    for a, b in zip(house.instances, back.instances, strict=True):
        np.testing.assert_allclose(_triangles(b), _triangles(a), atol=atol)
        np.testing.assert_allclose(b.material.base_color, a.material.base_color, atol=color_tol)
    table, back_table = house.instances[2], back.instances[2]
    if suffix == ".ply":  # PLY keeps uv only when every instance has some; no textures
        assert back_table.uv is None and back_table.material.texture is None
        return
    pairs = lambda i: np.unique(np.round(np.hstack([i.vertices, i.uv]), 5), axis=0)  # noqa: E731
    np.testing.assert_allclose(pairs(back_table), pairs(table), atol=1e-5)
    np.testing.assert_array_equal(_image_array(back_table.material.texture),
                                  _image_array(table.material.texture))


@pytest.mark.parametrize("suffix", (".glb", ".ply"))
def test_trimesh_reads_our_files_the_same(house, tmp_path, suffix):
    """trimesh, an independent reader, sees the same triangles in what we write."""
    path = write_house(house, tmp_path / f"scene{suffix}")
    ours = np.concatenate([i.vertices[i.faces] for i in house.instances]).reshape(-1, 9)
    if suffix == ".glb":
        scene = trimesh.load(path, force="scene")
        assert sorted(scene.graph.nodes_geometry) == sorted(tagged_name(i) for i in house.instances)
        theirs = scene.to_geometry()
    else:
        theirs = trimesh.load(path, process=False)
    tri = theirs.vertices[theirs.faces].reshape(-1, 9)
    np.testing.assert_allclose(tri[np.lexsort(tri.T[::-1])], ours[np.lexsort(ours.T[::-1])], atol=1e-6)


def test_writing_is_deterministic_and_load_dispatches(house, tmp_path):
    a = write_house(house, tmp_path / "a" / "scene.glb")
    b = write_house(house, tmp_path / "b" / "scene.glb")
    assert a.read_bytes() == b.read_bytes()
    first, second = load(a, LoadOptions()), load(a, LoadOptions())
    assert first.source_format == "gltf" and first.id == "a"  # scene.glb is a generic name: the folder names it
    for x, y in zip(first.instances, second.instances, strict=True):
        assert x.name == y.name
        np.testing.assert_array_equal(x.vertices, y.vertices)
        np.testing.assert_array_equal(x.faces, y.faces)


def test_scale_and_z_up(house, tmp_path):
    path = write_house(house, tmp_path / "scene.obj")
    back = load_house(path, LoadOptions(scale=2.5, up_axis="z"))
    for a, b in zip(house.instances, back.instances, strict=True):
        x, y, z = a.vertices.T
        expected = 2.5 * np.column_stack([x, z, -y])  # right-handed Z-up → Y-up
        np.testing.assert_allclose(np.unique(b.vertices, axis=0), np.unique(expected, axis=0), atol=1e-12)
    # a rotation, not a reflection: outward normals stay outward
    chair = trimesh.Trimesh(back.instances[1].vertices, back.instances[1].faces, process=False)
    assert chair.volume == pytest.approx(0.45 ** 3 * 2.5 ** 3)
    assert back.instances[0].vertices[:, 1].max() == pytest.approx(2.5 * 2.0)  # floor's 4 m depth now spans y


@pytest.mark.parametrize("options, message", [
    (LoadOptions(scale=0), "scale must be a finite number > 0, got 0"),
    (LoadOptions(scale=-1.0), "scale must be"),
    (LoadOptions(scale=float("nan")), "scale must be"),
    (LoadOptions(up_axis="x"), "up_axis must be 'auto', 'y' or 'z', got 'x'"),
])
def test_bad_options_raise(house, tmp_path, options, message):
    path = write_house(house, tmp_path / "scene.obj")
    with pytest.raises(SceneforgeError, match=message):
        load_house(path, options)


OBJ_UNKNOWN = """o Blob
v 0 0 0
v 1 0 0
v 0 1 0
f 1 2 3
o Gizmo.003
v 0 0 1
v 1 0 1
v 0 1 1
f 4 5 6
"""


def test_name_map_override(tmp_path):
    path = tmp_path / "things.obj"
    path.write_text(OBJ_UNKNOWN)
    default = load_house(path, LoadOptions())
    assert [i.category for i in default.instances] == [0, 0]
    assert "unknown category 'Blob' mapped to void" in default.warnings
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"patterns": [["^blob", "sofa"], ["gizmo", "lamp"]]}))
    custom = load_house(path, LoadOptions(name_map=str(mapping)))
    assert [(i.name, i.label, i.category_name) for i in custom.instances] == [
        ("Blob", "Blob", "sofa"), ("Gizmo.003", "Gizmo", "lamp")]
    with pytest.raises(HouseError, match=r"things.obj: unknown category 'Blob' \(--strict\)"):
        load_house(path, LoadOptions(strict=True))


def test_persons_and_plants_are_dropped(tmp_path):
    path = tmp_path / "people.obj"
    path.write_text(OBJ_UNKNOWN.replace("Blob", "Person").replace("Gizmo.003", "Plant.002")
                    + "o Chair\nv 2 0 0\nv 3 0 0\nv 2 1 0\nf 7 8 9\n")
    h = load_house(path, LoadOptions(strict=True, up_axis="y"))  # a plant has no NYU40 class: dropped, not "unknown"
    assert [i.name for i in h.instances] == ["Chair"]
    assert sum("dropped" in w for w in h.warnings) == 2


def test_obj_groups_polygons_negative_indices_and_materials(tmp_path):
    (tmp_path / "wood.png").write_bytes(b"")  # only its path is kept
    (tmp_path / "room.mtl").write_text(
        "newmtl red\nKd 1 0 0\nd 0.5\nnewmtl wood\nKd 0.2 0.3 0.4\nmap_Kd wood.png\n")
    (tmp_path / "room.obj").write_text(
        "mtllib room.mtl\n"
        "v 0 0 0\nv 2 0 0\nv 2 0 2\nv 0 0 2\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "g floor_1\nusemtl wood\nf 1/1 2/2 3/3 4/4\n"  # a quad: two triangles, area 4
        "v 0 1 0\nv 1 1 0\nv 1 2 0\nv 0 2 0\nv 0.5 2.5 0\n"
        "g cabinet\nusemtl red\nf -5 -4 -3 -2 -1\n"  # a pentagon by relative indices: three triangles
        "usemtl wood\nf 5 6 7\n"  # less wood than red in the cabinet: red wins
    )
    h = load_house(tmp_path / "room.obj", LoadOptions())
    floor, cabinet = h.instances
    assert (floor.name, floor.category_name, len(floor.faces)) == ("floor_1", "floor", 2)
    assert (cabinet.name, cabinet.category_name, len(cabinet.faces)) == ("cabinet", "cabinet", 4)
    assert trimesh.Trimesh(floor.vertices, floor.faces).area == pytest.approx(4.0)
    assert trimesh.Trimesh(cabinet.vertices, cabinet.faces).area == pytest.approx(1.25 + 0.5)
    assert h.warnings == []  # every material kept: a face group each, in order of first use
    assert [m.base_color for m in cabinet.materials] == [(1.0, 0.0, 0.0, 0.5), (0.2, 0.3, 0.4, 1.0)]
    np.testing.assert_array_equal(cabinet.face_material, [0, 0, 0, 1])
    assert floor.material.texture == tmp_path / "wood.png"
    assert floor.material.base_color == (0.2, 0.3, 0.4, 1.0)
    assert cabinet.material.base_color == (1.0, 0.0, 0.0, 0.5) and cabinet.uv is None  # the most area
    np.testing.assert_allclose(floor.uv[np.argsort(floor.vertices[:, 0] * 3 + floor.vertices[:, 2])],
                               [[0, 0], [0, 1], [1, 0], [1, 1]])


def test_obj_nan_vertex_names_the_file(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("o chair\nv 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(HouseError, match="NaN") as e:
        load_house(path, LoadOptions())
    assert e.value.house == "nan" and e.value.file == str(path)


@pytest.mark.parametrize("text, message", [
    ("o chair\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "line 5: face index 9 is outside the 3 vertices"),
    ("o chair\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -7\n", "line 5: face index -3 is outside the 3 vertices"),
    ("o chair\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "line 5: a face needs 3 vertices, got 2"),
    ("o chair\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1  2\n", "line 6: a face needs 3 vertices, got 2"),
    ("o chair\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 x 3\n", "line 6: cannot read face '1 x 3'"),
    ("o chair\nv 0 0 zero\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "line 2: cannot read vertex '0 0 zero'"),
    ("o chair\nv 0 0 0\n", "no faces"),
])
def test_bad_obj_raises_house_error(tmp_path, text, message):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(HouseError, match=message):
        load_house(path, LoadOptions())


PLY_HEADER = """ply
format ascii 1.0
comment instance 7 chair__Chair
element vertex 6
property float x
property float y
property float z
property int {vprop}
element face 2
property list uchar int vertex_indices
property int {fprop}
end_header
"""
PLY_BODY = """0 0 0 7
1 0 0 7
1 1 0 7
0 1 0 3
0 0 1 3
1 0 1 3
4 0 1 2 3 7
3 3 4 5 3
"""


@pytest.mark.parametrize("vprop, fprop", [("w", "object_id"), ("instance", "w")])
def test_ply_instances_from_face_or_vertex_property(tmp_path, vprop, fprop):
    """Face 0 is a quad of instance 7 (named by a comment), face 1 a triangle of instance 3.
    With the property on vertices, a face takes its first corner's instance."""
    path = tmp_path / "blob.ply"
    path.write_text(PLY_HEADER.format(vprop=vprop, fprop=fprop) + PLY_BODY)
    h = load_house(path, LoadOptions())
    assert [(i.name, i.category_name, len(i.faces)) for i in h.instances] == [("blob_3", "void", 1),
                                                                              ("Chair", "chair", 2)]
    quad = h.instances[1]
    assert trimesh.Trimesh(quad.vertices, quad.faces).area == pytest.approx(1.0)


def test_ply_without_instance_property_is_one_instance(tmp_path):
    path = tmp_path / "table.ply"
    path.write_text(PLY_HEADER.format(vprop="w", fprop="w") + PLY_BODY)
    h = load_house(path, LoadOptions())
    assert [(i.name, i.category_name, len(i.faces)) for i in h.instances] == [("table", "table", 3)]


def test_binary_ply_with_mixed_polygons(tmp_path):
    """Lists of varying length in a binary file (trimesh 5.2 refuses these)."""
    header = PLY_HEADER.format(vprop="w", fprop="object_id").replace("ascii", "binary_big_endian")
    verts = np.zeros(6, [("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("w", ">i4")])
    corners = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1]]
    verts["x"], verts["y"], verts["z"] = np.array(corners).T
    body = (verts.tobytes() + struct.pack(">B4ii", 4, 0, 1, 2, 3, 7) + struct.pack(">B3ii", 3, 3, 4, 5, 3))
    path = tmp_path / "mixed.ply"
    path.write_bytes(header.encode() + body)
    h = load_house(path, LoadOptions(up_axis="y"))
    assert [(i.name, len(i.faces)) for i in h.instances] == [("mixed_3", 1), ("Chair", 2)]
    np.testing.assert_array_equal(h.instances[0].vertices, [[0, 1, 0], [0, 0, 1], [1, 0, 1]])
    path.write_bytes(header.encode() + body[:-6])
    with pytest.raises(HouseError, match="PLY is truncated"):
        load_house(path, LoadOptions())


def test_ply_face_past_vertices(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_text(PLY_HEADER.format(vprop="w", fprop="w") + PLY_BODY.replace("3 3 4 5", "3 3 4 6"))
    with pytest.raises(HouseError, match="face index 6 is outside the 6 vertices"):
        load_house(path, LoadOptions())


# --------------------------------------------------------------------------- hand-made glTF


def _pack(*arrays) -> dict:
    """A glTF document skeleton with one data-URI buffer holding ``arrays`` (one accessor each)."""
    blob, views, accessors = b"", [], []
    kinds = {1: "SCALAR", 2: "VEC2", 3: "VEC3"}
    for a in arrays:
        a = np.asarray(a)
        comp, data = (5126, a.astype("<f4")) if a.dtype.kind == "f" else (5125, a.astype("<u4"))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes})
        accessors.append({"bufferView": len(views) - 1, "componentType": comp, "count": len(a),
                          "type": kinds[1 if a.ndim == 1 else a.shape[1]]})
        blob += data.tobytes()
    uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    return {"asset": {"version": "2.0"}, "buffers": [{"uri": uri, "byteLength": len(blob)}],
            "bufferViews": views, "accessors": accessors}


TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
S = np.sqrt(0.5)


def _handmade(tmp_path):
    """A parent (translated, turned 90° about +Y) with a scaled child triangle, a node given
    by a matrix holding a two-primitive mesh (one primitive a strip), a mirrored triangle."""
    strip = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    doc = _pack(TRI, np.array([0, 1, 2]), strip, np.array([0, 1, 2, 3]), TRI * 10)
    doc["materials"] = [{"name": "small", "pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]}},
                        {"name": "big", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 1, 1]}}]
    doc["meshes"] = [
        {"name": "tri", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]},
        {"name": "combo", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0},
                                         {"attributes": {"POSITION": 2}, "indices": 3, "mode": 5},
                                         {"attributes": {"POSITION": 4}, "material": 1}]},
    ]
    matrix = np.eye(4)
    matrix[:3, 3] = (0, 0, -5)
    doc["nodes"] = [
        {"name": "Parent", "translation": [1, 2, 3], "rotation": [0, S, 0, S], "children": [1]},
        {"name": "Chair.004", "mesh": 0, "scale": [2, 2, 2]},
        {"name": "TableTop", "mesh": 1, "matrix": matrix.T.ravel().tolist()},
        {"name": "Mirror", "mesh": 0, "scale": [-1, 1, 1]},
        {"name": "Camera", "camera": 0},
    ]
    doc["cameras"] = [{"type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.1}}]
    doc["scenes"] = [{"nodes": [0, 2, 3, 4]}]
    doc["scene"] = 0
    path = tmp_path / "hand.gltf"
    path.write_text(json.dumps(doc))
    return path, doc


def test_handmade_gltf_transforms_order_and_merging(tmp_path):
    path, _ = _handmade(tmp_path)
    h = load_house(path, LoadOptions())
    assert [(i.name, i.category_name) for i in h.instances] == [
        ("Chair.004", "chair"), ("TableTop", "table"), ("Mirror", "mirror")]
    chair, table, mirror = h.instances
    # child scale 2, then 90° about +Y ((x, y, z) → (z, y, -x)), then the parent's translation
    np.testing.assert_allclose(chair.vertices, [[1, 2, 3], [1, 2, 1], [1, 4, 3]], atol=1e-6)
    # three primitives merged: 1 triangle + 2 strip triangles + 1 big triangle, at z = -5
    assert len(table.faces) == 4 and np.allclose(table.vertices[:, 2], -5)
    normals = trimesh.Trimesh(table.vertices, table.faces, process=False).face_normals
    np.testing.assert_allclose(normals, [[0, 0, 1]] * 4, atol=1e-9)  # strip winding alternates correctly
    assert table.material.base_color == (0.0, 0.0, 1.0, 1.0)  # of the primitive with the most area
    # every primitive keeps its material: red, glTF's default white, blue
    assert [m.base_color for m in table.materials] == [(1.0, 0.0, 0.0, 1.0), (1.0, 1.0, 1.0, 1.0), (0.0, 0.0, 1.0, 1.0)]
    np.testing.assert_array_equal(table.face_material, [0, 1, 1, 2])
    assert not any("materials" in w for w in h.warnings)
    # a mirroring node flips the winding so that the normal still follows the surface
    np.testing.assert_allclose(mirror.vertices, TRI * [-1, 1, 1])
    np.testing.assert_allclose(trimesh.Trimesh(mirror.vertices, mirror.faces).face_normals, [[0, 0, 1]])


def test_handmade_gltf_agrees_with_trimesh(tmp_path):
    path, _ = _handmade(tmp_path)
    ours = np.concatenate([i.vertices for i in load_house(path, LoadOptions()).instances])
    theirs = trimesh.load(path, force="scene").to_geometry().vertices
    np.testing.assert_allclose(np.unique(ours.round(6), axis=0), np.unique(theirs.round(6), axis=0),
                               atol=1e-6)


def test_gltf_index_past_vertices(tmp_path):
    doc = _pack(TRI, np.array([0, 1, 5]))
    doc |= {"meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "nodes": [{"name": "chair", "mesh": 0}], "scenes": [{"nodes": [0]}]}
    path = tmp_path / "bad.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(HouseError, match="primitive 0: index 5 is outside its 3 vertices"):
        load_house(path, LoadOptions())


def _textured(tmp_path, texture: dict, present: list[str]):
    for name in present:
        PIL.Image.new("RGB", (2, 2)).save(tmp_path / name)
    doc = _pack(TRI, np.array([0, 1, 2]), np.array([[0, 0], [1, 0], [0, 1]], float))
    doc |= {"images": [{"uri": "wood.jpg"}, {"uri": "wood.dds", "mimeType": "image/vnd-ms.dds"}],
            "textures": [texture],
            "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1,
                                        "material": 0}]}],
            "nodes": [{"name": "table", "mesh": 0}], "scenes": [{"nodes": [0]}],
            "extensionsUsed": ["MSFT_texture_dds"]}
    path = tmp_path / "tex.gltf"
    path.write_text(json.dumps(doc))
    return load_house(path, LoadOptions())


DDS = {"extensions": {"MSFT_texture_dds": {"source": 1}}}


@pytest.mark.parametrize("texture, present, expected, warning", [
    ({"source": 0} | DDS, ["wood.jpg"], "wood.jpg", None),
    ({"source": 0} | DDS, ["wood.png"], "wood.png", "texture wood.jpg is missing, using wood.png"),
    (DDS, ["wood.jpg"], "wood.jpg", "texture wood.dds is missing, using wood.jpg"),
    (DDS, [], None, "textures[0]: no readable image (wood.dds); no texture"),
])
def test_missing_texture_falls_back_to_twin_or_none(tmp_path, texture, present, expected, warning):
    h = _textured(tmp_path, texture, present)
    table = h.instances[0]
    assert table.material.texture == (tmp_path / expected if expected else None)
    assert h.warnings == ([warning] if warning else [])
    np.testing.assert_allclose(table.uv, [[0, 1], [1, 1], [0, 0]])  # glTF v flipped to OBJ/OpenGL's


def _corruptions(glb: bytes):
    yield "cut to 10 bytes", glb[:10], "truncated"
    yield "cut in half", glb[: len(glb) // 2], "truncated"
    yield "last bytes missing", glb[:-4], "truncated"
    yield "bad JSON", glb[:20] + b"#" * 8 + glb[28:], "JSON does not parse"
    yield "version 1", glb[:4] + struct.pack("<I", 1) + glb[8:], "GLB version 1"
    yield "not glTF at all", b"\x00\x01garbage" * 10, "not a glTF file"
    length = struct.unpack_from("<I", glb, 12)[0]  # JSON chunk length → bin chunk past the end
    yield "chunk overruns", glb[:12] + struct.pack("<I", length + 1000) + glb[16:], "truncated"


def test_corrupt_glb_raises_one_line_house_error(house, tmp_path):
    glb = write_house(house, tmp_path / "good.glb").read_bytes()
    for what, data, message in _corruptions(glb):
        path = tmp_path / "broken.glb"
        path.write_bytes(data)
        with pytest.raises(HouseError, match=message) as e:
            load_house(path, LoadOptions())
        assert "\n" not in str(e.value) and "broken.glb" in str(e.value), what


def test_gltf_with_missing_buffer_names_it(house, tmp_path):
    path = write_house(house, tmp_path / "scene.gltf")
    (tmp_path / "scene.bin").unlink()
    with pytest.raises(HouseError, match=r"scene.bin: cannot read buffer 'scene.bin'"):
        load_house(path, LoadOptions())


# --------------------------------------------------------------------------- the real scene


@needs_shared(BREAKFAST_ROOM)
def test_breakfast_room_categories():
    h = load_house(BREAKFAST_ROOM, LoadOptions())
    # "Walls" holds the walls and the ceiling: the bundled map sends it to "shell", split in two
    parts = {i.name: i.category_name for i in h.instances if i.label == "Walls"}
    assert parts == {"Walls/wall": "wall", "Walls/ceiling": "ceiling"}
    ceiling = next(i for i in h.instances if i.name == "Walls/ceiling")
    assert np.ptp(ceiling.vertices[:, 1]) < 1e-6 and ceiling.vertices[0, 1] == pytest.approx(3.0, abs=5e-3)
    assert [r.id for r in h.rooms] == ["room_0"] and {i.room_id for i in h.instances} == {"room_0"}
    expected = {"Walls": "wall", "Skirting": "wall", "Floor": "floor", "Blind": "blinds",
                "Picture": "picture",
                "Chair": "chair", "ChairLegs": "chair", "TableTop": "table", "TableLegs": "table",
                "Light": "lamp", "LightShade": "lamp", "TeaPot": "otherprop", "TeaCup": "otherprop",
                "Spoon": "otherprop"}
    assert {i.label: i.category_name for i in h.instances if i.name != "Walls/ceiling"} == expected
    counts = {label: sum(i.label == label for i in h.instances) for label in expected}
    assert counts == {"Walls": 2, "Skirting": 2, "Floor": 1, "Blind": 1, "Picture": 1, "Chair": 6,
                      "ChairLegs": 6, "TableTop": 1, "TableLegs": 1, "Light": 2, "LightShade": 2,
                      "TeaPot": 1, "TeaCup": 3, "Spoon": 3}
    lo, hi = h.bounds()
    np.testing.assert_allclose(hi - lo, [3.72, 3.00, 4.65], atol=0.01)
    assert abs(lo[1]) < 1e-3  # floor at y = 0
    textured = {i.name: i.material.texture.name for i in h.instances if i.material.texture is not None}
    assert textured == {"TableTop": "marble.jpg", "Floor": "tiles.png", "Picture": "picture3.jpg"}
    reference = trimesh.load(BREAKFAST_ROOM, force="scene")
    assert h.triangle_count == sum(len(g.faces) for g in reference.dump())
    np.testing.assert_allclose(h.bounds(), reference.bounds, atol=1e-6)


def test_written_names_carry_class_and_label(house, tmp_path):
    text = write_house(house, tmp_path / "scene.obj").read_text()
    objects = [line[2:] for line in text.splitlines() if line.startswith("o ")]
    assert objects == ["floor__Floor", "chair__chair_1__chair_1", "table__table", "otherprop__Lamp",
                       "void__mystery", "otherfurniture__fireplace__obj__7"]
