"""Camera models checked against peers: the public CHI3D formula, cv2.projectPoints, pycolmap."""
from dataclasses import replace

import casadi as ca
import cv2
import numpy as np
import pycolmap
import pytest

from calib import (
    Camera,
    cam_from_world,
    camera_vector,
    look_at,
    normalized_from_pixels,
    project,
    project_cs,
    project_jacobian,
    undistort_pixels,
    world_to_cam,
)
from calib.convert import convert_distortion, from_opencv, opencv_dist, to_opencv


def random_camera(rng, model="h36m", name="cam"):
    a = rng.uniform(0, 2 * np.pi)
    centre = [4 * np.cos(a), 4 * np.sin(a), rng.uniform(1.0, 2.5)]
    target = rng.normal([0, 0, 1.0], 0.2)
    return look_at(
        name, centre, target,
        f=rng.uniform(900, 1200, 2), c=rng.uniform(400, 500, 2), width=900, height=900,
        k=[rng.uniform(-0.3, 0.1), rng.uniform(-0.1, 0.3), rng.uniform(-0.05, 0.05)],
        p=rng.uniform(-3e-3, 3e-3, 2), model=model)


def random_points(rng, cam, n=200):
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (n * 3, 3))
    uv = project(cam, X)
    ok = (world_to_cam(cam, X)[:, 2] > 0.5) & np.all((uv > 0) & (uv < 900), axis=1)
    return X[ok][:n]


def chi3d_reference(points_cam, f, c, k, p):
    """The public CHI3D tools' formula (util/dataset_util.py project_3d_to_2d), as FORMATS.md
    states it: p' = (p2, p1); x_d = x (radial + x.p') + r2 p'; uv = f x_d + c."""
    x = points_cam[:, :2] / points_cam[:, 2:3]
    r2 = np.sum(x**2, axis=1)
    radial = 1 + (np.array(k).reshape(1, 3) @ np.array([r2, r2**2, r2**3])).T
    pp = np.array(p).reshape(1, 2)[:, [1, 0]]
    tan = x @ pp.T
    return np.asarray(f) * (x * (tan + radial) + r2[:, None] * pp) + np.asarray(c)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_h36m_matches_public_chi3d_formula(rng):
    for _ in range(5):
        cam = random_camera(rng)
        X = random_points(rng, cam)
        ref = chi3d_reference((X - cam.T) @ cam.R.T, cam.f, cam.c, cam.k, cam.p)
        assert np.abs(project(cam, X) - ref).max() < 1e-9


def test_h36m_equals_opencv_thin_prism_exactly(rng):
    for _ in range(5):
        cam = random_camera(rng, "h36m")
        X = random_points(rng, cam)
        rvec, tvec, K, dist = to_opencv(cam)
        assert dist.size == 12
        uv_cv, _ = cv2.projectPoints(X, rvec, tvec, K, dist)
        assert np.abs(project(cam, X) - uv_cv[:, 0]).max() < 1e-6


def test_opencv_model_matches_cv2_and_pycolmap(rng):
    for _ in range(5):
        cam = random_camera(rng, "opencv")
        X = random_points(rng, cam)
        uv = project(cam, X)
        rvec, tvec, K, dist = to_opencv(cam)
        assert dist.size == 5
        uv_cv, _ = cv2.projectPoints(X, rvec, tvec, K, dist)
        assert np.abs(uv - uv_cv[:, 0]).max() < 1e-6
        k1, k2, k3 = cam.k
        p1, p2 = cam.p
        pc = pycolmap.Camera(model="FULL_OPENCV", width=cam.width, height=cam.height,
                             params=[*cam.f, *cam.c, k1, k2, p1, p2, k3, 0, 0, 0])
        uv_colmap = pc.img_from_cam(world_to_cam(cam, X))
        assert np.abs(uv - uv_colmap).max() < 1e-6


