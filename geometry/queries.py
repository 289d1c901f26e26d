"""Point queries against a triangle mesh (libigl): inside/outside by the generalized winding
number, nearest surface point, penetration depth, and the symmetric nearest-facet distances
between two sets of facets (the paper's contact distance, ``Phi_D``).

Meshes: ``vertices (V, 3) float`` metres, ``faces (T, 3) int`` (outward orientation);
points ``(N, 3)`` in the same frame.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from geometry import constants as C
from geometry.mesh import face_centroids


def _mesh(vertices, faces, name="vertices") -> tuple[np.ndarray, np.ndarray]:
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name}: expected (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces: expected (T, 3), got {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces: vertex index outside 0..{len(v) - 1}")
    return v, f


def _points(points) -> np.ndarray:
    p = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected (N, 3), got {p.shape}")
    return p


def winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) generalized winding number of ``points`` (N, 3) with respect to the mesh (libigl's
    fast winding number): ~1 inside, ~0 outside, smooth across holes in the surface."""
    v, f = _mesh(vertices, faces)
    p = _points(points)
    if not len(p):
        return np.zeros(0)
    import igl

    return np.asarray(igl.fast_winding_number(v, f, p))


def winding_number_exact(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                         chunk: int = 200_000) -> np.ndarray:
    """(N,) exact generalized winding number, in numpy: the sum over the faces of their
    signed solid angles seen from each point / 4 pi (Van Oosterom and Strackee's formula).
    O(N x T): meant for a few points against a part of a surface (winding numbers add up over
    faces, so the part's own number is exact, open or not); :func:`winding_number` (libigl's
    fast, hierarchical one) for many points."""
    v, f = _mesh(vertices, faces)
    p = _points(points)
    out = np.zeros(len(p))
    if not len(p) or not len(f):
        return out
    step = max(1, chunk // len(f))
    for s0 in range(0, len(p), step):
        a = v[f[:, 0]][None] - p[s0:s0 + step, None]  # (n, T, 3)
        b = v[f[:, 1]][None] - p[s0:s0 + step, None]
        c = v[f[:, 2]][None] - p[s0:s0 + step, None]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("ntd,ntd->nt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ntd,ntd->nt", a, b) * lc
               + np.einsum("ntd,ntd->nt", b, c) * la + np.einsum("ntd,ntd->nt", c, a) * lb)
        out[s0:s0 + step] = np.arctan2(det, den).sum(1) / (2 * np.pi)
    return out


def is_inside(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) bool: winding number > constants.INSIDE_WINDING (tolerant of holes)."""
    return winding_number(points, vertices, faces) > C.INSIDE_WINDING


class Nearest(NamedTuple):
    """Nearest surface points. distance: (N,) metres (unsigned); face: (N,) int, the face the
    point lies on; point: (N, 3) the closest surface point."""

    distance: np.ndarray
    face: np.ndarray
    point: np.ndarray


def nearest_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> Nearest:
    """Exact closest point on the mesh of each of ``points`` (N, 3) (libigl's
    ``point_mesh_squared_distance``)."""
    import igl

    v, f = _mesh(vertices, faces)
    p = _points(points)
    if not len(p):
        return Nearest(np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)))
    d2, fi, cp = igl.point_mesh_squared_distance(p, v, f)
    return Nearest(np.sqrt(np.maximum(d2, 0.0)), np.asarray(fi, np.int64), np.asarray(cp))


class Inside(NamedTuple):
    """Points inside a mesh. index: (n,) int, which of the queried points; depth: (n,) metres,
    their distance to the mesh's surface (how deep they are); face: (n,) int, the nearest face
    of the mesh."""

    index: np.ndarray
    depth: np.ndarray
    face: np.ndarray


def points_inside(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> Inside:
    """The ``points`` (N, 3) that are inside the mesh (:func:`is_inside`) with their exact
    depth below its surface and the nearest face."""
    ins = np.flatnonzero(is_inside(points, vertices, faces))
    if not len(ins):
        return Inside(ins, np.zeros(0), np.zeros(0, np.int64))
    near = nearest_surface(_points(points)[ins], vertices, faces)
    return Inside(ins, near.distance, near.face)


def penetration_depths(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) depth of each of ``points`` (N, 3) inside the mesh, metres (0 outside)."""
    out = np.zeros(len(_points(points)))
    ins = points_inside(points, vertices, faces)
    out[ins.index] = ins.depth
    return out


def inside_points(V0: np.ndarray, V1: np.ndarray, faces0: np.ndarray,
                  faces1: np.ndarray | None = None) -> list[Inside]:
    """The vertices of each of two meshes that are inside the other, with their depth.

    V0: (V0, 3), V1: (V1, 3) metres; faces0: (T0, 3); faces1: (T1, 3), default ``faces0`` (two
    bodies of one model). Returns [vertices of mesh 0 inside mesh 1, vertices of mesh 1 inside
    mesh 0] as :class:`Inside` (index = vertex id, face = the other mesh's nearest face)."""
    faces1 = faces0 if faces1 is None else faces1
    if apart(V0, faces0, V1, faces1):
        none = Inside(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64))
        return [none, none]
    return [points_inside(V0, V1, faces1), points_inside(V1, V0, faces0)]


_CLOSED: dict[str, bool] = {}


def is_closed(faces: np.ndarray) -> bool:
    """Every edge of ``faces`` (T, 3) is shared by exactly two faces (a closed surface, maybe
    of several components); remembered per faces array content."""
    import hashlib

    f = np.ascontiguousarray(faces, dtype=np.int64)
    key = hashlib.sha1(f.tobytes()).hexdigest() + str(f.shape)
    if key not in _CLOSED:
        e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, counts = np.unique(e, axis=0, return_counts=True)
        _CLOSED[key] = bool(len(f)) and bool(np.all(counts == 2))
    return _CLOSED[key]


