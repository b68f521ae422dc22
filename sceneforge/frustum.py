"""Frustum planes, triangle clipping and the ground-truth mesh of one view (docs/spec.md §5).

The ground truth a reconstruction is scored against is what the view can see *(ref)*:

- **objects**: the object instances that fill a frontal layer, with triangles cut at the
  left, right, top, bottom and near planes, and faces that lie behind the envelope depth
  ``D5`` removed. Unlike the reference, a face only partly hidden behind the envelope is
  refined first so that its visible part stays (``ViewMeshConfig(max_edge_pixels=None)``
  is the reference rule);
- **envelope**: not the envelope polygons but the D5 layer itself as a surface
  (:func:`envelope_surface`): D5 traced at 1.5× the view's resolution and triangulated
  by the depth → mesh rule of docs/spec.md §11.1 (:mod:`sceneforge.depth_mesh`) at ``a = 15``. The
  polygons behind the visible envelope — back faces of thin walls, the next room's wall
  skin, floor-slab undersides — are seen by no layer, yet lie within the 0.1 m margin of
  the object rule, so by that rule they would be ground truth that nothing can cover.

Planes are rows ``(nx, ny, nz, d)`` in world coordinates with unit normals pointing into
the frustum: a point ``p`` is inside when ``n · p + d >= 0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .conventions import ENVELOPE_LAYER, tol
from .depth_mesh import depth_surface

try:
    from .raytrace._embree import face_classes as _compiled_face_classes
    from .raytrace._embree import vertex_codes as _compiled_vertex_codes
    from .raytrace._embree import weld_faces as _compiled_weld_faces
except ImportError:  # the extension is not built: the numpy versions serve
    _compiled_face_classes = _compiled_vertex_codes = _compiled_weld_faces = None

#: whether the per-vertex and per-face tests of :func:`_settle_fast` and the renumbering of
#: :func:`_weld_pieces` run compiled (sceneforge's extension) by default; the numpy versions
#: are the reference, and the tests hold both equal
COMPILED = _compiled_vertex_codes is not None

if TYPE_CHECKING:
    from .cameras import Camera
    from .houses import House
    from .layers import Layers
    from .raytrace import HouseTracer

#: Order of the rows of :func:`frustum_planes`.
PLANE_NAMES: tuple[str, ...] = ("left", "right", "top", "bottom", "near")


@dataclass(frozen=True)
class ViewMeshConfig:
    """How the ground-truth mesh of a view is made: objects cut out of the house, the
    envelope from its D5 layer."""

    #: distance of the near clipping plane from the camera centre, metres
    near: float = 0.01
    #: object faces with a vertex further than this behind ``D5`` at its pixel are dropped, metres
    behind_envelope: float = tol.behind_envelope
    #: vertices up to this far outside a plane count as inside (no sliver cuts), metres
    clip_tolerance: float = tol.clip
    #: an object face with a vertex behind ``D5`` is bisected down to edges of this many
    #: pixels and only its hidden pieces are dropped; None drops the whole face (the reference)
    max_edge_pixels: float | None = 4.0
    #: the envelope is D5 traced at this many times the view's width and height (the reference: 1.5)
    envelope_upscale: float = 1.5
    #: edge factor of the depth → mesh rule (docs/spec.md §11.1) the traced D5 is triangulated with (the reference: 15)
    envelope_a: float = 15.0

    def __post_init__(self):
        if not self.near > 0:
            raise ValueError(f"near must be > 0 m, got {self.near}")
        if self.max_edge_pixels is not None and not self.max_edge_pixels >= 1:
            raise ValueError(f"max_edge_pixels must be None or >= 1, got {self.max_edge_pixels}")
        if not self.envelope_upscale > 0:
            raise ValueError(f"envelope_upscale must be > 0, got {self.envelope_upscale}")
        if not self.envelope_a > 0:
            raise ValueError(f"envelope_a must be > 0, got {self.envelope_a}")


@dataclass(frozen=True, eq=False)
class ClippedMesh:
    """A world-space triangle mesh of part of a house: faces cut out of its instances, or
    the envelope's D5 surface (:func:`envelope_surface`).

    vertices : (n, 3) float64  world coordinates, metres
    faces    : (m, 3) int32    indices into ``vertices``; cut faces keep the winding of their
                               source faces, D5 surface faces face the camera
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
    """Ground-truth geometry of one view: objects and room envelope kept apart.

    objects  : frustum-clipped faces of the layer instances; ``instance`` their instance
    envelope : the D5 surface (:func:`envelope_surface`); ``instance`` the D5 instance of
               each face's first corner pixel
    """

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
    a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    # The cross product spelled out as np.cross computes it (bit-identical), without its
    # axis juggling and copies: clipping calls this for a few pieces many times per view.
    c = np.empty_like(a)
    np.multiply(a[:, 1], b[:, 2], out=c[:, 0])
    c[:, 0] -= a[:, 2] * b[:, 1]
    np.multiply(a[:, 2], b[:, 0], out=c[:, 1])
    c[:, 1] -= a[:, 0] * b[:, 2]
    np.multiply(a[:, 0], b[:, 1], out=c[:, 2])
    c[:, 2] -= a[:, 1] * b[:, 0]
    c *= c
    return 0.5 * np.sqrt(np.add.reduce(c, axis=1))  # np.linalg.norm(c, axis=1), same arithmetic


