"""The in-memory house model every loader produces and everything downstream consumes.

A :class:`House` is a list of :class:`Instance` placed in world space (metres, +Y up),
plus its :class:`Room` and :class:`Level` records. It knows nothing about file formats,
renderers or ray tracers. Instances are built through :func:`make_instance`, the one
place that checks geometry and decides the envelope flag.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import NYU40_NAMES, is_envelope, tol
from ..errors import HouseError

if TYPE_CHECKING:
    import PIL.Image


#: how texture coordinates outside [0, 1] sample a texture (OpenGL's REPEAT,
#: CLAMP_TO_EDGE and MIRRORED_REPEAT; glTF's 10497, 33071 and 33648)
WRAPS = ("repeat", "clamp", "mirror")


@dataclass
class Material:
    """How a group of faces looks when rendered.

    base_color : (4,) float  linear RGBA in [0, 1]; multiplies the texture (SUNCG's ``Kd``
                 tints its ``map_Kd``, glTF's base-colour factor its texture)
    texture    : path of an image file, a PIL image (textures embedded in GLB), or None;
                 sampled with the instance's ``uv``; its texels are sRGB-encoded (decoded to
                 linear before shading)
    wrap       : (s, t) wrapping of the texture, each one of :data:`WRAPS`
    emission   : (3,) float  linear RGB the faces give off themselves (glTF's emissive factor
                 times its ``KHR_materials_emissive_strength``, OBJ's ``Ke``); (0, 0, 0) for
                 none. Read so that loaders know light emitters
                 (:mod:`sceneforge.houses.cleanup`); the renderers light a house their own
                 way (:mod:`sceneforge.render.lights`) and the native format does not keep it
    """

    base_color: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    texture: "Path | PIL.Image.Image | None" = None
    wrap: tuple[str, str] = ("repeat", "repeat")
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class Instance:
    """One object or envelope part of a house.

    vertices      : (n, 3) float64  world coordinates, metres, +Y up
    faces         : (m, 3) int64    counter-clockwise seen from outside (normals out)
    uv            : (n, 2) float32  texture coordinates, or None; OpenGL/OBJ convention: (0, 0)
                    is the bottom-left corner of the image, v = 0 its bottom row, v = 1 its top row
    category      : NYU40 id (0 = void)
    label         : the source's own category name (e.g. SUNCG fine class), kept for rules
                    that NYU40 cannot express (fireplace, chandelier, ...)
    envelope      : part of the room envelope (wall, floor, ceiling, door, window, ...)
    materials     : the materials of the instance's face groups (a chair's fabric and legs);
                    every one is used by some face
    face_material : (m,) int32  each face's index into ``materials``, or None: all use
                    ``materials[0]``
    colors        : (n, 4) float32  linear RGBA per vertex that multiplies the material
                    (PLY vertex colours), or None

    ``material`` is the one material of code that knows of one: the material covering the
    most area; setting it gives every face that material.
    """

    id: int
    name: str
    category: int
    label: str
    room_id: str | None
    vertices: np.ndarray
    faces: np.ndarray
    envelope: bool
    materials: tuple[Material, ...] = field(default_factory=lambda: (Material(),))
    uv: np.ndarray | None = None
    face_material: np.ndarray | None = None
    colors: np.ndarray | None = None

    @property
    def category_name(self) -> str:
        return NYU40_NAMES[self.category]

    @property
    def material(self) -> Material:
        if self.face_material is None or len(self.materials) == 1:
            return self.materials[0]
        area = np.linalg.norm(np.cross(*(self.vertices[self.faces[:, k]] - self.vertices[self.faces[:, 0]]
                                         for k in (1, 2))), axis=1)
        return self.materials[int(np.argmax(np.bincount(self.face_material, area, len(self.materials))))]

    @material.setter
    def material(self, material: Material) -> None:
        self.materials, self.face_material = (material,), None

    def face_materials(self) -> np.ndarray:
        """(m,) int32 each face's index into ``materials`` (zeros for one material)."""
        if self.face_material is None:
            return np.zeros(len(self.faces), np.int32)
        return self.face_material


@dataclass
class Room:
    """A room: id, type name (e.g. ``bedroom``) and the level it is on."""

    id: str
    type: str
    level: int


@dataclass
class Level:
    """A storey and the height of its floor (metres, world Y)."""

    id: int
    floor_y: float


