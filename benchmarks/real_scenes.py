"""Real scenes as people have them, each case run as a user runs it: ``sceneforge ...`` in a
child process, from the folder a user would be in.

Makes, in a temporary folder, the kinds of export issue 38's user met (from the bundled toy
houses, named as modelling tools name objects): a Z-up OBJ living room with a
``CeilingLampshade`` and four area lights outside its windows; a GLB desk room whose walls,
floor and ceiling are one closed box named ``Wall``; the living room exported one OBJ per
object (recognised by the files' names) and one whose files are numbered, the objects'
names inside them (told by a ``scene.json``, as ``houses inspect`` suggests), then a
``Stool.obj`` added to the per-object folder (render again: refused, naming the house;
``--update`` takes it in); a lone sofa (no up axis to tell); the living room exported upside
down (-Y up); a relative ``--name-map``. Then runs
every case and prints one row each: the exit code, the lines printed (progress bars left
out), whether a traceback appeared, and the line that matters; then whether every case gave
what it should (a working store, or one line naming the fix).

    python benchmarks/real_scenes.py [--keep DIR] [--baseline CHECKOUT]

``--baseline`` runs every case again with an earlier checkout's sceneforge (a world of its
own), so the table of before and after comes from one run.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

CLI = "from sceneforge.cli.main import main; main()"
PROGRESS = re.compile(r"━|\d+/\d+ .*ETA")
SMALL = ["--views-per-house", "2", "--resolution", "64x48", "--overhead-resolution", "32", "--no-rgb"]
AREA_LIGHTS = ("BackLight", "FrontLight", "LeftLight", "RightLight")


def sceneforge(*args, cwd: Path, path: Path | None = None) -> tuple[int, list[str]]:
    """Run ``sceneforge ARGS`` in ``cwd``: this one, or the package at ``path`` (a baseline)."""
    env = None if path is None else {**os.environ, "PYTHONPATH": str(path)}
    res = subprocess.run([sys.executable, "-c", CLI, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                         env=env)
    lines = [line for line in (res.stdout + res.stderr).splitlines() if line.strip() and not PROGRESS.search(line)]
    return res.returncode, lines


def _quad(house, name: str, centre) -> None:
    """An upright 2 m area-light quad at ``centre`` (+Y up)."""
    from sceneforge.houses import make_instance

    c = np.asarray(centre, float)
    v = c + np.array([(0, -1, -1), (0, -1, 1), (0, 1, 1), (0, 1, -1)], float)
    make_instance(house, name=name, category=0, label=name, room_id=None, vertices=v, faces=[(0, 1, 2), (0, 2, 3)])


def _box(house, name: str, lo, hi, inward: bool = False) -> None:
    import trimesh

    from sceneforge.houses import make_instance

    b = trimesh.creation.box(bounds=np.array([lo, hi], float))
    make_instance(house, name=name, category=0, label=name, room_id=None, vertices=b.vertices,
                  faces=b.faces[:, ::-1] if inward else b.faces)


def setup(root: Path) -> None:
    """The scenes of the module doc under ``root/scenes``."""
    from sceneforge.houses import House, bundled_toy_dir, load
    from sceneforge.testing.generic import write_house
    from sceneforge.testing.scenes import object_names, rotated_z_up, write_object_files

    scenes = root / "scenes"
    living = load(bundled_toy_dir() / "toy_0_000")
    names = object_names(living)
    names[names.index("CeilingLamp")] = "CeilingLampshade"
    lo, hi = living.bounds()
    middle = (lo + hi) / 2
    for name, centre in zip(AREA_LIGHTS, ((hi[0] + 6, 1.5, middle[2]), (lo[0] - 6, 1.5, middle[2]),
                                          (middle[0], 1.5, lo[2] - 5), (middle[0], 1.5, hi[2] + 7))):
        _quad(living, name, centre)
        names.append(name)
    write_house(rotated_z_up(living), scenes / "living.obj", names=names)  # Blender's OBJ export: Z up

    desk = House(id="desk_room", instances=[])
    _box(desk, "Wall", (0, 0, 0), (4, 2.6, 5), inward=True)  # walls, floor and ceiling: one closed box
    _box(desk, "Desk", (0.2, 0, 3.8), (1.6, 0.75, 4.6))
    _box(desk, "OfficeChair", (0.6, 0, 3.0), (1.1, 0.95, 3.5))
    _box(desk, "DeskLamp", (1.2, 0.75, 4.2), (1.4, 1.2, 4.4))
    _box(desk, "Bookshelf", (3.4, 0, 0.2), (3.9, 2.0, 1.4))
    _box(desk, "CeilingLampshade", (1.8, 2.2, 2.3), (2.2, 2.55, 2.7))
    for name, centre in zip(AREA_LIGHTS, ((10, 1.5, 2.5), (-6, 1.5, 2.5), (2, 1.5, -5), (2, 1.5, 12))):
        _quad(desk, name, centre)
    write_house(desk, scenes / "desk_room.glb", names=[i.name for i in desk.instances])

    plain = load(bundled_toy_dir() / "toy_0_001")
    write_object_files(rotated_z_up(plain), scenes / "studio_parts")  # Floor.obj, Walls.obj, Chair.001.obj, ...
    for k, (inst, name) in enumerate(zip(plain.instances, object_names(plain))):  # Sketchfab-style: files by
        write_house(House(id="x", instances=[replace(inst, id=0)]), scenes / "export" / f"mesh_{k:03d}.obj",
                    names=[name])                                             # number, the object's name inside
    sofa = next(i for i in plain.instances if i.category_name == "sofa")
    write_house(House(id="sofa", instances=[replace(sofa, id=0)]), scenes / "lone_sofa.obj", names=["Sofa"])
    # a stool in the middle of the studio's floor, for the case that adds it to the folder later
    floor = next(i for i in plain.instances if i.category_name == "floor")
    (x, y, z), stool = floor.vertices.mean(axis=0), House(id="stool", instances=[])
    _box(stool, "Stool", (x - 0.2, y, z - 0.2), (x + 0.2, y + 0.45, z + 0.2))
    write_house(rotated_z_up(stool), root / "spare" / "Stool.obj", names=["Stool"])
    flip = np.diag([1.0, -1.0, -1.0])  # turned 180° about X: -Y up
    write_house(House(id="living", instances=[replace(i, vertices=i.vertices @ flip) for i in living.instances]),
                scenes / "upside_down.obj", names=names)
    (scenes / "living_map.json").write_text(json.dumps({"patterns": [["^Dresser", "cabinet"]]}))
    (root / "elsewhere").mkdir()


#: the rooms of each house a render case's store must record (toy_0_000 has 3, toy_0_001 2,
#: the desk room 1): a store of a misread scene (Z-up taken for Y-up: walls for floors) has others
ROOMS = {"living.zarr": [3], "desk.zarr": [1], "parts.zarr": [2], "export.zarr": [2], "named.zarr": [3]}


def cases(root: Path) -> list[tuple[str, list, Path, str]]:
    """(case, arguments, folder run from, what must hold: "ok" exit 0 (and a render's store
    with the houses and rooms of :data:`ROOMS`), "one line" a failure whose one message line
    names the fix, "hint" the scene-folder hint, "usage" a suggested command, "taken in" as
    "ok" and the store's house read with the file added to its folder)."""
    r, e = root, root / "elsewhere"
    return [
        ("Z-up OBJ, no --up-axis: inspect", ["houses", "inspect", "scenes/living.obj"], r, "ok"),
        ("Z-up OBJ, no --up-axis: render", ["render", "scenes/living.obj", "living.zarr", *SMALL], r, "ok"),
        ("GLB desk room, one closed box 'Wall'", ["render", "scenes/desk_room.glb", "desk.zarr", *SMALL], r, "ok"),
        ("one OBJ per object (Z-up), by names", ["render", "scenes/studio_parts", "parts.zarr", *SMALL], r, "ok"),
        ("one OBJ per object, file names say nothing", ["houses", "inspect", "scenes/export"], r, "hint"),
        ("... with the scene.json the hint names", ["render", "scenes/export", "export.zarr", *SMALL], r, "ok"),
        ("a file added to the studio's folder", ["render", "scenes/studio_parts", "parts.zarr", *SMALL], r,
         "one line"),
        ("... render --update", ["render", "scenes/studio_parts", "parts.zarr", *SMALL, "--update"], r,
         "taken in"),
        ("a lone sofa: no up axis to tell", ["houses", "inspect", "scenes/lone_sofa.obj"], r, "one line"),
        ("an upside-down export (-Y up)", ["houses", "inspect", "scenes/upside_down.obj"], r, "one line"),
        ("relative --name-map: render", ["render", "scenes/living.obj", "named.zarr", *SMALL, "--name-map",
                                          "scenes/living_map.json"], r, "ok"),
        ("... evaluate from another folder", ["evaluate", "coverage", "../named.zarr", "--limit", "1",
                                              "--density", "500"], e, "ok"),
        ("... overhead-camera from another folder", ["overhead-camera", "--store", "../named.zarr", "--view", "0"], e,
         "ok"),
        ("typo: bundled:toyy", ["houses", "inspect", "bundled:toyy"], r, "one line"),
        ("typo: rendr", ["rendr", "bundled:toy", "x.zarr"], r, "usage"),
    ]


def baseline_package(checkout: Path, into: Path) -> Path:
    """A folder to put on PYTHONPATH that imports ``checkout``'s sceneforge as installed
    (its top-level ``cli/`` and ``schemas/`` as ``sceneforge.cli`` and ``sceneforge.schemas``)."""
    package = into / "sceneforge"
    package.mkdir(parents=True)
    for entry in (checkout / "sceneforge").iterdir():
        if entry.name not in ("cli", "schemas", "__pycache__"):
            (package / entry.name).symlink_to(entry)
    for name in ("cli", "schemas"):
        (package / name).symlink_to(checkout / name)
    return into


def run(root: Path, baseline: Path | None = None) -> int:
    t0 = time.perf_counter()
    setup(root / "now")
    bad = _run_cases(root / "now", None, "this checkout")
    if baseline is not None:
        setup(root / "baseline")
        path = baseline_package(baseline.resolve(), root / "baseline_package")
        base_bad = _run_cases(root / "baseline", path, f"baseline: {baseline}")
        print(f"\nbaseline: {len(cases(root)) - base_bad} of {len(cases(root))} as they should be")
    print(f"{time.perf_counter() - t0:.0f} s in all")
    return 1 if bad else 0


def _run_cases(root: Path, path: Path | None, title: str) -> int:
    """Every case in the world at ``root`` with the package at ``path`` (None: this one);
    prints the table and the facts; returns how many were not as they should be."""
    print(f"\n{title}\n")
    rows, bad = [], 0
    for name, args, cwd, want in cases(root):
        if name.startswith("... with the scene.json"):
            (root / "scenes" / "export" / "scene.json").write_text('{"files": ["*.obj"]}')
        if name.startswith("a file added to the studio"):
            for spare in (root / "spare").iterdir():  # Stool.obj and its material library
                spare.rename(root / "scenes" / "studio_parts" / spare.name)
        t = time.perf_counter()
        code, lines = sceneforge(*args, cwd=cwd, path=path)
        traceback = any("Traceback" in line for line in lines)
        key = _key_line(lines, want)
        store = next((a for a in args if str(a).endswith(".zarr")), None) if args[0] == "render" else None
        rooms = _rooms(cwd / store) if store else None
        if store:
            key = f"{key} (rooms: {rooms})"
        good = not traceback and {
            "ok": code == 0 and (store is None or rooms == ROOMS[store]),
            "taken in": code == 0 and store is not None and rooms == ROOMS[store] and _read_stool(cwd / store),
            "hint": any(line.startswith("hint: ") for line in lines),
            "one line": code != 0 and sum(line.startswith(("error:", "failed:")) for line in lines) == 1
            and ("pass --" in key or "did you mean" in key),
            "usage": code == 2 and "Did you mean 'render'?" in key,
        }[want]
        bad += not good
        rows.append((name, code, len(lines), "yes" if traceback else "no", "yes" if good else "NO",
                     f"{time.perf_counter() - t:.1f}", key))
    _table(rows)
    if path is None:
        _facts(root)
    print(f"\n{len(rows)} cases: {len(rows) - bad} as they should be, {bad} not; "
          f"{sum(r[3] == 'yes' for r in rows)} tracebacks")
    return bad


def _read_stool(store: Path) -> bool:
    """Whether the store's houses were read with the ``Stool.obj`` added to their folder."""
    from sceneforge.store import open_store

    return any(path.endswith("Stool.obj") for h in open_store(str(store)).attrs["houses"]
               for path in h.get("inputs") or {})


def _rooms(store: Path) -> list[int] | None:
    """The rooms of each house the store at ``store`` records (None: no store there)."""
    from sceneforge.errors import SceneforgeError
    from sceneforge.store import open_store

    try:
        return [h.get("rooms") for h in open_store(str(store)).attrs["houses"] if "failure" not in h]
    except SceneforgeError:
        return None


def _key_line(lines: list[str], want: str) -> str:
    """The line that says what happened: the hint, the error, the note, or the summary."""
    for prefix in {"hint": ("hint: ",), "one line": ("error:", "failed:"), "usage": ("Error:",)}.get(want, ()):
        found = [line for line in lines if line.startswith(prefix)]
        if found:
            return found[0]
    notes = [line for line in lines if line.startswith("note: up axis")]
    return notes[0] if notes else (lines[-1] if lines else "")


def _table(rows) -> None:
    print("| case | exit | lines | traceback | as it should | s | what it said |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, code, n, tb, good, seconds, key in rows:
        short = key if len(key) <= 150 else key[:149] + "…"
        print(f"| {name} | {code} | {n} | {tb} | {good} | {seconds} | `{short}` |")


def _facts(root: Path) -> None:
    """What the stores hold: the classes the names got, what was dropped, the rooms."""
    from sceneforge.store import open_store

    print()
    for store in ("living.zarr", "desk.zarr", "parts.zarr", "export.zarr", "named.zarr"):
        s = open_store(str(root / store))
        houses = s.attrs["houses"]
        print(f"{store}: {len(s)} views of {len(houses)} house(s) "
              f"({', '.join(h['id'] for h in houses)}); failures: {len(s.attrs['failures'])}; "
              f"name map recorded: {s.config.houses.name_map}")
    from sceneforge.houses import load

    for scene in ("living.obj", "desk_room.glb"):
        house = load(root / "scenes" / scene)
        classes = {i.name: i.category_name for i in house.instances}
        dropped = [w for w in house.warnings if "light emitters" in w]
        split = [i.name for i in house.instances if "/" in i.name]
        print(f"{scene}: CeilingLampshade → {classes.get('CeilingLampshade')}; "
              f"area lights kept: {[n for n in AREA_LIGHTS if n in classes]}; {dropped[0] if dropped else 'none dropped'}; "
              f"split envelope meshes: {split or 'none'}; rooms {len(house.rooms)}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, default=None, help="work in this folder and keep it")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="also run every case with the sceneforge of this checkout (e.g. `git worktree add "
                             "/tmp/before c89d18a`), in a world of its own")
    args = parser.parse_args()
    if args.keep is not None:
        shutil.rmtree(args.keep, ignore_errors=True)
        args.keep.mkdir(parents=True)
        return run(args.keep, args.baseline)
    with tempfile.TemporaryDirectory() as tmp:
        return run(Path(tmp), args.baseline)


if __name__ == "__main__":
    sys.exit(main())
