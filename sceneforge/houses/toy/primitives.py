"""Geometry of the toy houses: closed axis-aligned boxes and vertical cylinders (:class:`Part`),
their meshes, overlap tests, and the four placements that keep them axis-aligned (:class:`Frame`).

Sizes drawn with :func:`cm` are rounded to centimetres; the circle of a cylinder is a fixed
rounded table, so that meshes are the same bytes on every platform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: corners of a cylinder's polygon on the unit circle, (12, 2) float64 (cos, sin). Rounded
#: so that a last-bit difference between platforms' libm cannot change the written bytes.
_CIRCLE = np.round(
    np.array([(math.cos(a), math.sin(a)) for a in np.arange(12) * (2 * math.pi / 12)]), 12
)
EPS = 1e-9  # parts closer than this count as touching, not overlapping


@dataclass(frozen=True)
class Part:
    """A closed primitive given by its axis-aligned bounds: a box, or a vertical cylinder
    inscribed in them (``cyl``; its footprint is square)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    cyl: bool = False


def box(x0, y0, z0, x1, y1, z1) -> Part:
    return Part((x0, y0, z0), (x1, y1, z1))


def cyl(cx, cz, r, y0, y1) -> Part:
    return Part((cx - r, y0, cz - r), (cx + r, y1, cz + r), cyl=True)


# corner i of a box is (x[i & 1], y[i >> 1 & 1], z[i >> 2 & 1]); faces wind outwards
_BOX_FACES = np.array([
    [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5],  # -x, +x
    [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3],  # -y, +y
    [0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6],  # -z, +z
], dtype=np.int64)


def part_mesh(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(n, 3) float64`` and outward-wound faces ``(m, 3) int64`` of one part.

    Vertices are the part's bounds themselves (no transform), so faces meant to touch
    another part's lie exactly in the same plane.
    """
    lo, hi = np.array(part.lo), np.array(part.hi)
    if not part.cyl:
        i = np.arange(8)
        v = np.stack([np.where(i & 1, hi[0], lo[0]), np.where(i >> 1 & 1, hi[1], lo[1]),
                      np.where(i >> 2 & 1, hi[2], lo[2])], axis=1)
        return v, _BOX_FACES
    n = len(_CIRCLE)
    r, cx, cz = (hi[0] - lo[0]) / 2, (hi[0] + lo[0]) / 2, (hi[2] + lo[2]) / 2
    ring = np.stack([cx + r * _CIRCLE[:, 0], cz + r * _CIRCLE[:, 1]], axis=1)
    v = np.concatenate([
        np.insert(ring, 1, lo[1], axis=1), np.insert(ring, 1, hi[1], axis=1),
        [[cx, lo[1], cz], [cx, hi[1], cz]],
    ])
    k, k1 = np.arange(n), (np.arange(n) + 1) % n
    bottom, top = 2 * n, 2 * n + 1
    f = np.concatenate([
        np.stack([k, n + k, k1], 1), np.stack([k1, n + k, n + k1], 1),
        np.stack([np.full(n, bottom), k, k1], 1), np.stack([np.full(n, top), n + k1, n + k], 1),
    ])
    return v, f


def mesh(parts: list[Part]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for p in parts:
        v, f = part_mesh(p)
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def overlaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, m) bool: boxes ``a`` (n, 2, 3) and ``b`` (m, 2, 3) share a volume (not just a face)."""
    return ((a[:, None, 0] < b[None, :, 1] - EPS) & (b[None, :, 0] < a[:, None, 1] - EPS)).all(-1)


@dataclass(frozen=True)
class Frame:
    """A placement: local x runs along a wall (or a table edge), local z away from it, y up.

    World ``b``-axis (X when ``baxis == 0``, else Z) = ``b + sb * z_local`` and the other
    horizontal axis = ``u + su * x_local``: one of the four rotations about +Y, so boxes
    stay axis-aligned and heights are never touched.
    """

    baxis: int
    sb: int
    su: int
    b: float
    u: float

    def point(self, lx: float, lz: float) -> tuple[float, float]:
        """World (x, z) of local (x, z)."""
        pb, pu = self.b + self.sb * lz, self.u + self.su * lx
        return (pb, pu) if self.baxis == 0 else (pu, pb)

    def part(self, p: Part) -> Part:
        (ax, az), (bx, bz) = self.point(p.lo[0], p.lo[2]), self.point(p.hi[0], p.hi[2])
        return Part((min(ax, bx), p.lo[1], min(az, bz)), (max(ax, bx), p.hi[1], max(az, bz)), p.cyl)

    def shifted(self, lx: float, lz: float) -> "Frame":
        """The same orientation with its origin at this frame's local (lx, lz)."""
        return Frame(self.baxis, self.sb, self.su, self.b + self.sb * lz, self.u + self.su * lx)


def cm(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A length drawn uniformly from [lo, hi], rounded to the centimetre."""
    return round(float(rng.uniform(lo, hi)), 2)
