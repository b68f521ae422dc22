"""Frustum planes, triangle clipping and the ground-truth mesh of one view (SPEC §5).

The ground truth a reconstruction is scored against is the part of the house inside the
view frustum *(ref)*: object instances that fill a frontal layer and the room envelope,
with triangles cut at the left, right, top, bottom and near planes, and faces that lie
behind the envelope depth ``D5`` removed. Unlike the reference, a face only partly
hidden behind the envelope is refined first so that its visible part stays: on the
bundled toy houses, dropping whole faces kept only 22–88 % (median about half) of the
envelope area that the refined mesh keeps.

Planes are rows ``(nx, ny, nz, d)`` in world coordinates with unit normals pointing into
the frustum: a point ``p`` is inside when ``n · p + d >= 0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .conventions import tol

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses import House
    from .layers import Layers

#: Order of the rows of :func:`frustum_planes`.
PLANE_NAMES: tuple[str, ...] = ("left", "right", "top", "bottom", "near")


@dataclass(frozen=True)
class ViewMeshConfig:
    """How the ground-truth mesh of a view is cut out of the house."""

    #: distance of the near clipping plane from the camera centre, metres
    near: float = 0.01
    #: faces with a vertex further than this behind ``D5`` at its pixel are dropped, metres
    behind_envelope: float = tol.behind_envelope
    #: vertices up to this far outside a plane count as inside (no sliver cuts), metres
    clip_tolerance: float = tol.clip
    #: a face with a vertex behind ``D5`` is bisected down to edges of this many pixels
    #: and only its hidden pieces are dropped; None drops the whole face (the reference)
    max_edge_pixels: float | None = 4.0

    def __post_init__(self):
        if not self.near > 0:
            raise ValueError(f"near must be > 0 m, got {self.near}")
        if self.max_edge_pixels is not None and not self.max_edge_pixels >= 1:
            raise ValueError(f"max_edge_pixels must be None or >= 1, got {self.max_edge_pixels}")


@dataclass(frozen=True, eq=False)
class ClippedMesh:
    """A world-space triangle mesh cut out of a house.

    vertices : (n, 3) float64  world coordinates, metres
    faces    : (m, 3) int32    indices into ``vertices``, winding of the source faces
    instance : (m,) int32      instance of every face (index into ``house.instances``)
    """

    vertices: np.ndarray
    faces: np.ndarray
    instance: np.ndarray

    @property
    def area(self) -> float:
        """Total surface area, m²."""
        return float(triangle_areas(self.vertices[self.faces]).sum())


@dataclass(frozen=True, eq=False)
class ViewMesh:
    """Ground-truth geometry of one view: objects and room envelope kept apart."""

    objects: ClippedMesh
    envelope: ClippedMesh


def frustum_planes(camera: "Camera", near: float = ViewMeshConfig.near) -> np.ndarray:
    """The left, right, top, bottom and near planes of a pinhole camera.

    The side planes pass through the camera centre and the image borders (pixel edges
    ``u = 0``, ``u = width``, ``v = 0``, ``v = height``); the near plane is ``z = near``
    in camera coordinates.

    Returns
    -------
    planes : (5, 4) float64  rows ``(nx, ny, nz, d)`` in :data:`PLANE_NAMES` order, world
             frame, unit normals pointing inside
    """
    if not near > 0:
        raise ValueError(f"near plane distance must be > 0, got {near}")
    K = np.asarray(camera.K, dtype=np.float64)
    # For a camera-frame point p with z > 0, u·z = K[0]·p and v·z = K[1]·p, so each image
    # border is a linear inequality in p: the side planes fall out of K rows directly.
    n_cam = np.stack([
        K[0],
        camera.width * K[2] - K[0],
        K[1],
        camera.height * K[2] - K[1],
        np.array([0.0, 0.0, 1.0]),
    ])
    d_cam = np.array([0.0, 0.0, 0.0, 0.0, -near])
    scale = np.linalg.norm(n_cam, axis=1)
    n_cam, d_cam = n_cam / scale[:, None], d_cam / scale
    T = np.asarray(camera.cam_to_world, dtype=np.float64)
    n_world = n_cam @ T[:3, :3].T
    d_world = d_cam - n_world @ T[:3, 3]
    return np.column_stack([n_world, d_world])


def triangle_areas(triangles: np.ndarray) -> np.ndarray:
    """(m,) float64 areas of ``triangles`` (m, 3, 3)."""
    t = np.asarray(triangles, dtype=np.float64)
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _roll(triangles: np.ndarray, dist: np.ndarray, first: np.ndarray):
    """Rotate each triangle's vertices (keeping the winding) so that vertex ``first`` leads."""
    order = (first[:, None] + np.arange(3)) % 3
    rows = np.arange(len(triangles))[:, None]
    return triangles[rows, order], dist[rows, order]