def max_edge(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The longest edge of the mesh (metres)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    return float(max(np.linalg.norm(v[f[:, i]] - v[f[:, (i + 1) % 3]], axis=1).max()
                     for i in range(3)))


def apart(V0: np.ndarray, faces0: np.ndarray, V1: np.ndarray, faces1: np.ndarray) -> bool:
    """True when two closed meshes provably neither cross nor hold one another: every vertex
    of one lies farther than the sum of their longest edges from every vertex of the other (a
    point where the surfaces cross lies within an edge's length of a vertex of each), so the
    surfaces do not cross, and then no vertex of one is inside the other unless one mesh is
    nested in the other, which needs its bounding box inside the other's. A broad phase: it
    spares the winding numbers of frames where two bodies are apart; False (do the exact
    test) for nested boxes and for a mesh that is not closed, whose winding number can pass
    0.5 without a crossing."""
    if not (len(V0) and len(V1) and is_closed(faces0) and is_closed(faces1)):
        return False
    from scipy.spatial import cKDTree

    v0, v1 = np.asarray(V0, np.float64), np.asarray(V1, np.float64)
    b0, b1 = (v0.min(0), v0.max(0)), (v1.min(0), v1.max(0))
    if np.all(b0[0] >= b1[0]) and np.all(b0[1] <= b1[1]) or (
            np.all(b1[0] >= b0[0]) and np.all(b1[1] <= b0[1])):
        return False
    reach = max_edge(v0, faces0) + max_edge(v1, faces1)
    lo, hi = np.maximum(b0[0], b1[0]), np.minimum(b0[1], b1[1])
    if np.any(lo - hi > reach):  # the bounding boxes are farther apart than that
        return True
    box = [np.all((v >= lo - reach) & (v <= hi + reach), axis=1) for v in (v0, v1)]
    if not box[0].any() or not box[1].any():
        return True
    d, _ = cKDTree(v1[box[1]]).query(v0[box[0]], distance_upper_bound=reach)
    return bool(np.all(np.isinf(d)))


class Deepest(NamedTuple):
    """The deepest point of one mesh inside another. depth: metres (0 if none); body: 0/1, the
    mesh the point belongs to, or -1; vertex: its vertex id, or -1."""

    depth: float
    body: int
    vertex: int


def deepest_inside(inside: list[Inside]) -> Deepest:
    """The deepest of the points found by :func:`inside_points`."""
    best = Deepest(0.0, -1, -1)
    for a, (ins, d, _) in enumerate(inside):
        if len(ins):
            k = int(np.argmax(d))
            if d[k] > best.depth:
                best = Deepest(float(d[k]), a, int(ins[k]))
    return best


def interpenetration(V0: np.ndarray, V1: np.ndarray, faces0: np.ndarray,
                     faces1: np.ndarray | None = None) -> Deepest:
    """The deepest interpenetration of two meshes: over the vertices of each that are inside
    the other (winding number), the largest exact distance to the other's surface. Arguments
    as :func:`inside_points`."""
    return deepest_inside(inside_points(V0, V1, faces0, faces1))


def interpenetration_per_frame(V0: np.ndarray, V1: np.ndarray, faces0: np.ndarray,
                               faces1: np.ndarray | None = None) -> np.ndarray:
    """(F,) deepest interpenetration (metres) of two meshes' vertices (F, V, 3) per frame."""
    if len(V0) != len(V1):
        raise ValueError(f"V0, V1: {len(V0)} and {len(V1)} frames")
    return np.array([interpenetration(V0[f], V1[f], faces0, faces1).depth
                     for f in range(len(V0))])


class FacetDistances(NamedTuple):
    """Symmetric nearest-facet distances between facet sets A (of mesh a) and B (of mesh b).
    a_to_b: (nA,) metres, from each facet of A (its centroid) to the nearest facet of B;
    a_nearest: (nA,) that facet's id in mesh b; b_to_a, b_nearest: (nB,) the other way."""

    a_to_b: np.ndarray
    a_nearest: np.ndarray
    b_to_a: np.ndarray
    b_nearest: np.ndarray

    def total(self) -> float:
        """The paper's region distance ``Phi_D``: the sum over both directions, metres."""
        return float(self.a_to_b.sum() + self.b_to_a.sum())


def facet_distances(Va: np.ndarray, Fa: np.ndarray, sel_a: np.ndarray,
                    Vb: np.ndarray, Fb: np.ndarray, sel_b: np.ndarray) -> FacetDistances:
    """Contact distances between the facets ``sel_a`` of mesh (Va, Fa) and ``sel_b`` of mesh
    (Vb, Fb) (the paper's ``Phi_D``: for each facet of one set, the distance to the nearest
    facet of the other set, both ways). The facet-to-facet distance ``phi_D`` is measured from
    a facet's centroid to the other triangle (exact point-to-triangle; an upper bound of the
    triangle-to-triangle distance, equal when the facets face each other).

    Va, Vb: (V, 3) metres; Fa, Fb: (T, 3); sel_a, sel_b: face ids, non-empty."""
    out = []
    for (V, F, sel), (W, G, other) in (((Va, Fa, sel_a), (Vb, Fb, sel_b)),
                                        ((Vb, Fb, sel_b), (Va, Fa, sel_a))):
        sel = np.asarray(sel, np.int64).reshape(-1)
        other = np.asarray(other, np.int64).reshape(-1)
        if not len(sel) or not len(other):
            raise ValueError("sel_a, sel_b: facet sets must not be empty")
        near = nearest_surface(face_centroids(V, np.asarray(F)[sel]), W, np.asarray(G)[other])
        out += [near.distance, other[near.face]]
    return FacetDistances(*out)
