"""Rotations: axis-angle (rotation vectors), rotation matrices, Procrustes; numpy and CasADi twins.

The one home of ``rodrigues`` and friends (ARCHITECTURE.md). Conventions:

- a rotation vector ``r: (..., 3)`` is axis * angle in radians; ``rodrigues(r) -> (..., 3, 3)``
  maps it to the matrix ``R`` with ``R @ x`` rotating column vectors ``x``;
- ``*_cs`` functions are the CasADi twins of the numpy ones, for one rotation (``(3,)`` symbol ->
  ``(3, 3)`` expression); they use the same formulas (including the small-angle series) so numpy
  and CasADi agree to round-off, and their derivatives stay finite at zero.
"""
from __future__ import annotations

import numpy as np

# Below this squared angle (rad^2) the Rodrigues coefficients use their Taylor series.
SMALL_ANGLE_SQ = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices. v: (..., 3) -> (..., 3, 3) with skew(v) @ x = v x x."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def _coeffs(th2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a = sin(t)/t and b = (1 - cos t)/t^2 of the squared angle, series near 0."""
    small = th2 < SMALL_ANGLE_SQ
    th2_s = np.where(small, 1.0, th2)
    th_s = np.sqrt(th2_s)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(th_s) / th_s)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(th_s)) / th2_s)
    return a, b


def rodrigues(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vectors to matrices. rotvec: (..., 3) radians -> (..., 3, 3)."""
    r = np.asarray(rotvec, dtype=float)
    K = skew(r)
    a, b = _coeffs(np.sum(r * r, axis=-1))
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotmat_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices to rotation vectors with angle in [0, pi]. R: (..., 3, 3) -> (..., 3).

    Robust near 0 and near pi (uses scipy's quaternion route)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(R.shape[:-2] + (3,))


def wrap_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """The equivalent rotation vector with angle in [0, pi] (re-wraps vectors past 180 deg).

    rotvec: (..., 3) -> (..., 3). DESIGN.md: wrapped elbow/wrist vectors fool the pose prior."""
    return rotmat_to_rotvec(rodrigues(rotvec))


def special_procrustes(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to each matrix (polar factor with det +1). M: (..., 3, 3) -> (..., 3, 3).

    R = U diag(1, 1, det(U V^T)) V^T from the SVD M = U S V^T (roma.special_procrustes)."""
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


# ----------------------------------------------------------------------------- CasADi twins


def skew_cs(v):
    """CasADi twin of :func:`skew` for one vector: (3,) -> (3, 3)."""
    import casadi as ca

    return ca.vertcat(
        ca.horzcat(0, -v[2], v[1]),
        ca.horzcat(v[2], 0, -v[0]),
        ca.horzcat(-v[1], v[0], 0),
    )


def rodrigues_cs(rotvec):
    """CasADi twin of :func:`rodrigues` for one rotation vector: (3,) SX/MX -> (3, 3).

    Finite value and derivatives at zero (series branch, guarded square root)."""
    import casadi as ca

    r = ca.vec(rotvec)
    th2 = ca.dot(r, r)
    small = th2 < SMALL_ANGLE_SQ
    th2_s = ca.if_else(small, 1.0, th2)
    th_s = ca.sqrt(th2_s)
    a = ca.if_else(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, ca.sin(th_s) / th_s)
    b = ca.if_else(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - ca.cos(th_s)) / th2_s)
    K = skew_cs(r)
    return ca.DM.eye(3) + a * K + b * ca.mtimes(K, K)