def _cut(inside_v, inside_d, outside_v, outside_d):
    """Points where edges from an inside to an outside vertex meet the plane ``d = 0``.

    Always interpolating from the inside end makes the cut point of an edge shared by two
    triangles bit-identical in both, so welding reconnects them. A vertex that is inside
    only within the tolerance (``d < 0``) gives ``t < 0``; clamping puts the cut on the
    vertex itself and the sliver triangle it creates is dropped as degenerate.
    """
    t = np.clip(inside_d / (inside_d - outside_d), 0.0, 1.0)
    return inside_v + t[:, None] * (outside_v - inside_v)


def clip_triangles_by_plane(
    triangles: np.ndarray, plane: np.ndarray, tolerance: float = tol.clip
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the part of each triangle on the inside of one plane.

    A triangle wholly inside (every vertex at most ``tolerance`` outside) is kept as is, one
    wholly outside is dropped, and one that crosses the plane is cut into one triangle (one
    vertex inside) or two (two vertices inside, the quad split along a diagonal). Windings
    are preserved; zero-area pieces are dropped.

    Parameters
    ----------
    triangles : (m, 3, 3) float  vertices of each triangle
    plane     : (4,) float       ``(nx, ny, nz, d)``, unit normal pointing inside
    tolerance : float            metres a vertex may lie outside and still count as inside

    Returns
    -------
    clipped : (k, 3, 3) float64  the kept pieces
    source  : (k,) int64         index into ``triangles`` of the triangle each piece came from
    """
    tris = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    plane = np.asarray(plane, dtype=np.float64)
    dist = tris @ plane[:3] + plane[3]
    inside = dist >= -tolerance
    n_in = inside.sum(axis=1)

    whole = np.flatnonzero(n_in == 3)
    pieces, sources = [tris[whole]], [whole]

    one = np.flatnonzero(n_in == 1)
    if len(one):
        t, d = _roll(tris[one], dist[one], np.argmax(inside[one], axis=1))
        b = _cut(t[:, 0], d[:, 0], t[:, 1], d[:, 1])
        c = _cut(t[:, 0], d[:, 0], t[:, 2], d[:, 2])
        pieces.append(np.stack([t[:, 0], b, c], axis=1))
        sources.append(one)

    two = np.flatnonzero(n_in == 2)
    if len(two):
        # Lead with the outside vertex o; the inside ones a, b follow in winding order,
        # so the kept quad is a, b, cut(b→o), cut(a→o).
        t, d = _roll(tris[two], dist[two], np.argmin(inside[two], axis=1))
        a, b = t[:, 1], t[:, 2]
        pb = _cut(b, d[:, 2], t[:, 0], d[:, 0])
        pa = _cut(a, d[:, 1], t[:, 0], d[:, 0])
        pieces += [np.stack([a, b, pb], axis=1), np.stack([a, pb, pa], axis=1)]
        sources += [two, two]

    out = np.concatenate(pieces)
    src = np.concatenate(sources).astype(np.int64)
    keep = np.ones(len(out), dtype=bool)
    keep[len(whole):] = triangle_areas(out[len(whole):]) > tol.degenerate_area  # cut pieces only
    return out[keep], src[keep]


def clip_triangles(
    triangles: np.ndarray, planes: np.ndarray, tolerance: float = tol.clip
) -> tuple[np.ndarray, np.ndarray]:
    """Clip triangles against several planes in turn (their intersection is kept).

    triangles : (m, 3, 3) float, planes : (p, 4) float. Returns ``clipped (k, 3, 3)
    float64`` and ``source (k,) int64`` (index of the input triangle of each piece).
    """
    tris = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    planes = np.asarray(planes, dtype=np.float64).reshape(-1, 4)
    # Most triangles of a house are wholly inside every plane or wholly outside one: settle
    # those at once and cut only the few that cross a plane.
    dist = tris @ planes[:, :3].T + planes[:, 3]  # (m, 3, p)
    nearest = dist.min(axis=1) >= -tolerance      # (m, p) every corner inside the plane
    farthest = dist.max(axis=1) >= -tolerance     # (m, p) some corner inside the plane
    whole_mask = nearest.all(axis=1)
    whole = np.flatnonzero(whole_mask)
    crossing = np.flatnonzero(~whole_mask & farthest.all(axis=1))
    cut, source = tris[crossing], crossing
    for plane in planes:
        if not len(cut):
            break
        cut, src = clip_triangles_by_plane(cut, plane, tolerance)
        source = source[src]
    return np.concatenate([tris[whole], cut]), np.concatenate([whole, source]).astype(np.int64)


def weld(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indexed mesh of a triangle soup, merging bit-identical vertices.

    triangles : (m, 3, 3) float64 → vertices (n, 3) float64, faces (m, 3) int32
    """
    flat = np.asarray(triangles, dtype=np.float64).reshape(-1, 3)
    if not len(flat):
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32)
    vertices, inverse = _unique_rows(flat)
    return vertices, inverse.reshape(-1, 3)