def _all_last(mask: np.ndarray) -> np.ndarray:
    """``mask.all(axis=-1)`` for a short last axis: &-ing its few columns is several times
    faster than numpy's reduction over an axis of 3 to 9 elements."""
    out = mask[..., 0].copy()
    for j in range(1, mask.shape[-1]):
        out &= mask[..., j]
    return out


#: Row k: the vertices of a triangle rotated (keeping the winding) so that vertex k leads.
_ROLL = np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]])


def _roll(triangles: np.ndarray, dist: np.ndarray, rows: np.ndarray, first: np.ndarray):
    """Triangles ``rows`` of ``triangles`` (m, 3, 3) and their ``dist`` (m, 3), each rotated
    (keeping the winding) so that its vertex ``first`` leads, in one gather each."""
    flat = _ROLL[first]
    flat += 3 * rows[:, None]
    return triangles.reshape(-1, 3)[flat], dist.ravel()[flat]


def _cut(inside_v, inside_d, outside_v, outside_d):
    """Points where edges from an inside to an outside vertex meet the plane ``d = 0``.

    ``inside_v``, ``outside_v`` (..., 3) and ``inside_d``, ``outside_d`` (...). Always
    interpolating from the inside end makes the cut point of an edge shared by two
    triangles bit-identical in both, so welding reconnects them. A vertex that is inside
    only within the tolerance (``d < 0``) gives ``t < 0``; clamping puts the cut on the
    vertex itself and the sliver triangle it creates is dropped as degenerate.
    """
    t = np.clip(inside_d / (inside_d - outside_d), 0.0, 1.0)
    return inside_v + t[..., None] * (outside_v - inside_v)


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
    return _clip_by_plane(tris, tris @ plane[:3] + plane[3], tolerance)


