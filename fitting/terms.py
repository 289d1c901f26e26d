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
The partner fit adds ``L_sc``, ``L_ic``, ``L_gp``, ``L_D``, ``L_N`` here, same shape:
``L_x(model quantities, observations/parameters) -> residual vector``.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from fitting.lm import Box, Quadratic

TERMS = ("L_3d", "L_2d", "L_theta", "L_s")  # the terms this module defines


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
