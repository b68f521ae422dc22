"""What every mesh file reader shares, whatever the format.

A reader turns a file into :class:`Mesh` records (source units and axes, no sceneforge
categories) and reports what it cannot read as :class:`MeshFileError`; the loader that
called it names the house. The writers (tests only) are in :mod:`sceneforge.testing`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..model import Material

#: Receives each problem a reader tolerated (a missing texture, a dropped material, ...).
Warn = Callable[[str], None]

# Image files tried, in order, in place of a missing texture image with the same stem.
_TWIN_SUFFIXES = (".png", ".jpg", ".jpeg")


class MeshFileError(ValueError):
    """A mesh file cannot be read: ``problem``, and the ``file`` at fault when it is not the
    file being read (a glTF buffer, ...)."""

    def __init__(self, problem: str, file: Path | None = None):
        super().__init__(problem)
        self.problem, self.file = problem, file


@dataclass
class Mesh:
    """One triangle mesh as a file holds it.

    vertices : (n, 3) float64  source units and axes
    faces    : (m, 3) int64    indices into ``vertices``, counter-clockwise seen from outside
    uv       : (n, 2) float    texture coordinates as :class:`~sceneforge.houses.model.Instance`
               has them (v = 0 at the image bottom), or None
    material : the mesh's one material, None for the default, or the materials (a tuple) of
               its face groups that ``face_material`` assigns
    name     : the object/node name in the file ("" when it has none)
    aliases  : further names its category may be looked up by (a glTF node's mesh name)
    face_material : (m,) int32  each face's index into the ``material`` tuple, or None
    colors   : (n, 4) float32  linear RGBA per vertex multiplying the material, or None
    material_names : the file's name of each face group's material (OBJ ``usemtl``; "" for
               the default), in :attr:`materials` order; () when the format has none
    library  : every material the file's libraries define, by name in file order (OBJ
               ``newmtl``, used or not: SUNCG's node overrides count materials in it)
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    material: Material | tuple[Material, ...] | None = None
    name: str = ""
    aliases: tuple[str, ...] = ()
    face_material: np.ndarray | None = None
    colors: np.ndarray | None = None
    material_names: tuple[str, ...] = ()
    library: tuple[str, ...] = ()

    @property
    def materials(self) -> tuple[Material, ...]:
        """The materials of the face groups (one for a one-material mesh)."""
        m = self.material
        return m if isinstance(m, tuple) else (m or Material(),)

    def face_materials(self) -> np.ndarray:
        """(m,) int32 each face's index into :attr:`materials`."""
        if self.face_material is None:
            return np.zeros(len(self.faces), np.int32)
        return np.asarray(self.face_material, np.int32)

    def instance_args(self) -> dict:
        """The material keywords of :func:`~sceneforge.houses.model.make_instance` for this mesh."""
        return {"material": self.material, "face_material": self.face_material, "colors": self.colors}


def ignore(message: str) -> None:
    """A :data:`Warn` that drops the message."""


# --------------------------------------------------------------------------- geometry


def place(vertices, faces, matrix) -> tuple[np.ndarray, np.ndarray]:
    """Apply an affine 4×4 ``matrix`` to a mesh; a mirroring matrix also reverses the winding.

    vertices : (n, 3) float64 → (n, 3) float64
    faces    : (m, 3) int64   → (m, 3) int64, each triangle reversed when det < 0 so that
               normals still point outward
    """
    m = np.asarray(matrix, dtype=np.float64)
    v = np.asarray(vertices, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]
    f = np.asarray(faces, dtype=np.int64)
    if np.linalg.det(m[:3, :3]) < 0:
        f = f[:, ::-1]
    return v, f


def quaternion_matrix(q) -> np.ndarray:
    """(3, 3) float64 rotation of the unit quaternion ``q = (x, y, z, w)`` (normalised here)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def fan(polygons: np.ndarray) -> np.ndarray:
    """Triangles (n * (k - 2), 3) of n convex k-gons (n, k) by fans around their first corners."""
    k = polygons.shape[1]
    fans = np.stack([np.repeat(polygons[:, :1], k - 2, axis=1), polygons[:, 1:-1], polygons[:, 2:]], axis=2)
    return fans.reshape(-1, 3)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) float64 areas of faces (m, 3) int over vertices (n, 3) float."""
    v = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def compact(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices ``faces`` (m, 3) int uses, in index order: (used (n,) int64, faces (m, 3)
    int64 re-indexed into ``used``)."""
    used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
    return used, inverse.reshape(-1, 3).astype(np.int64)


# --------------------------------------------------------------------------- materials, textures


def find_image(path: Path, warn: Warn, warn_missing: bool = False) -> Path | None:
    """``path`` if it exists, else a ``.png``/``.jpg`` twin beside it (with a warning), else None."""
    if path.is_file():
        return path
    for twin in (path.with_suffix(s) for s in _TWIN_SUFFIXES):
        if twin != path and twin.is_file():
            warn(f"texture {path.name} is missing, using {twin.name}")
            return twin
    if warn_missing:
        warn(f"texture {path.name} is missing; no texture")
    return None