def _unique_rows(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(points, axis=0, return_inverse=True) for (n, 3) float64, several times
    faster: sort rows by (x, y, z) and start a new row wherever one differs from the last."""
    order = np.lexsort(points.T[::-1])
    rows = points[order]
    new = np.r_[True, (rows[1:] != rows[:-1]).any(axis=1)]
    inverse = np.empty(len(points), dtype=np.int32)
    inverse[order] = np.cumsum(new) - 1
    return rows[new], inverse


def _soup(house: "House", ids, planes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The instances ``ids`` (indices into ``house.instances``) not wholly outside a plane.

    Returns triangles (m, 3, 3) float64, their instance (m,) int32, their corners as indices
    (m, 3) int64 into the returned vertices (v, 3) float64 (the instances' own, stacked).
    """
    tris, owner = [np.zeros((0, 3, 3))], [np.zeros(0, dtype=np.int32)]
    corners, vertices = [np.zeros((0, 3), dtype=np.int64)], [np.zeros((0, 3))]
    base = 0
    for i in ids:
        inst = house.instances[int(i)]
        # An instance whose every vertex is outside one plane cannot reach the frustum.
        dist = inst.vertices @ planes[:, :3].T + planes[:, 3]
        if (dist.max(axis=0) < -tol.clip).any():
            continue
        tris.append(inst.vertices[inst.faces])
        owner.append(np.full(len(inst.faces), int(i), dtype=np.int32))
        corners.append(inst.faces + base)
        vertices.append(inst.vertices)
        base += len(inst.vertices)
    return np.concatenate(tris), np.concatenate(owner), np.concatenate(corners), np.concatenate(vertices)


def _weld_pieces(pieces: np.ndarray, source: np.ndarray, tris: np.ndarray, corners: np.ndarray,
                 vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An indexed mesh of ``pieces`` (k, 3, 3) cut from ``tris[source]``, whose corners are
    ``vertices[corners]``, without sorting every vertex as :func:`weld` does.

    Uncut pieces keep their triangle's vertices; a cut piece's corner that is a corner of
    its triangle keeps that vertex; only new points (cuts, midpoints) are welded by
    coordinates. Vertices no piece uses are dropped. Returns vertices (n, 3) float64 and
    faces (k, 3) int32.
    """
    parent = tris[source]
    uncut = (pieces == parent).all(axis=(1, 2))
    index = np.empty((len(pieces), 3), dtype=np.int64)
    index[uncut] = corners[source[uncut]]
    table = vertices
    if not uncut.all():
        cut = ~uncut
        piece, inherited = pieces[cut], corners[source[cut]]
        same = (piece[:, :, None, :] == parent[cut][:, None, :, :]).all(axis=3)  # (c, 3, 3)
        idx = np.where(same.any(axis=2), np.take_along_axis(inherited, same.argmax(axis=2), axis=1), -1)
        fresh = idx < 0
        new_vertices, new_index = _unique_rows(piece[fresh])
        idx[fresh] = len(vertices) + new_index
        index[cut] = idx
        table = np.concatenate([vertices, new_vertices])
    used = np.zeros(len(table), dtype=bool)
    used[index.ravel()] = True
    renumber = np.cumsum(used) - 1
    return table[used], renumber[index].astype(np.int32)


def _in_front_of_envelope(uv: np.ndarray, z: np.ndarray, d5: np.ndarray, margin: float) -> np.ndarray:
    """(...) bool: a point does not project more than ``margin`` behind ``D5`` at its pixel.

    uv : (..., 2) pixel coordinates and z : (...) planar depth of points in the frustum.
    Where ``D5`` is NaN the ray left the house without meeting the envelope, so there is
    nothing to be behind and the point counts as in front (as in the reference).
    """
    h, w = d5.shape
    # Points on the right/bottom frustum planes project onto the image border itself.
    col = np.clip(uv[..., 0], 0, w - 1).astype(np.int64)
    row = np.clip(uv[..., 1], 0, h - 1).astype(np.int64)
    limit = d5[row, col].astype(np.float64) + margin
    return ~(np.isfinite(limit) & (z > limit))


def _bisect(triangles: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Cut each triangle (m, 3, 3) from the midpoint of its longest edge (``edge`` (m, 3):
    length of edge k from vertex k to k+1) to the opposite vertex, keeping the winding.

    Returns (2m, 3, 3): the first halves of all triangles, then the second halves.
    """
    t, _ = _roll(triangles, edge, np.argmax(edge, axis=1))
    m = 0.5 * (t[:, 0] + t[:, 1])
    return np.concatenate([np.stack([t[:, 0], m, t[:, 2]], axis=1),
                           np.stack([m, t[:, 1], t[:, 2]], axis=1)])


def drop_behind_envelope(
    triangles: np.ndarray, camera: "Camera", d5: np.ndarray, config: "ViewMeshConfig"
) -> tuple[np.ndarray, np.ndarray]:
    """Remove what projects more than ``config.behind_envelope`` behind ``D5``.

    A face goes when any vertex does (SPEC §5). A face straddling an occlusion boundary
    (a big wall triangle half hidden by a door jamb) would take its visible part with it,
    so a face that fails is bisected along its longest edge and its halves are tested
    again, down to edges of ``config.max_edge_pixels``; only the pieces that still fail
    are dropped. Faces that pass at once are kept unchanged.

    triangles : (m, 3, 3) float64  world, inside the frustum of ``camera``
    d5        : (H, W) float       envelope depth of the view, NaN where none
    Returns the kept triangles (k, 3, 3) float64 and source (k,) int64 (input index).
    """
    # The world triangles are bisected alongside camera-frame copies, so kept faces stay
    # exact while each round projects only once.
    world = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    rot, centre = camera.cam_to_world[:3, :3], camera.cam_to_world[:3, 3]
    cam = (world - centre) @ rot
    src = np.arange(len(world), dtype=np.int64)
    kept, kept_src = [np.zeros((0, 3, 3))], [np.zeros(0, dtype=np.int64)]
    (fx, skew, cx), (fy, cy) = camera.K[0], camera.K[1, 1:]

    def front(points):
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([(fx * points[..., 0] + skew * points[..., 1]) / z + cx, fy * points[..., 1] / z + cy], -1)
        return _in_front_of_envelope(uv, z, d5, config.behind_envelope), uv

    while len(world):
        vertex_ok, uv = front(cam)
        ok = vertex_ok.all(axis=1)
        kept.append(world[ok])
        kept_src.append(src[ok])
        if config.max_edge_pixels is None or ok.all():
            break
        world, cam, src, uv, vertex_ok = world[~ok], cam[~ok], src[~ok], uv[~ok], vertex_ok[~ok]
        # Refine only what may be partly visible: a vertex, an edge midpoint or the centroid
        # is in front. Wholly hidden faces go at once instead of splitting into thousands.
        samples = np.concatenate([0.5 * (cam + cam[:, [1, 2, 0]]), cam.mean(axis=1, keepdims=True)], axis=1)
        partly = vertex_ok.any(axis=1) | front(samples)[0].any(axis=1)
        edge = np.linalg.norm(uv[:, [1, 2, 0]] - uv, axis=2)
        split = partly & (edge.max(axis=1) > config.max_edge_pixels)
        world, cam = _bisect(world[split], edge[split]), _bisect(cam[split], edge[split])
        src = np.tile(src[split], 2)
    return np.concatenate(kept), np.concatenate(kept_src)


def _clipped_mesh(house, ids, camera, planes, d5, config: ViewMeshConfig) -> ClippedMesh:
    tris, owner, corners, vertices = _soup(house, ids, planes)
    # Triangles with every corner inside every plane need no clipping; deciding that per
    # vertex is cheaper than per triangle corner.
    inside = ((vertices @ planes[:, :3].T + planes[:, 3]) >= -config.clip_tolerance).all(axis=1)
    whole = inside[corners].all(axis=1)
    rest = np.flatnonzero(~whole)
    cut, cut_src = clip_triangles(tris[rest], planes, config.clip_tolerance)
    clipped = np.concatenate([tris[whole], cut])
    src = np.concatenate([np.flatnonzero(whole), rest[cut_src]])
    kept_tris, kept = drop_behind_envelope(clipped, camera, d5, config)
    vertices, faces = _weld_pieces(kept_tris, src[kept], tris, corners, vertices)
    return ClippedMesh(vertices, faces, owner[src[kept]])


def view_mesh(
    house: "House", camera: "Camera", layers: "Layers", config: ViewMeshConfig | None = None
) -> ViewMesh:
    """The ground-truth mesh of one view (SPEC §5).

    Objects: the instances that fill a frontal layer (ids in ``layers.instance``).
    Envelope: every envelope instance of the house. Both are clipped to the frustum
    (:func:`frustum_planes`), then faces with any vertex projecting more than
    ``config.behind_envelope`` behind ``D5`` (``layers.depth[4]``) at its pixel are
    dropped, after refining the faces that fail (:func:`drop_behind_envelope`); a NaN
    ``D5`` pixel drops nothing.
    """
    config = config or ViewMeshConfig()
    d5 = np.asarray(layers.depth[4])
    if d5.shape != (camera.height, camera.width):
        raise ValueError(
            f"layers are {d5.shape[1]}×{d5.shape[0]} pixels but the camera is "
            f"{camera.width}×{camera.height}"
        )
    planes = frustum_planes(camera, config.near)
    inst = np.asarray(layers.instance)
    object_ids = np.unique(inst[inst >= 0])
    envelope_ids = [k for k, inst in enumerate(house.instances) if inst.envelope]
    return ViewMesh(
        objects=_clipped_mesh(house, object_ids, camera, planes, d5, config),
        envelope=_clipped_mesh(house, envelope_ids, camera, planes, d5, config),
    )
