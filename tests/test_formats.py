"""The format registry: names, the order formats are asked in, roots, the 3D-FRONT fallback."""

from __future__ import annotations

import json

import pytest

from sceneforge.errors import UnknownFormatError
from sceneforge.houses import FORMATS, HouseSource, discover
from sceneforge.houses.formats import REGISTRY, base, detect, find, front3d, native, suncg
from sceneforge.houses.formats.native import write_house
from sceneforge.testing import front3d as front3d_writer
from sceneforge.testing import generic as generic_writer
from sceneforge.testing import suncg as suncg_writer


def test_registry_names_and_cli_order():
    assert FORMATS == ("sceneforge", "gltf", "obj", "ply", "suncg", "front3d", "scene")
    assert all(fmt.name == name for name, fmt in REGISTRY.items())


def test_sceneforge_json_is_asked_before_suncg(small_house, tmp_path):
    path = write_house(small_house, tmp_path / "small")
    assert suncg.detect(path)  # a sceneforge house.json has SUNCG's "levels" and "up" too
    assert detect(path) is native.FORMAT
    assert detect(path.parent) is native.FORMAT


def test_generic_formats_by_suffix_files_only(small_house, tmp_path):
    for name, suffix in (("gltf", ".glb"), ("gltf", ".gltf"), ("obj", ".obj"), ("ply", ".PLY")):
        path = generic_writer.write_house(small_house, tmp_path / f"scene{suffix}")
        assert detect(path) is REGISTRY[name]
    folder = tmp_path / "folder.obj"
    folder.mkdir()
    assert not REGISTRY["obj"].detect(folder) and detect(folder) is None


def test_folder_layout_wins_over_a_sceneforge_house_folder(small_house, tmp_path):
    suncg_writer.write_house(small_house, tmp_path / "suncg")
    inside = tmp_path / "suncg" / "house" / "natx"
    write_house(small_house, inside)
    assert detect(inside) is suncg.FORMAT
    write_house(small_house, tmp_path / "both")
    front3d_writer.write_house(small_house, tmp_path / "both")
    assert detect(tmp_path / "both") is front3d.FORMAT


def test_roots_list_their_houses(small_house, tmp_path):
    suncg_writer.write_house(small_house, tmp_path / "suncg")
    assert suncg.list_houses(tmp_path / "suncg") == [
        HouseSource(small_house.id, "suncg", tmp_path / "suncg" / "house" / small_house.id / "house.json")]
    front3d_writer.write_house(small_house, tmp_path / "front")
    scene = tmp_path / "front" / "3D-FRONT" / f"{small_house.id}.json"
    assert front3d.list_houses(tmp_path / "front") == [HouseSource(small_house.id, "front3d", scene)]


def test_front3d_takes_unrecognised_json_only_when_asked_for(small_house, tmp_path):
    front3d_writer.write_house(small_house, tmp_path / "front")
    (tmp_path / "front" / "3D-FRONT" / "odd.json").write_text('{"rooms only": []}')
    write_house(small_house, tmp_path / "front" / "3D-FRONT" / "native")  # another format: not a scene
    assert [s.id for s in discover(tmp_path / "front")] == ["odd", small_house.id]
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "odd.json").write_text('{"rooms only": []}')
    with pytest.raises(UnknownFormatError, match="no house found"):
        discover(loose)
    assert [(s.id, s.format) for s in discover(loose, "front3d")] == [("odd", "front3d")]
    assert find(loose / "odd.json", REGISTRY["suncg"])[0].format == "suncg"  # a file: the format asked for


def test_a_json_file_is_parsed_once_per_detection(tmp_path, monkeypatch):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"furniture": [], "scene": {"room": []}}))
    calls = []
    real = base.json.loads
    monkeypatch.setattr(base.json, "loads", lambda text: calls.append(1) or real(text))
    assert detect(path) is front3d.FORMAT  # suncg asks about the file first
    assert len(calls) == 1
    path.write_text(json.dumps({"levels": [], "version": "suncg@1.0.0", "padding": "x" * 100}))
    assert detect(path) is suncg.FORMAT  # nothing stale is kept between detections
