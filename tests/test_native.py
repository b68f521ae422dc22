"""sceneforge's own house format: round trip, schema, determinism and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sceneforge import schemas
from sceneforge.errors import HouseError, SceneforgeError, UnknownFormatError
from sceneforge.houses import House, discover, iter_houses, load, make_instance
from sceneforge.houses.formats.native import write_house

from .conftest import assert_same_geometry, box_instance


def test_round_trip_is_exact(small_house, tmp_path):
    write_house(small_house, tmp_path / "small")
    back = load(tmp_path / "small")
    assert_same_geometry(small_house, back, atol=0)
    for a, b in zip(small_house.instances, back.instances):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        assert (a.name, a.label, a.material.base_color) == (b.name, b.label, b.material.base_color)
    assert [r.id for r in back.rooms] == ["r0"] and back.levels[0].floor_y == 0.0


def test_written_json_validates_and_bytes_are_deterministic(small_house, tmp_path):
    p1 = write_house(small_house, tmp_path / "a")
    p2 = write_house(small_house, tmp_path / "b")
    assert schemas.errors(json.loads(p1.read_text()), "house") == []
    assert p1.read_bytes() == p2.read_bytes()
    assert (p1.parent / "house.bin").read_bytes() == (p2.parent / "house.bin").read_bytes()


def test_envelope_flag_comes_from_conventions(small_house):
    env = {i.name for i in small_house.instances if i.envelope}
    assert env == {"floor", "ceiling", "wall0", "wall1", "wall2", "wall3"}
    h = House(id="fp", instances=[])
    fp = box_instance(h, "fp", 38, (1, 1, 1), (0, 0, 0), label="fireplace")
    assert fp.envelope  # fireplace is envelope by its source label, not by NYU40 name


def _tri_house():
    return House(id="bad", instances=[])


def test_nan_vertices_raise_naming_house_and_instance():
    h = _tri_house()
    with pytest.raises(HouseError, match=r"house bad.*'sheet'.*NaN"):
        make_instance(h, name="sheet", category=5, label="x", room_id=None,
                      vertices=[[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], faces=[[0, 1, 2]])


def test_faces_past_vertex_array_raise():
    h = _tri_house()
    with pytest.raises(HouseError, match="face index 7 is outside the 3 vertices"):
        make_instance(h, name="s", category=5, label="x", room_id=None,
                      vertices=np.eye(3), faces=[[0, 1, 7]])


def test_degenerate_faces_dropped_and_counted():
    h = _tri_house()
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]]
    inst = make_instance(h, name="s", category=5, label="x", room_id=None, vertices=v,
                         faces=[[0, 1, 2], [0, 1, 3], [2, 2, 1]])
    assert len(inst.faces) == 1
    assert h.warnings == ["instance 's': dropped 2 degenerate faces"]


def test_empty_house_raises(tmp_path):
    h = House(id="empty", instances=[])
    write_house(h, tmp_path / "empty")
    with pytest.raises(HouseError, match="house empty: .*house.json: house is empty"):
        load(tmp_path / "empty")


def test_unknown_category_and_schema_violation(small_house, tmp_path):
    p = write_house(small_house, tmp_path / "small")
    doc = json.loads(p.read_text())
    doc["instances"][0]["category"] = "spaceship"
    p.write_text(json.dumps(doc))
    with pytest.raises(HouseError, match="unknown NYU40 class 'spaceship'"):
        load(p)
    del doc["instances"][0]["faces"]
    p.write_text(json.dumps(doc))
    with pytest.raises(SceneforgeError, match="does not match the house schema: instances/0: 'faces'"):
        load(p)


def test_missing_and_truncated_buffer(small_house, tmp_path):
    p = write_house(small_house, tmp_path / "small")
    buf = p.parent / "house.bin"
    buf.write_bytes(buf.read_bytes()[:100])
    with pytest.raises(HouseError, match="house.bin: buffer is 100 bytes"):
        load(p)
    buf.unlink()
    with pytest.raises(HouseError, match="house.bin: cannot read buffer"):
        load(p)


def test_unknown_format_and_missing_path(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(UnknownFormatError, match="not a house in any supported format"):
        discover(tmp_path / "notes.txt")
    with pytest.raises(UnknownFormatError, match="no house found"):
        discover(tmp_path)
    with pytest.raises(SceneforgeError, match="no such file or folder"):
        discover(tmp_path / "nope")
    with pytest.raises(UnknownFormatError, match="unknown format 'blend'"):
        discover(tmp_path, "blend")


def test_one_broken_house_never_stops_the_others(small_house, tmp_path):
    for name in ("a", "b", "c"):
        small_house.id = name
        write_house(small_house, tmp_path / name)
    (tmp_path / "b" / "house.bin").write_bytes(b"\0" * 8)
    results = list(iter_houses(tmp_path))
    assert [s.id for s, _, _ in results] == ["a", "b", "c"]
    assert [h is not None for _, h, _ in results] == [True, False, True]
    assert "house b" in str(results[1][2]) and "buffer is 8 bytes" in str(results[1][2])
