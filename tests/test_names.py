"""Names → classes for generic scenes (:mod:`sceneforge.houses.names`): the head-word rule of the
bundled map on the names real scenes have, the tag and the user's rules before it, and the
names sceneforge's own writers give."""

from __future__ import annotations

import json

import pytest

from sceneforge.conventions import NYU40_IDS, NYU40_NAMES
from sceneforge.houses import LoadOptions
from sceneforge.houses.formats.generic import load_house, tagged_name
from sceneforge.houses.names import NameMap, words
from sceneforge.houses.toy import build_toy_house
from sceneforge.testing.scenes import DOWNLOADED_NAMES

from .conftest import BREAKFAST_ROOM, needs_shared

#: node names as scenes come (the breakfast room's, the issue's, and what Blender, SketchUp,
#: 3ds Max and Sketchfab exports call things) → the target the bundled map must give them
#: (an NYU40 name, "drop", "shell"; None: unknown, void)
NAMES = {
    # the breakfast room (../shared/scenes/breakfast_room)
    "Walls": "shell", "Floor": "floor", "Skirting": "wall", "Skirting.001": "wall", "Blind": "blinds",
    "Chair": "chair", "Chair.003": "chair", "ChairLegs": "chair", "ChairLegs.002": "chair",
    "TableTop": "table", "TableLegs": "table", "TeaPot": "otherprop", "TeaCup": "otherprop",
    "TeaCup.001": "otherprop", "Spoon": "otherprop", "Spoon.002": "otherprop", "Light": "lamp",
    "Light.001": "lamp", "LightShade": "lamp", "LightShade.001": "lamp", "Picture": "picture",
    # the names the issue reports: a compound's head word decides, an object beats the envelope
    "CeilingLampshade": "lamp", "WallLight": "lamp", "FloorLamp": "lamp", "TableLamp": "lamp",
    "CoffeeTable": "table", "WindowFrame": "window", "DoorHandle": "door", "Walls.001": "shell",
    "Ceiling": "ceiling", "FloorMat": "floor_mat", "BookShelf": "bookshelf", "Lamp_Ceiling": "lamp",
    "BackLight": "lamp", "LeftLight": "lamp", "RightLight": "lamp", "FrontLight": "lamp",
    # modelling tools' and downloads' names
    "Sofa_01": "sofa", "Cube.004": None, "Plane": None, "Cylinder.002": None, "Object_7": None,
    "Pendant_Light": "lamp", "Window_Glass": "window", "Curtain_Rod": "curtain",
    "Kitchen_Cabinet_Door": "cabinet", "Bookshelf_Books": "books", "Rug": "floor_mat",
    "TV_Stand": "otherfurniture", "Armchair": "chair", "Bar Stool": "chair", "Wall.003": "wall",
    "Floor_Tiles": "floor", "Ceiling_Fan": "otherprop", "Door_Frame": "door", "Window_Sill": "window",
    "Kitchen Counter": "counter", "Countertop": "counter", "Sofa_Cushion": "sofa", "Cushion": "pillow",
    "Throw_Pillow": "pillow", "Toilet_Seat": "toilet", "Seat": "chair", "Bedside_Table": "night_stand",
    "Nightstand": "night_stand", "NightStand": "night_stand", "Bed_Frame": "bed", "Bathroom_Floor": "floor",
    "Bathroom_Mirror": "mirror", "Glass_Door": "door", "Outdoor_Chair": "chair", "Desk_Lamp": "lamp",
    "Desk_Chair": "chair", "Shower_Curtain": "shower_curtain", "Curtain": "curtain",
    "Picture_Frame": "picture", "Mirror_Frame": "mirror", "Frame": "picture", "Baseboard": "wall",
    "Crown_Moulding": "wall", "Wallpaper": "wall", "Roof": "ceiling", "Plaster": "ceiling",
    "Kitchen_Sink": "sink", "Bathtub": "bathtub", "Towel_Rail": "towel", "Wardrobe_Door_Left": "cabinet",
    "Fridge_Door": "refridgerator", "Glass": "otherprop", "WineGlass": "otherprop",
    "Coffee_Table_Glass": "table", "Window_Blind": "blinds", "Window_Curtain": "curtain",
    "Doormat": "floor_mat", "Ground": "floor", "Background": None, "Spotlight": "lamp",
    "Cupboard": "cabinet", "Television": "television", "TV": "television", "Monitor": "television",
    "Refrigerator": "refridgerator", "Box001": "box", "room_skeleton": "shell", "Shell": "shell",
    "TableCloth": "table", "Cloth": "clothes", "Clamp": None, "Lamp_Stand": "otherfurniture",
    # left out: plants, persons, helper geometry, whatever else the name says
    "Potted_Plant": "drop", "Plant_Pot": "drop", "DecoPlant": "drop", "Leaves": "drop",
    "Person.001": "drop", "Chair_Collider": "drop", "Skybox": "drop",
}


