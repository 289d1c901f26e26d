"""Skinned points as fitting unknowns: the fit skeleton, slot coefficients, the CasADi graph.

The full mesh is skinned in numpy (``body.lbs``); the symbolic graph only carries a fixed
number of *slots* (markers, keypoints) whose coefficients are parameters, so one compiled
function serves every subject, sequence and frame (DESIGN.md, "Skinning").

Reduction to the fit skeleton. ``body.lbs`` poses every joint ``j`` with ``D_j``; the fit
solves only the joints ``Q = model.fit_joints`` (root first) and keeps ``D_j = I`` elsewhere.
A joint ``j`` outside Q then moves rigidly with its nearest fitted ancestor ``a(j)``:
``G_j = G_a``, ``t_j = t_a + G_a s_j`` with ``s_j`` the sum of rest offsets ``o`` from ``a`` to
``j``. Substituting in the skinning equation of ``body/lbs.py``,

    v = sum_j w_vj (G_j A_j (v_c - h_j) + t_j)
      = sum_{q in Q} (G_q  l_vq + W_vq t_q),
    l_vq = sum_{j: a(j)=q} w_vj (A_j (v_c - h_j) + s_j),   W_vq = sum_{j: a(j)=q} w_vj,

exactly (no pose correctives: Anny has none; SMPL-family ``posedirs`` are ignored here, a
documented approximation). A slot is the (Q, 4) matrix ``H = [l | W]``; a point regressed
linearly from vertices (a keypoint) is the same linear combination of its vertices' ``H``.
The reduced tree: ``G_0 = R``, ``t_0 = h_0 + T``; ``G_q = G_p D_q``, ``t_q = t_p + G_p u_q`` with
``p`` the fitted parent and ``u_q`` the summed offsets from ``p`` to ``q``.

Unknowns of one frame, ``x (n,) = [r (3) global rotation vector, T (3) metres,
theta ((Q-1)*3) local rotation vectors of Q[1:]]``, radians.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from body.lbs import RestState
from body.model import BodyModel
from body.rotations import rodrigues, rodrigues_cs, skew
from geometry import face_normals


@dataclass(frozen=True, eq=False)
class FitSkeleton:
    """The fitted joints and their reduced tree.

    joints : (Q,) model joint indices fitted, root first, parents before children.
    parents : (Q,) index into ``joints`` of each fitted joint's fitted parent, -1 for the root.
    owner : (J,) index into ``joints`` of each model joint's nearest fitted ancestor (itself if
        fitted).
    names : (Q,) joint names.
    """

    joints: np.ndarray
    parents: np.ndarray
    owner: np.ndarray
    names: tuple[str, ...]

    @property
    def n(self) -> int:
        """Number of unknowns of one frame."""
        return 3 * len(self.joints) + 3

    @property
    def topology(self) -> tuple[int, ...]:
        return tuple(int(p) for p in self.parents)


def fit_skeleton(model: BodyModel, joints=None) -> FitSkeleton:
    """The reduced tree of ``joints`` (default ``model.fit_joints``); must include joint 0."""
    q = np.array(sorted(set(int(j) for j in (model.fit_joints if joints is None else joints))))
    if len(q) == 0 or q[0] != 0:
        raise ValueError("fit joints must include the root (joint 0)")
    par = np.asarray(model.parents)
    pos = {int(j): i for i, j in enumerate(q)}
    owner = np.zeros(len(par), dtype=np.int64)
    for j in range(len(par)):
        owner[j] = pos[j] if j in pos else owner[par[j]]
    parents = np.array([-1] + [owner[par[j]] for j in q[1:]], dtype=np.int64)
    return FitSkeleton(q, parents, owner, tuple(model.joint_names[j] for j in q))


def reduced_offsets(model: BodyModel, rest: RestState, skel: FitSkeleton) -> tuple[np.ndarray, np.ndarray]:
    """``(u (Q, 3), s (J, 3))``: u_q offsets of the reduced tree (u_0 = h_0, the rest root), and
    s_j the offset of every model joint from its owner (0 for fitted joints). Metres."""
    par = np.asarray(model.parents)
    off = rest.offsets[0]
    J = len(par)
    fitted = np.zeros(J, dtype=bool)
    fitted[skel.joints] = True
    s = np.zeros((J, 3))
    for j in range(1, J):
        if not fitted[j]:
            s[j] = s[par[j]] + off[j] if not fitted[par[j]] else off[j]
    u = np.zeros((len(skel.joints), 3))
    u[0] = off[0]
    for i, j in enumerate(skel.joints[1:], start=1):
        p = par[j]
        u[i] = off[j] + (0.0 if fitted[p] else s[p])
    return u, s


def vertex_coeffs(model: BodyModel, rest: RestState, skel: FitSkeleton, weights: sp.csr_matrix,
                  points: np.ndarray) -> np.ndarray:
    """Slot coefficients ``H (S, Q, 4)`` of rest points with given skinning weight rows.

    weights : (S, J) sparse or dense skinning weights of the slots; points : (S, 3) rest
    positions (metres, the rest mesh's frame) that skin like vertices with those weights."""
    W = sp.csr_matrix(weights)
    pts = np.asarray(points, dtype=float)
    _, s = reduced_offsets(model, rest, skel)
    h = rest.joints[0]
    A = rest.bind_rot[0] if rest.bind_rot is not None else None
    H = np.zeros((W.shape[0], len(skel.joints), 4))
    Wc = W.tocoo()
    i, j, w = Wc.row, Wc.col, Wc.data
    d = pts[i] - h[j]
    if A is not None:
        d = np.einsum("nab,nb->na", A[j], d)
    q = np.asarray(skel.owner)[j]
    np.add.at(H, (i, q), np.concatenate([w[:, None] * (d + s[j]), w[:, None]], axis=1))
    return H


def slot_positions_np(skel: FitSkeleton, u: np.ndarray, H: np.ndarray, x: np.ndarray) -> np.ndarray:
    """numpy twin of the graph: world positions (..., S, 3) of slots ``H (S, Q, 4)`` at
    unknowns x (..., n) (leading axes: frames)."""
    G, t = _fk_np(skel, u, x)
    S, Q = H.shape[:2]
    Gr = np.swapaxes(G, -3, -2).reshape(G.shape[:-3] + (3, 3 * Q))  # [..., a, (q, b)]
    out = Gr @ H[..., :3].reshape(S, 3 * Q).T + np.swapaxes(t, -1, -2) @ H[..., 3].T
    return np.swapaxes(out, -1, -2)  # two matrix products (an einsum here was ~10x slower)


def _fk_np(skel: FitSkeleton, u: np.ndarray, x: np.ndarray):
    """(G (..., Q, 3, 3), t (..., Q, 3)): the fit joints' world frames at unknowns x (..., n)."""
    x = np.asarray(x, dtype=float)
    lead = x.shape[:-1]
    Q = len(skel.joints)
    D = rodrigues(x[..., 6:].reshape(lead + (Q - 1, 3)))
    G = np.zeros(lead + (Q, 3, 3))
    t = np.zeros(lead + (Q, 3))
    G[..., 0, :, :] = rodrigues(x[..., :3])
    t[..., 0, :] = u[0] + x[..., 3:6]
    for i in range(1, Q):
        p = skel.parents[i]
        G[..., i, :, :] = G[..., p, :, :] @ D[..., i - 1, :, :]
        t[..., i, :] = t[..., p, :] + G[..., p, :, :] @ u[i]
    return G, t


# ---------------------------------------------------------------------------- exact Jacobians in numpy

JR_SMALL = 1e-8  # below this angle the SO(3) right Jacobian is its series


def right_jacobian(rv: np.ndarray) -> np.ndarray:
    """(..., 3, 3) SO(3) right Jacobian of rotation vectors (..., 3):
    ``exp(r + d) = exp(r) exp(J_r(r) d)`` to first order."""
    rv = np.asarray(rv, float)
    th = np.linalg.norm(rv, axis=-1)[..., None, None]
    K = skew(rv)
    small = th < JR_SMALL
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6.0, (ths - np.sin(ths)) / ths ** 3)
    return np.eye(3) - a * K + b * (K @ K)