def _clip_by_plane(tris: np.ndarray, dist: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`clip_triangles_by_plane` given ``dist`` (m, 3), the signed distances of the
    corners of ``tris`` (m, 3, 3) float64 to the plane. The pieces are written straight
    into the output: kept whole triangles, then one piece per triangle with one vertex
    inside, then the first and the second halves of the quads left of those with two."""
    inside = dist >= -tolerance
    n_in = inside.sum(axis=1)
    whole = np.flatnonzero(n_in == 3)
    one = np.flatnonzero(n_in == 1)
    two = np.flatnonzero(n_in == 2)
    w, m1, m2 = len(whole), len(one), len(two)
    out = np.empty((w + m1 + 2 * m2, 3, 3))
    src = np.concatenate([whole, one, two, two])
    np.take(tris, whole, axis=0, out=out[:w])
    if m1:
        # Lead with the inside vertex: the kept tip is it and its edges' cuts b, c.
        t, d = _roll(tris, dist, one, np.argmax(inside[one], axis=1))
        tip = out[w:w + m1]
        tip[:, 0] = t[:, 0]
        tip[:, 1:] = _cut(t[:, :1], d[:, :1], t[:, 1:], d[:, 1:])
    if m2:
        # Lead with the outside vertex o; the inside ones a, b follow in winding order,
        # so the kept quad is a, b, cut(b→o), cut(a→o).
        t, d = _roll(tris, dist, two, np.argmin(inside[two], axis=1))
        cuts = _cut(t[:, :0:-1], d[:, :0:-1], t[:, :1], d[:, :1])  # cut(b→o), cut(a→o)
        first, second = out[w + m1:w + m1 + m2], out[w + m1 + m2:]
        first[:, :2] = t[:, 1:]
        first[:, 2] = cuts[:, 0]
        second[:, 0] = t[:, 1]
        second[:, 1:] = cuts
    keep = triangle_areas(out[w:]) > tol.degenerate_area  # cut pieces only
    if keep.all():
        return out, src
    keep = np.concatenate([np.ones(w, dtype=bool), keep])
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
        # A plane that every piece is inside of leaves them as they are: skip its cutting.
        dist = cut @ plane[:3] + plane[3]
        if (dist >= -tolerance).all():
            continue
        cut, src = _clip_by_plane(cut, dist, tolerance)
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
    faster: rows in lexicographic (x, y, z) order, each the first of its equal rows.

    np.lexsort would do it in three stable sorts, each several times slower than numpy's
    default (vectorised) sort. Instead each coordinate is ranked among its distinct values
    with the default sort, and the rows are sorted once by their three ranks packed into
    one integer; ties are then whole equal rows, and the first of each is found by index.
    """
    n = len(points)
    if n < 1000 or n > 2_000_000:  # sorting overhead; ranks whose product overflows int64
        return _unique_rows_lexsort(points)
    q = points + 0.0  # -0.0 → +0.0: equal coordinates are then equal bit for bit
    if np.isnan(q).any():  # NaN equals nothing, not even itself
        return _unique_rows_lexsort(points)
    key = np.zeros(n, dtype=np.int64)
    for column in q.T:
        distinct, rank = np.unique(column, return_inverse=True)
        key *= len(distinct)
        key += rank
    order = np.argsort(key)
    key = key[order]
    new = np.empty(n, dtype=bool)
    new[0] = True
    np.not_equal(key[1:], key[:-1], out=new[1:])
    first = np.minimum.reduceat(order, np.flatnonzero(new))
    inverse = np.empty(n, dtype=np.int32)
    inverse[order] = np.cumsum(new) - 1
    return points[first], inverse


def _unique_rows_lexsort(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_unique_rows` by np.lexsort: sort rows by (x, y, z) and start a new row
    wherever one differs from the last."""
    order = np.lexsort(points.T[::-1])
    rows = points[order]
    new = np.empty(len(points), dtype=bool)
    new[:1] = True
    np.not_equal(rows[1:, 0], rows[:-1, 0], out=new[1:])
    new[1:] |= rows[1:, 1] != rows[:-1, 1]
    new[1:] |= rows[1:, 2] != rows[:-1, 2]
    inverse = np.empty(len(points), dtype=np.int32)
    inverse[order] = np.cumsum(new) - 1
    return rows[new], inverse


#: Bits of the per-vertex code of :func:`_settle_fast`: inside plane p (bit p, within the clip
#: tolerance), and not behind the envelope.
_INSIDE, _FRONT = 0b11111, 0b100000
#: Bytes 0/1 of a uint64 times this, shifted right by 56: byte k's bit becomes bit k (the
#: bits land at distinct places, so nothing carries).
_PACK = np.uint64(0x0102040810204080)


class _Soup(NamedTuple):
    """The faces of one mesh's instances, sorted by :func:`_settle_fast`; face arrays index
    ``corners``."""

    vertices: np.ndarray  # (n, 3) float64  the instances' vertices, stacked
    corners: np.ndarray   # (m, 3) int64    faces of the instances that may reach the frustum
    ids: np.ndarray       # (k,) int32      those instances (index into house.instances)
    start: np.ndarray     # (k + 1,) int64  first face of each, then m
    kept: np.ndarray      # (a,) int64      faces wholly inside, no corner behind the envelope
    hidden: np.ndarray    # (b,) int64      faces wholly inside, a corner behind the envelope
    cross: np.ndarray     # (c,) int64      faces that may cross a plane (the rest are outside)


def _settle_fast(house: "House", ids, planes: np.ndarray, camera: "Camera", lens: tuple, limit: np.ndarray,
                tolerance: float, compiled: bool | None = None) -> _Soup:
    """The faces of instances ``ids`` sorted by tests on their vertices (the fast kernel).

    The plain algorithm it computes: clip every face of the instances against the planes
    (:func:`clip_triangles`) and test every piece against the envelope
    (:func:`drop_behind_envelope`). A face wholly inside every plane and with no corner
    behind the envelope comes out of both as it is (``kept``); one wholly inside with a
    corner behind goes to the envelope test uncut (``hidden``); one wholly outside a plane
    comes out of neither; the rest may cross a plane (``cross``). ``plain_clipped_mesh`` in
    tests/test_frustum.py is that plain pipeline, and
    ``test_clipped_meshes_of_toy_houses_match_the_plain_pipeline`` (with the occluded-view
    tests next to it) holds :func:`_clipped_meshes`, and so this, to it bit for bit.

    Why it is fast: on a big house nearly every face of a view's mesh is kept or dropped
    whole. Both are settled here by testing each vertex once (plane distances, projection,
    depth against the envelope, packed into one byte) and combining the bytes of each
    face's three corners, with no per-face geometry (view_mesh 7 times faster on 1 M
    faces).

    Those plain steps compute the same matmul rows per corner from the same numbers (a row
    does not depend on the rest of the batch) and project elementwise, so the decisions
    are theirs bit for bit. Should a BLAS round a row differently, a face wrongly found
    outside here could only lie within the tolerance of the plane: a corner inside only
    within the tolerance has a negative distance, and the cuts towards it collapse onto
    it, leaving no area.

    ``compiled``: run :func:`_vertex_codes` and :func:`_face_classes` in sceneforge's
    extension (True), in numpy (False, the reference), or compiled where it is built (None).
    """
    compiled = COMPILED if compiled is None else compiled
    if compiled and _compiled_vertex_codes is None:
        raise RuntimeError("the compiled frustum tests need sceneforge's Embree extension, which is not built")
    instances = [house.instances[int(i)] for i in ids]
    n_vertices = np.array([len(inst.vertices) for inst in instances], dtype=np.int64)
    first = np.zeros(len(instances) + 1, dtype=np.int64)
    np.cumsum(n_vertices, out=first[1:])
    empty = np.zeros(0, dtype=np.int64)
    if not first[-1]:
        return _Soup(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int32),
                     np.zeros(1, dtype=np.int64), empty, empty, empty)
    vertices = np.concatenate([inst.vertices for inst in instances]).astype(np.float64, copy=False)
    code = _vertex_codes(vertices, planes, camera, lens, limit, tolerance, compiled)
    # An instance whose every vertex is outside one plane cannot reach the frustum: its
    # faces are skipped rather than found outside one by one.
    some = n_vertices > 0
    reaching = np.flatnonzero(some)
    reaching = reaching[(np.bitwise_or.reduceat(code, first[:-1][some]) & _INSIDE) == _INSIDE]
    # The faces of the instances that may reach the frustum, as indices into ``vertices``.
    n_faces = np.array([len(instances[k].faces) for k in reaching], dtype=np.int64)
    start = np.zeros(len(reaching) + 1, dtype=np.int64)
    np.cumsum(n_faces, out=start[1:])
    corners = np.empty((start[-1], 3), dtype=np.int64)
    for k, a, b in zip(reaching, start[:-1], start[1:]):
        np.add(instances[k].faces, first[k], out=corners[a:b])
    kept, hidden, cross = _face_classes(code, corners, compiled)
    return _Soup(vertices, corners, np.asarray(ids, dtype=np.int32)[reaching], start, kept, hidden, cross)


def _vertex_codes(vertices: np.ndarray, planes: np.ndarray, camera: "Camera", lens: tuple, limit: np.ndarray,
                  tolerance: float, compiled: bool) -> np.ndarray:
    """(n,) uint8: each vertex's bits (:data:`_INSIDE`: inside plane p within ``tolerance``,
    bit p; :data:`_FRONT`: not behind the envelope) of ``vertices`` (n, 3) float64.

    The compiled kernel repeats these float64 operations one for one, the matrix products
    as numpy's OpenBLAS computes their 3-term rows (from +0, fused multiply-adds in k order).
    """
    if compiled:
        rot, centre = camera.cam_to_world[:3, :3], camera.cam_to_world[:3, 3]
        fx, skew, cx, fy, cy, width, border = lens
        return np.frombuffer(_compiled_vertex_codes(
            np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(planes, dtype=np.float64),
            np.ascontiguousarray(rot, dtype=np.float64), np.ascontiguousarray(centre, dtype=np.float64),
            fx, skew, cx, fy, cy, width, int(border[1, 0]) + 1, np.ascontiguousarray(limit, dtype=np.float64),
            tolerance), dtype=np.uint8)
    n = len(vertices)
    # Planar (coordinate, vertex) layouts: numpy's passes over (n, 3) or (n, 5) arrays
    # broadcast along their short rows and take several times longer.
    buffer = np.empty((6, n))
    dist = np.matmul(planes[:, :3], vertices.T, out=buffer[:5])  # rows of vertices @ planes[:, :3].T
    dist += planes[:, 3:]
    # Each vertex's bits in the bytes of one uint64, then packed into one byte (spares a
    # pass over the vertices per bit, and a gather per bit and corner).
    bits = np.zeros((n, 8), dtype=bool)
    np.greater_equal(dist, -tolerance, out=bits.T[:5])
    # The camera frame, (vertices - centre) @ rot transposed, projected in place.
    rot, centre = camera.cam_to_world[:3, :3], camera.cam_to_world[:3, 3]
    projected = np.matmul(rot.T, np.subtract(vertices.T, centre[:, None], out=buffer[:3]), out=buffer[3:])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # (vertices behind the camera get garbage pixels; only those inside are used)
        _project(projected, projected, lens, limit)
    np.equal(projected[2], 0.0, out=bits[:, 5])
    code = bits.view(np.uint64).ravel() * _PACK
    code >>= np.uint64(56)
    return code.astype(np.uint8)


def _face_classes(code: np.ndarray, corners: np.ndarray, compiled: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces ``corners`` (m, 3) int64 (indices into ``code``, :func:`_vertex_codes`)
    every corner of which is inside every plane and in front of the envelope (kept), inside
    every plane with a corner behind it (hidden), and inside each plane at some corner but
    outside one at some corner (cross), each (k,) int64 ascending."""
    if compiled:
        return tuple(np.frombuffer(a, dtype=np.int64) for a in _compiled_face_classes(
            np.ascontiguousarray(code, dtype=np.uint8), np.ascontiguousarray(corners, dtype=np.int64)))
    # Per face, the bits all its corners have and those some corner has.
    corner = code.take(corners)
    every = corner[:, 0] & corner[:, 1]
    every &= corner[:, 2]
    some = corner[:, 0] | corner[:, 1]
    some |= corner[:, 2]
    cross = (some & _INSIDE) == _INSIDE  # inside each plane at some corner
    cross &= (every & _INSIDE) != _INSIDE  # outside some plane at some corner
    return np.flatnonzero(every == _INSIDE | _FRONT), np.flatnonzero(every == _INSIDE), np.flatnonzero(cross)


def _weld_pieces(soup: _Soup, pieces: np.ndarray, source: np.ndarray, compiled: bool = False) -> ClippedMesh:
    """The mesh of the faces ``soup.kept`` followed by ``pieces`` (k, 3, 3) cut from faces
    ``source`` of ``soup``, without sorting every vertex as :func:`weld` does.

    Kept faces keep their vertices, and so do uncut pieces; a cut piece's corner that is a
    corner of its face keeps that vertex; only new points (cuts, midpoints) are welded by
    coordinates and come after the instances' vertices. Vertices no face uses are dropped.
    ``compiled``: the kept faces' gather and the renumbering in sceneforge's extension.
    """
    corners, kept, table = soup.corners, soup.kept, soup.vertices
    index = np.empty((len(pieces) if compiled else len(kept) + len(pieces), 3), dtype=np.int64)
    if not compiled:
        np.take(corners, kept, axis=0, out=index[:len(kept)])
    tail = index[len(index) - len(pieces):]
    new_vertices = np.zeros((0, 3))
    if len(pieces):
        parent = table[corners[source]]
        inherited = corners[source]  # right for every uncut piece
        uncut = _all_last((pieces == parent).reshape(-1, 9))
        if not uncut.all():
            cut = np.flatnonzero(~uncut)
            piece, parent, idx = pieces[cut], parent[cut], inherited[cut]
            # Each corner takes the first corner of its face it equals, if any.
            fresh = np.ones(idx.shape, dtype=bool)
            for k in (2, 1, 0):
                # (== per coordinate, then &: .all over an axis of 3 is several times slower)
                corner = parent[:, None, k]
                same = piece[..., 0] == corner[..., 0]
                same &= piece[..., 1] == corner[..., 1]
                same &= piece[..., 2] == corner[..., 2]
                np.copyto(idx, inherited[cut, k:k + 1], where=same)
                fresh &= ~same
            new_vertices, new_index = _unique_rows(piece[fresh])
            idx[fresh] = len(table) + new_index
            inherited[cut] = idx
        tail[:] = inherited
    # The instance of each face: kept faces are sorted, so count them per instance.
    instance = np.empty(len(kept) + len(pieces), dtype=np.int32)
    instance[:len(kept)] = np.repeat(soup.ids, np.diff(np.searchsorted(kept, soup.start)))
    instance[len(kept):] = soup.ids[np.searchsorted(soup.start, source, side="right") - 1]
    if compiled:
        used, faces = _compiled_weld_faces(corners, kept, tail, len(table) + len(new_vertices))
        used, faces = np.frombuffer(used, dtype=np.int64), np.frombuffer(faces, dtype=np.int32).reshape(-1, 3)
        n_old = int(np.searchsorted(used, len(table)))
        vertices = np.empty((len(used), 3))
        np.take(table, used[:n_old], axis=0, out=vertices[:n_old])
        np.take(new_vertices, used[n_old:] - len(table), axis=0, out=vertices[n_old:])
        return ClippedMesh(vertices, faces, instance)
    used = np.zeros(len(table) + len(new_vertices), dtype=bool)
    used[index] = True
    renumber = np.cumsum(used, dtype=np.int32)
    renumber -= 1
    old, new = used[:len(table)], used[len(table):]
    vertices = np.empty((renumber[-1] + 1 if len(used) else 0, 3))
    n_old = renumber[len(table) - 1] + 1 if len(table) else 0
    np.compress(old, table, axis=0, out=vertices[:n_old])
    np.compress(new, new_vertices, axis=0, out=vertices[n_old:])
    return ClippedMesh(vertices, renumber.take(index), instance)


def _envelope_limit(d5: np.ndarray, margin: float) -> np.ndarray:
    """(H·W,) float64: the depth beyond which a point at each pixel is behind the envelope.

    ``D5 + margin`` where ``D5`` is finite and +inf elsewhere: where ``D5`` is NaN the ray
    left the house without meeting the envelope, so there is nothing to be behind and the
    point counts as in front (as in the reference). Built once per view so that each test
    of a batch of points is a single lookup and comparison.
    """
    limit = np.asarray(d5).astype(np.float64).ravel()
    limit += margin
    limit[~np.isfinite(limit)] = np.inf
    return limit


def _project(cam: np.ndarray, out: np.ndarray, lens: tuple, limit: np.ndarray) -> None:
    """Project camera-frame points and test them against the envelope, writing into ``out``.

    cam  : (3, N) planar camera coordinates (x, y, z) of points in the frustum.
    out  : (3, N) receives pixel ``u``, ``v`` and 1.0 where the point lies beyond
           ``limit`` (:func:`_envelope_limit`) at its pixel, else 0.0.
    lens : ``(fx, skew, cx, fy, cy, width, border)`` from :func:`_lens`.
    Elementwise arithmetic only, so a point gets the same pixel however it is batched;
    ``out`` may be ``cam`` itself (each coordinate is read before it is overwritten).
    Call under ``np.errstate(divide="ignore", invalid="ignore")``.
    """
    fx, skew, cx, fy, cy, width, border = lens
    x, y, z, u, v = cam[0], cam[1], cam[2], out[0], out[1]
    np.multiply(fx, x, out=u)
    if skew:  # else skew · y is ±0: adding it could change only the sign of a zero u
        u += skew * y
    u /= z
    u += cx
    np.multiply(fy, y, out=v)
    v /= z
    v += cy
    # Points on the right/bottom frustum planes project onto the image border itself
    # (maximum/minimum: np.clip with the same bounds, without its overhead).
    pixel = np.maximum(out[:2], 0.0)
    np.minimum(pixel, border, out=pixel)
    pixel = pixel.astype(np.int64)
    pixel[1] *= width
    pixel[1] += pixel[0]
    np.greater(z, limit.take(pixel[1], mode="clip"), out=out[2])


def _lens(camera: "Camera", shape: tuple[int, int]) -> tuple:
    """The intrinsics :func:`_project` needs, unpacked once per view."""
    K = np.asarray(camera.K, dtype=np.float64)
    h, w = shape
    return (K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], w,
            np.array([[w - 1], [h - 1]], dtype=np.float64))


#: The halves of a triangle bisected at its edge k (corner k to k+1) are (k, m, k+2) and
#: (m, k+1, k+2), m the edge's midpoint: their corners (axis 0) for each half (axis 1) are
#: corner (k + offset) % 3, with corner k standing in for m until it is computed.
_HALF_OFFSET = np.array([[0, 0], [0, 1], [2, 2]])[:, :, None]
_MOD3 = np.array([0, 1, 2, 0, 1])


def drop_behind_envelope(
    triangles: np.ndarray, camera: "Camera", d5: np.ndarray, config: "ViewMeshConfig",
    limit: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Remove what projects more than ``config.behind_envelope`` behind ``D5``.

    A face goes when any vertex does (docs/spec.md §5.1). A face straddling an occlusion boundary
    (a big wall triangle half hidden by a door jamb) would take its visible part with it,
    so a face that fails is bisected along its longest edge and its halves are tested
    again, down to edges of ``config.max_edge_pixels``; only the pieces that still fail
    are dropped. Faces that pass at once are kept unchanged.

    triangles : (m, 3, 3) float64  world, inside the frustum of ``camera``
    d5        : (H, W) float       envelope depth of the view, NaN where none
    limit     : :func:`_envelope_limit` of ``d5``, if already at hand
    Returns the kept triangles (k, 3, 3) float64 and source (k,) int64 (input index).
    """
    if limit is None:
        limit = _envelope_limit(d5, config.behind_envelope)
    lens = _lens(camera, np.shape(d5))
    world = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    rot, centre = camera.cam_to_world[:3, :3], camera.cam_to_world[:3, 3]
    # Every corner carries all the refinement needs in one column of ``state`` (field,
    # corner, face): world (0-2) and camera (3-5) coordinates, pixel (6-7) and whether it
    # is behind the envelope (8); fields first keeps each pass over one field contiguous.
    # The world triangles are bisected alongside the camera-frame copies, so kept faces
    # stay exact, and a corner is projected only when it is made: a midpoint is computed
    # as 0.5 · (corner k + corner k+1) like every sample point, and projection is
    # elementwise, so it is bit-identical however it is batched.
    state = np.empty((9, 3, len(world)))
    state[:3] = world.transpose(2, 1, 0)
    state[3:6] = ((world - centre) @ rot).transpose(2, 1, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        kept, kept_src = _refine_fast(state, lens, limit, config.max_edge_pixels)
    return np.ascontiguousarray(np.concatenate(kept, axis=2).transpose(2, 1, 0)), np.concatenate(kept_src)


def _refine_fast(state: np.ndarray, lens: tuple, limit: np.ndarray, max_edge: float | None):
    """The loop of :func:`drop_behind_envelope` on ``state`` (9, 3, m) (the fast kernel):
    lists of the kept world triangles (3, 3, k) (field, corner, face) and of their
    sources (k,) int64.

    The plain algorithm it computes, round by round: project every corner; keep the faces
    with no corner more than ``behind_envelope`` behind D5 at its pixel; of the others,
    drop those wholly hidden (every corner, edge midpoint and the centroid behind) and
    those whose longest edge is at most ``max_edge`` pixels; bisect the rest at the
    midpoint of their first longest edge and test the halves in the next round (all first
    halves, then all second halves). ``plain_drop_behind_envelope`` in tests/test_frustum.py
    is that loop, and ``test_drop_behind_envelope_matches_the_plain_refinement_bit_for_bit``
    and ``test_clipped_meshes_of_toy_houses_match_the_plain_pipeline`` hold this to it bit
    for bit.

    Why it is fast: a dozen rounds over a few hundred to a few thousand faces each cost
    about half the number of numpy calls per round and half the data they move, so each
    round makes few calls, builds the next round's faces with a single gather and projects
    each new point once.
    """
    _project(state[3:6].reshape(3, -1), state[6:].reshape(3, -1), lens, limit)
    src = np.arange(state.shape[2], dtype=np.int64)
    kept, kept_src = [np.zeros((3, 3, 0))], [np.zeros(0, dtype=np.int64)]
    while state.shape[2]:
        n = state.shape[2]
        hidden = state[8]
        failed = hidden.any(axis=0)
        if not failed.any():
            kept.append(state[:3])
            kept_src.append(src)
            break
        ok = ~failed
        kept.append(np.compress(ok, state[:3], axis=2))
        kept_src.append(src[ok])
        if max_edge is None:
            break
        # Pixel length of edge k, from corner k to corner k+1. A face whose pixel is NaN
        # (see "gone" below) has NaN edges and so is never cut again.
        uv = state[6:8]
        step = np.empty_like(uv)
        np.subtract(uv[:, 1:], uv[:, :2], out=step[:, :2])
        np.subtract(uv[:, 0], uv[:, 2], out=step[:, 2])
        step *= step
        edge = np.sqrt(np.add(step[0], step[1], out=step[0]), out=step[0])
        longest = edge.max(axis=0)
        failed &= longest > max_edge
        cut = np.flatnonzero(failed)
        c = len(cut)
        if not c:
            break
        # The first longest edge (np.argmax over the three, without its slow strided pass).
        not0 = edge[0] != longest
        k = not0.astype(np.int64)
        not0 &= edge[1] != longest
        k += not0
        # Both halves of every face to cut, all first halves, then all second halves, in one
        # gather; then the midpoint m of edge k (a, b) fills the first half's corner 1 and
        # the second half's corner 0. m = 0.5 · (a + b) exactly as the sample points below.
        corner = k[cut] + _HALF_OFFSET
        corner = (_MOD3 * n).take(corner)
        corner += cut
        halves = np.take(state.reshape(9, -1), corner.reshape(3, -1), axis=1, mode="clip")  # (9, 3, 2c)
        mid = halves[:, 1, :c]
        np.add(halves[:6, 0, :c], halves[:6, 1, c:], out=mid[:6])
        mid[:6] *= 0.5
        # Refine only what may be partly visible: a vertex, an edge midpoint or the centroid
        # is in front. Wholly hidden faces go at once instead of splitting into thousands.
        # Only faces with every corner hidden ("doubt") need these samples; they are
        # projected in one batch with the midpoints.
        doubt = np.flatnonzero(hidden.all(axis=0)[cut])
        nd = len(doubt)
        points = np.empty((6, c + 4 * nd))  # camera coordinates, then pixel and hidden
        points[:3, :c] = mid[3:6]
        if nd:
            tip = np.take(state[3:6], cut[doubt], axis=2, mode="clip")
            sample = points[:3, c:].reshape(3, 4, nd)
            np.add(tip[:, :2], tip[:, 1:], out=sample[:, :2])
            np.add(tip[:, 2], tip[:, 0], out=sample[:, 2])
            sample[:, :3] *= 0.5
            np.add(tip[:, 0], tip[:, 1], out=sample[:, 3])
            sample[:, 3] += tip[:, 2]
            sample[:, 3] /= 3
        _project(points[:3], points[3:], lens, limit)
        mid[6:] = points[3:, :c]
        halves[:, 0, c:] = mid
        if nd:
            # Faces that are wholly hidden go: their halves get a NaN pixel, which makes
            # them fail (every corner is hidden) without being cut in the next round.
            gone = doubt[points[5, c:].reshape(4, nd).all(axis=0)]
            halves[6, 0].reshape(2, c)[:, gone] = np.nan
        state = halves
        src = src[cut]
        src = np.concatenate([src, src])
    return kept, kept_src


def _clipped_meshes(house, id_lists, camera, planes, d5, limit, config: ViewMeshConfig,
                    compiled: bool | None = None) -> list[ClippedMesh]:
    """The :class:`ClippedMesh` of each list of instance ids in ``id_lists``.

    Per mesh, :func:`_settle_fast` keeps the faces wholly inside the frustum and in front of the
    envelope and drops those wholly outside a plane. The rest are clipped and refined in
    one batch for all meshes: those steps cost a number of numpy calls per plane or per
    round, nearly regardless of how many triangles they carry. Every step keeps the order
    of the pieces of each face and decides each face on its own, so each mesh comes out
    exactly as it would alone, and as if all its faces had gone through
    :func:`clip_triangles` (faces wholly inside first) and :func:`drop_behind_envelope`:
    those keep settled faces as they are, and in order, ahead of any cut or refined piece.
    ``compiled`` as for :func:`_settle_fast`.
    """
    lens = _lens(camera, np.shape(d5))
    soups = [_settle_fast(house, ids, planes, camera, lens, limit, config.clip_tolerance, compiled)
             for ids in id_lists]
    crossing = [soup.vertices[soup.corners[soup.cross]] for soup in soups]
    first = np.cumsum([0] + [len(c) for c in crossing])  # of each mesh's crossing faces
    cut, cut_src = clip_triangles(np.concatenate(crossing), planes, config.clip_tolerance)
    cut_mesh = np.searchsorted(first, cut_src, side="right") - 1
    # Per mesh, its hidden faces then its cut pieces (as one mesh alone would have them).
    pieces, src, count = [], [], []
    for m, soup in enumerate(soups):
        own = np.flatnonzero(cut_mesh == m)
        pieces += [soup.vertices[soup.corners[soup.hidden]], cut[own]]
        src += [soup.hidden, soup.cross[cut_src[own] - first[m]]]
        count.append(len(soup.hidden) + len(own))
    pieces, src = np.concatenate(pieces), np.concatenate(src)
    kept_tris, kept = drop_behind_envelope(pieces, camera, d5, config, limit)
    mesh = np.repeat(np.arange(len(soups)), count)[kept]
    src = src[kept]
    meshes = []
    for m, soup in enumerate(soups):
        own = np.flatnonzero(mesh == m)
        meshes.append(_weld_pieces(soup, kept_tris[own], src[own], COMPILED if compiled is None else compiled))
    return meshes


def envelope_surface(tracer: "HouseTracer", camera: "Camera", config: ViewMeshConfig | None = None,
                     compiled: bool | None = None) -> ClippedMesh:
    """The envelope's ground truth of a view (docs/spec.md §5.2): the D5 layer as a surface.

    D5 (each ray's first envelope hit, a first-hit query) is traced from ``camera`` at
    ``config.envelope_upscale`` times its resolution (same pose and field of view,
    :meth:`Camera.resized`) and triangulated by the depth → mesh rule of docs/spec.md §11.1 at
    ``config.envelope_a`` (:func:`sceneforge.depth_mesh.grid_faces`). Pixels whose ray
    leaves the house give no vertex. Each face's ``instance`` is the envelope instance
    its first corner pixel sees (the block's top-left pixel, or its top-right one).
    ``compiled`` as for :func:`sceneforge.depth_mesh.depth_surface` (the same mesh).
    """
    from .raytrace.embree_backend import every_core

    config = config or ViewMeshConfig()
    fine = camera.resized(round(camera.width * config.envelope_upscale),
                          round(camera.height * config.envelope_upscale))
    origins, directions, depth_scale = fine.rays()
    d5 = tracer.first_hit(origins, directions, instances=tracer.triangles.envelope)
    # the tracer's threads, at most two: the compiled triangulation takes a few milliseconds,
    # and more threads would cost about as much to start as they save
    threads = min(2, tracer.threads or every_core())
    return ClippedMesh(*depth_surface(d5.t, depth_scale, d5.instance, fine.K, fine.cam_to_world, fine.shape,
                                      config.envelope_a, compiled, threads))


def mesh_provenance(config: ViewMeshConfig, width: int, height: int) -> dict:
    """The rules that made the ground-truth meshes of ``width``×``height`` views, as a
    store records them."""
    upscaled = f"{round(width * config.envelope_upscale)}x{round(height * config.envelope_upscale)}"
    return {
        "objects": {
            "rule": "layer instances clipped to the frustum, faces behind D5 dropped (docs/spec.md §5.1)",
            "behind_envelope": config.behind_envelope, "max_edge_pixels": config.max_edge_pixels,
        },
        "envelope": {
            "rule": "D5 surface: D5 traced at envelope_upscale x the view resolution, "
                    "triangulated by the depth to mesh rule at edge factor envelope_a (docs/spec.md §5.2, §11.1)",
            "envelope_upscale": config.envelope_upscale, "resolution": upscaled, "envelope_a": config.envelope_a,
        },
    }


def object_mesh(
    house: "House", camera: "Camera", layers: "Layers", config: ViewMeshConfig | None = None
) -> ClippedMesh:
    """The objects' ground truth of a view (docs/spec.md §5.1).

    The instances that fill a frontal layer (ids in ``layers.instance``), clipped to the
    frustum (:func:`frustum_planes`); faces with any vertex projecting more than
    ``config.behind_envelope`` behind ``D5`` (``layers.depth[ENVELOPE_LAYER]``) at its pixel
    are dropped, after refining the faces that fail (:func:`drop_behind_envelope`); a NaN
    ``D5`` pixel drops nothing.
    """
    config = config or ViewMeshConfig()
    d5 = np.asarray(layers.depth[ENVELOPE_LAYER])
    if d5.shape != (camera.height, camera.width):
        raise ValueError(
            f"layers are {d5.shape[1]}×{d5.shape[0]} pixels but the camera is "
            f"{camera.width}×{camera.height}"
        )
    planes = frustum_planes(camera, config.near)
    limit = _envelope_limit(d5, config.behind_envelope)
    inst = np.asarray(layers.instance)
    # np.unique(inst[inst >= 0]) without sorting every pixel.
    object_ids = np.flatnonzero(np.bincount(inst[inst >= 0].ravel()))
    (objects,) = _clipped_meshes(house, [object_ids], camera, planes, d5, limit, config)
    return objects


def view_mesh(
    house: "House", camera: "Camera", layers: "Layers", config: ViewMeshConfig | None = None,
    tracer: "HouseTracer | None" = None,
) -> ViewMesh:
    """The ground-truth mesh of one view (docs/spec.md §5): :func:`object_mesh` and
    :func:`envelope_surface`, traced with ``tracer`` (a :class:`~sceneforge.raytrace.HouseTracer`
    of ``house``, built here when omitted)."""
    from .raytrace import HouseTracer

    objects = object_mesh(house, camera, layers, config)
    return ViewMesh(objects=objects, envelope=envelope_surface(tracer or HouseTracer(house), camera, config))
