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
from body.rotations import rodrigues, rodrigues_cs


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
    for i, j, w in zip(Wc.row, Wc.col, Wc.data, strict=True):
        d = pts[i] - h[j]
        if A is not None:
            d = A[j] @ d
        q = skel.owner[j]
        H[i, q, :3] += w * (d + s[j])
        H[i, q, 3] += w
    return H


def slot_positions_np(skel: FitSkeleton, u: np.ndarray, H: np.ndarray, x: np.ndarray) -> np.ndarray:
    """numpy twin of the graph: world positions (S, 3) of slots ``H (S, Q, 4)`` at unknowns x."""
    G, t = _fk_np(skel, u, x)
    return np.einsum("qab,sqb->sa", G, H[..., :3]) + np.einsum("qa,sq->sa", t, H[..., 3])


def _fk_np(skel: FitSkeleton, u: np.ndarray, x: np.ndarray):
    Q = len(skel.joints)
    D = rodrigues(np.asarray(x[6:], dtype=float).reshape(Q - 1, 3))
    G = np.zeros((Q, 3, 3))
    t = np.zeros((Q, 3))
    G[0] = rodrigues(np.asarray(x[:3], dtype=float))
    t[0] = u[0] + x[3:6]
    for i in range(1, Q):
        p = skel.parents[i]
        G[i] = G[p] @ D[i - 1]
        t[i] = t[p] + G[p] @ u[i]
    return G, t


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