def subtree(skel: FitSkeleton) -> np.ndarray:
    """(Q, Q) bool, ``A[i, q]``: fitted joint q is i or a descendant of i."""
    Q = len(skel.joints)
    A = np.eye(Q, dtype=bool)
    for q in range(1, Q):  # parents come before children
        p = int(skel.parents[q])
        while p >= 0:
            A[p, q] = True
            p = int(skel.parents[p])
    return A


_EPS = np.zeros((3, 3, 3))  # the Levi-Civita symbol: (a x b)_i = eps_ijk a_j b_k
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0
_LEVELS: dict[tuple[int, ...], list[tuple[np.ndarray, np.ndarray]]] = {}


def _levels(skel: FitSkeleton) -> list[tuple[np.ndarray, np.ndarray]]:
    """The reduced tree by depth below the root: [(joints, their parents)] per level, so
    forward kinematics runs one batched product per level, not one per joint (cached)."""
    key = skel.topology
    if key not in _LEVELS:
        par = np.asarray(skel.parents)
        depth = np.zeros(len(par), np.int64)
        for i in range(1, len(par)):  # parents come before children
            depth[i] = depth[par[i]] + 1
        _LEVELS[key] = [(np.flatnonzero(depth == d), par[depth == d])
                        for d in range(1, int(depth.max(initial=0)) + 1)]
    return _LEVELS[key]


