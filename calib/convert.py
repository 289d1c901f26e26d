"""Conversions between CHI3D (Human3.6M) and OpenCV camera conventions.

Extrinsics: CHI3D ``(R, T = camera centre)`` <-> OpenCV ``(rvec, tvec)`` with
``X_cam = R X_world + tvec``, ``tvec = -R T``: exact.

Distortion: the Human3.6M tangential term ``p2 (r2 + x^2) + p1 x y`` is not OpenCV's
``p2 (r2 + 2 x^2) + 2 p1 x y``, so a 5-coefficient OpenCV vector cannot hold it. It is exactly
OpenCV's 12-coefficient model (thin prism) with::

    p1' = p1 / 2,  p2' = p2 / 2,  s1 = p2 / 2,  s3 = p1 / 2,  k4 = k5 = k6 = s2 = s4 = 0

(expand both: ``x_d - x radial = p1 x y + p2 r2 + p2 x^2``, ``y_d - y radial = p1 r2 + p1 y^2
+ p2 x y``). :func:`to_opencv` uses that (``cv2.projectPoints`` accepts 12 coefficients; the
test checks it to 1e-6 px). Where only 5 coefficients are accepted (COLMAP ``FULL_OPENCV``,
EasyMocap ``dist``), :func:`convert_distortion` fits the other model by linear least squares
over the image and returns the residual in pixels; it is exact when ``p = 0``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib import constants
from calib.camera import Camera, distort, normalized_from_pixels


def _rodrigues(v: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(v, dtype=np.float64).reshape(3, 1))[0]


def _rvec(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].reshape(3)


def opencv_dist(cam: Camera) -> np.ndarray:
    """Exact OpenCV distortion vector of ``cam``: (5,) ``k1 k2 p1 p2 k3`` for ``model="opencv"``,
    (12,) ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`` (thin prism) for ``model="h36m"``."""
    k1, k2, k3 = cam.k
    p1, p2 = cam.p
    if cam.model == "opencv":
        return np.array([k1, k2, p1, p2, k3])
    return np.array([k1, k2, p1 / 2, p2 / 2, k3, 0, 0, 0, p2 / 2, 0, p1 / 2, 0])


def to_opencv(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact OpenCV form of ``cam``: ``(rvec (3,), tvec (3,) metres, K (3, 3), dist (5,|12,))``,
    ready for ``cv2.projectPoints(X_world, rvec, tvec, K, dist)``."""
    return _rvec(cam.R), cam.t.copy(), cam.K, opencv_dist(cam)


def from_opencv(name: str, R_or_rvec, tvec, K, dist, width: int, height: int) -> Camera:
    """Camera from OpenCV parameters.

    R_or_rvec: (3, 3) rotation or (3,) Rodrigues vector, cam_from_world; tvec: (3,) metres
    (``X_cam = R X + tvec``); K: (3, 3) without skew; dist: 4, 5, 8, 12 or 14 coefficients.
    A vector whose extra coefficients are zero gives ``model="opencv"``; a 12/14-vector with the
    thin-prism pattern of :func:`opencv_dist` gives ``model="h36m"`` exactly. Anything else
    (rational k4-k6, tilt, other thin prism) raises ValueError: fit it with OpenCV instead.
    """
    Rr = np.asarray(R_or_rvec, dtype=np.float64)
    R = Rr if Rr.shape == (3, 3) else _rodrigues(Rr.reshape(3))
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"from_opencv: K must be (3, 3), got {K.shape}")
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise ValueError(f"from_opencv: K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
    d = np.zeros(14)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    if dist.size not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"from_opencv: dist must have 4, 5, 8, 12 or 14 values, got {dist.size}")
    d[: dist.size] = dist
    k1, k2, p1, p2, k3 = d[:5]
    rest = d[5:]
    f, c = (K[0, 0], K[1, 1]), (K[0, 2], K[1, 2])
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    T = -R.T @ t
    if not np.any(rest):
        return Camera(name, f, c, (k1, k2, k3), (p1, p2), R, T, width, height, model="opencv")
    s1, s2, s3, s4 = rest[3:7]
    tol = 1e-12 + 1e-9 * max(abs(p1), abs(p2))
    if (not np.any(rest[:3]) and s2 == 0 and s4 == 0 and not np.any(rest[7:])
            and abs(s1 - p2) <= tol and abs(s3 - p1) <= tol):
        return Camera(name, f, c, (k1, k2, k3), (2 * p1, 2 * p2), R, T, width, height, model="h36m")
    raise ValueError(f"from_opencv: distortion {dist.tolist()} is neither OpenCV k1 k2 p1 p2 k3 "
                     "nor the Human3.6M thin-prism pattern")


@dataclass(frozen=True)
class Conversion:
    """Result of :func:`convert_distortion`: the camera in the target model and how far its
    projection is from the source's over the image (pixels; 0 when the conversion is exact)."""

    camera: Camera
    rms_px: float
    max_px: float
    exact: bool


def convert_distortion(cam: Camera, model: str, grid: int = constants.CONVERSION_GRID) -> Conversion:
    """Express ``cam`` in distortion ``model`` (``"h36m"`` or ``"opencv"``).

    Same f, c, R, T. The target k, p minimise the pixel distance of the two lens models over a
    ``grid x grid`` lattice of pixels covering the image (distortion is linear in k, p, so this
    is one linear least-squares solve). Exact (copied) when the models agree or ``p = 0``.
    """
    if model == cam.model:
        return Conversion(cam, 0.0, 0.0, True)
    if not np.any(cam.p):
        return Conversion(replace(cam, model=model), 0.0, 0.0, True)
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, grid), np.linspace(0, cam.height - 1, grid))
    uv = np.stack([u.ravel(), v.ravel()], axis=-1)
    xy = normalized_from_pixels(cam, uv)
    xy = xy[np.all(np.isfinite(xy), axis=-1)]
    target = distort(xy, cam.k, cam.p, cam.model) - xy
    # Columns: effect of each unit coefficient (k1, k2, k3, p1, p2) in the target model.
    cols = []
    for i in range(5):
        e = np.zeros(5)
        e[i] = 1.0
        cols.append(distort(xy, e[:3], e[3:], model) - xy)
    A = np.stack(cols, axis=-1) * cam.f[None, :, None]  # (N, 2, 5) pixels per unit coefficient
    sol, *_ = np.linalg.lstsq(A.reshape(-1, 5), (target * cam.f).reshape(-1), rcond=None)
    out = replace(cam, k=sol[:3], p=sol[3:], model=model)
    err = np.linalg.norm((distort(xy, out.k, out.p, model) - xy - target) * cam.f, axis=-1)
    return Conversion(out, float(np.sqrt(np.mean(err**2))), float(err.max()), False)
