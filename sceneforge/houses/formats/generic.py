"""Generic scenes: glTF 2.0 (``.gltf``/``.glb``), Wavefront OBJ and PLY, read as houses.

A generic scene has no rooms and no categories, only named meshes. Each format module
turns its file into meshes (:mod:`~sceneforge.houses.formats.gltf`: one per node,
:mod:`~sceneforge.houses.formats.obj`: one per ``o`` object or ``g`` group,
:mod:`~sceneforge.houses.formats.ply`: one per ``instance`` property value);
this module makes instances of the meshes and names them:

- The category of an instance comes from its name through a
  :class:`~sceneforge.houses.names.NameMap` (the rules of ``LoadOptions.name_map`` by first
  match, then the bundled ones by the name's head word); its ``label`` is the name without Blender-style copy numbers
  (``Chair.001`` → ``Chair``), so that rules on source labels (fireplace, plant, ...) see
  the object's kind. Persons, plants and names sent to ``drop`` are left out; a mesh sent
  to ``shell`` becomes up to three instances ``<name>/wall``, ``<name>/floor`` and
  ``<name>/ceiling`` (:func:`~sceneforge.houses.shell.split_shell`).
- Names can be wrong where the geometry is not: once every mesh is an instance, a closed
  room box is split like a shell and light emitters outside every room are dropped
  (:func:`~sceneforge.houses.cleanup.clean_up`).
- The scene has no rooms: they are derived from its floors (:mod:`sceneforge.houses.rooms`).
- ``LoadOptions.scale`` and ``up_axis`` take the source's units and axes to metres, +Y up.
  With ``up_axis`` ``auto`` (the default) every mesh of the file is read first and the axis
  decided from them (:func:`~sceneforge.houses.up_axis.detect_up_axis`); the decision and its
  evidence are the house's first note, and a scene it cannot tell fails with a one-line hint.
- The three formats (:data:`GLTF`, :data:`OBJ`, :data:`PLY`, as the registry holds them) are
  recognised by their file suffixes (:data:`SUFFIXES`) and all read by :func:`load_house`,
  which also reads the files of a scene folder as one house (:mod:`.scene`); there a mesh
  whose name says nothing (:data:`GENERIC_NAME`: ``default``, ``Mesh``, ``Object001``...) is
  named after its file.
- The writers (:mod:`sceneforge.testing.generic`) name every instance ``<nyu40 name>__<name>``, or
  ``<nyu40 name>__<label>__<name>`` when the label is not the one the name gives (or the
  name holds ``__``): the bundled pattern map sends the tag back to the same class, and the
  loader takes tag and label off the name.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...conventions import NYU40_IDS, NYU40_NAMES, is_dropped
from ...errors import HouseError, SceneforgeError
from ..categories import resolve
from ..cleanup import clean_up
from ..model import House, Instance, make_instance
from ..names import DROP, SHELL, TAG, NameMap, Rule
from ..rooms import derive_rooms
from ..shell import pieces, split_shell
from ..up_axis import Part, detect_up_axis
from .base import Format, HouseSource
from .gltf import read_gltf
from .meshio import Mesh, MeshFileError
from .obj import read_objects
from .ply import read_ply

if TYPE_CHECKING:
    from .. import LoadOptions

__all__ = ["GENERIC_NAME", "GLTF", "OBJ", "PLY", "SUFFIXES", "UP_AXES", "load_house", "tagged_name"]

#: file suffix → the generic format it is
SUFFIXES = {".gltf": "gltf", ".glb": "gltf", ".obj": "obj", ".ply": "ply"}

#: rotation taking a Z-up source to +Y up, right-handed: (x, y, z) → (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: the values of ``LoadOptions.up_axis``: detect it, or the source's +Y or +Z
UP_AXES = ("auto", "y", "z")

#: object names a tool gives when the user gave none: in a scene folder such a mesh is
#: named after its file (``Chair.obj`` holding ``o default``: ``Chair``)
GENERIC_NAME = re.compile(
    r"^(?:default(?:_?object)?|mesh|object|obj|node|group|geometry|model|body|part|shape|submesh|primitive|"
    r"untitled|scene|polysurface|p?cube)?(?:[._ -]?\d+)*$", re.IGNORECASE)

#: format → the reader of its files: ``reader(path, warn)`` yields the file's meshes
_READERS = {"gltf": read_gltf, "obj": read_objects, "ply": read_ply}

# Blender ".001", "_2", " 3": copies of one object, not different kinds of object.
_COPY_NUMBER = re.compile(r"(?:[._ -]\d+)+$")


def load_house(path: str | Path, options: LoadOptions | None = None, house_id: str | None = None, *,
               files: Sequence[Path] | None = None, rules: tuple[Rule, ...] = ()) -> House:
    """Read a glTF/GLB, OBJ or PLY scene as a house (id ``house_id``, default the file stem).

    ``options`` is a :class:`sceneforge.houses.LoadOptions`; ``scale``, ``up_axis``,
    ``name_map`` and ``strict`` apply. Rooms and levels are derived from the floors. Raises
    :class:`HouseError` naming the house, the file and the problem for anything unreadable
    (a scene whose up axis cannot be told too), and :class:`SceneforgeError` for a bad option.

    files : the mesh files of the scene folder ``path``, read as one house in this order
            (:mod:`.scene`); None: ``path`` is the one file
    rules : name rules tried before those of ``options.name_map`` (a ``scene.json``'s)
    """
    from .. import LoadOptions

    path = Path(path)
    options = options or LoadOptions()
    fmt = "scene" if files is not None else SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise SceneforgeError(f"{path}: not a generic scene (expected one of {', '.join(SUFFIXES)})")
    files = [path] if files is None else [Path(f) for f in files]
    builder = _Builder(path, fmt, options, house_id or path.stem, rules,
                       prefer_y=all(SUFFIXES.get(f.suffix.lower()) == "gltf" for f in files))
    count = 0
    for file in files:
        if not file.is_file():
            raise HouseError(builder.house.id, file, "no such file")
        try:
            for mesh in _READERS[SUFFIXES[file.suffix.lower()]](file, builder.warn):
                builder.add(mesh, file)  # one at a time: warnings stay in file order
                count += 1
        except MeshFileError as e:
            raise HouseError(builder.house.id, e.file or file, e.problem) from None
    if not count:
        raise HouseError(builder.house.id, path, "no faces")
    builder.finish()
    return derive_rooms(clean_up(builder.house.check_not_empty(), builder.names))


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
    """Turns the named meshes of one file (or of a scene folder's files) into instances:
    options, up axis, categories, checks.

    With ``up_axis`` ``auto`` the meshes wait (with the reader warnings said before each)
    until :meth:`finish` has decided the axis from all of them; else each is placed as it comes.
    """

    def __init__(self, path: Path, fmt: str, options: LoadOptions, house_id: str,
                 rules: tuple[Rule, ...] = (), *, prefer_y: bool = False):
        scale, up = options.scale, str(options.up_axis).lower()
        number = isinstance(scale, (int, float)) and not isinstance(scale, bool)
        if not number or not np.isfinite(scale) or scale <= 0:
            raise SceneforgeError(f"scale must be a finite number > 0, got {scale!r}")
        if up not in UP_AXES:
            raise SceneforgeError(f"up_axis must be 'auto', 'y' or 'z', got {options.up_axis!r}")
        self.path = path
        self.fmt = fmt
        self.options = options
        self.prefer_y = prefer_y
        names = NameMap.with_user_rules(options.name_map)
        self.names = replace(names, user=tuple(rules) + names.user) if rules else names
        self.scale = float(scale)
        #: (3, 3) float64 source → world linear map (scale and up axis); None until decided
        self.to_world = None if up == "auto" else self._world(up)
        #: the meshes waiting for the up axis: (warnings said before it, mesh, its file)
        self._waiting: list[tuple[list[str], Mesh, Path]] | None = [] if up == "auto" else None
        self._unsaid: list[str] = []
        self.house = House(id=house_id, instances=[], rooms=[], source_format=fmt, source_path=str(path))

    def _world(self, up: str) -> np.ndarray:
        return self.scale * (Z_UP_TO_Y_UP if up == "z" else np.eye(3))

    def warn(self, message: str) -> None:
        if self._waiting is not None:
            self._unsaid.append(message)
        elif message not in self.house.warnings:
            self.house.warnings.append(message)

    def add(self, mesh: Mesh, file: Path) -> None:
        """Add one mesh of ``file`` (in source units and axes): now, or when the up axis is
        decided (:meth:`finish`). In a scene folder a generic name gives way to the file's."""
        if self.fmt == "scene" and GENERIC_NAME.match(_split_name(mesh.name)[0]):
            mesh = replace(mesh, name=file.stem)
        if self._waiting is None:
            self._place(mesh, file)
        else:
            self._waiting.append((self._unsaid, mesh, file))
            self._unsaid = []

    def finish(self) -> None:
        """Decide the up axis of the meshes that wait for it and place them; the decision is
        the house's first note. Raises :class:`HouseError` when it cannot be told."""
        if self._waiting is None:
            return
        parts = []
        for _, mesh, _ in self._waiting:
            target, label = self._target(mesh)[1:3]
            v = np.asarray(mesh.vertices, np.float64).reshape(-1, 3)
            f = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
            sound = np.isfinite(v).all() and (not len(f) or 0 <= f.min() and f.max() < len(v))
            if sound and target != DROP and not self._dropped(target, label):  # the others fail when placed
                kind = {NYU40_IDS["floor"]: "floor", NYU40_IDS["ceiling"]: "ceiling"}.get(target)
                parts.append(Part(v, f, kind))
        up = detect_up_axis(parts, prefer_y=self.prefer_y)
        waiting, unsaid = self._waiting, self._unsaid
        self._waiting, self._unsaid = None, []
        # undecided, the meshes are still placed (+Y up) so that a broken one's own error comes first
        self.to_world = self._world(up.axis or "y")
        for said, mesh, file in waiting:
            for message in said:
                self.warn(message)
            self._place(mesh, file)
        for message in unsaid:
            self.warn(message)
        if up.axis is not None:
            if up.upside_down and self.house.instances:  # read so, its layers and cameras would be upside down
                raise HouseError(self.house.id, self.path,
                                 f"the scene is upside down (-{up.axis.upper()} up: {up.upside_down}): export it "
                                 f"+Y or +Z up (if it is not upside down, pass --up-axis {up.axis})")
            self.house.notes.insert(0, f"up axis: {up.axis} ({up.reason}); pass --up-axis to override")
        elif self.house.instances:  # an empty house fails as one (House.check_not_empty)
            raise HouseError(self.house.id, self.path,
                             f"cannot tell the up axis ({up.reason}): pass --up-axis y or --up-axis z")

    def _target(self, mesh: Mesh):
        """(clean name, target, label, rule) of a mesh by its names (:mod:`..names`)."""
        clean, label = _split_name(mesh.name)
        target, rule = self.names.match(mesh.name)
        for other in mesh.aliases:
            if target is None:
                target, rule = self.names.match(other)
        return clean, target, label, rule

    @staticmethod
    def _dropped(target, label: str) -> bool:
        """Persons and plants (by class and label) are not kept."""
        return isinstance(target, int) and is_dropped(target, label) or target is None and is_dropped(0, label)

    def _place(self, mesh: Mesh, file: Path) -> None:
        """Add one mesh as an instance, unless it is dropped; a shell is split into its wall,
        floor and ceiling instances."""
        clean, target, label, rule = self._target(mesh)
        if target == DROP:
            self.warn(f"instance {clean!r} dropped by {rule.describe()}")
            return
        if self._dropped(target, label):
            self.warn(f"instance {clean!r} ({label}) dropped: persons and plants are not kept")
            return
        v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3) @ self.to_world.T
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
        if target == SHELL:
            part = split_shell(v, faces)
            uv = None if mesh.uv is None or len(mesh.uv) != len(v) else np.asarray(mesh.uv)
            args = mesh.instance_args()
            for name, used, f, keep in pieces(faces, part):  # each keeps its vertices and their materials
                part_args = {**args, "colors": None if args["colors"] is None else np.asarray(args["colors"])[used],
                             "face_material": None if args["face_material"] is None
                             else np.asarray(args["face_material"])[keep]}
                self._add(f"{clean}/{name}", NYU40_IDS[name], label, v[used], f, None if uv is None else uv[used],
                          part_args, file)
            return
        category = resolve(self.house, label, target, strict=self.options.strict, file=file)
        self._add(clean, category, label, v, faces, mesh.uv, mesh.instance_args(), file)

    def _add(self, name: str, category: int, label: str, v: np.ndarray, faces: np.ndarray, uv, material_args,
             file: Path) -> None:
        make_instance(self.house, name=name, category=category, label=label, room_id=None,
                      vertices=v, faces=faces, file=file, uv=uv, **material_args)


def _load(source: HouseSource, options: LoadOptions) -> House:
    return load_house(source.path, options, source.id)


def _generic_format(name: str) -> Format:
    """The generic format ``name``: files with one of its suffixes, read by :func:`load_house`."""
    suffixes = tuple(s for s, fmt in SUFFIXES.items() if fmt == name)

    def detect(path: Path) -> bool:
        return path.suffix.lower() in suffixes and not path.is_dir()

    return Format(name, detect=detect, load=_load)


GLTF, OBJ, PLY = _generic_format("gltf"), _generic_format("obj"), _generic_format("ply")