def _fk_axes(skel: FitSkeleton, u: np.ndarray, x: np.ndarray):
    """G (Q, 3, 3), t (Q, 3) of the reduced tree (fitting/skinned.py) and the world axes
    ``G_i J_r(theta_i)`` (Q, 3, 3) of each joint's local rotation vector (the root: r)."""
    Q = len(skel.joints)
    rv = np.concatenate([x[:3], x[6:]]).reshape(Q, 3)
    D = rodrigues(rv)
    Jr = right_jacobian(rv)
    G = np.empty((Q, 3, 3))
    t = np.empty((Q, 3))
    G[0], t[0] = D[0], u[0] + x[3:6]
    for idx, par in _levels(skel):
        Gp = G[par]
        G[idx] = Gp @ D[idx]
        t[idx] = t[par] + (Gp @ u[idx][..., None])[..., 0]
    return G, t, G @ Jr


class JacobianPattern:
    """The sparsity of :func:`point_jacobian` for fixed slots ``H (N, Q, 4)``: a point moves
    only with the joints it is skinned to (its *support*, a few of the Q) and their
    ancestors, so its positions and Jacobian are sums over those pairs alone, not over all Q.
    Build once per ``H`` (the keypoints of a fit, an LM round's extra points) and call
    :meth:`evaluate` at every unknowns ``x``; results equal the dense formula's.

    ``E``: the (joint q, point n) pairs with a nonzero coefficient; ``F``: the (joint i,
    point n) pairs with i an ancestor-or-self of a support joint of n, each the sum
    ``S_i(n) = sum_{e in E: n_e = n, q_e under i} (G_q l_e + W_e (t_q - t_i))`` through the
    sparse matrix ``B (F, E)``."""

    def __init__(self, skel: FitSkeleton, H: np.ndarray, sub: np.ndarray | None = None):
        H = np.asarray(H, float)
        A = subtree(skel) if sub is None else np.asarray(sub, bool)
        self.Q, self.N = len(skel.joints), len(H)
        n_e, q_e = np.nonzero(np.any(H != 0, axis=2))  # the support pairs
        self.q_e, self.n_e = q_e, n_e
        self.l_e, self.w_e = H[n_e, q_e, :3], H[n_e, q_e, 3]
        e_i, i_i = np.nonzero(A[:, q_e].T)  # (pair e, ancestor-or-self i of q_e)
        key = i_i * max(self.N, 1) + n_e[e_i]
        fkey, f_of = np.unique(key, return_inverse=True)
        self.i_f, self.n_f = fkey // max(self.N, 1), fkey % max(self.N, 1)
        self.B = sp.csr_matrix((np.ones(len(e_i)), (f_of.reshape(-1), e_i)),
                               shape=(len(fkey), len(q_e)))
        self.P = sp.csr_matrix((np.ones(len(n_e)), (n_e, np.arange(len(n_e)))),
                               shape=(self.N, len(n_e)))
        self.w_f = self.B @ self.w_e
        col = np.where(self.i_f == 0, 0, 3 + 3 * self.i_f)  # x: [r, T, theta_1..]
        n = skel.n  # J (N, 3 [a], n): the flat index of pair f's entry [a, k]
        self.flat = (self.n_f[:, None, None] * 3 * n + np.arange(3)[None, :, None] * n
                     + col[:, None, None] + np.arange(3)[None, None, :]).reshape(-1)
        self.dT = (np.arange(self.N)[:, None, None] * 3 * n + np.arange(3)[None, :, None] * n
                   + 3 + np.arange(3)[None, :, None]).reshape(-1)  # dp_a / dT_a
        self.w_n = np.repeat(H[..., 3].sum(1), 3)

    def evaluate(self, skel: FitSkeleton, u: np.ndarray, x: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(pos (N, 3), J (N, 3, n)) at unknowns x, as :func:`point_jacobian`."""
        G, t, axes = _fk_axes(skel, u, x)
        Pe = np.einsum("eab,eb->ea", G[self.q_e], self.l_e) + self.w_e[:, None] * t[self.q_e]
        pos = self.P @ Pe
        S = self.B @ Pe - self.w_f[:, None] * t[self.i_f]
        # d p / d rv_i[k] = axes_i[:, k] x S_i, the Levi-Civita symbol folded into the axes
        M = np.einsum("abc,qbk->qcak", _EPS, axes).reshape(self.Q, 3, 9)  # [q, c, (a, k)]
        Jf = S[:, None, :] @ M[self.i_f]  # (F, 1, 9)
        J = np.zeros(self.N * 3 * skel.n)
        J[self.flat] = Jf.reshape(-1)
        J[self.dT] = self.w_n
        return pos, J.reshape(self.N, 3, skel.n)


def point_jacobian(skel: FitSkeleton, u: np.ndarray, H: np.ndarray, x: np.ndarray,
                   sub: np.ndarray | None = None, pattern: JacobianPattern | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """World positions (N, 3) and their exact Jacobian (N, 3, n) w.r.t. the unknowns ``x`` of
    slots ``H (N, Q, 4)`` (:func:`vertex_coeffs`; a point is
    ``sum_q G_q l_q + W_q t_q``).

    Turning joint i's rotation vector by ``d`` turns everything below i about ``t_i`` by the
    world axis ``a = G_i J_r(theta_i) d``: ``dp = a x S_i``, ``S_i = sum_{q under i}
    (G_q l_q + W_q (t_q - t_i))``; ``dp/dT = (sum_q W_q) I``. ``sub``: :func:`subtree` (cached
    by the caller); ``pattern``: :class:`JacobianPattern` of this H (cached by the caller,
    evaluates only the nonzero pairs; same result)."""
    if pattern is not None:
        return pattern.evaluate(skel, u, x)
    H = np.asarray(H, float)
    G, t, axes = _fk_axes(skel, u, x)
    A = (subtree(skel) if sub is None else sub).astype(float)
    Q, N = len(skel.joints), len(H)
    Hq = H.transpose(1, 0, 2)  # (Q, N, 4): one GEMM per joint instead of N x Q tiny ones
    P = Hq[..., :3] @ G.transpose(0, 2, 1) + Hq[..., 3:] * t[:, None]  # (Q, N, 3)
    pos = P.sum(0)
    S = (A @ P.reshape(Q, N * 3)).reshape(Q, N, 3) - (A @ Hq[..., 3])[..., None] * t[:, None]
    # d p / d rv_i[k] = axes_i[:, k] x S_i: one product per joint with the Levi-Civita
    # symbol folded into the axes, M[i, c, (a, k)] = eps[a, b, c] axes_i[b, k]
    M = np.einsum("abc,qbk->qcak", _EPS, axes).reshape(Q, 3, 9)
    Jrot = (S @ M).reshape(Q, N, 3, 3).transpose(1, 2, 0, 3)  # (N, 3 [a], Q, 3 [k])
    J = np.empty((N, 3, 3 * Q + 3))
    J[:, :, 0:3] = Jrot[:, :, 0]
    J[:, :, 3:6] = Hq[..., 3].sum(0)[:, None, None] * np.eye(3)[None]
    J[:, :, 6:] = Jrot[:, :, 1:].reshape(N, 3, 3 * (Q - 1))
    return pos, J


def fk_cs(parents: tuple[int, ...], x, u):
    """CasADi forward kinematics of the reduced tree.

    parents : (Q,) topology; x : (3Q+3,) SX unknowns; u : (Q, 3) SX offsets.
    Returns lists G[q] (3, 3) and t[q] (3, 1)."""
    Q = len(parents)
    G = [rodrigues_cs(x[0:3])]
    t = [u[0, :].T + x[3:6]]
    for i in range(1, Q):
        p = parents[i]
        D = rodrigues_cs(x[6 + 3 * (i - 1): 9 + 3 * (i - 1)])
        G.append(ca.mtimes(G[p], D))
        t.append(t[p] + ca.mtimes(G[p], u[i, :].T))
    return G, t


def slots_cs(G, t, H, support):
    """World positions (S, 3) SX of slots: ``H`` a list of S SX blocks (len(support_s), 4),
    the coefficients of slot s on the fitted joints ``support[s]`` (the others are zero)."""
    rows = []
    for Hs, sup in zip(H, support, strict=True):
        GT = ca.horzcat(*[ca.horzcat(G[q], t[q]) for q in sup])  # (3, 4 |sup|)
        rows.append(ca.mtimes(GT, ca.reshape(Hs.T, -1, 1)).T)
    return ca.vertcat(*rows)


def support_of(H: np.ndarray, tol: float = 0.0) -> tuple[tuple[int, ...], ...]:
    """Fitted joints with a nonzero coefficient (|W| > tol) in each slot of ``H (S, Q, 4)``."""
    return tuple(tuple(int(q) for q in np.flatnonzero(np.abs(h[:, 3]) > tol)) or (0,) for h in H)


def neighbourhood_support(model: BodyModel, rest: RestState, skel: FitSkeleton,
                          points: np.ndarray, radius: float) -> tuple[tuple[int, ...], ...]:
    """For each rest point (S, 3): the fitted joints owning any skinning weight of the rest
    vertices within ``radius`` metres. A superset of what a marker sliding that far needs, so
    a graph built on it serves every subject's placement."""
    from scipy.spatial import cKDTree

    tree = cKDTree(rest.vertices[0])
    W = model.weights.tocsr()
    out = []
    for pt in np.asarray(points, float):
        vids = tree.query_ball_point(pt, radius)
        if not vids:
            vids = [int(tree.query(pt)[1])]
        js = np.unique(W[vids].indices)
        out.append(tuple(sorted(set(int(skel.owner[j]) for j in js))))
    return tuple(out)


def restrict(H: np.ndarray, support) -> tuple[np.ndarray, float]:
    """Pack ``H (S, Q, 4)`` on ``support`` (flat, slot-major) and the largest dropped weight
    (coefficients outside the support are dropped and the rest rescaled to keep sum W = 1)."""
    parts = []
    dropped = 0.0
    for h, sup in zip(H, support, strict=True):
        keep = h[list(sup)]
        tot, kept = h[:, 3].sum(), keep[:, 3].sum()
        dropped = max(dropped, float(tot - kept))
        if kept > 0 and abs(tot - kept) > 0:
            keep = keep * (tot / kept)
        parts.append(keep.reshape(-1))
    return np.concatenate(parts) if parts else np.zeros(0), dropped


def regressed_coeffs(model: BodyModel, rest: RestState, skel: FitSkeleton,
                     regressor) -> np.ndarray:
    """Slot coefficients (K, Q, 4) of points regressed linearly from the posed vertices, or
    from the stacked posed vertices and joints: ``regressor (K, V)`` or ``(K, V + J)``
    (body.joints.regressor), sparse or dense. A joint j is ``t_j = t_q + G_q s_j`` with q its
    owner (fitting/skinned.py), i.e. the slot ``[s_j | 1]`` on q."""
    R = sp.csr_matrix(regressor)
    V, J = model.num_vertices, model.num_joints
    if R.shape[1] not in (V, V + J):
        raise ValueError(f"regressor: expected {V} or {V + J} columns, got {R.shape[1]}")
    Q = len(skel.joints)
    Rv = R[:, :V].tocsr()
    vids = np.unique(Rv.indices)
    H = np.zeros((R.shape[0], Q, 4))
    if len(vids):
        Hv = vertex_coeffs(model, rest, skel, model.weights[vids], rest.vertices[0, vids])
        H += (Rv[:, vids] @ Hv.reshape(len(vids), -1)).reshape(R.shape[0], Q, 4)
    if R.shape[1] == V + J:
        _, s = reduced_offsets(model, rest, skel)
        Hj = np.zeros((J, Q, 4))
        Hj[np.arange(J), skel.owner, :3] = s
        Hj[np.arange(J), skel.owner, 3] = 1.0
        H += (R[:, V:] @ Hj.reshape(J, -1)).reshape(R.shape[0], Q, 4)
    return H


# ---------------------------------------------------------------------------- surface points


@dataclass(frozen=True, eq=False)
class SurfacePoints:
    """Points on the skinned surface (markers, contact facets, colliding proxy vertices).

    face : (N,) int face ids; bary : (N, 3) barycentric coordinates on the face's corners
    (rows >= 0, sum 1); offset : (N,) metres along the outward unit normal of the *posed*
    triangle. One definition (``body.markers.marker_positions`` is its full-mesh form):

        p = sum_k bary_k v_k + offset * (v_1 - v_0) x (v_2 - v_0) / |...|,  v_k posed corners.

    A vertex is the point of an incident face with a one-hot ``bary`` and offset 0
    (:meth:`at_vertices`); a facet's centroid is bary 1/3 (:meth:`facets`)."""

    face: np.ndarray
    bary: np.ndarray
    offset: np.ndarray

    def __post_init__(self):
        f = np.asarray(self.face, np.int64).reshape(-1)
        b = np.asarray(self.bary, float).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(self.offset, float), f.shape).copy()
        if len(b) != len(f):
            raise ValueError(f"surface points: {len(f)} faces, {len(b)} bary rows")
        object.__setattr__(self, "face", f)
        object.__setattr__(self, "bary", b)
        object.__setattr__(self, "offset", o)

    def __len__(self) -> int:
        return len(self.face)

    @classmethod
    def at_vertices(cls, faces: np.ndarray, vertex_ids) -> SurfacePoints:
        """The vertices ``vertex_ids`` (N,) as surface points: the first face of ``faces``
        (T, 3) using each, one-hot bary on it, offset 0. A vertex of no face is an error."""
        F = np.asarray(faces, np.int64)
        ids = np.asarray(vertex_ids, np.int64).reshape(-1)
        first = np.full(max(int(F.max(initial=-1)), int(ids.max(initial=-1))) + 1, len(F))
        np.minimum.at(first, F.reshape(-1), np.repeat(np.arange(len(F)), 3))
        bad = ids[first[ids] == len(F)] if len(ids) else ids
        if len(bad):
            raise ValueError(f"vertices {bad[:5].tolist()} belong to no face")
        face = first[ids]  # the lowest face id using each vertex (reproducible)
        bary = (F[face] == ids[:, None]).astype(float)
        return cls(face, bary, np.zeros(len(ids)))

    @classmethod
    def facets(cls, face_ids) -> SurfacePoints:
        """Facet centroids (bary 1/3, offset 0); with :func:`facets_cs` their normals too."""
        f = np.asarray(face_ids, np.int64).reshape(-1)
        return cls(f, np.full((len(f), 3), 1.0 / 3.0), np.zeros(len(f)))


