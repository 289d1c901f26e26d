"""Multi-view geometry with pycolmap: triangulation of 2D keypoints, and a calibration check /
refinement of the camera rig by bundle adjustment against points whose 3D positions are known
(Vicon markers).

Both lens models reach pycolmap exactly: observations are undistorted with our own lens model
first (:func:`calib.camera.undistort_pixels`, Newton to 1e-14) and pycolmap sees ``PINHOLE``
cameras with the same f and c. (COLMAP's ``FULL_OPENCV`` cannot hold the Human3.6M lens.) For
``model="opencv"`` cameras whose distortion is refined, the raw pixels and COLMAP's ``OPENCV``
model (k1 k2 p1 p2) are used instead; that needs ``k3 = 0``, because COLMAP refines all
distortion parameters of a model together and ``FULL_OPENCV`` would also free the rational
k4-k6 (measured: they absorb the fit and the result diverges from the 5-coefficient lens). Reprojection errors are always measured by :func:`calib.camera.project` against
the observed (distorted) pixels.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.camera import Camera, project, undistort_pixels


def _rigid(cam: Camera):
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t)


def _pinhole(cam: Camera, camera_id: int | None = None):
    import pycolmap

    kw = {} if camera_id is None else {"camera_id": camera_id}
    return pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                           params=[*cam.f, *cam.c], **kw)


# --------------------------------------------------------------------------------- triangulation
@dataclass(frozen=True)
class TriangulateOptions:
    """ransac: LO-RANSAC over the views (pycolmap ``estimate_triangulation``); False: all
    valid views at once (``triangulate_multi_view_point``).
    max_error_px: RANSAC inlier threshold, pixels (undistorted image).
    min_views: fewer valid (or inlier) views -> failure.
    min_conf: observations with confidence below are ignored.
    min_angle_deg: minimum triangulation angle between inlier rays.
    seed: RANSAC random seed (-1: pycolmap's default, non-deterministic)."""

    ransac: bool = True
    max_error_px: float = 8.0
    min_views: int = 2
    min_conf: float = 0.1
    min_angle_deg: float = 1.0
    seed: int = 0


@dataclass(frozen=True)
class PointEstimate:
    """xyz: (3,) world metres; inliers: (C,) bool views used; errors_px: (C,) reprojection
    error in each view with an observation (NaN where none), pixels."""

    xyz: np.ndarray
    inliers: np.ndarray
    errors_px: np.ndarray


def _colmap_views(cams: Sequence[Camera]):
    return [_pinhole(c) for c in cams], [_rigid(c) for c in cams]


def _solve_point(und: np.ndarray, ok: np.ndarray, views, opts: TriangulateOptions):
    """Core of the triangulation: und (C, 2) undistorted pixels, ok (C,) usable views.
    Returns (xyz (3,), inliers (C,)) or None."""
    import pycolmap

    pcams, rigids = views
    idx = np.flatnonzero(ok)
    if len(idx) < opts.min_views:
        return None
    inl = np.zeros(len(ok), bool)
    if opts.ransac:
        o = pycolmap.EstimateTriangulationOptions()
        o.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
        o.ransac.max_error = float(opts.max_error_px)
        o.ransac.random_seed = int(opts.seed)
        o.min_tri_angle = float(np.deg2rad(opts.min_angle_deg))
        r = pycolmap.estimate_triangulation(und[idx], [rigids[i] for i in idx],
                                            [pcams[i] for i in idx], o)
        if r is None:
            return None
        xyz = np.asarray(r["xyz"], dtype=np.float64).reshape(3)
        inl[idx[np.asarray(r["inliers"], bool)]] = True
    else:
        xy = np.stack([_normalized(pcams[i], und[i]) for i in idx])
        rays = np.concatenate([xy, np.ones((len(idx), 1))], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        X = pycolmap.triangulate_multi_view_point([rigids[i].matrix() for i in idx], rays)
        if X is None:
            return None
        xyz = np.asarray(X, dtype=np.float64).reshape(3)
        inl[idx] = True
    if inl.sum() < opts.min_views or not np.all(np.isfinite(xyz)):
        return None
    return xyz, inl


def _normalized(pcam, uv: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy = pcam.params
    return np.array([(uv[0] - cx) / fx, (uv[1] - cy) / fy])


def _in_front(cams: Sequence[Camera], xyz: np.ndarray, inl: np.ndarray) -> np.ndarray:
    """(n,) bool: every inlier camera sees the point (n, 3) in front of it."""
    ok = np.ones(len(xyz), bool)
    for i, c in enumerate(cams):
        z = ((xyz - c.T) @ c.R.T)[:, 2]
        ok &= ~inl[:, i] | (z > 0)
    return ok


def triangulate_point(cams: Sequence[Camera], uv: np.ndarray, valid: np.ndarray | None = None,
                      opts: TriangulateOptions = TriangulateOptions()) -> PointEstimate | None:
    """Triangulate one point seen in several views.

    cams: C cameras; uv: (C, 2) observed pixels; valid: (C,) bool which views observed it
    (default: finite uv). Returns :class:`PointEstimate`, or None when fewer than
    ``min_views`` views agree, the point lands behind a camera, or pycolmap fails.
    """
    t = triangulate(cams, np.concatenate([np.asarray(uv, dtype=np.float64),
                                          np.ones((len(cams), 1))], axis=1)[:, None],
                    opts, valid=None if valid is None else np.asarray(valid, bool)[:, None])
    if not np.all(np.isfinite(t.xyz[0])):
        return None
    return PointEstimate(t.xyz[0], t.inliers[0], t.errors_px[0])


@dataclass(frozen=True)
class Triangulation:
    """xyz: (..., 3) world metres, NaN where triangulation failed; errors_px: (..., C)
    reprojection error per view (NaN where unobserved or failed); inliers: (..., C) bool."""

    xyz: np.ndarray
    errors_px: np.ndarray
    inliers: np.ndarray


def triangulate(cams: Sequence[Camera], kp: np.ndarray,
                opts: TriangulateOptions = TriangulateOptions(),
                valid: np.ndarray | None = None) -> Triangulation:
    """Triangulate keypoints over the views.

    kp: (C, ..., 3) float (x, y pixels, confidence), e.g. ``(C, F, K, 3)`` for one person of
    ``keypoints.npz``; an observation counts when its confidence >= ``min_conf`` (and
    ``valid`` (C, ...) bool, if given, is True) and its pixels are finite.
    Returns :class:`Triangulation` with leading shape ``...``. Observations are undistorted
    for all points at once; pycolmap then runs once per point.
    """
    kp = np.asarray(kp, dtype=np.float64)
    C = len(cams)
    if kp.shape[0] != C or kp.shape[-1] != 3:
        raise ValueError(f"triangulate: kp must be ({C}, ..., 3), got {kp.shape}")
    lead = kp.shape[1:-1]
    flat = kp.reshape(C, -1, 3)
    n = flat.shape[1]
    und = np.stack([undistort_pixels(c, flat[i, :, :2]) for i, c in enumerate(cams)])  # (C, n, 2)
    obs = (flat[..., 2] >= opts.min_conf) & np.all(np.isfinite(flat[..., :2]), axis=-1)
    if valid is not None:
        obs &= np.asarray(valid, bool).reshape(C, n)
    usable = obs & np.all(np.isfinite(und), axis=-1)
    xyz = np.full((n, 3), np.nan)
    inl = np.zeros((n, C), bool)
    views = _colmap_views(cams)
    for j in np.flatnonzero(usable.sum(axis=0) >= opts.min_views):
        r = _solve_point(und[:, j], usable[:, j], views, opts)
        if r is not None:
            xyz[j], inl[j] = r
    bad = np.all(np.isfinite(xyz), axis=1) & ~_in_front(cams, np.nan_to_num(xyz), inl)
    xyz[bad] = np.nan
    inl[bad] = False
    err = np.full((n, C), np.nan)
    solved = np.all(np.isfinite(xyz), axis=1)
    for i, c in enumerate(cams):
        m = solved & obs[i]
        err[m, i] = np.linalg.norm(project(c, xyz[m]) - flat[i, m, :2], axis=-1)
    return Triangulation(xyz.reshape(lead + (3,)), err.reshape(lead + (C,)), inl.reshape(lead + (C,)))


# ------------------------------------------------------------------------- rig check / refinement
def reprojection_errors(cams: Sequence[Camera], X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """X: (N, 3) world metres; uv: (C, N, 2) observed pixels (NaN = unobserved).
    Returns (C, N) pixel distances between ``project(cam, X)`` and uv (NaN where unobserved)."""
    X = np.asarray(X, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([np.linalg.norm(project(c, X) - uv[i], axis=-1) for i, c in enumerate(cams)])


@dataclass(frozen=True)
class RefineOptions:
    """What the bundle adjustment may change (poses always; 3D points never: they fix the
    world frame and scale).

    refine_focal, refine_principal: intrinsics f, c of every camera.
    refine_distortion: k1, k2, p1, p2 of ``model="opencv"`` cameras with ``k3 = 0`` (COLMAP
        ``OPENCV``; ValueError otherwise); Human3.6M lenses stay fixed (COLMAP cannot hold them).
    loss: ``"trivial"``, ``"huber"``, ``"cauchy"`` or ``"soft_l1"``; loss_scale_px its scale.
    max_error_px: observations whose error before refinement exceeds this are dropped (wrong
        detections); None keeps all.
    outer_iters: when f/c are refined on undistorted observations (every camera whose lens is
        not refined), re-undistort with the new intrinsics and solve again this many times.
    """

    refine_focal: bool = False
    refine_principal: bool = False
    refine_distortion: bool = False
    loss: str = "huber"
    loss_scale_px: float = 2.0
    max_error_px: float | None = 50.0
    outer_iters: int = 3
    max_iterations: int = 100


@dataclass(frozen=True)
class RigRefinement:
    """cameras: the refined cameras (same order); rms_before_px / rms_after_px: (C,) RMS
    reprojection error per camera over the observations used; n_obs: (C,) observations used
    per camera; converged: the solver reported convergence."""

    cameras: tuple[Camera, ...]
    rms_before_px: np.ndarray
    rms_after_px: np.ndarray
    n_obs: np.ndarray
    converged: bool


def _rms(e: np.ndarray, used: np.ndarray) -> np.ndarray:
    out = np.full(len(e), np.nan)
    for i in range(len(e)):
        if used[i].any():
            out[i] = float(np.sqrt(np.mean(e[i][used[i]] ** 2)))
    return out


def refine_rig(cams: Sequence[Camera], X: np.ndarray, uv: np.ndarray,
               opts: RefineOptions = RefineOptions()) -> RigRefinement | None:
    """Bundle-adjust the camera rig against known 3D points (pycolmap, Ceres).

    cams: C cameras; X: (N, 3) world metres, e.g. Vicon marker positions of all frames
    stacked; uv: (C, N, 2) their detections in each view, pixels, NaN where not detected.
    The 3D points are held constant, so they fix the world frame and scale; each camera's pose
    (and, if asked, intrinsics) is refined. Returns :class:`RigRefinement`, or None when a
    camera has fewer than 6 usable observations.
    """
    import pycolmap

    X = np.asarray(X, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    C = len(cams)
    if uv.shape != (C, len(X), 2):
        raise ValueError(f"refine_rig: uv must be ({C}, {len(X)}, 2), got {uv.shape}")
    err0 = reprojection_errors(cams, X, uv)
    used = np.isfinite(err0) & np.all(np.isfinite(X), axis=1)[None]
    if opts.max_error_px is not None:
        used &= err0 <= opts.max_error_px
    if np.any(used.sum(axis=1) < 6):
        return None
    if opts.refine_distortion and any(c.model == "opencv" and c.k[2] != 0 for c in cams):
        raise ValueError("refine_rig: refine_distortion needs k3 = 0 on OpenCV-lens cameras "
                         "(COLMAP's OPENCV model has k1 k2 p1 p2 only)")
    rms_before = _rms(err0, used)

    cur = list(cams)
    converged = True
    raw_mode = [c.model == "opencv" and opts.refine_distortion for c in cams]
    undist_intr = (opts.refine_focal or opts.refine_principal) and not all(raw_mode)
    for _ in range(opts.outer_iters if undist_intr else 1):
        rec = pycolmap.Reconstruction()
        for i, c in enumerate(cur):
            if raw_mode[i]:
                pc = pycolmap.Camera(model="OPENCV", width=c.width, height=c.height,
                                     params=[*c.f, *c.c, c.k[0], c.k[1], c.p[0], c.p[1]],
                                     camera_id=i + 1)
                obs = uv[i]
            else:
                pc = _pinhole(c, camera_id=i + 1)
                obs = undistort_pixels(c, uv[i])
            rec.add_camera_with_trivial_rig(pc)
            kps = np.where(np.isfinite(obs), obs, 0.0)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=c.name, keypoints=kps, camera_id=i + 1, image_id=i + 1), _rigid(c))
        ok_und = used.copy()
        for i, c in enumerate(cur):
            if not raw_mode[i]:
                ok_und[i] &= np.all(np.isfinite(undistort_pixels(c, uv[i])), axis=1)
        cfg = pycolmap.BundleAdjustmentConfig()
        for i in range(C):
            cfg.add_image(i + 1)
        for j in np.flatnonzero(ok_und.any(axis=0)):
            track = pycolmap.Track([pycolmap.TrackElement(i + 1, int(j)) for i in np.flatnonzero(ok_und[:, j])])
            cfg.add_constant_point(rec.add_point3D(X[j], track))
        o = pycolmap.BundleAdjustmentOptions()
        o.refine_focal_length = opts.refine_focal
        o.refine_principal_point = opts.refine_principal
        o.refine_extra_params = opts.refine_distortion
        o.refine_points3D = False
        o.print_summary = False
        o.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, opts.loss.upper())
        o.ceres.loss_function_scale = float(opts.loss_scale_px)
        o.ceres.solver_options.max_num_iterations = int(opts.max_iterations)
        o.ceres.solver_options.num_threads = 1
        summary = pycolmap.create_default_bundle_adjuster(o, cfg, rec).solve()
        converged = str(summary.termination_type).endswith("CONVERGENCE")
        new = []
        for i, c in enumerate(cur):
            pose = rec.image(i + 1).cam_from_world()
            R = pose.rotation.matrix()
            t = np.asarray(pose.translation, dtype=np.float64)
            prm = np.asarray(rec.camera(i + 1).params, dtype=np.float64)
            kw = dict(R=R, T=-R.T @ t, f=prm[0:2], c=prm[2:4])
            if raw_mode[i]:
                kw.update(k=(prm[4], prm[5], 0.0), p=(prm[6], prm[7]))
            new.append(replace(c, **kw))
        cur = new
    rms_after = _rms(reprojection_errors(cur, X, uv), used)
    return RigRefinement(tuple(cur), rms_before, rms_after, used.sum(axis=1), converged)
