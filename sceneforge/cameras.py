"""Pinhole cameras: intrinsics, poses and PBRS camera files (docs/spec.md §1); the seeded camera
sampler that places them in a house is :mod:`sceneforge.camera_sampler` (docs/spec.md §3).

The conventions cameras follow are defined in :mod:`sceneforge.conventions` (OpenCV axes
``CAMERA_AXES``, pixel centres at integer + ``PIXEL_CENTRE``, planar depth). This module
implements them: ``cam_to_world`` is a 4×4 float64 pose whose columns are the camera
axes and the camera centre in world coordinates; the default principal point is the
image centre ``(W/2, H/2)``; and :func:`opencv_to_opengl` is the only conversion to the
pyrender/OpenGL axes (x right, y up, z backward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np

from .conventions import tol
from .errors import SceneforgeError

#: PBRS default horizontal half field of view, radians (docs/spec.md §1).
DEFAULT_HALF_FOV_X = 0.5534
#: PBRS default downward pitch: the view direction drops 1 m per 5 m (11.31°).
DEFAULT_PITCH = math.atan(0.2)

_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole camera, OpenCV axes (x right, y down, z forward), pixel centres at integer + 0.5.

    K            : (3, 3) float64  intrinsics in pixels
    cam_to_world : (4, 4) float64  pose; rotation part orthonormal with determinant +1
    width, height: image size in pixels
    """

    K: np.ndarray
    cam_to_world: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        K = np.array(self.K, dtype=np.float64)
        pose = np.array(self.cam_to_world, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite (3, 3) matrix with positive focal lengths, got {K!r}")
        if pose.shape != (4, 4) or not np.isfinite(pose).all() or not np.array_equal(pose[3], [0, 0, 0, 1]):
            raise ValueError(f"cam_to_world must be a finite (4, 4) rigid transform, got {pose!r}")
        R = pose[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=tol.rotation) or np.linalg.det(R) < 0:
            raise ValueError("cam_to_world rotation must be orthonormal and right-handed")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}×{self.height}")
        K.flags.writeable = False
        pose.flags.writeable = False
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "cam_to_world", pose)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self.height, self.width

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates."""
        return self.cam_to_world[:3, 3].copy()

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) float64 camera-to-world rotation; columns are the x, y, z camera axes."""
        return self.cam_to_world[:3, :3].copy()

    @property
    def view_direction(self) -> np.ndarray:
        """(3,) float64 unit forward (camera +z) axis in world coordinates."""
        return self.cam_to_world[:3, 2].copy()

    @property
    def half_fov(self) -> tuple[float, float]:
        """Horizontal and vertical half-angles (radians) of a centred principal point."""
        return (
            math.atan(0.5 * self.width / self.K[0, 0]),
            math.atan(0.5 * self.height / self.K[1, 1]),
        )

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera (pose, field of view) rendering ``width``×``height`` pixels."""
        scale = np.diag([width / self.width, height / self.height, 1.0])
        return Camera(scale @ self.K, self.cam_to_world, width, height)

    def rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One ray per pixel, through the pixel centre (computed once per camera, read-only).

        Returns
        -------
        origins     : (H*W, 3) float64  camera centre, world (one row, broadcast)
        directions  : (H*W, 3) float64  unit directions, world, row-major pixel order
        depth_scale : (H*W,) float64    planar depth of the point ``origin + t * direction``
                      is ``t * depth_scale``
        """
        return self._rays

    @cached_property
    def _rays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d_cam, depth_scale = _pixel_directions(self.K.tobytes(), self.width, self.height)
        from .raytrace import checked_directions

        directions = d_cam @ self.cam_to_world[:3, :3].T
        directions.flags.writeable = False
        checked_directions(directions)  # unit and finite: the tracers need not scan them again
        origins = np.broadcast_to(self.cam_to_world[:3, 3], directions.shape)
        return origins, directions, depth_scale

    def world_to_camera(self, points_world) -> np.ndarray:
        """(n, 3) float64 camera-frame coordinates of (n, 3) world points."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return (p - self.cam_to_world[:3, 3]) @ self.cam_to_world[:3, :3]

    def project(self, points_world) -> tuple[np.ndarray, np.ndarray]:
        """Project world points into the image.

        points_world : (n, 3) float
        Returns ``uv`` (n, 2) float64 continuous pixel coordinates (pixel ``(i, j)`` has its
        centre at ``(j + 0.5, i + 0.5)``) and ``z`` (n,) float64 planar depth. Points with
        ``z <= 0`` are behind the camera; their ``uv`` is meaningless (inf/NaN at z = 0).
        """
        p = self.world_to_camera(points_world)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = p @ self.K.T
            uv = uvw[:, :2] / z[:, None]
        return uv, z


@lru_cache(maxsize=8)
def _pixel_directions(K_bytes: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit camera-frame directions (H*W, 3) through the pixel centres of intrinsics ``K``
    (its float64 bytes), and their z (the planar depth of unit distance). Shared, read-only:
    every view of a render has the same intrinsics, only the pose changes."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    n = width * height
    pixels = np.ones((n, 3))
    pixels[:, 0] = np.tile(np.arange(width) + 0.5, height)
    pixels[:, 1] = np.repeat(np.arange(height) + 0.5, width)
    d_cam = pixels @ np.linalg.inv(K).T
    d_cam /= np.sqrt(np.einsum("ij,ij->i", d_cam, d_cam))[:, None]
    depth_scale = d_cam[:, 2].copy()
    d_cam.flags.writeable = False
    depth_scale.flags.writeable = False
    return d_cam, depth_scale


def opencv_to_opengl(cam_to_world) -> np.ndarray:
    """Convert a (..., 4, 4) OpenCV pose (x right, y down, z forward) to OpenGL axes
    (x right, y up, z backward), as pyrender expects. The conversion is its own inverse."""
    return np.asarray(cam_to_world, dtype=np.float64) @ _OPENCV_TO_OPENGL


def default_intrinsics(
    width: int = 320, height: int = 240, half_fov_x: float = DEFAULT_HALF_FOV_X
) -> np.ndarray:
    """(3, 3) float64 PBRS-style intrinsics: square pixels, principal point at the image centre.

    With the defaults, fx = fy = 160 / tan(0.5534) ≈ 259.0 px and the vertical half-FOV is
    atan(120 / fy) ≈ 0.4339 rad (docs/spec.md §1).
    """
    if not 0 < half_fov_x < math.pi / 2:
        raise ValueError(f"half_fov_x must be in (0, pi/2) radians, got {half_fov_x}")
    f = 0.5 * width / math.tan(half_fov_x)
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def pose_from_view(position, view_dir, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) float64 OpenCV ``cam_to_world`` at ``position`` looking along ``view_dir``.

    ``up`` only fixes the roll: camera y (down) is the component of ``-up`` orthogonal to
    the view direction. Raises ValueError when ``view_dir`` is zero or parallel to ``up``.
    """
    position = np.asarray(position, dtype=np.float64).reshape(3)
    z = np.asarray(view_dir, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    nz = np.linalg.norm(z)
    if not nz > 0 or not np.isfinite(nz):
        raise ValueError(f"view direction must be a non-zero finite vector, got {z}")
    z = z / nz
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < tol.parallel * max(np.linalg.norm(up), 1e-300):
        raise ValueError(f"view direction {z} is parallel to the up vector {up}")
    x /= nx
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, position
    return pose


def look_at_camera(
    position, view_dir, up=(0.0, 1.0, 0.0), K=None, width: int = 320, height: int = 240
) -> Camera:
    """A :class:`Camera` at ``position`` looking along ``view_dir`` with roll set by ``up``.

    ``K`` defaults to :func:`default_intrinsics` for ``width``×``height``.
    """
    if K is None:
        K = default_intrinsics(width, height)
    return Camera(K, pose_from_view(position, view_dir, up), width, height)


# ---------------------------------------------------------------------------------------
# PBRS camera files: one camera per line, ``px py pz  vx vy vz  ux uy uz  xfov yfov score``
# (position, view direction, up vector, horizontal and vertical half-FOV in radians, score).


def camera_from_pbrs(fields: str | Sequence[float], width: int = 320, height: int = 240) -> Camera:
    """A camera from one PBRS line (a string or its 11 or 12 numbers; the score is ignored).

    The focal lengths come from the half-FOVs: fx = (W/2) / tan(xfov), fy = (H/2) / tan(yfov).
    Raises ValueError for a malformed line.
    """
    values = fields.split() if isinstance(fields, str) else list(fields)
    if len(values) not in (11, 12):
        raise ValueError(
            f"expected 12 numbers (px py pz vx vy vz ux uy uz xfov yfov score), got {len(values)}"
        )
    try:
        v = np.array([float(x) for x in values], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"not a list of numbers: {' '.join(map(str, values))}") from None
    if not np.isfinite(v).all():
        raise ValueError("camera values must be finite")
    xfov, yfov = v[9], v[10]
    if not (0 < xfov < math.pi / 2 and 0 < yfov < math.pi / 2):
        raise ValueError(f"half-FOVs must be in (0, pi/2) radians, got {xfov} and {yfov}")
    K = np.array([
        [0.5 * width / math.tan(xfov), 0.0, 0.5 * width],
        [0.0, 0.5 * height / math.tan(yfov), 0.5 * height],
        [0.0, 0.0, 1.0],
    ])
    return Camera(K, pose_from_view(v[0:3], v[3:6], v[6:9]), width, height)


def read_pbrs_cameras(path: str | Path, width: int = 320, height: int = 240) -> list[Camera]:
    """All cameras of a PBRS camera file (blank lines and ``#`` comments are skipped).

    Raises :class:`SceneforgeError` naming the file and line when it cannot be read.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SceneforgeError(f"{path}: cannot read camera file ({e.strerror or e})") from None
    cameras = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            cameras.append(camera_from_pbrs(line, width, height))
        except ValueError as e:
            raise SceneforgeError(f"{path}:{lineno}: {e}") from None
    return cameras


def pbrs_fields(camera: Camera, score: float = 0.0) -> list[float]:
    """The 12 PBRS numbers of a camera. Raises ValueError when the principal point is not the
    image centre or the intrinsics are skewed (the format cannot express that)."""
    K = camera.K
    centre = (0.5 * camera.width, 0.5 * camera.height)
    if not (np.isclose(K[0, 2], centre[0]) and np.isclose(K[1, 2], centre[1]) and K[0, 1] == 0):
        raise ValueError(
            "PBRS camera files need an unskewed camera with the principal point at the image centre"
        )
    xfov, yfov = camera.half_fov
    return [
        *camera.position, *camera.view_direction, *(-camera.cam_to_world[:3, 1]), xfov, yfov, float(score)
    ]


def write_pbrs_cameras(
    path: str | Path, cameras: Sequence[Camera], scores: Sequence[float] | None = None
) -> None:
    """Write cameras as a PBRS camera file (FOVs as half-angles, score 0 unless given).

    Numbers are written with ``repr`` precision, so reading the file back gives the same
    cameras to within float64 rounding.
    """
    scores = [0.0] * len(cameras) if scores is None else list(scores)
    if len(scores) != len(cameras):
        raise ValueError(f"{len(scores)} scores for {len(cameras)} cameras")
    lines = [" ".join(repr(float(x)) for x in pbrs_fields(c, s)) for c, s in zip(cameras, scores)]
    Path(path).write_text("".join(line + "\n" for line in lines))
