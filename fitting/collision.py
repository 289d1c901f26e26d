"""Collision and contact geometry of the partner fit, in numpy (run between solver iterations;
only what it finds enters the symbolic graph as slots of ``fitting/terms.py``'s ``L_ic``,
``L_sc``, ``L_gp``, ``L_D``, ``L_N``).

- :class:`ProxyMesh`: a coarse proxy of a body mesh (the paper's PHUM idea): libigl's
  quadric-error decimation (``igl.qslim``) of the template to ~``n_vertices``, each proxy
  vertex attached to the full mesh by a face and barycentric coordinates, so it follows the
  skinned mesh (``proxy.points(vertices)``) and can be skinned as a 3-vertex slot like a
  marker (``proxy.corners``, ``proxy.bary``). Quadric decimation rather than libigl's
  shortest-edge ``decimate``: on Anny at 2,000 vertices its surface stays within 3.1 mm of the
  full mesh (``decimate``: 8.9 mm) and its inside/outside agrees with the full mesh on 99.6 %
  of random points within 5 cm of the body (``decimate``: 98.8 %).
- :func:`interpenetration`: the points of one body inside the other (generalized winding
  number, ``geometry``), each with its nearest point on the other surface (the paper's
  ``NN(V, M)``), both directions.
- :func:`self_collisions`: proxy points inside the own proxy, counting only the parts of the
  body that are not neighbours of the point's region (``body.regions`` adjacency, ``rings``
  steps), by the winding number of the non-neighbouring faces alone (winding numbers add up
  over faces, so this is exact for the part of the surface that is kept).
- :func:`ground_candidates`: the top-k lowest points for ``L_gp``.
- :func:`psi_D`, :func:`match_facets`, :func:`contact_pairs`: the facet selection operator and
  the symmetric nearest-facet matches of ``Phi_D`` for the region pairs of a contact
  signature; ``L_N`` re-uses the same pairs (the paper's ``psi_N``).

Meshes: ``vertices (V, 3)`` metres, ``faces (T, 3)`` int, outward orientation.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import numpy as np

from body.model import BodyModel
from geometry import (
    face_centroids,
    facet_distances,
    nearest_surface,
    winding_number,
    winding_number_exact,
)

# constants
PROXY_VERTICES = 2000  # default proxy size (the paper: PHUM, ~1-2k vertices)
#: a point pushed out of a surface is pushed this far beyond it (metres), so the fit
#: leaves the surface in finitely many steps instead of approaching it from inside.
MARGIN_M = 5e-4
INSIDE_WINDING = 0.5  # a point is inside (a kept part of) a surface above this winding number
#: self-collision candidates: winding number w.r.t. the whole own proxy above this. A point on
#: the surface gets ~0.5 from its own neighbourhood, one inside another part ~1.5; the exact
#: test on the non-neighbouring faces follows.
SELF_CANDIDATE_WINDING = 0.75
#: regions within this many adjacency steps of a point's region are its neighbours (never
#: colliders): 2 keeps the elbow crease (forearm - elbow - upper arm) out of L_sc.
SELF_RINGS = 2
GROUND_K = 20  # default number of lowest vertices for L_gp
SELECTIONS = ("all", "uniform", "annotated")  # psi_D modes


def barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of ``points`` (N, 3) in triangles (a, b, c), each (N, 3)
    (of the point's projection onto the triangle's plane; degenerate triangles: the centroid)."""
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-300
    den = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / den, 1 / 3)
    w = np.where(ok, (d00 * d21 - d01 * d20) / den, 1 / 3)
    return np.stack([1.0 - v - w, v, w], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class ProxyMesh:
    """A coarse proxy of a body mesh whose vertices ride on the full mesh.

    faces : (T', 3) proxy triangles (indices into the proxy vertices, outward).
    corners : (P, 3) full-mesh vertex ids of the face each proxy vertex lies on.
    face : (P,) that full-mesh face; bary : (P, 3) its barycentric coordinates.
    face_region : (T',) region of each proxy face (-1 none), or None when built without regions.
    vertex_region : (P,) region of each proxy vertex (that of its full-mesh face), or None.
    region_adjacency : (R, R) bool, regions sharing an edge on the full mesh, or None.
    """

    faces: np.ndarray
    corners: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    face_region: np.ndarray | None = None
    vertex_region: np.ndarray | None = None
    region_adjacency: np.ndarray | None = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v.flags.writeable = False

    @property
    def num_vertices(self) -> int:
        return len(self.face)

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, faces: np.ndarray, n_vertices: int = PROXY_VERTICES,
                  face_region: np.ndarray | None = None,
                  region_adjacency: np.ndarray | None = None) -> ProxyMesh:
        """Decimate the mesh (``igl.qslim`` to ``2 n_vertices`` faces, about ``n_vertices``
        vertices) and attach each proxy vertex to its nearest point of the full mesh.
        ``face_region`` (T,) of the full mesh and ``region_adjacency`` (R, R) enable
        :func:`self_collisions`."""
        import igl

        V = np.ascontiguousarray(vertices, dtype=np.float64)
        F = np.ascontiguousarray(faces, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3:
            raise ValueError(f"vertices: expected (V, 3), got {V.shape}")
        if n_vertices < 4:
            raise ValueError(f"n_vertices: expected >= 4, got {n_vertices}")
        if 2 * n_vertices >= len(F):
            U, G = V, F
        else:
            U, G, _, _ = igl.qslim(V, F.astype(np.int32), int(2 * n_vertices))
        near = nearest_surface(U, V, F)
        corners = F[near.face]
        bary = barycentric(near.point, V[corners[:, 0]], V[corners[:, 1]], V[corners[:, 2]])
        fr = vr = None
        if face_region is not None:
            face_region = np.asarray(face_region, np.int64)
            if face_region.shape != (len(F),):
                raise ValueError(f"face_region: expected ({len(F)},), got {face_region.shape}")
            G = np.asarray(G, np.int64)
            P = near.point
            fr = face_region[nearest_surface(face_centroids(P, G), V, F).face]
            vr = face_region[near.face]
        return cls(np.asarray(G, np.int64), corners, near.face, bary, fr, vr,
                   None if region_adjacency is None else np.asarray(region_adjacency, bool))

    @classmethod
    def from_model(cls, model: BodyModel, n_vertices: int = PROXY_VERTICES, rmap=None) -> ProxyMesh:
        """The proxy of ``model``'s template (betas 0), with the regions of ``rmap`` (default
        ``body.regions.region_map(model)``) for self-collision. The attachment holds for any
        shape and pose: ``proxy.points(forward(...).vertices)``."""
        from body.regions import region_map

        rmap = region_map(model) if rmap is None else rmap
        F = np.asarray(model.faces)
        return cls.from_mesh(model.v_template, F, n_vertices, rmap.face_region,
                             rmap.adjacency(F))

    def points(self, vertices: np.ndarray) -> np.ndarray:
        """Proxy vertices (..., P, 3) of full-mesh vertices (..., V, 3) (any leading axes)."""
        v = np.asarray(vertices, dtype=float)
        return (v[..., self.corners, :] * self.bary[..., None]).sum(-2)

    def self_regions(self, rings: int = SELF_RINGS) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Per region r of a proxy vertex: (the proxy faces a point of r can collide with:
        those of regions more than ``rings`` adjacency steps away, the rest of the faces),
        face ids each. Found once per proxy and ``rings`` (the proxy is immutable), for
        :func:`self_collisions` and :func:`self_penetration`."""
        if self.face_region is None or self.region_adjacency is None:
            raise ValueError("proxy: built without regions (use ProxyMesh.from_model or pass "
                             "face_region and region_adjacency)")
        memo = self.__dict__.setdefault("_self_regions", {})
        if rings not in memo:
            near_r = _neighbours(self.region_adjacency, rings)
            fr = np.asarray(self.face_region)
            out = {}
            for r in np.unique(self.vertex_region[self.vertex_region >= 0]):
                kept = (fr >= 0) & ~near_r[r][np.maximum(fr, 0)]
                out[int(r)] = (np.flatnonzero(kept), np.flatnonzero(~kept))
            memo[rings] = out
        return memo[rings]


class Collisions(NamedTuple):
    """Query points inside a surface and where each must go.

    index : (n,) which of the queried points are inside.
    depth : (n,) metres, their distance to the nearest point of the surface.
    target : (n, 3) that nearest point, pushed ``margin`` beyond the surface (away from the
        point): the ``targets`` of ``L_ic`` / ``L_sc``.
    face : (n,) the face of the surface the nearest point lies on; bary : (n, 3) its
        barycentric coordinates there.
    """

    index: np.ndarray
    depth: np.ndarray
    target: np.ndarray
    face: np.ndarray
    bary: np.ndarray

    @property
    def n(self) -> int:
        """Number of colliding points."""
        return len(self.index)

    @property
    def deepest(self) -> float:
        return float(self.depth.max()) if len(self.index) else 0.0


def _empty() -> Collisions:
    return Collisions(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                      np.zeros((0, 3)))


def _pushed(points, near_points, margin):
    d = near_points - points
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return near_points + margin * d / np.maximum(n, 1e-12)


def _collisions(points, idx, vertices, faces, margin, face_ids=None) -> Collisions:
    if not len(idx):
        return _empty()
    near = nearest_surface(points[idx], vertices, faces)
    f = np.asarray(faces)[near.face]
    bary = barycentric(near.point, vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]])
    face = near.face if face_ids is None else np.asarray(face_ids)[near.face]
    return Collisions(np.asarray(idx, np.int64), near.distance,
                      _pushed(points[idx], near.point, margin), face, bary)


def inside(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
           margin: float = MARGIN_M) -> Collisions:
    """The ``points`` (N, 3) inside the mesh (generalized winding number > 0.5) with their
    nearest surface points ``NN(V, M)`` (exact, ``geometry.nearest_surface``)."""
    p = np.asarray(points, dtype=float)
    V = np.asarray(vertices, dtype=float)
    # a point outside the mesh's bounding box is outside the mesh: only the rest is tested
    # (the winding number costs per point; two people side by side overlap little)
    box = np.flatnonzero(np.all((p >= V.min(axis=0)) & (p <= V.max(axis=0)), axis=1))
    if not len(box):
        return _empty()
    idx = box[winding_number(p[box], V, faces) > INSIDE_WINDING]
    return _collisions(p, idx, V, faces, margin)


def interpenetration(points_a: np.ndarray, vertices_a: np.ndarray, faces_a: np.ndarray,
                     points_b: np.ndarray, vertices_b: np.ndarray, faces_b: np.ndarray,
                     margin: float = MARGIN_M) -> tuple[Collisions, Collisions]:
    """Both sums of the paper's ``L_ic`` for body a (being fitted) against body b.

    points_a : (Na, 3) proxy points of a; (vertices_a, faces_a) the mesh of a they are tested
    against by b (its proxy: ``proxy.points(V)``, ``proxy.faces``, or the full mesh); the same
    for b. Returns ``(a_in_b, b_in_a)``:

    - ``a_in_b``: points of a inside b, ``target`` their nearest point on b (pushed out by
      ``margin``): ``L_ic(points_a[a_in_b.index], a_in_b.target, w)``;
    - ``b_in_a``: points of b inside a; here ``face`` / ``bary`` locate the nearest point on
      the mesh of a (the slot that moves with a) and ``target`` is where that surface point
      must go: b's point, pushed ``margin`` past it:
      ``L_ic(surface_point_a(face, bary), b_in_a.target, w)``.
    """
    a_in_b = inside(points_a, vertices_b, faces_b, margin)
    b_in_a = inside(points_b, vertices_a, faces_a, margin=0.0)
    if b_in_a.n:
        pb = np.asarray(points_b, dtype=float)[b_in_a.index]
        # b_in_a.target is the surface point of a (margin 0); a's surface must pass b's point
        b_in_a = b_in_a._replace(target=_pushed(b_in_a.target, pb, margin))
    return a_in_b, b_in_a


def _neighbours(adjacency: np.ndarray, rings: int) -> np.ndarray:
    A = np.asarray(adjacency, bool)
    N = A | np.eye(len(A), dtype=bool)
    R = N.copy()
    for _ in range(rings - 1):
        R = (R.astype(np.int64) @ N.astype(np.int64)) > 0
    return R


def _self_hits(proxy: ProxyMesh, p: np.ndarray, rings: int, winding=None
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per region with a colliding point: (the region's collidable faces, its proxy points
    inside them). A candidate is a point the whole proxy's winding number puts inside; winding
    numbers add up over faces, so the collidable part's number is the whole's minus the rest's
    (exact, in numpy over the few candidates and the small rest: no hierarchy per region).
    ``winding``: the whole proxy's (fast) winding number of query points, when the caller
    already has its hierarchy (the same numbers as :func:`geometry.winding_number`)."""
    regions = proxy.self_regions(rings)
    if p.shape != (proxy.num_vertices, 3):
        raise ValueError(f"points: expected ({proxy.num_vertices}, 3), got {p.shape}")
    vr = proxy.vertex_region
    w_all = winding_number(p, p, proxy.faces) if winding is None else np.asarray(winding(p))
    cand = np.flatnonzero((w_all > SELF_CANDIDATE_WINDING) & (vr >= 0))
    out = []
    for r in np.unique(vr[cand]):
        far, rest = regions[int(r)]
        if not len(far):
            continue
        pts = cand[vr[cand] == r]
        w_far = w_all[pts] - winding_number_exact(p[pts], p, proxy.faces[rest])
        hit = pts[w_far > INSIDE_WINDING]
        if len(hit):
            out.append((far, hit))
    return out


def self_collisions(proxy: ProxyMesh, points: np.ndarray, rings: int = SELF_RINGS,
                    margin: float = MARGIN_M) -> Collisions:
    """Proxy points (P, 3) (``proxy.points(V)``) inside the own body, counting only the faces
    of regions more than ``rings`` adjacency steps away from the point's region; ``target`` =
    the nearest point on those faces (pushed out by ``margin``), ``face`` a proxy face.
    Points and faces without a region (-1) never collide."""
    p = np.asarray(points, dtype=float)
    out = [_collisions(p, hit, p, proxy.faces[far], margin, face_ids=far)
           for far, hit in _self_hits(proxy, p, rings)]
    if not out:
        return _empty()
    c = Collisions(*[np.concatenate(x) for x in zip(*out, strict=True)])
    order = np.argsort(c.index)
    return Collisions(*[x[order] for x in c])


def self_penetration(proxy: ProxyMesh, points: np.ndarray, rings: int = SELF_RINGS,
                     winding=None) -> float:
    """The deepest self-penetration (m) of the proxy points (P, 3), 0 when none: the
    ``deepest`` of :func:`self_collisions` without its targets (the QA's per-frame figure).
    ``winding``: optional, the fast winding number of query points against this posed proxy
    (a hierarchy the caller keeps for other queries; the same numbers)."""
    p = np.asarray(points, dtype=float)
    return max((float(nearest_surface(p[hit], p, proxy.faces[far]).distance.max())
                for far, hit in _self_hits(proxy, p, rings, winding)), default=0.0)


def ground_candidates(points: np.ndarray, normal, offset: float, k: int = GROUND_K) -> np.ndarray:
    """(min(k, N),) indices of the k points (N, 3) lowest along ``normal`` (signed distance
    ``normal . x - offset``, lowest first): the slots of ``L_gp``, which is 0 for those above."""
    p = np.asarray(points, dtype=float)
    n = np.asarray(normal, dtype=float).reshape(3)
    d = p @ n - float(offset)
    k = min(int(k), len(d))
    idx = np.argpartition(d, k - 1)[:k] if k < len(d) else np.arange(len(d))
    return idx[np.argsort(d[idx], kind="stable")]


def psi_D(region_faces: np.ndarray, mode: str = "all", n: int | None = None,
          rng: np.random.Generator | None = None, annotated: np.ndarray | None = None) -> np.ndarray:
    """The paper's facet selection operator ``psi_D`` on a region (its facet ids).

    ``"all"``: every facet of the region; ``"uniform"``: ``n`` facets drawn without
    replacement (``rng``; all of them if the region has fewer); ``"annotated"``: the given
    facets (e.g. the signature's facet-level correspondences)."""
    faces = np.asarray(region_faces, np.int64).reshape(-1)
    if mode == "all":
        return faces
    if mode == "uniform":
        if n is None or n < 1 or rng is None:
            raise ValueError("psi_D: mode 'uniform' needs n >= 1 and rng")
        return faces if len(faces) <= n else np.sort(rng.choice(faces, size=n, replace=False))
    if mode == "annotated":
        if annotated is None or not len(np.asarray(annotated).reshape(-1)):
            raise ValueError("psi_D: mode 'annotated' needs a non-empty list of facets")
        return np.unique(np.asarray(annotated, np.int64).reshape(-1))
    raise ValueError(f"psi_D: mode must be one of {SELECTIONS}, got {mode!r}")


class FacetPairs(NamedTuple):
    """Matched facet pairs for ``L_D`` / ``L_N``: face_1 (P,) on mesh 1, face_2 (P,) on mesh 2,
    pair (P,) the index of the region pair (of ``contact_pairs``) each match belongs to."""

    face_1: np.ndarray
    face_2: np.ndarray
    pair: np.ndarray

    @property
    def n(self) -> int:
        return len(self.face_1)


def match_facets(V1: np.ndarray, F1: np.ndarray, sel_1: np.ndarray,
                 V2: np.ndarray, F2: np.ndarray, sel_2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both directions of ``Phi_D``'s nearest-facet match between the facets ``sel_1`` of
    mesh 1 and ``sel_2`` of mesh 2 (``geometry.facet_distances``: nearest by centroid to
    triangle). Returns ``(face_1, face_2)``, each (|sel_1| + |sel_2|,): first every facet of
    sel_1 with its nearest facet of sel_2, then every facet of sel_2 with its nearest of sel_1."""
    s1 = np.asarray(sel_1, np.int64).reshape(-1)
    s2 = np.asarray(sel_2, np.int64).reshape(-1)
    fd = facet_distances(V1, F1, s1, V2, F2, s2)
    return (np.concatenate([s1, fd.b_nearest]).astype(np.int64),
            np.concatenate([fd.a_nearest, s2]).astype(np.int64))


def contact_pairs(V1: np.ndarray, F1: np.ndarray, rmap1, V2: np.ndarray, F2: np.ndarray, rmap2,
                  region_pairs: Sequence[tuple[int, int]], mode: str = "all",
                  n: int | None = None, rng: np.random.Generator | None = None,
                  annotated: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> FacetPairs:
    """The matched facets of every region pair ``(r1, r2)`` of a contact signature (region ids
    of ``rmap1`` on mesh 1 and of ``rmap2`` on mesh 2, ``body.regions.RegionMap``), with the
    selection ``psi_D`` (``mode``, ``n``, ``rng``; for ``"annotated"``, ``annotated[k] =
    (facets_1, facets_2)`` of pair k). Matches are redone between solver iterations; ``L_D``
    and ``L_N`` take the centres and corners of ``face_1`` / ``face_2``."""
    if mode == "annotated" and (annotated is None or len(annotated) != len(region_pairs)):
        raise ValueError("contact_pairs: mode 'annotated' needs one (facets_1, facets_2) per "
                         "region pair")
    f1, f2, k_of = [], [], []
    for k, (r1, r2) in enumerate(region_pairs):
        a1 = a2 = None
        if mode == "annotated":
            a1, a2 = annotated[k]
        s1 = psi_D(rmap1.faces_of(int(r1)), mode, n, rng, a1)
        s2 = psi_D(rmap2.faces_of(int(r2)), mode, n, rng, a2)
        if not len(s1) or not len(s2):
            raise ValueError(f"contact_pairs: region pair {k} ({r1}, {r2}) has no facets")
        a, b = match_facets(V1, F1, s1, V2, F2, s2)
        f1.append(a)
        f2.append(b)
        k_of.append(np.full(len(a), k, np.int64))
    if not f1:
        z = np.zeros(0, np.int64)
        return FacetPairs(z, z, z)
    return FacetPairs(np.concatenate(f1), np.concatenate(f2), np.concatenate(k_of))
