"""Refinement of a camera rig from the person: a bundle adjustment of the cameras against a
person's 2D detections in every view, the 3D points unknown (issue #28: a lab's calibration
off by several to tens of pixels).

``calib.geometry.refine_rig`` refines poses against points whose 3D positions are known
(markers); here the points (keypoints of a moving person) are unknown and solved with the
cameras, so the solution has a gauge freedom (a similarity of the world: 7 degrees of
freedom). Two things hold it:

- a prior towards the given calibration on every camera parameter that is refined (rotation,
  centre, and when asked focal length and principal point), in units of ``sigma_*``: the
  refinement moves a camera only as far as the detections pull it against that prior; and a
  weak prior of each point towards its triangulation with the given rig, which together hold
  where the people are: for a ring of cameras around them, all cameras pitched alike with
  the people moved up or down explains the detections almost as well (a near-degenerate
  direction the gauge does not remove; on the studio's exact rig it drifted 2 degrees);
- the gauge, fixed exactly after the solve: the refined camera centres are mapped onto the
  given ones by the least-squares similarity (Umeyama: rotation, translation, scale), applied
  to the cameras and the points alike (no reprojection changes). So the centres' centroid,
  their spread (the scale) and their overall orientation are the given calibration's, and the
  world frame and ground plane stay where the recipe put them.

Observations are in pixels as detected (distorted); the lens distortion is kept as given.
Residuals are in units of ``detection_px`` with a robust loss (soft L1), and observations
further than ``max_error_px`` from the given rig's triangulation are dropped first.

Solved with ``scipy.optimize.least_squares`` (trust region, sparse finite-difference Jacobian:
each point touches only its own observations).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.camera import Camera, project


@dataclass(frozen=True)
class PersonRefineOptions:
    """sigma_rotation_deg, sigma_position_mm: the prior's scale on each camera's rotation and
    centre (how far the given calibration is believed to be off, one sigma);
    refine_focal / sigma_focal_rel: the focal length (fx, fy together, relative);
    refine_principal / sigma_principal_px: the principal point;
    sigma_points_mm: each point's prior towards its triangulation with the given rig: weak
    for one point, together they hold where the people are (all cameras pitched alike with the
    people moved up or down is otherwise nearly free for a ring of cameras around them);
    detection_px: the detections' noise, pixels (the unit of the reprojection residuals);
    loss: ``"soft_l1"``, ``"huber"``, ``"cauchy"`` or ``"linear"`` (scipy's names), with scale
    ``loss_scale`` in units of ``detection_px``;
    max_error_px: an observation further than this from the given rig's triangulation is not
    used (a wrong detection); min_views: a point is used when seen in at least this many views;
    max_points: at most this many points (an even subsample), to bound the cost;
    max_nfev: the solver's evaluation budget."""

    sigma_rotation_deg: float = 1.0
    sigma_position_mm: float = 30.0
    refine_focal: bool = False
    sigma_focal_rel: float = 0.02
    refine_principal: bool = False
    sigma_principal_px: float = 20.0
    sigma_points_mm: float = 100.0
    detection_px: float = 4.0
    loss: str = "soft_l1"
    loss_scale: float = 2.0
    max_error_px: float = 80.0
    min_views: int = 2
    max_points: int = 4000
    max_nfev: int = 60

    def __post_init__(self):
        for name in ("sigma_rotation_deg", "sigma_position_mm", "sigma_focal_rel",
                     "sigma_principal_px", "sigma_points_mm", "detection_px", "loss_scale",
                     "max_error_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be a positive number, got {v!r}")
        if self.loss not in ("soft_l1", "huber", "cauchy", "linear", "arctan"):
            raise ValueError(f"loss: must be one of soft_l1, huber, cauchy, linear, arctan, "
                             f"got {self.loss!r}")
        if not (isinstance(self.min_views, int) and self.min_views >= 2):
            raise ValueError(f"min_views: must be an integer >= 2, got {self.min_views!r}")
        if not (isinstance(self.max_points, int) and self.max_points >= 10):
            raise ValueError(f"max_points: must be an integer >= 10, got {self.max_points!r}")
        if not (isinstance(self.max_nfev, int) and self.max_nfev >= 1):
            raise ValueError(f"max_nfev: must be an integer >= 1, got {self.max_nfev!r}")


@dataclass(frozen=True)
class PersonRefinement:
    """cameras: the refined cameras (same order, gauge fixed); points: (N, 3) the solved
    points (NaN where not used); used: (C, N) the observations used; per camera (C,):
    moved_mm (centre), rotated_deg, focal_rel (fx change / fx), principal_px (change, norm);
    before_px / after_px: (C, N) reprojection error of each used observation against the
    points triangulated (DLT, all views) with the given / refined rig; gauge: how the gauge
    was fixed (words); cost_before / cost_after: the robust cost; nfev; status (scipy's)."""

    cameras: tuple[Camera, ...]
    points: np.ndarray
    used: np.ndarray
    moved_mm: np.ndarray
    rotated_deg: np.ndarray
    focal_rel: np.ndarray
    principal_px: np.ndarray
    before_px: np.ndarray
    after_px: np.ndarray
    gauge: str
    cost_before: float
    cost_after: float
    nfev: int
    status: int


GAUGE = ("the refined camera centres mapped onto the given ones by their least-squares "
         "similarity (Umeyama): centroid, scale and overall orientation of the centres are "
         "the given calibration's")


def rodrigues(w: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the rotation vector ``w`` (radians)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = np.asarray(w, float) / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    """The angle of ``A B^T``, degrees."""
    c = (np.trace(np.asarray(A, float) @ np.asarray(B, float).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, Q, t)`` minimising ``sum |s Q src_i + t - dst_i|^2`` (Umeyama 1991)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    Q = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, Q, md - s * Q @ ms


def apply_similarity(cams, X, s: float, Q: np.ndarray, t: np.ndarray):
    """Cameras and points moved by ``X' = s Q X + t`` (projections unchanged)."""
    out = [replace(c, R=np.asarray(c.R, float) @ Q.T, T=s * Q @ np.asarray(c.T, float) + t)
           for c in cams]
    X = np.asarray(X, float)
    return out, (s * X @ Q.T + t)


def reprojection(cams, X: np.ndarray, uv: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(C, N) pixel error of the points ``X (N, 3)`` against ``uv (C, N, 2)`` where ``used``
    (NaN elsewhere)."""
    err = np.full(used.shape, np.nan)
    for i, c in enumerate(cams):
        m = used[i] & np.all(np.isfinite(X), axis=1)
        if m.any():
            err[i, m] = np.linalg.norm(project(c, X[m]) - uv[i, m], axis=1)
    return err


def _triangulate(cams, uv, ok):
    from calib.dlt import triangulate_points

    return triangulate_points(cams, np.where(np.isfinite(uv), uv, 0.0), ok)


def refine_from_points(cams, uv: np.ndarray, opts: PersonRefineOptions = PersonRefineOptions(),
                       log=lambda _m: None) -> PersonRefinement:
    """Refine ``cams`` (C ``calib.Camera``) from ``uv (C, N, 2)``: the same N unknown 3D
    points seen in each view, pixels as detected (NaN = not seen). Returns
    :class:`PersonRefinement`. ValueError when a camera has fewer than 20 usable observations
    (nothing to refine it from)."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    cams = list(cams)
    uv = np.asarray(uv, float)
    C, N = len(cams), uv.shape[1]
    if uv.shape != (C, N, 2):
        raise ValueError(f"refine_from_points: uv must be ({C}, N, 2), got {uv.shape}")
    seen = np.all(np.isfinite(uv), axis=-1)
    X0 = _triangulate(cams, uv, seen)
    used = seen & (reprojection(cams, X0, uv, seen) <= opts.max_error_px)
    keep = used.sum(0) >= opts.min_views
    if keep.sum() > opts.max_points:  # an even subsample
        sel = np.flatnonzero(keep)
        keep[:] = False
        keep[sel[np.linspace(0, len(sel) - 1, opts.max_points).round().astype(int)]] = True
    used &= keep[None]
    n_obs = used.sum(1)
    if np.any(n_obs < 20):
        bad = [cams[i].name for i in np.flatnonzero(n_obs < 20)]
        raise ValueError(f"refine_from_points: camera(s) {bad} have fewer than 20 usable "
                         f"observations ({n_obs.tolist()})")
    pts = np.flatnonzero(keep)
    X0 = _triangulate(cams, uv[:, pts], used[:, pts])
    P = len(pts)
    obs_c, obs_p = np.nonzero(used[:, pts])  # observation i: camera obs_c[i], point obs_p[i]
    obs_uv = uv[:, pts][obs_c, obs_p]
    M = len(obs_c)
    # camera block: rot (3) + centre (3) [+ focal (1)] [+ principal (2)], in prior sigmas
    nf, npp = int(opts.refine_focal), 2 * int(opts.refine_principal)
    B = 6 + nf + npp
    s_rot = np.radians(opts.sigma_rotation_deg)
    s_pos = opts.sigma_position_mm / 1000.0
    s_pts = opts.sigma_points_mm / 1000.0

    def cams_of(q):
        out = []
        for i, c in enumerate(cams):
            b = q[i * B:(i + 1) * B]
            kw = dict(R=rodrigues(b[:3] * s_rot) @ np.asarray(c.R, float),
                      T=np.asarray(c.T, float) + b[3:6] * s_pos)
            j = 6
            if nf:
                kw["f"] = np.asarray(c.f, float) * (1 + b[j] * opts.sigma_focal_rel)
                j += 1
            if npp:
                kw["c"] = np.asarray(c.c, float) + b[j:j + 2] * opts.sigma_principal_px
            out.append(replace(c, **kw))
        return out

    def residuals(x):
        q, X = x[:C * B], x[C * B:].reshape(P, 3)
        cc = cams_of(q)
        r = np.empty((M, 2))
        for i, c in enumerate(cc):
            m = obs_c == i
            r[m] = project(c, X[obs_p[m]]) - obs_uv[m]
        return np.concatenate([_robust(r / opts.detection_px, opts).ravel(), q,
                               ((X - X0) / s_pts).ravel()])

    # the robust loss on each observation's 2-vector (isotropic); the prior stays quadratic
    J = lil_matrix((2 * M + C * B + 3 * P, C * B + 3 * P), dtype=np.int8)
    rows = np.arange(M)
    for k in range(B):
        J[2 * rows, obs_c * B + k] = 1
        J[2 * rows + 1, obs_c * B + k] = 1
    for k in range(3):
        J[2 * rows, C * B + 3 * obs_p + k] = 1
        J[2 * rows + 1, C * B + 3 * obs_p + k] = 1
    J[2 * M + np.arange(C * B), np.arange(C * B)] = 1
    J[2 * M + C * B + np.arange(3 * P), C * B + np.arange(3 * P)] = 1
    x0 = np.concatenate([np.zeros(C * B), X0.ravel()])
    log(f"rig refinement: {C} cameras x {B} parameters, {P} points, {M} observations")
    sol = least_squares(residuals, x0, jac_sparsity=J.tocsr(), method="trf", x_scale="jac",
                        max_nfev=opts.max_nfev, tr_solver="lsmr")
    new = cams_of(sol.x[:C * B])
    Xs = sol.x[C * B:].reshape(P, 3)
    # the gauge: the refined centres onto the given ones (similarity)
    s, Q, t = umeyama(np.array([c.T for c in new]), np.array([c.T for c in cams]))
    new, Xs = apply_similarity(new, Xs, s, Q, t)
    points = np.full((N, 3), np.nan)
    points[pts] = Xs
    before = reprojection(cams, _triangulate(cams, uv, used), uv, used)
    after = reprojection(new, _triangulate(new, uv, used), uv, used)
    return PersonRefinement(
        cameras=tuple(new), points=points, used=used,
        moved_mm=np.array([np.linalg.norm(a.T - b.T) * 1000 for a, b in zip(new, cams, strict=True)]),
        rotated_deg=np.array([rotation_angle_deg(a.R, b.R) for a, b in zip(new, cams, strict=True)]),
        focal_rel=np.array([a.f[0] / b.f[0] - 1 for a, b in zip(new, cams, strict=True)]),
        principal_px=np.array([np.linalg.norm(a.c - b.c) for a, b in zip(new, cams, strict=True)]),
        before_px=before, after_px=after, gauge=GAUGE,
        cost_before=0.5 * float(np.sum(residuals(x0) ** 2)), cost_after=float(sol.cost),
        nfev=int(sol.nfev), status=int(sol.status))


def _robust(r: np.ndarray, opts: PersonRefineOptions) -> np.ndarray:
    """Each row of ``r (M, 2)`` (units of the detection noise) scaled so that its squared norm
    is ``s^2 rho(|r|^2 / s^2)`` (scipy's robust losses, ``s = loss_scale``)."""
    s = opts.loss_scale
    z = np.sum(r ** 2, axis=1) / s ** 2
    rho = {"linear": lambda z: z, "soft_l1": lambda z: 2 * (np.sqrt(1 + z) - 1),
           "huber": lambda z: np.where(z <= 1, z, 2 * np.sqrt(np.maximum(z, 1)) - 1),
           "cauchy": np.log1p, "arctan": np.arctan}[opts.loss](z)
    w = np.sqrt(np.where(z > 1e-12, rho / np.maximum(z, 1e-12), 1.0))
    return r * w[:, None]
