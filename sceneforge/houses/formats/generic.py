"""Generic scenes: glTF 2.0 (``.gltf``/``.glb``), Wavefront OBJ and PLY, read as houses.

A generic scene has no rooms and no categories, only named meshes. Each format module
turns its file into meshes (:mod:`~sceneforge.houses.formats.gltf`: one per node,
:mod:`~sceneforge.houses.formats.obj`: one per ``o`` object or ``g`` group,
:mod:`~sceneforge.houses.formats.ply`: one per ``instance`` property value);
this module makes instances of the meshes and names them:

- The category of an instance comes from its name through a
  :class:`~sceneforge.houses.names.NameMap` (the rules of ``LoadOptions.name_map`` before
  the bundled ones); its ``label`` is the name without Blender-style copy numbers
  (``Chair.001`` → ``Chair``), so that rules on source labels (fireplace, plant, ...) see
  the object's kind. Persons, plants and names sent to ``drop`` are left out; a mesh sent
  to ``shell`` becomes up to three instances ``<name>/wall``, ``<name>/floor`` and
  ``<name>/ceiling`` (:func:`~sceneforge.houses.shell.split_shell`).
- The scene has no rooms: they are derived from its floors (:mod:`sceneforge.houses.rooms`).
- ``LoadOptions.scale`` and ``up_axis`` take the source's units and axes to metres, +Y up.
- The three formats (:data:`GLTF`, :data:`OBJ`, :data:`PLY`, as the registry holds them) are
  recognised by their file suffixes (:data:`SUFFIXES`) and all read by :func:`load_house`.
- The writers (:mod:`sceneforge.testing.generic`) name every instance ``<nyu40 name>__<name>``, or
  ``<nyu40 name>__<label>__<name>`` when the label is not the one the name gives (or the
  name holds ``__``): the bundled pattern map sends the tag back to the same class, and the
  loader takes tag and label off the name.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_IDS, NYU40_NAMES, is_dropped
from ...errors import HouseError, SceneforgeError
from ..categories import resolve
from ..model import House, Instance, make_instance
from ..names import DROP, SHELL, TAG, NameMap
from ..rooms import derive_rooms
from ..shell import PARTS, split_shell
from .base import Format, HouseSource
from .meshio import Mesh, MeshFileError

if TYPE_CHECKING:
    from .. import LoadOptions

__all__ = ["GLTF", "OBJ", "PLY", "SUFFIXES", "load_house", "tagged_name"]

#: file suffix → the generic format it is
SUFFIXES = {".gltf": "gltf", ".glb": "gltf", ".obj": "obj", ".ply": "ply"}

#: rotation taking a Z-up source to +Y up, right-handed: (x, y, z) → (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# Blender ".001", "_2", " 3": copies of one object, not different kinds of object.
_COPY_NUMBER = re.compile(r"(?:[._ -]\d+)+$")


def load_house(path: str | Path, options: LoadOptions | None = None, house_id: str | None = None) -> House:
    """Read a glTF/GLB, OBJ or PLY scene as a house (id ``house_id``, default the file stem).

    ``options`` is a :class:`sceneforge.houses.LoadOptions`; ``scale``, ``up_axis``,
    ``name_map`` and ``strict`` apply. Rooms and levels are derived from the floors. Raises :class:`HouseError` naming the house, the
    file and the problem for anything unreadable, and :class:`SceneforgeError` for a bad
    option.
    """
    from .. import LoadOptions
    from .gltf import read_gltf
    from .obj import read_objects
    from .ply import read_ply

    path = Path(path)
    options = options or LoadOptions()
    fmt = SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise SceneforgeError(f"{path}: not a generic scene (expected one of {', '.join(SUFFIXES)})")
    builder = _Builder(path, fmt, options, house_id or path.stem)
    if not path.is_file():
        raise HouseError(builder.house.id, path, "no such file")
    read = {"gltf": read_gltf, "obj": read_objects, "ply": read_ply}[fmt]
    count = 0
    try:
        for mesh in read(path, builder.warn):  # one at a time: warnings stay in file order
            builder.add(mesh)
            count += 1
    except MeshFileError as e:
        raise HouseError(builder.house.id, e.file or path, e.problem) from None
    if not count:
        raise HouseError(builder.house.id, path, "no faces")
    return derive_rooms(builder.house.check_not_empty())


def tagged_name(instance: Instance) -> str:
    """The name the writers give ``instance``: ``<nyu40 name>__[<label>__]<name>`` (module docs)."""
    name = re.sub(r"\s+", " ", instance.name).strip() or f"instance{instance.id}"
    label = re.sub(r"\s+", " ", re.sub(r"_{2,}", "_", instance.label)).strip() or _label_of(name)
    tag = NYU40_NAMES[instance.category]
    if "__" in name or label != _label_of(name):
        return f"{tag}__{label}__{name}"
    return f"{tag}__{name}"


def _label_of(name: str) -> str:
    """The kind of object a name stands for: the name without copy numbers (``Chair.001``)."""
    return _COPY_NUMBER.sub("", name) or name


def _split_name(node_name: str) -> tuple[str, str]:
    """(name, label) of a node/object name, taking off a :func:`tagged_name` tag and label."""
    tag = TAG.match(node_name)
    if tag is None:
        return node_name, _label_of(node_name)
    label, sep, name = node_name[tag.end():].partition("__")
    if sep and label and name:
        return name, label
    rest = node_name[tag.end():]
    return rest, _label_of(rest)


class _Builder:
    """Turns the named meshes of one file into instances: options, categories, checks."""

    def __init__(self, path: Path, fmt: str, options: LoadOptions, house_id: str):
        scale, up = options.scale, str(options.up_axis).lower()
        number = isinstance(scale, (int, float)) and not isinstance(scale, bool)
        if not number or not np.isfinite(scale) or scale <= 0:
            raise SceneforgeError(f"scale must be a finite number > 0, got {scale!r}")
        if up not in ("y", "z"):
            raise SceneforgeError(f"up_axis must be 'y' or 'z', got {options.up_axis!r}")
        self.path = path
        self.options = options
        self.names = NameMap.with_user_rules(options.name_map)
        #: (3, 3) float64 source → world linear map (scale and up axis)
        self.to_world = float(scale) * (Z_UP_TO_Y_UP if up == "z" else np.eye(3))
        self.house = House(id=house_id, instances=[], rooms=[], source_format=fmt, source_path=str(path))

    def warn(self, message: str) -> None:
        if message not in self.house.warnings:
            self.house.warnings.append(message)

    def add(self, mesh: Mesh) -> None:
        """Add one mesh (in source units and axes) as an instance, unless it is dropped; a
        shell is split into its wall, floor and ceiling instances."""
        clean, label = _split_name(mesh.name)
        target, rule = self.names.match(mesh.name)
        for other in mesh.aliases:
            if target is None:
                target, rule = self.names.match(other)
        if target == DROP:
            self.warn(f"instance {clean!r} dropped by {rule.describe()}")
            return
        if isinstance(target, int) and is_dropped(target, label) or target is None and is_dropped(0, label):
            self.warn(f"instance {clean!r} ({label}) dropped: persons and plants are not kept")
            return
        v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3) @ self.to_world.T
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
        if target == SHELL:
            part = split_shell(v, faces)
            uv = None if mesh.uv is None or len(mesh.uv) != len(v) else np.asarray(mesh.uv)
            args = mesh.instance_args()
            for k, name in enumerate(PARTS):
                keep = part == k
                if keep.any():  # each part keeps the vertices its faces use, and their materials
                    used, f = np.unique(faces[keep], return_inverse=True)
                    part_args = {**args, "colors": None if args["colors"] is None else np.asarray(args["colors"])[used],
                                 "face_material": None if args["face_material"] is None
                                 else np.asarray(args["face_material"])[keep]}
                    self._add(f"{clean}/{name}", NYU40_IDS[name], label, v[used], f.reshape(-1, 3),
                              None if uv is None else uv[used], part_args)
            return
        category = resolve(self.house, label, target, strict=self.options.strict, file=self.path)
        self._add(clean, category, label, v, faces, mesh.uv, mesh.instance_args())

    def _add(self, name: str, category: int, label: str, v: np.ndarray, faces: np.ndarray, uv, material_args) -> None:
        make_instance(self.house, name=name, category=category, label=label, room_id=None,
                      vertices=v, faces=faces, file=self.path, uv=uv, **material_args)


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, options, source.id)


def _generic_format(name: str) -> Format:
    """The generic format ``name``: files with one of its suffixes, read by :func:`load_house`."""
    suffixes = tuple(s for s, fmt in SUFFIXES.items() if fmt == name)

    def detect(path: Path) -> bool:
        return path.suffix.lower() in suffixes and not path.is_dir()

    return Format(name, detect=detect, load=_load)


GLTF, OBJ, PLY = _generic_format("gltf"), _generic_format("obj"), _generic_format("ply")