def test_project_jacobian_matches_cv2_and_finite_differences(rng):
    """d uv / d X: against OpenCV's own Jacobian (its d/d tvec times R, opencv model) and
    central differences (both models)."""
    for model in ("opencv", "h36m"):
        cam = random_camera(rng, model)
        X = random_points(rng, cam, 50)
        uv, J = project_jacobian(cam, X)
        assert np.abs(uv - project(cam, X)).max() < 1e-9
        h = 1e-6
        fd = np.stack([(project(cam, X + h * e) - project(cam, X - h * e)) / (2 * h)
                       for e in np.eye(3)], axis=-1)
        assert np.abs(J - fd).max() < 1e-4 * np.abs(fd).max()
        if model == "opencv":
            rvec, tvec, K, dist = to_opencv(cam)
            _, jac = cv2.projectPoints(X, rvec, tvec, K, dist)
            J_cv = jac[:, 3:6].reshape(len(X), 2, 3) @ cam.R  # d uv / d tvec = d uv / d Xc
            assert np.abs(J - J_cv).max() < 1e-6 * np.abs(J_cv).max()


def test_models_differ_when_p_nonzero(rng):
    cam = random_camera(rng, "h36m")
    X = random_points(rng, cam)
    other = replace(cam, model="opencv")
    assert np.abs(project(cam, X) - project(other, X)).max() > 0.05
    flat = replace(cam, p=(0, 0))
    assert np.abs(project(flat, X) - project(replace(flat, model="opencv"), X)).max() < 1e-12


@pytest.mark.parametrize("model", ["h36m", "opencv"])
def test_casadi_twin_matches_numpy_and_finite_differences(rng, model):
    cam = random_camera(rng, model)
    X = random_points(rng, cam, 20)
    x = ca.SX.sym("x", 3)
    v = ca.SX.sym("v", 21)
    f_const = ca.Function("f", [x], [project_cs(cam, x)])
    f_sym = ca.Function("g", [x, v], [project_cs(v, x, model=model)])
    ref = project(cam, X)
    got_const = np.array(f_const.map(len(X))(X.T)).T
    got_sym = np.array(f_sym.map(len(X))(X.T, np.tile(camera_vector(cam)[:, None], len(X)))).T
    assert np.abs(got_const - ref).max() < 1e-9
    assert np.abs(got_sym - ref).max() < 1e-9
    # Jacobians w.r.t. the point and the camera vector against central differences of numpy.
    jac = ca.Function("j", [x, v], [ca.jacobian(project_cs(v, x, model=model), ca.vertcat(x, v))])
    vec = camera_vector(cam)

    def proj_from_vec(xx, vv):
        c = Camera("c", vv[0:2], vv[2:4], vv[4:7], vv[7:9], vv[9:18].reshape(3, 3), vv[18:21],
                   900, 900, model)
        return project(c, xx)

    J = np.array(jac(X[0], vec))
    z = np.concatenate([X[0], vec])
    for i in [0, 1, 2, 3, 4, 5, 6, 9, 11, 18, 20]:  # point, f, c, k, p, T (R must stay a rotation)
        h = 1e-6 * max(1.0, abs(z[i]))
        zp, zm = z.copy(), z.copy()
        zp[i] += h
        zm[i] -= h
        fd = (proj_from_vec(zp[:3], zp[3:]) - proj_from_vec(zm[:3], zm[3:])) / (2 * h)
        assert np.allclose(J[:, i], fd, rtol=1e-5, atol=1e-4), i


@pytest.mark.parametrize("model", ["h36m", "opencv"])
def test_undistortion_round_trip(rng, model):
    cam = random_camera(rng, model)
    X = random_points(rng, cam)
    Xc = world_to_cam(cam, X)
    xy = normalized_from_pixels(cam, project(cam, X))
    assert np.abs(xy - Xc[:, :2] / Xc[:, 2:]).max() < 1e-12
    assert np.abs(undistort_pixels(cam, project(cam, X)) - project(cam, X, distorted=False)).max() < 1e-8
    # OpenCV's iterative undistortion, as a peer (it stops at its own tolerance).
    _, _, K, dist = to_opencv(cam)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPointsIter(project(cam, X)[:, None], K, dist, None, None, crit)[:, 0]
    assert np.abs(und - xy).max() < 1e-8


def test_undistortion_matches_pycolmap(rng):
    cam = random_camera(rng, "opencv")
    uv = rng.uniform(50, 850, (100, 2))
    pc = pycolmap.Camera(model="FULL_OPENCV", width=900, height=900,
                         params=[*cam.f, *cam.c, cam.k[0], cam.k[1], *cam.p, cam.k[2], 0, 0, 0])
    assert np.abs(pc.cam_from_img(uv) - normalized_from_pixels(cam, uv)).max() < 1e-9


