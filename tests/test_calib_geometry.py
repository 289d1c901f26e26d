"""Triangulation and rig refinement with pycolmap: synthetic round trips with known noise."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calib_camera import random_camera

from calib import project
from calib.geometry import (
    RefineOptions,
    TriangulateOptions,
    refine_rig,
    reprojection_errors,
    triangulate,
    triangulate_point,
)


def rig(rng, model):
    return [random_camera(rng, model, name=f"c{i}") for i in range(4)]


def visible_points(rng, cams, n):
    X = rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 1.9], (n, 3))
    uv = np.stack([project(c, X) for c in cams])
    return X, uv


@pytest.mark.parametrize("model", ["h36m", "opencv"])
def test_triangulate_noise_free_is_exact_and_errors_are_reprojections(model):
    rng = np.random.default_rng(1)
    cams = rig(rng, model)
    X, uv = visible_points(rng, cams, 50)
    kp = np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], axis=-1)  # (C, N, 3)
    for ransac in (True, False):
        t = triangulate(cams, kp, TriangulateOptions(ransac=ransac))
        assert np.abs(t.xyz - X).max() < 1e-6
        assert np.nanmax(t.errors_px) < 1e-4 and t.inliers.all()


def test_triangulate_rejects_an_outlier_view_and_reports_its_error():
    rng = np.random.default_rng(2)
    cams = rig(rng, "h36m")
    X, uv = visible_points(rng, cams, 30)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    uv[2, :10] += 40.0  # camera 2 is wrong on the first 10 points
    kp = np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], axis=-1)
    t = triangulate(cams, kp, TriangulateOptions(max_error_px=4.0))
    assert not t.inliers[:10, 2].any() and t.inliers[10:].all()
    assert np.linalg.norm(t.xyz - X, axis=1).max() < 0.01
    assert np.all(t.errors_px[:10, 2] > 30)
    ref = reprojection_errors(cams, t.xyz, uv).T
    assert np.allclose(t.errors_px, ref, equal_nan=True)
    # the same data without RANSAC is pulled off by the outliers
    t_all = triangulate(cams, kp, TriangulateOptions(ransac=False))
    assert np.linalg.norm(t_all.xyz[:10] - X[:10], axis=1).mean() > 3 * np.linalg.norm(
        t.xyz[:10] - X[:10], axis=1).mean()


def test_triangulate_failures_are_none_or_nan():
    rng = np.random.default_rng(3)
    cams = rig(rng, "opencv")
    X, uv = visible_points(rng, cams, 4)
    assert triangulate_point(cams, uv[:, 0], valid=np.array([True, False, False, False])) is None
    kp = np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], axis=-1)
    kp[1:, 1, 2] = 0.0  # point 1 seen in one view only (others below min_conf)
    kp[:, 2, :2] = np.nan  # point 2 not seen at all
    t = triangulate(cams, kp[:, None], TriangulateOptions())  # extra axis: (C, 1, N, 3)
    assert t.xyz.shape == (1, 4, 3) and t.errors_px.shape == (1, 4, 4)
    assert np.isnan(t.xyz[0, 1]).all() and np.isnan(t.xyz[0, 2]).all()
    assert np.isfinite(t.xyz[0, [0, 3]]).all()
    # views that disagree by far more than the threshold: no consensus
    bad = uv[:, 0].copy()
    bad[1] += [200, 0]
    bad[2] += [0, 200]
    bad[3] += [-200, 100]
    assert triangulate_point(cams, bad, opts=TriangulateOptions(min_views=3, max_error_px=2)) is None


def perturb(rng, cam, deg=1.0, metres=0.03):
    dR = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(deg)).as_matrix()
    return replace(cam, R=dR @ cam.R, T=cam.T + rng.normal(size=3) / np.sqrt(3) * metres)


def pose_error(a, b):
    return (np.linalg.norm(a.T - b.T),
            np.rad2deg(np.linalg.norm(Rotation.from_matrix(a.R @ b.R.T).as_rotvec())))


@pytest.mark.parametrize("model", ["h36m", "opencv"])
def test_refine_rig_recovers_a_bumped_camera(model):
    rng = np.random.default_rng(4)
    cams = rig(rng, model)
    X, uv = visible_points(rng, cams, 39 * 40)  # 39 markers over 40 frames
    uv = uv + rng.normal(0, 0.5, uv.shape)
    uv[:, rng.random(len(X)) < 0.2] = np.nan  # occlusions
    uv[1, :15] += 80.0  # a few wrong detections in camera 1
    start = list(cams)
    start[2] = perturb(rng, cams[2])
    r = refine_rig(start, X, uv)
    assert r is not None and r.converged
    assert r.rms_before_px[2] > 10 and r.rms_after_px.max() < 0.8  # noise: 0.5 px per axis
    assert r.n_obs[1] < r.n_obs[0] + 20  # outliers beyond max_error_px were dropped
    for a, b in zip(r.cameras, cams, strict=True):
        dt, dr = pose_error(a, b)
        assert dt < 0.003 and dr < 0.02
        assert np.array_equal(a.f, b.f) and np.array_equal(a.k, b.k)


def test_refine_rig_intrinsics():
    rng = np.random.default_rng(5)
    cams = [replace(c, k=(c.k[0], c.k[1], 0.0)) for c in rig(rng, "opencv")]
    X, uv = visible_points(rng, cams, 2000)
    uv = uv + rng.normal(0, 0.3, uv.shape)
    start = [replace(c, f=c.f * 1.02, c=c.c + 5, k=c.k * 0.8) for c in cams]
    opts = RefineOptions(refine_focal=True, refine_principal=True, refine_distortion=True)
    r = refine_rig(start, X, uv, opts)
    assert r.rms_after_px.max() < 0.5 < r.rms_before_px.min()
    # c, p and the rotation are nearly interchangeable over a 1.2 m volume seen from 4 m, so
    # judge the cameras by how they project points they were not refined on.
    held, _ = visible_points(rng, cams, 500)
    for a, b in zip(r.cameras, cams, strict=True):
        assert np.abs(a.f - b.f).max() < 2.0
        assert np.abs(project(a, held) - project(b, held)).max() < 0.3
    with pytest.raises(ValueError, match="k3"):
        refine_rig([replace(c, k=(0, 0, 0.01)) for c in cams], X, uv, opts)
    # Human3.6M lens: f/c refined through re-undistortion, lens kept
    cams = rig(rng, "h36m")
    X, uv = visible_points(rng, cams, 2000)
    uv = uv + rng.normal(0, 0.3, uv.shape)
    start = [replace(c, f=c.f * 1.01, c=c.c + 3) for c in cams]
    r = refine_rig(start, X, uv, RefineOptions(refine_focal=True, refine_principal=True))
    assert r.rms_after_px.max() < 0.5 < r.rms_before_px.min()
    held, _ = visible_points(rng, cams, 500)
    for a, b in zip(r.cameras, cams, strict=True):
        assert np.abs(a.f - b.f).max() < 2.0
        assert np.abs(project(a, held) - project(b, held)).max() < 0.3


def test_refine_rig_needs_observations():
    rng = np.random.default_rng(6)
    cams = rig(rng, "h36m")
    X, uv = visible_points(rng, cams, 20)
    uv[3, 3:] = np.nan
    assert refine_rig(cams, X, uv) is None
    with pytest.raises(ValueError, match="uv must be"):
        refine_rig(cams, X, uv[:, :5])
