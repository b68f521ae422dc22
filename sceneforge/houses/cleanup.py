"""What a generic scene's names get wrong, put right from its geometry after loading.

A glTF/OBJ/PLY scene's classes come from its names (:mod:`sceneforge.houses.names`); two kinds
of mesh are named for the tool that made the scene rather than for the house.
:func:`clean_up` runs two passes on such a house once all its meshes are instances, before
its rooms are derived from its floors (:func:`sceneforge.houses.rooms.derive_rooms`):

1. **The room box.** One mesh that is a whole closed room (often named ``Wall``, ``Room`` or
   ``Cube``; its normals may point in): its bounding box holds every other instance but the
   light emitters (to ``enclose`` metres) and :func:`~sceneforge.houses.shell.split_shell`
   finds room-sized floor and ceiling faces in it. It is split into wall, floor and ceiling
   (``<name>/wall``, ``<name>/floor``, ``<name>/ceiling``) like a mesh named ``shell``, with
   one warning, whatever class its name gave it, so that the rooms come from its floor. A
   mesh whose name the user's name map matches (``--name-map``) keeps the class the user
   gave it.
2. **Light emitters outside every room.** An instance of class ``lamp``, or with a material
   that emits (:attr:`~sceneforge.houses.model.Material.emission`), whose footprint lies
   over no floor and more than ``margin`` metres beyond the bounds of every floor is a light
   of the original scene (an area light 5 m outside a window: ``BackLight``), not a lamp of
   the house: it is dropped, all of them in one warning naming them. A scene without a
   floor (or whose floors stand on their edges) keeps its emitters: there is no room to be
   outside of.

Instances keep their order (a box's parts take its place) and are numbered again.
"""

from __future__ import annotations

import numpy as np

from ..conventions import NYU40_IDS
from ..errors import listed
from .model import House, Instance, make_instance
from .names import NameMap
from .rooms import points_in_triangles
from .shell import CEILING, FLOOR, pieces, split_shell

__all__ = ["clean_up", "drop_outside_emitters", "is_emitter", "split_room_box"]

_LAMP, _FLOOR = NYU40_IDS["lamp"], NYU40_IDS["floor"]
# footprint sample points of an instance: up to this many of its vertices and its centre
_SAMPLES = 64


def clean_up(house: House, names: NameMap) -> House:
    """The two passes of the module doc on a loaded generic house (changed in place); returns it.

    names : the map the house was named with; a box whose name its user rules match stays whole
    """
    split_room_box(house, keep=lambda inst: names.user_rule(inst.name) is not None)
    drop_outside_emitters(house)
    return house


def is_emitter(inst: Instance) -> bool:
    """True for a light emitter: class ``lamp``, or a material that gives off light."""
    return inst.category == _LAMP or any(max(m.emission) > 0 for m in inst.materials)


def split_room_box(house: House, *, keep=lambda inst: False, enclose: float = 0.25) -> Instance | None:
    """Split the room box of ``house`` (module doc, pass 1) in place; returns the box, or None.

    keep    : ``keep(instance)`` True for an instance that must stay whole (the user named it)
    enclose : how far (metres) another instance's bounding box may reach out of the box's
    """
    solid = [inst for inst in house.instances if not is_emitter(inst)]
    if not solid:
        return None
    lo = np.array([inst.vertices.min(0) for inst in solid])  # (n, 3)
    hi = np.array([inst.vertices.max(0) for inst in solid])
    k = int(np.argmax(np.prod(hi - lo, axis=1)))
    box = solid[k]
    if keep(box) or (lo < lo[k] - enclose).any() or (hi > hi[k] + enclose).any():
        return None
    part = split_shell(box.vertices, box.faces)
    if not ((part == FLOOR).any() and (part == CEILING).any()):
        return None
    scratch = House(id=house.id, instances=[], source_path=house.source_path)
    for name, used, f, faces in pieces(box.faces, part):  # each keeps its vertices and their materials
        fm = None if box.face_material is None else box.face_material[faces]
        make_instance(scratch, name=f"{box.name}/{name}", category=NYU40_IDS[name], label=box.label,
                      room_id=box.room_id, vertices=box.vertices[used], faces=f,
                      material=box.materials if fm is not None else box.materials[0], face_material=fm,
                      uv=None if box.uv is None else box.uv[used],
                      colors=None if box.colors is None else box.colors[used])
    at = house.instances.index(box)
    house.instances[at:at + 1] = scratch.instances
    _renumber(house)
    house.warnings.append(f"instance {box.name!r} ({box.category_name}) is a closed room holding every other "
                          f"object: split into {', '.join(i.name for i in scratch.instances)}")
    return box


def drop_outside_emitters(house: House, *, margin: float = 1.0) -> list[Instance]:
    """Drop the light emitters outside every room (module doc, pass 2); returns them.

    margin : how far (metres) beyond every floor's bounds an emitter's footprint must lie
    """
    floors = [inst for inst in house.instances if inst.category == _FLOOR]
    if not floors:
        return []
    xz = np.concatenate([inst.vertices[inst.faces][..., [0, 2]] for inst in floors])  # (t, 3, 2)
    e1, e2 = xz[:, 1] - xz[:, 0], xz[:, 2] - xz[:, 0]
    if not (np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) > 0).any():
        return []  # floors on their edges (a wrong up axis, which the rooms then report): no room to tell
    bounds = np.array([[inst.vertices[:, [0, 2]].min(0), inst.vertices[:, [0, 2]].max(0)] for inst in floors])
    dropped = [inst for inst in house.instances
               if is_emitter(inst) and inst.category != _FLOOR and _outside(inst, xz, bounds, margin)]
    if not dropped:
        return []
    house.instances = [inst for inst in house.instances if all(inst is not d for d in dropped)]
    _renumber(house)
    n = len(dropped)
    house.warnings.append(f"dropped {n} light emitter{'s' if n > 1 else ''} outside every room: "
                          f"{listed(inst.name for inst in dropped)} (area lights of the original scene)")
    return dropped


def _outside(inst: Instance, floor_xz: np.ndarray, floor_bounds: np.ndarray, margin: float) -> bool:
    """True when ``inst`` stands over no floor triangle (``floor_xz`` (t, 3, 2) float) and its
    footprint box is more than ``margin`` from every floor's (``floor_bounds`` (f, 2, 2) float)."""
    v = inst.vertices[:, [0, 2]]
    lo, hi = v.min(0), v.max(0)
    samples = np.concatenate([v[::max(1, len(v) // _SAMPLES)], ((lo + hi) / 2)[None]])
    if points_in_triangles(samples, floor_xz).any():
        return False
    gap = np.maximum(np.maximum(floor_bounds[:, 0] - hi, lo - floor_bounds[:, 1]), 0)  # (f, 2)
    return bool(np.hypot(gap[:, 0], gap[:, 1]).min() > margin)


def _renumber(house: House) -> None:
    """Instance ids are their places in ``house.instances`` again."""
    for k, inst in enumerate(house.instances):
        inst.id = k