def test_undistortion_outside_lens_range_is_nan():
    cam = Camera("c", (1000, 1000), (450, 450), (-0.5, 0, 0), (0, 0), np.eye(3), (0, 0, 0), 900, 900)
    # x_d = x (1 - 0.5 x^2) peaks at x_d = 0.544: beyond that no undistorted point exists.
    xy = normalized_from_pixels(cam, np.array([[450 + 300.0, 450], [450 + 1000.0, 450]]))
    assert np.isfinite(xy[0]).all() and np.isnan(xy[1]).all()


def test_cam_from_world_and_look_at(rng):
    cam = random_camera(rng)
    X = rng.normal(size=(10, 3))
    M = cam_from_world(cam)
    Xh = np.c_[X, np.ones(10)] @ M.T
    assert np.allclose(Xh[:, :3], world_to_cam(cam, X))
    centred = look_at("c", (3, 0, 1.5), (0, 0, 1), (1000, 1000), (450, 440), 900, 900)
    assert np.allclose(project(centred, np.array([0, 0, 1.0])), [450, 440])
    # z-up world: a point above the target appears higher in the image (smaller v).
    assert project(centred, np.array([0, 0, 1.5]))[1] < 440


def test_opencv_round_trip_both_models(rng):
    for model, n in (("h36m", 12), ("opencv", 5)):
        cam = random_camera(rng, model)
        rvec, tvec, K, dist = to_opencv(cam)
        assert dist.size == n
        back = from_opencv(cam.name, rvec, tvec, K, dist, 900, 900)
        assert back.allclose(cam, atol=1e-12)
    with pytest.raises(ValueError, match="neither"):
        from_opencv("x", np.zeros(3), np.zeros(3), cam.K, [0, 0, 0, 0, 0, 0.1, 0, 0], 900, 900)
    with pytest.raises(ValueError, match="K must be"):
        K = cam.K
        K[0, 1] = 3.0
        from_opencv("x", np.zeros(3), np.zeros(3), K, np.zeros(5), 900, 900)


def test_convert_distortion_reports_its_true_residual(rng):
    cam = random_camera(rng, "h36m")
    conv = convert_distortion(cam, "opencv")
    assert conv.camera.model == "opencv" and not conv.exact
    u, v = np.meshgrid(np.linspace(0, 899, 30), np.linspace(0, 899, 30))
    uv = np.c_[u.ravel(), v.ravel()]
    xy = normalized_from_pixels(cam, uv)
    Xc = np.c_[xy, np.ones(len(xy))] * 3.0
    X = Xc @ cam.R + cam.T  # back to world
    err = np.linalg.norm(project(conv.camera, X) - project(cam, X), axis=1)
    assert err.max() <= conv.max_px * 1.05 + 1e-9
    assert 0 < conv.rms_px < 0.5  # an approximation, but a usable one for |p| <= 3e-3
    # the fit beats the naive copy of the coefficients
    naive = np.linalg.norm(project(replace(cam, model="opencv"), X) - project(cam, X), axis=1)
    assert err.max() < naive.max()
    # back again is close, and p = 0 converts exactly
    assert convert_distortion(replace(cam, p=(0, 0)), "opencv").exact
    assert np.allclose(opencv_dist(convert_distortion(replace(cam, p=(0, 0)), "opencv").camera),
                       [cam.k[0], cam.k[1], 0, 0, cam.k[2]])


def test_camera_validation():
    good = dict(name="c", f=(1000, 1000), c=(450, 450), k=(0, 0, 0), p=(0, 0), R=np.eye(3),
                T=(0, 0, 0), width=900, height=900)
    Camera(**good)
    for bad, match in ((dict(R=np.diag([1, 1, -1.0])), "rotation"), (dict(f=(1, 2, 3)), "f"),
                       (dict(T=(0, np.nan, 0)), "T"), (dict(model="fisheye"), "model"),
                       (dict(f=(-1, 1)), "positive")):
        with pytest.raises(ValueError, match=match):
            Camera(**{**good, **bad})
    cam = Camera(**good)
    with pytest.raises(ValueError):
        cam.f[0] = 3.0  # read-only arrays
