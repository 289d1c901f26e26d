"""Plain linear (DLT) triangulation, one point at a time, no outlier rejection: the baseline a
body model is compared with (``fitting.heldout``) and the cross-view association of people
(``detect.markerless``). ``calib.geometry.triangulate`` is the robust one (pycolmap, RANSAC).
"""
from __future__ import annotations

import numpy as np

from calib.camera import normalized_from_pixels


def dlt(Ps: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """Linear triangulation of one point: ``Ps (V, 3, 4)`` normalised projection matrices
    ``[R | -R T]``, ``xn (V, 2)`` undistorted normalised image points. Returns (3,) (NaN when
    the point is at infinity)."""
    A = np.concatenate([xn[:, :1] * Ps[:, 2] - Ps[:, 0], xn[:, 1:2] * Ps[:, 2] - Ps[:, 1]])
    _, _, vt = np.linalg.svd(A)
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


def projection_matrices(cams) -> np.ndarray:
    """(C, 3, 4) ``[R | -R T]`` of ``calib.Camera`` s (normalised image coordinates; R
    cam_from_world, T the camera centre)."""
    return np.stack([np.hstack([np.asarray(c.R, float), -(np.asarray(c.R, float)
                                                          @ np.asarray(c.T, float))[:, None]])
                     for c in cams])


def triangulate_points(cams, uv: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per-point DLT: ``uv (V, K, 2)`` pixels (distorted, as detected) in the views ``cams``,
    ``ok (V, K)`` which views see each point. Returns (K, 3) world metres, NaN where fewer
    than two views see the point."""
    P = projection_matrices(cams)
    xn = np.stack([normalized_from_pixels(c, np.asarray(uv[v], float).reshape(-1, 2))
                   for v, c in enumerate(cams)])  # (V, K, 2)
    ok = np.asarray(ok, bool) & np.all(np.isfinite(xn), axis=-1)
    X = np.full((uv.shape[1], 3), np.nan)
    for k in range(uv.shape[1]):
        sel = np.flatnonzero(ok[:, k])
        if len(sel) >= 2:
            X[k] = dlt(P[sel], xn[sel, k])
    return X
