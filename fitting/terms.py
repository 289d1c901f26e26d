"""The energy terms of the paper, one function each, named after it.

Each term returns a *residual vector* ``r`` (LM needs residuals and Jacobians, not a scalar):
the paper's term is ``|r|^2``. No term takes a weight: the recipe gives weights by term name
(``weights: {L_3d: 1.0, L_2d: 1e-4, ...}``) and the caller scales ``r`` by ``sqrt(weight)``.

The nonlinear terms (``L_3d``, ``L_2d``) work on numpy arrays *and* on CasADi ``SX``
expressions with the same code, so the compiled residual function and the numpy checks
share one definition. The quadratic terms (``L_theta``'s Gaussian part, ``L_s``) are linear
residuals in the unknowns; the LM loop adds their normal equations in numpy
(``fitting/lm.py``), and ``quadratic_*`` helpers below build those from the same arrays.

Equations refer to ``paper.tex``, section "3D Reconstruction in a Controlled Setup".
The partner fit's terms (``L_sc``, ``L_ic``, ``L_gp``, ``L_D``, ``L_N``; section "3D
Reconstruction in a Controlled Setup" and ``L_G = L_D + L_N`` of the Methodology) have the same
shape: ``L_x(model quantities, observations/parameters) -> residual vector``. What is
discrete in them (which points are inside, their nearest surface points, the top-k lowest
vertices, the matched facet pairs) is found in numpy between solver iterations
(``fitting/collision.py``) and enters here as arrays: the graph stays fixed, only the
offending points are its slots. The paper sums unsquared norms (``sum |V - NN(V)|_2``,
``sum |x|_2``, ``sum phi_D``, ``sum phi_N``); as residuals for least squares each of those
quantities becomes one residual (vector), so the solver minimises their squares: the same
zero set, with a smooth Jacobian at it.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from fitting.lm import Box, Quadratic

TERMS = ("L_3d", "L_2d", "L_theta", "L_s")  # the marker fit's terms (validates its weights)
#: the partner fit's terms (validates its weights)
PARTNER_TERMS = TERMS + ("L_sc", "L_ic", "L_gp", "L_D", "L_N")


def _is_cs(*xs) -> bool:
    return any(isinstance(x, (ca.SX, ca.MX, ca.DM)) for x in xs)


def _rowmajor(a):
    """(N, d) -> (N*d,) in row-major order (one point's coordinates together)."""
    if _is_cs(a):
        return ca.reshape(a.T, -1, 1)
    return np.asarray(a).reshape(-1)


def _rep_cols(v, d: int):
    """(N,) or (N, 1) -> (N, d), each row repeated."""
    if _is_cs(v):
        return ca.repmat(ca.reshape(v, -1, 1), 1, d)
    return np.repeat(np.asarray(v, dtype=float).reshape(-1, 1), d, axis=1)


def _count(v):
    """Number of entries > 0 of a mask (at least 1)."""
    if _is_cs(v):
        return ca.fmax(ca.sum1(ca.reshape(v, -1, 1) > 0), 1)
    return max(int(np.count_nonzero(np.asarray(v) > 0)), 1)


def _col(a, i: int):
    """Column ``i`` of an (N, d) array or SX, as (N,) numpy or (N, 1) SX."""
    return a[:, i]


def _hcat(cols):
    if _is_cs(*cols):
        return ca.horzcat(*[ca.reshape(c, -1, 1) for c in cols])
    return np.stack([np.asarray(c, dtype=float).reshape(-1) for c in cols], axis=1)


def _sqrt_w(weights):
    if _is_cs(weights):
        return ca.sqrt(ca.reshape(weights, -1, 1))
    return np.sqrt(np.asarray(weights, dtype=float).reshape(-1))


def _matrix(a):
    """numpy arrays as float arrays; SX/MX/DM unchanged."""
    return a if _is_cs(a) else np.asarray(a, dtype=float)


def _pull(points, targets, weights):
    """``sqrt(w_i) (p_i - t_i)``, row-major (3N,)."""
    points, targets = _matrix(points), _matrix(targets)
    return _rowmajor(_rep_cols(_sqrt_w(weights), 3) * (points - targets))


def L_3d(markers, observed, visible):
    """3D marker alignment, paper eq. ``L_3d = 1/K sum_i |m_i - M_i|^2``.

    markers : (K, 3) model markers m_i, metres, world (numpy or SX).
    observed : (K, 3) Vicon markers M_i, metres, world; anything (e.g. 0) where not visible.
    visible : (K,) 1 where M_i is observed, 0 in a gap (or a weight in [0, 1]).
    Returns (3K,): ``sqrt(visible_i / K_vis) * (m_i - M_i)``, one marker's xyz together, where
    ``K_vis`` counts the visible markers (the paper's K).
    """
    s = (visible / _count(visible)) ** 0.5
    return _rowmajor(_rep_cols(s, 3) * (markers - observed))


def L_2d(uv, observed, confidence):
    """2D keypoint alignment, paper eq. ``L_2d = 1/K sum_i |j_i - J_i|^2``.

    uv : (N, 2) projected model keypoints j_i, pixels (N = cameras x keypoints, flattened).
    observed : (N, 2) detected keypoints J_i, pixels.
    confidence : (N,) detector confidence in [0, 1]; 0 = missing.
    Returns (2N,): ``sqrt(c_i / K) * (j_i - J_i)`` with K the number of detected keypoints.
    """
    s = (confidence / _count(confidence)) ** 0.5
    return _rowmajor(_rep_cols(s, 2) * (uv - observed))


def L_theta(theta, mean, sqrt_precision, lo, hi, limit_idx):
    """Pose prior, paper ``L_theta = |NF(theta)|^2`` with the normalizing flow replaced by a
    whitening transform learned from data plus joint limits (``fitting/priors.py``).

    theta : (n,) pose unknowns (local axis-angle of the posed joints, flattened), radians.
    mean : (n,); sqrt_precision : (k, n), ``A`` with ``A^T A`` = inverse covariance.
    lo, hi, limit_idx : joint limits on ``theta[limit_idx]`` (radians).
    Returns (k + len(limit_idx),): ``[A (theta - mean), hinge(theta[idx]; lo, hi)]``.
    """
    if _is_cs(theta):
        A = ca.DM(np.asarray(sqrt_precision))
        white = ca.mtimes(A, theta - ca.DM(np.asarray(mean)))
        v = theta[list(np.asarray(limit_idx))]
        hinge = ca.fmax(0, v - ca.DM(np.asarray(hi))) + ca.fmin(0, v - ca.DM(np.asarray(lo)))
        return ca.vertcat(white, hinge)
    theta = np.asarray(theta, dtype=float)
    white = np.asarray(sqrt_precision) @ (theta - mean)
    v = theta[np.asarray(limit_idx)]
    hinge = np.maximum(0.0, v - hi) + np.minimum(0.0, v - lo)
    return np.concatenate([white, hinge])


def L_s(state, state_prev):
    """Temporal smoothing, paper ``L_s = |theta_t - theta_t-1|^2 + |R_t - R_t-1|^2 +
    |T_t - T_t-1|^2``.

    state, state_prev : (n,) the frame's unknowns ``[global rotation vector (3), T (3),
    theta]`` now and at the previous frame (radians, metres). The rotation difference is
    taken on (continuous, re-wrapped) rotation vectors instead of matrices: the same minimum,
    and a linear residual.
    Returns (n,): ``state - state_prev``.
    """
    return state - state_prev


def L_ic(points, targets, weights):
    """Interpenetration, paper ``L_ic = sum_{l in L_1+} |V_1,l - NN(V_1,l, M_2)|_2`` (+ the
    other body's points inside this one, the second sum; see ``fitting/collision.py``).

    points : (N, 3) proxy points of this body found inside the other body (numpy or SX),
        metres, world; or, for the second sum, points on this body's surface (the nearest
        surface points of the other body's penetrating vertices, as face + barycentric slots).
    targets : (N, 3) where each is pushed: its nearest point on the other surface (a little
        beyond it, ``collision.MARGIN_M``), or the other body's penetrating vertex.
    weights : (N,) per point (0 for an unused slot).
    Returns (3N,): ``sqrt(w_i) (p_i - t_i)``, one point's xyz together.
    """
    return _pull(points, targets, weights)


def L_sc(points, targets, weights):
    """Self-collision, paper ``L_sc = sum_{l in L+} |V_l - NN(V_l, M)|_2``: the same form as
    :func:`L_ic` for proxy points inside the own body (parts that are not neighbours).

    points : (N, 3) the penetrating proxy points (numpy or SX), metres; targets : (N, 3) their
    nearest points on the own surface, outside the neighbouring regions; weights : (N,).
    Returns (3N,): ``sqrt(w_i) (p_i - t_i)``.
    """
    return _pull(points, targets, weights)


def L_gp(points, normal, offset):
    """Ground-plane penetration, paper ``L_gp = sum_{x in D_k} |x|_2`` with ``D_k`` the top k
    of ``max(0, -d(V, T))``.

    points : (k, 3) the candidate vertices (the k lowest, ``collision.ground_candidates``),
        numpy or SX, metres, world.
    normal : (3,) unit normal of the ground plane (pointing up, into the free half-space);
    offset : scalar, the plane is ``normal . x = offset`` (metres).
    Returns (k,): ``min(0, normal . p_i - offset)``: minus the depth below the plane, 0 above.
    """
    normal = np.asarray(normal, dtype=float).reshape(3)
    points = _matrix(points)
    d = _col(points, 0) * normal[0] + _col(points, 1) * normal[1] + _col(points, 2) * normal[2]
    d = d - float(offset)
    if _is_cs(d):
        return ca.fmin(0, ca.reshape(d, -1, 1))
    return np.minimum(0.0, d)


def L_D(centres_1, centres_2, weights):
    """Contact distance, paper ``L_D = sum_{(r1, r2) in C} Phi_D(r1, r2)``, ``Phi_D`` the sum
    over both directions of the nearest-facet matches between ``psi_D(r1)`` and ``psi_D(r2)``
    of ``phi_D(f1, f2)``, the distance between the facet centres.

    centres_1, centres_2 : (P, 3) centres of the matched facets, row i one pair (both
        directions of every region pair stacked, ``collision.contact_pairs``), numpy or SX,
        metres, world.
    weights : (P,) per pair (e.g. ``1 / P`` per region pair, 0 for an unused slot).
    Returns (3P,): ``sqrt(w_i) (c1_i - c2_i)``.
    """
    return _pull(centres_1, centres_2, weights)


def _triangle(tri):
    """Corners (a, b, c), each (N, 3), of ``tri``: numpy (N, 3, 3), a sequence of three (N, 3)
    arrays or SX, or an (N, 9) SX (row = a, b, c)."""
    if isinstance(tri, (list, tuple)):
        if len(tri) != 3:
            raise ValueError(f"tri: expected 3 corner arrays, got {len(tri)}")
        return tuple(_matrix(t) for t in tri)
    if _is_cs(tri):
        if tri.shape[1] != 9:
            raise ValueError(f"tri: expected an (N, 9) CasADi matrix, got {tri.shape}")
        return tri[:, 0:3], tri[:, 3:6], tri[:, 6:9]
    t = np.asarray(tri, dtype=float)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise ValueError(f"tri: expected (N, 3, 3), got {t.shape}")
    return t[:, 0], t[:, 1], t[:, 2]


def facet_normals(tri):
    """Unit normals ``N(f) / |N(f)|``, ``N(f) = (v2 - v1) x (v3 - v1)`` (paper, phi_N), of
    triangles ``tri`` (see :func:`L_N`); (N, 3) numpy or SX. (The numpy mesh version is
    ``geometry.face_normals``; this one is differentiable in CasADi.)"""
    a, b, c = _triangle(tri)
    u, v = b - a, c - a
    n = [_col(u, 1) * _col(v, 2) - _col(u, 2) * _col(v, 1),
         _col(u, 2) * _col(v, 0) - _col(u, 0) * _col(v, 2),
         _col(u, 0) * _col(v, 1) - _col(u, 1) * _col(v, 0)]
    norm = (n[0] ** 2 + n[1] ** 2 + n[2] ** 2) ** 0.5
    return _hcat([k / norm for k in n])


def L_N(tri_1, tri_2, weights):
    """Orientation alignment, paper ``L_N = sum_{(r1, r2) in C} Phi_N(r1, r2)``, ``Phi_N`` the
    sum of ``phi_N(f1, f2) = 1 + N(f1)/|N(f1)| . N(f2)/|N(f2)|`` over the matched facet pairs
    (``psi_N`` re-uses the matches of ``L_D``): 0 when the normals are opposite.

    tri_1, tri_2 : (P, 3, 3) corner positions of the matched facets (row i one pair; corners in
        the mesh's outward order), numpy; for CasADi a tuple of three (P, 3) SX or a (P, 9) SX.
    weights : (P,) per pair.
    Returns (P,): ``sqrt(w_i) (1 + n1_i . n2_i)``.
    """
    n1, n2 = facet_normals(tri_1), facet_normals(tri_2)
    dot = _col(n1, 0) * _col(n2, 0) + _col(n1, 1) * _col(n2, 1) + _col(n1, 2) * _col(n2, 2)
    w = _sqrt_w(weights)
    if _is_cs(dot, w):
        return ca.reshape(w, -1, 1) * (1 + ca.reshape(dot, -1, 1))
    return w * (1.0 + dot)


# ---- normal equations of the linear terms, for fitting/lm.py -------------------------------


def quadratic_L_theta(n: int, pose_idx, mean, sqrt_precision, weight: float) -> Quadratic:
    """``weight * |A (x[pose_idx] - mean)|^2`` as LM normal equations over all ``n`` unknowns
    (the Gaussian part of :func:`L_theta`)."""
    A = np.zeros((np.asarray(sqrt_precision).shape[0], n))
    A[:, np.asarray(pose_idx)] = np.asarray(sqrt_precision)
    sw = np.sqrt(weight)
    return Quadratic.from_residual(sw * A, sw * (A[:, np.asarray(pose_idx)] @ mean))


def box_L_theta(pose_idx, lo, hi, limit_idx, weight: float) -> Box:
    """The joint-limit hinge of :func:`L_theta` as an LM :class:`~fitting.lm.Box`."""
    idx = np.asarray(pose_idx)[np.asarray(limit_idx)]
    return Box(idx=idx, lo=np.asarray(lo, float), hi=np.asarray(hi, float), weight=weight)


def quadratic_L_s(n: int, state_idx, state_prev, weight) -> Quadratic:
    """``sum_i weight_i (x[state_idx_i] - state_prev_i)^2``, :func:`L_s` as normal equations.
    ``weight``: scalar or (len(state_idx),) (e.g. separate weights for R, T and theta)."""
    return Quadratic.diagonal(n, np.asarray(state_idx), weight, np.asarray(state_prev, float))