def _target(t):
    return t if t is None or isinstance(t, str) else NYU40_NAMES[t]


def test_the_bundled_map_gives_every_real_style_name_its_class():
    bundled = NameMap.bundled()
    got = {name: _target(bundled.lookup(name)) for name in NAMES}
    assert {n: (got[n], want) for n, want in NAMES.items() if got[n] != want} == {}


@pytest.mark.parametrize("name, expected", [
    ("CeilingLampshade.001", ["ceiling", "lampshade"]), ("TV_Stand", ["tv", "stand"]),
    ("LightShade", ["light", "shade"]), ("Kitchen Cabinet-Door_2", ["kitchen", "cabinet", "door"]),
    ("room_skeleton", ["room", "skeleton"]), ("Box001", ["box"]), ("WC", ["wc"]), ("", []),
])
def test_words_split_at_humps_digits_and_separators(name, expected):
    assert words(name) == expected


def test_every_part_word_alone_has_a_class_of_its_own():
    # a part word defers to the rest of the name; alone it is claimed like any word
    bundled = NameMap.bundled()
    assert bundled.parts and all(bundled.lookup(word) is not None for word in bundled.parts)


def _toy_instances():
    return [i for seed in range(12) for i in build_toy_house(seed).house.instances]


def test_toy_labels_as_downloads_name_them_keep_their_classes():
    # the names write_downloaded gives a toy house (sceneforge.testing.scenes): the true class
    # comes back, the merged walls as a shell; and the bare labels (coffee_table, floor_lamp) too
    bundled = NameMap.bundled()
    pairs = {(i.category_name, i.label) for i in _toy_instances()}
    wrong = {}
    for cname, label in sorted(pairs):
        downloaded = DOWNLOADED_NAMES.get(cname) or label.title().replace("_", "")
        want = "shell" if cname == "wall" else cname
        for name in (downloaded, label):
            got = _target(bundled.lookup(name))
            if got != (want if name == downloaded else cname):
                wrong[name] = (got, cname)
    assert wrong == {}


def test_writers_tags_win_over_every_rule(tmp_path):
    # sceneforge's own writers tag every name: the tag decides, whatever the words or the
    # user's rules say ("otherprop__Lamp" stays otherprop, "void__CeilingLampshade" void)
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps([["lamp|chair", "sofa"]]))
    names = NameMap.with_user_rules(mapping)
    instances = _toy_instances()
    assert [names.lookup(tagged_name(i)) for i in instances] == [i.category for i in instances]
    for cname in NYU40_NAMES:
        for name in ("CeilingLampshade", "Chair.001", "Plant_Pot", "Walls"):
            assert names.lookup(f"{cname}__{name}") == NYU40_IDS[cname]


def test_user_rules_match_the_whole_name_first(tmp_path):
    # the user's rules keep their documented meaning: re.search on the name as written, in
    # file order, the first match winning over the bundled head-word rule
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"patterns": [["^Ceiling", "ceiling"], ["_Rod$", "otherprop"],
                                                ["lamp", "otherfurniture"], ["shade", "drop"]]}))
    names = NameMap.with_user_rules(mapping)
    got = {n: _target(names.lookup(n)) for n in ("CeilingLampshade", "Curtain_Rod", "TableLamp", "LightShade",
                                                 "CoffeeTable", "Walls")}
    assert got == {"CeilingLampshade": "ceiling", "Curtain_Rod": "otherprop", "TableLamp": "otherfurniture",
                   "LightShade": "drop", "CoffeeTable": "table", "Walls": "shell"}
    rule = names.match("TableLamp")[1]
    assert rule.source == "map.json #3" and names.user_rule("TableLamp") is rule
    assert names.user_rule("CoffeeTable") is None and NameMap.bundled().user_rule("TableLamp") is None


@needs_shared(BREAKFAST_ROOM)
def test_breakfast_room_classes_are_unchanged():
    # every node name resolves as before the head-word rule, and the geometry passes find
    # nothing to change: no room box (its "Walls" is a shell by name), no light outside it
    nodes = {n["name"] for n in json.loads(BREAKFAST_ROOM.read_text())["nodes"] if "mesh" in n}
    bundled = NameMap.bundled()
    assert {n: _target(bundled.lookup(n)) for n in nodes} == {n: NAMES[n.split(".")[0]] for n in nodes}
    h = load_house(BREAKFAST_ROOM, LoadOptions())
    assert not [w for w in h.warnings if "closed room" in w or "light emitter" in w]
    lamps = sorted(i.name for i in h.instances if i.category_name == "lamp")
    assert lamps == ["Light", "Light.001", "LightShade", "LightShade.001"]