@dataclass(frozen=True, eq=False)
class SkinnedPoints:
    """What the graph needs of :class:`SurfacePoints` for one shape and fit skeleton:
    corners (N, 3, Q, 4) slot coefficients of each point's three face corners
    (:func:`vertex_coeffs`), bary (N, 3), offset (N,) metres."""

    corners: np.ndarray
    bary: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:
        return len(self.corners)

    def corner_positions(self, skel: FitSkeleton, u: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(..., N, 3, 3) posed corners at unknowns x (..., n) (numpy twin of
        :func:`corners_cs`)."""
        N, _, Q, _ = self.corners.shape
        return slot_positions_np(skel, u, self.corners.reshape(3 * N, Q, 4), x).reshape(
            np.shape(x)[:-1] + (N, 3, 3))

    def positions(self, skel: FitSkeleton, u: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(..., N, 3) world positions at unknowns x (..., n) (numpy twin of
        :func:`surface_points_cs`)."""
        return points_on_corners(self.corner_positions(skel, u, x), self.bary, self.offset)


def points_on_corners(corners: np.ndarray, bary: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(..., N, 3) = sum_k bary_k c_k + offset * unit normal of (c_0, c_1, c_2), for corners
    (..., N, 3, 3) metres (the numpy form of the definition in :class:`SurfacePoints`)."""
    c = np.asarray(corners, float)
    N = c.shape[-3]
    flat = c.reshape(c.shape[:-3] + (3 * N, 3))
    n = face_normals(flat, np.arange(3 * N).reshape(N, 3))
    return np.einsum("...nkd,nk->...nd", c, bary) + np.asarray(offset)[:, None] * n


def surface_coeffs(model: BodyModel, rest: RestState, skel: FitSkeleton,
                   pts: SurfacePoints) -> SkinnedPoints:
    """:class:`SkinnedPoints` of ``pts`` on the shape ``rest`` (each corner skins as its
    vertex: its own weights and rest position)."""
    vids = np.asarray(model.faces, np.int64)[pts.face].reshape(-1)  # (3N,)
    H = vertex_coeffs(model, rest, skel, model.weights[vids], rest.vertices[0, vids])
    return SkinnedPoints(H.reshape(len(pts), 3, len(skel.joints), 4), pts.bary, pts.offset)


def corners_cs(G, t, corners, support):
    """Posed corners of N points: ``corners`` a list of N SX blocks (3 |sup_n|, 4) (corner k
    of point n on rows k |sup_n| ...), the three corners sharing the point's ``support[n]``.
    Returns a list of N (3, 3) SX, one corner per column."""
    out = []
    for Hs, sup in zip(corners, support, strict=True):
        GT = ca.horzcat(*[ca.horzcat(G[q], t[q]) for q in sup])  # (3, 4 |sup|)
        n = len(sup)
        cols = [ca.reshape(Hs[k * n:(k + 1) * n, :].T, -1, 1) for k in range(3)]
        out.append(ca.mtimes(GT, ca.horzcat(*cols)))
    return out


def unit_normal_cs(c):
    """Unit normal (3, 1) SX of a triangle given as a (3, 3) SX, one corner per column."""
    n = ca.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    return n / ca.norm_2(n)


def surface_points_cs(corners, bary, offset):
    """World positions (N, 3) SX: ``corners`` from :func:`corners_cs`, ``bary`` (N, 3) SX,
    ``offset`` (N,) SX metres along the posed unit normal (:class:`SurfacePoints`)."""
    rows = []
    for i, c in enumerate(corners):
        rows.append((ca.mtimes(c, bary[i, :].T) + offset[i] * unit_normal_cs(c)).T)
    return ca.vertcat(*rows) if rows else ca.SX(0, 3)


def facets_cs(corners):
    """Facets for L_N / L_D: (centroids (N, 3), unit normals (N, 3)) SX of posed triangles."""
    cen = [ca.sum2(c).T / 3 for c in corners]
    nrm = [unit_normal_cs(c).T for c in corners]
    return ca.vertcat(*cen), ca.vertcat(*nrm)


def restrict_points(pts: SkinnedPoints, support) -> tuple[np.ndarray, float]:
    """Pack the corners of ``pts`` on ``support`` (per point, shared by its three corners;
    the layout :func:`corners_cs` reads) and the largest dropped weight (:func:`restrict`)."""
    N, _, Q, _ = pts.corners.shape
    sup3 = [s for s in support for _ in range(3)]
    parts, dropped = [], 0.0
    for n in range(N):
        flat, d = restrict(pts.corners[n], sup3[3 * n:3 * n + 3])
        dropped = max(dropped, d)
        parts.append(flat)
    return (np.concatenate(parts) if parts else np.zeros(0)), dropped


def points_support(pts: SkinnedPoints, tol: float = 0.0) -> tuple[tuple[int, ...], ...]:
    """Per point: the fitted joints with a nonzero coefficient (|W| > tol) in any corner."""
    return tuple(tuple(sorted(set(q for c in support_of(h, tol) for q in c))) for h in pts.corners)
