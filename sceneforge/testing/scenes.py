"""Houses written the way downloaded scenes come: one merged envelope mesh, the names people
give objects in a modelling tool, plants and helper geometry, none of sceneforge's tags.

:func:`write_downloaded` writes a house (a toy house, say, whose true classes are known) as
glTF/OBJ/PLY so that tests can check what the loader makes of it: the shell split into
wall, floor and ceiling, the bundled name map's classes, plants dropped, unknown names void.
:func:`write_object_files` writes a house one file per object, as tools export a scene, and
:func:`rotated_z_up` turns a house the way a Z-up tool has it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..conventions import NYU40_IDS, NYU40_NAMES
from ..houses.formats.generic import Z_UP_TO_Y_UP
from ..houses.model import House, Instance, Material
from .generic import write_house

#: the name an instance of a class gets with ``generic_names`` (other classes: ``<Label>.<nnn>``)
DOWNLOADED_NAMES = {
    "wall": "room_skeleton", "ceiling": "Plaster", "floor": "Floor", "floor_mat": "Carpet",
    "door": "Door", "window": "WindowFrame", "curtain": "Curtain", "blinds": "Blinds", "picture": "Painting",
}
#: the extra instances ``generic_names`` adds: (name, (3,) lower corner offset, (3,) size), all
#: dropped by the bundled name map
PLANT_PARTS = (("DecoPlant", (0.0, 0.0, 0.0), (0.3, 0.3, 0.3)), ("Leaves", (0.0, 0.3, 0.0), (0.3, 0.4, 0.3)),
               ("Branches", (0.1, 0.3, 0.1), (0.1, 0.3, 0.1)), ("Collider", (0.0, 0.0, 0.0), (0.3, 0.7, 0.3)))
#: the name given to one otherprop instance with ``generic_names``: a name no rule knows (void)
UNKNOWN_NAME = "Object_7"
_ENVELOPE = (NYU40_IDS["wall"], NYU40_IDS["floor"], NYU40_IDS["ceiling"])


def write_downloaded(house: House, path: str | Path, *, merged_shell: bool = False,
                     generic_names: bool = False, plant_at=None) -> Path:
    """Write ``house`` (by suffix, as :func:`~sceneforge.testing.generic.write_house`) the way a
    download would have it; returns ``path``.

    merged_shell  : every wall, floor and ceiling instance merged into one mesh named ``Shell``
    generic_names : names of :data:`DOWNLOADED_NAMES`, ``<Label>.<nnn>`` for the rest, the
                    first ``otherprop`` named :data:`UNKNOWN_NAME`, and a plant and a helper
                    box (:data:`PLANT_PARTS`) at ``plant_at`` ((3,) float, default: the
                    lowest corner of the house's bounds, 0.5 m in)
    Without ``generic_names`` the instances keep sceneforge's tags (their classes load back).
    """
    out = House(id=house.id, instances=[], rooms=list(house.rooms), levels=list(house.levels))
    names: list[str] = []
    counts: dict[str, int] = {}
    unknown_given = False
    shell: list[Instance] = []
    for inst in house.instances:
        if merged_shell and inst.category in _ENVELOPE:
            shell.append(inst)
            continue
        name = None
        if generic_names:
            cname = NYU40_NAMES[inst.category]
            if cname == "otherprop" and not unknown_given:
                name, unknown_given = UNKNOWN_NAME, True
            else:
                base = DOWNLOADED_NAMES.get(cname) or inst.label.title().replace("_", "")
                counts[base] = counts.get(base, 0) + 1
                name = base if counts[base] == 1 else f"{base}.{counts[base] - 1:03d}"
        _append(out, inst, names, name)
    if shell:
        vs, fs, n = [], [], 0
        for inst in shell:
            vs.append(inst.vertices)
            fs.append(inst.faces + n)
            n += len(inst.vertices)
        merged = Instance(len(out.instances), "Shell", NYU40_IDS["wall"], "Shell", None, np.concatenate(vs),
                          np.concatenate(fs), True, materials=(shell[0].material,))
        out.instances.append(merged)
        names.append("Shell")
    if generic_names:
        corner = np.asarray(plant_at if plant_at is not None else house.bounds()[0] + (0.5, 0.0, 0.5))
        if plant_at is None:
            corner[1] = 0.0
        for name, offset, size in PLANT_PARTS:
            lo = corner + offset
            v, f = _box(lo, lo + np.asarray(size))
            out.instances.append(Instance(len(out.instances), name, 0, name, None, v, f, False,
                                          materials=(Material((0.2, 0.6, 0.2, 1.0)),)))
            names.append(name)
    return write_house(out, path, names=names)


def _append(out: House, inst: Instance, names: list[str], name: str | None) -> None:
    from dataclasses import replace

    from ..houses.formats.generic import tagged_name

    out.instances.append(replace(inst, id=len(out.instances)))
    names.append(name if name is not None else tagged_name(inst))


def _box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed axis-aligned box: (8, 3) vertices, (12, 3) outward faces."""
    import trimesh

    b = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return np.asarray(b.vertices), np.asarray(b.faces)


#: the name an instance of a class gets from :func:`object_names` (other classes: its label
#: in CamelCase, ``coffee_table`` → ``CoffeeTable``)
OBJECT_NAMES = {"wall": "Walls", "ceiling": "Ceiling", "floor": "Floor", "lamp": "CeilingLamp"}


def object_names(house: House) -> list[str]:
    """A name per instance of ``house`` as a modelling tool exports them, copies numbered the
    Blender way: ``Floor``, ``Walls``, ``Chair``, ``Chair.001``, ``CeilingLamp`` (:data:`OBJECT_NAMES`)."""
    counts: dict[str, int] = {}
    names = []
    for inst in house.instances:
        base = OBJECT_NAMES.get(NYU40_NAMES[inst.category]) or "".join(
            w.title() for w in inst.label.split("_"))
        counts[base] = counts.get(base, 0) + 1
        names.append(base if counts[base] == 1 else f"{base}.{counts[base] - 1:03d}")
    return names


def write_object_files(house: House, folder: str | Path, *, suffix: str = ".obj",
                       names: list[str] | None = None, object_name: str = "default") -> list[Path]:
    """Write every instance of ``house`` to a file of its own, ``folder/<name><suffix>`` (names:
    :func:`object_names` unless given), the mesh in it named ``object_name`` (a name that says
    nothing, so that the file's name is the object's). Returns the files, in instance order."""
    from dataclasses import replace

    folder = Path(folder)
    names = object_names(house) if names is None else list(names)
    files = []
    for inst, name in zip(house.instances, names, strict=True):
        one = House(id=house.id, instances=[replace(inst, id=0)])
        files.append(write_house(one, folder / f"{name}{suffix}", names=[object_name]))
    return files


def rotated_z_up(house: House) -> House:
    """``house`` (+Y up) as a Z-up tool has it: every vertex ``(x, y, z)`` → ``(x, -z, y)``,
    which :data:`~sceneforge.houses.formats.generic.Z_UP_TO_Y_UP` takes back exactly."""
    from dataclasses import replace

    back = Z_UP_TO_Y_UP  # (x, -z, y) @ back.T = (x, y, z): the inverse is the transpose
    return House(id=house.id, instances=[replace(i, vertices=i.vertices @ back) for i in house.instances],
                 rooms=list(house.rooms), levels=list(house.levels))