@dataclass
class House:
    """A house: instances, rooms and levels, plus where it came from.

    ``warnings`` lists the problems a loader repaired or tolerated (dropped degenerate
    faces, unknown categories mapped to void, ...), for ``sceneforge houses inspect`` and the
    store's provenance. ``losses`` counts, by reason, the pieces a loader left out or flagged
    (:meth:`count_loss`); each reason also has one line in ``warnings``. ``notes`` says what a
    loader decided that is no problem but worth knowing: the up axis it detected, and why
    (:mod:`sceneforge.houses.up_axis`).
    """

    id: str
    instances: list[Instance]
    rooms: list[Room] = field(default_factory=list)
    levels: list[Level] = field(default_factory=lambda: [Level(0, 0.0)])
    source_format: str = "sceneforge"
    source_path: str | None = None
    warnings: list[str] = field(default_factory=list)
    losses: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def count_loss(self, reason: str, n: int = 1) -> None:
        """Count ``n`` more pieces left out (or flagged) for ``reason``; the line
        ``"<reason>: <total>"`` in ``warnings`` says the running total."""
        old = self.losses.get(reason)
        self.losses[reason] = (old or 0) + n
        line = f"{reason}: {self.losses[reason]}"
        if old is None:
            self.warnings.append(line)
        else:
            self.warnings[self.warnings.index(f"{reason}: {old}")] = line

    @property
    def triangle_count(self) -> int:
        return int(sum(len(i.faces) for i in self.instances))

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 axis-aligned bounds of all instances."""
        v = np.concatenate([i.vertices for i in self.instances])
        return np.stack([v.min(0), v.max(0)])

    def check_not_empty(self) -> "House":
        """Raise :class:`HouseError` when no instance survived loading."""
        if not self.instances:
            raise HouseError(self.id, self.source_path, "house is empty (no instance with geometry)")
        return self


def make_instance(
    house: House,
    *,
    name: str,
    category: int,
    label: str,
    room_id: str | None,
    vertices,
    faces,
    file: str | Path | None = None,
    material: Material | Sequence[Material] | None = None,
    uv=None,
    face_material=None,
    colors=None,
) -> Instance | None:
    """Check one mesh and add it to ``house`` as a new instance.

    material      : one material, or the materials of the face groups that ``face_material``
                    ((m,) int, an index into them per face) assigns; None: the default one
    colors        : (n, 4) linear RGBA per vertex multiplying the material, or None

    Raises :class:`HouseError` for non-finite vertices, faces indexing past the vertex
    array or face materials past the materials. Degenerate faces (repeated index or zero
    area) are dropped and counted in ``house.warnings``; materials that no face is left
    with are dropped too. Returns None (and adds nothing) when no face is left.
    """
    where = file or house.source_path
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v).all(axis=1)).sum())
        raise HouseError(house.id, where, f"instance {name!r}: {bad} vertices are NaN or infinite")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise HouseError(
            house.id, where,
            f"instance {name!r}: face index {int(f.max() if f.max() >= len(v) else f.min())} "
            f"is outside the {len(v)} vertices",
        )
    materials = ((material or Material(),) if material is None or isinstance(material, Material)
                 else tuple(m or Material() for m in material))
    fm = None
    if face_material is not None:
        fm = np.asarray(face_material, dtype=np.int64).reshape(-1)
        if len(fm) != len(f) or (len(fm) and (fm.min() < 0 or fm.max() >= len(materials))):
            raise HouseError(house.id, where, f"instance {name!r}: face materials must be {len(f)} indices "
                                              f"into its {len(materials)} materials")
    elif len(materials) > 1:
        raise HouseError(house.id, where, f"instance {name!r}: {len(materials)} materials but no face materials")
    if not 0 <= category < len(NYU40_NAMES):
        raise HouseError(house.id, where, f"instance {name!r}: NYU40 id {category} is not in 0..40")
    if len(f):
        area2 = np.linalg.norm(
            np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1
        )
        keep = (area2 > 2 * tol.degenerate_area) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (
            f[:, 0] != f[:, 2]
        )
        dropped = int((~keep).sum())
        if dropped:
            house.warnings.append(f"instance {name!r}: dropped {dropped} degenerate faces")
            f = f[keep]
            fm = None if fm is None else fm[keep]
    if not len(f):
        house.warnings.append(f"instance {name!r}: no faces, skipped")
        return None
    if uv is not None:
        uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
        if len(uv) != len(v):
            uv = None
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float32).reshape(-1, 4)
        if len(colors) != len(v):
            raise HouseError(house.id, where, f"instance {name!r}: {len(colors)} vertex colours for {len(v)} vertices")
    if fm is not None:
        used, fm = np.unique(fm, return_inverse=True)
        materials = tuple(materials[k] for k in used)
        fm = fm.astype(np.int32) if len(materials) > 1 else None
    inst = Instance(
        id=len(house.instances),
        name=name,
        category=int(category),
        label=label,
        room_id=room_id,
        vertices=v,
        faces=f,
        envelope=is_envelope(int(category), label),
        materials=materials,
        uv=uv,
        face_material=fm,
        colors=colors,
    )
    house.instances.append(inst)
    return inst
