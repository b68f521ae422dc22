"""The gravity-aligned frame of a frontal camera, and boxes on its floor plane."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import tol
from ..errors import SceneforgeError

if TYPE_CHECKING:
    from ..cameras import Camera


@dataclass(frozen=True, eq=False)
class GravityFrame:
    """The gravity-aligned frame of a frontal camera.

    origin  : (3,) float64  camera centre, world
    right   : (3,) float64  unit, horizontal
    forward : (3,) float64  unit, horizontal: the view direction flattened
    theta   : float         angle (rad) between the view direction and gravity (−Y)
    """

    origin: np.ndarray
    right: np.ndarray
    forward: np.ndarray
    theta: float

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) float64 rows ``right, up, forward`` in world coordinates."""
        return np.stack([self.right, np.array([0.0, 1.0, 0.0]), self.forward])

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """World points (n, 3) → frame coordinates (n, 3) ``(right, up, forward)``."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Frame coordinates (n, 3) ``(right, up, forward)`` → world points (n, 3)."""
        return np.asarray(points, dtype=np.float64) @ self.axes + self.origin


def gravity_frame(camera: "Camera") -> GravityFrame:
    """The gravity-aligned frame of ``camera``. Raises for a camera looking straight up or down."""
    T = np.asarray(camera.cam_to_world, dtype=np.float64)
    view = T[:3, 2] / np.linalg.norm(T[:3, 2])
    flat = np.array([view[0], 0.0, view[2]])
    if np.linalg.norm(flat) < tol.horizontal_view:
        raise SceneforgeError(
            "the frontal camera looks straight up or down: its view direction has no "
            "horizontal part to align the overhead camera with"
        )
    forward = flat / np.linalg.norm(flat)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    theta = float(np.arccos(np.clip(-view[1], -1.0, 1.0)))
    return GravityFrame(origin=T[:3, 3].copy(), right=right, forward=forward, theta=theta)


@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box on the floor plane of a gravity-aligned frame.

    lo, hi : (2,) float64  corners as ``(right, forward)``, metres
    """

    lo: np.ndarray
    hi: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """(2,) float64 ``(right, forward)``."""
        return 0.5 * (self.lo + self.hi)

    @property
    def half_size(self) -> np.ndarray:
        """(2,) float64 half widths along ``(right, forward)``."""
        return 0.5 * (self.hi - self.lo)

    @property
    def area(self) -> float:
        """Floor area, m²."""
        w = self.hi - self.lo
        return float(w[0] * w[1])

    def square(self) -> "Box":
        """The smallest square with the same centre that contains this box."""
        half = float(self.half_size.max())
        return Box(self.center - half, self.center + half)

    def __repr__(self) -> str:
        return (f"Box(right {self.lo[0]:.3f}..{self.hi[0]:.3f}, "
                f"forward {self.lo[1]:.3f}..{self.hi[1]:.3f})")
