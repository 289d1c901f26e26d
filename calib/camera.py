"""A calibrated camera: pinhole + lens distortion, CHI3D extrinsics; projection in numpy and CasADi.

Conventions (the CHI3D release's, see ``shared/FORMATS.md``):

- Extrinsics: ``X_cam = (X_world - T) @ R.T``. ``R: (3, 3)`` is the rotation cam_from_world,
  ``T: (3,)`` the camera centre in world coordinates, metres. Camera axes as in OpenCV
  (x right, y down, z forward); pixel centres at integer coordinates, origin top-left pixel.
- Normalized coordinates ``x, y = X_cam[:2] / X_cam[2]``; ``r2 = x^2 + y^2``;
  ``radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3``.
- Distortion ``model="h36m"`` (Human3.6M / CHI3D, as the public CHI3D tools compute it:
  ``p' = (p2, p1)``, ``x_d = x (radial + x . p') + r2 p'``), written out::

      x_d = x radial + p2 (r2 + x^2) + p1 x y
      y_d = y radial + p1 (r2 + y^2) + p2 x y

- Distortion ``model="opencv"`` (OpenCV / COLMAP ``k1 k2 p1 p2 k3``)::

      x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
      y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

  Both are ``t_x = p2 (a x^2 + y^2) + b p1 x y``, ``t_y = p1 (x^2 + a y^2) + b p2 x y`` with
  ``(a, b) = (2, 1)`` for h36m and ``(3, 2)`` for opencv; the code uses that one form.
- Pixels: ``uv = f * (x_d, y_d) + c``.

Points at or behind the camera plane (``Z <= 0``) are projected by the same formula (no
cheirality test, the fitting terms need a smooth function); callers mask them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib import constants

DISTORTION_MODELS = ("h36m", "opencv")
# (a, b) of the shared tangential form above, per model.
_TANGENTIAL_FORM = {"h36m": (2.0, 1.0), "opencv": (3.0, 2.0)}


def _vec(x, n: int, name: str) -> np.ndarray:
    a = np.array(x, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"Camera.{name}: expected {n} values, got shape {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Camera.{name}: not finite: {a}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera (data only; arrays are read-only float64).

    name: camera id (CHI3D: the serial, e.g. ``"50591643"``)
    f: (2,) focal lengths fx, fy, pixels
    c: (2,) principal point cx, cy, pixels
    k: (3,) radial distortion k1, k2, k3
    p: (2,) tangential distortion p1, p2 (meaning depends on ``model``)
    R: (3, 3) rotation cam_from_world (orthonormal, det +1)
    T: (3,) camera centre, world, metres
    width, height: image size, pixels
    model: ``"h36m"`` (CHI3D JSON) or ``"opencv"`` (OpenCV / EasyMocap / COLMAP FULL_OPENCV)
    """

    name: str
    f: np.ndarray
    c: np.ndarray
    k: np.ndarray
    p: np.ndarray
    R: np.ndarray
    T: np.ndarray
    width: int
    height: int
    model: str = "h36m"

    def __post_init__(self):
        for name, n in (("f", 2), ("c", 2), ("k", 3), ("p", 2), ("T", 3)):
            object.__setattr__(self, name, _vec(getattr(self, name), n, name))
        R = np.array(self.R, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(f"Camera.R: expected a finite (3, 3) matrix, got shape {R.shape}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError(f"Camera.R: not a rotation (R R^T != I or det < 0): {R.tolist()}")
        R.setflags(write=False)
        object.__setattr__(self, "R", R)
        if self.model not in DISTORTION_MODELS:
            raise ValueError(f"Camera.model: expected one of {DISTORTION_MODELS}, got {self.model!r}")
        if np.any(self.f <= 0):
            raise ValueError(f"Camera.f: focal lengths must be positive, got {self.f}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera size: expected positive, got {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix (no skew)."""
        return np.array([[self.f[0], 0.0, self.c[0]], [0.0, self.f[1], self.c[1]], [0.0, 0.0, 1.0]])

    @property
    def t(self) -> np.ndarray:
        """(3,) OpenCV translation: ``X_cam = R X_world + t``, ``t = -R T``, metres."""
        return -self.R @ self.T

    def allclose(self, other: Camera, atol: float = 1e-9) -> bool:
        """Same model, size and (to ``atol``) the same parameters."""
        return (
            self.model == other.model
            and (self.width, self.height) == (other.width, other.height)
            and np.allclose(camera_vector(self), camera_vector(other), rtol=0, atol=atol)
        )


def cam_from_world(cam: Camera) -> np.ndarray:
    """(4, 4) homogeneous transform world -> camera: ``[[R, -R T], [0, 0, 0, 1]]``."""
    M = np.eye(4)
    M[:3, :3] = cam.R
    M[:3, 3] = cam.t
    return M


def world_to_cam(cam: Camera, X: np.ndarray) -> np.ndarray:
    """X: (..., 3) world metres -> (..., 3) camera frame metres, ``(X - T) @ R.T``."""
    return (np.asarray(X, dtype=np.float64) - cam.T) @ cam.R.T


# ----------------------------------------------------------------------------------- distortion
def distort(xy: np.ndarray, k, p, model: str) -> np.ndarray:
    """Apply lens distortion to normalized coordinates.

    xy: (..., 2) undistorted normalized coordinates (X/Z, Y/Z); k: (3,); p: (2,);
    model: ``"h36m"`` or ``"opencv"``. Returns (..., 2) distorted normalized coordinates.
    """
    a, b = _TANGENTIAL_FORM[model]
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    xd = x * radial + p[1] * (a * x * x + y * y) + b * p[0] * x * y
    yd = y * radial + p[0] * (x * x + a * y * y) + b * p[1] * x * y
    return np.stack([xd, yd], axis=-1)


def _distort_jacobian(xy: np.ndarray, k, p, model: str) -> np.ndarray:
    """(..., 2, 2) d(x_d, y_d) / d(x, y) of :func:`distort`."""
    a, b = _TANGENTIAL_FORM[model]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    dradial = k[0] + r2 * (2.0 * k[1] + 3.0 * r2 * k[2])  # d radial / d r2
    J = np.empty(xy.shape[:-1] + (2, 2))
    J[..., 0, 0] = radial + 2.0 * x * x * dradial + 2.0 * a * p[1] * x + b * p[0] * y
    J[..., 0, 1] = 2.0 * x * y * dradial + 2.0 * p[1] * y + b * p[0] * x
    J[..., 1, 0] = 2.0 * x * y * dradial + 2.0 * p[0] * x + b * p[1] * y
    J[..., 1, 1] = radial + 2.0 * y * y * dradial + 2.0 * a * p[0] * y + b * p[1] * x
    return J


def undistort(xy_d: np.ndarray, k, p, model: str) -> np.ndarray:
    """Invert :func:`distort` by Newton's method, per point.

    xy_d: (..., 2) distorted normalized coordinates. Returns (..., 2) undistorted normalized
    coordinates; a point where Newton does not converge to ``constants.UNDISTORT_TOL`` (beyond
    the lens model's monotonic range) is NaN.
    """
    xy_d = np.asarray(xy_d, dtype=np.float64)
    x = xy_d.copy()
    for _ in range(constants.UNDISTORT_MAX_ITERS):
        e = distort(x, k, p, model) - xy_d
        if np.all(np.abs(e[np.isfinite(e)]) < constants.UNDISTORT_TOL):
            break
        J = _distort_jacobian(x, k, p, model)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (J[..., 1, 1] * e[..., 0] - J[..., 0, 1] * e[..., 1]) / det
            dy = (-J[..., 1, 0] * e[..., 0] + J[..., 0, 0] * e[..., 1]) / det
        x = x - np.stack([dx, dy], axis=-1)
    e = np.abs(distort(x, k, p, model) - xy_d).max(axis=-1)
    bad = ~(e < 1e3 * constants.UNDISTORT_TOL)
    x[bad] = np.nan
    return x


# ------------------------------------------------------------------------------------ projection
def project(cam: Camera, X: np.ndarray, distorted: bool = True) -> np.ndarray:
    """Project world points to pixels.

    X: (..., 3) world, metres. Returns (..., 2) pixels; with ``distorted=False`` the ideal
    pinhole projection (CHI3D ``intrinsics_wo_distortion`` with the same f and c).
    """
    Xc = world_to_cam(cam, X)
    xy = Xc[..., :2] / Xc[..., 2:3]
    if distorted:
        xy = distort(xy, cam.k, cam.p, cam.model)
    return xy * cam.f + cam.c


def project_jacobian(cam: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of world points and their exact derivative in the point.

    X: (N, 3) world, metres. Returns ``uv (N, 2)`` (as :func:`project`) and ``J (N, 2, 3)``,
    ``d uv / d X`` through the camera rotation, the perspective division and the lens
    distortion (chain rule of :func:`world_to_cam`, :func:`distort`). Checked against
    ``cv2.projectPoints``'s own Jacobian in the tests."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    Xc = world_to_cam(cam, X)
    z = Xc[:, 2]
    xy = Xc[:, :2] / z[:, None]
    dxy = np.zeros((len(X), 2, 3))  # d(x/z, y/z) / d Xc
    dxy[:, 0, 0] = dxy[:, 1, 1] = 1.0 / z
    dxy[:, :, 2] = -xy / z[:, None]
    Jd = _distort_jacobian(xy, cam.k, cam.p, cam.model)
    uv = distort(xy, cam.k, cam.p, cam.model) * cam.f + cam.c
    J = cam.f[None, :, None] * (Jd @ dxy @ cam.R)
    return uv, J


def normalized_from_pixels(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """uv: (..., 2) observed (distorted) pixels -> (..., 2) undistorted normalized coordinates
    (X/Z, Y/Z in the camera frame); NaN where the lens model cannot be inverted."""
    xy_d = (np.asarray(uv, dtype=np.float64) - cam.c) / cam.f
    return undistort(xy_d, cam.k, cam.p, cam.model)


def undistort_pixels(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """uv: (..., 2) observed pixels -> (..., 2) pixels of the distortion-free pinhole camera
    with the same f and c (what ``project(cam, X, distorted=False)`` gives)."""
    return normalized_from_pixels(cam, uv) * cam.f + cam.c


def rays_from_pixels(cam: Camera, uv: np.ndarray) -> np.ndarray:
    """uv: (..., 2) observed pixels -> (..., 3) unit viewing directions in the camera frame."""
    xy = normalized_from_pixels(cam, uv)
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------- CasADi twin
def camera_vector(cam: Camera) -> np.ndarray:
    """(21,) packed parameters ``[f(2), c(2), k(3), p(2), R row-major(9), T(3)]``, the layout
    :func:`project_cs` accepts as a symbolic parameter (so one compiled graph serves every
    camera of a model)."""
    return np.concatenate([cam.f, cam.c, cam.k, cam.p, cam.R.reshape(-1), cam.T])


def project_cs(cam, X, model: str | None = None, distorted: bool = True):
    """CasADi twin of :func:`project` for one point.

    cam: a :class:`Camera` (its numbers become constants) or a CasADi (21, 1) symbol/matrix
    packed like :func:`camera_vector` (then ``model`` is required); X: CasADi (3, 1) world
    point, metres (SX or MX). Returns CasADi (2, 1) pixels. Batch with ``casadi.Function.map``.
    """
    import casadi as ca

    if isinstance(cam, Camera):
        if model is not None and model != cam.model:
            raise ValueError(f"project_cs: model {model!r} != camera model {cam.model!r}")
        model = cam.model
        v = ca.DM(camera_vector(cam))
    else:
        if model not in DISTORTION_MODELS:
            raise ValueError(f"project_cs: symbolic camera needs model in {DISTORTION_MODELS}")
        v = cam
        if v.shape != (constants.CAM_VECTOR_SIZE, 1):
            raise ValueError(f"project_cs: camera vector must be (21, 1), got {v.shape}")
    a, b = _TANGENTIAL_FORM[model]
    f, c, k, p = v[0:2], v[2:4], v[4:7], v[7:9]
    R = ca.reshape(v[9:18], 3, 3).T  # packed row-major, CasADi reshapes column-major
    T = v[18:21]
    Xc = ca.mtimes(R, X - T)
    x = Xc[0] / Xc[2]
    y = Xc[1] / Xc[2]
    if distorted:
        r2 = x * x + y * y
        radial = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
        xd = x * radial + p[1] * (a * x * x + y * y) + b * p[0] * x * y
        yd = y * radial + p[0] * (x * x + a * y * y) + b * p[1] * x * y
    else:
        xd, yd = x, y
    return ca.vertcat(f[0] * xd + c[0], f[1] * yd + c[1])


def look_at(name: str, centre, target, f, c, width: int, height: int, k=(0.0, 0.0, 0.0),
            p=(0.0, 0.0), up=(0.0, 0.0, 1.0), model: str = "h36m") -> Camera:
    """A camera at ``centre`` (3,) looking at ``target`` (3,) (world, metres) with image "up"
    towards ``up`` (world z-up by default). f, c: pixels; k, p, model as in :class:`Camera`."""
    centre = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Camera(name, f, c, k, p, np.stack([x, y, z]), centre, width, height, model)
