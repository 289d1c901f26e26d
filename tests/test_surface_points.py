"""The one surface-point primitive (fitting/skinned.py SurfacePoints): its numpy twin against
``body.forward`` + ``body.markers.marker_positions`` (exact), its CasADi graph against the twin
(values and Jacobian), one graph serving any points (they are parameters), the facet form
(normals follow the pose), and ``fit.npz`` reproducing its stored residuals through the
public API."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from body import forward, rest_state
from body.markers import marker_positions, plug_in_gait
from body.rotations import rodrigues
from fitting import skinned
from geometry import face_normals


def _pose(model, skel, x):
    pose = np.zeros((1, model.num_joints, 3))
    pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
    return pose


def _graph(skel, N):
    """x, corner coefficients, bary, offset -> (points, centroids, normals); full support."""
    Q = len(skel.joints)
    x = ca.SX.sym("x", skel.n)
    u = ca.SX.sym("u", Q, 3)
    H = [ca.SX.sym(f"H{i}", 3 * Q, 4) for i in range(N)]
    bary, off = ca.SX.sym("bary", N, 3), ca.SX.sym("offset", N)
    G, t = skinned.fk_cs(skel.topology, x, u)
    sup = [tuple(range(Q))] * N
    c = skinned.corners_cs(G, t, H, sup)
    pts = skinned.surface_points_cs(c, bary, off)
    cen, nrm = skinned.facets_cs(c)
    f = ca.Function("sp", [x, u, bary, off] + H, [pts, cen, nrm, ca.jacobian(ca.vec(pts), x)])
    return f, sup


def _call(f, x, u, sp: skinned.SkinnedPoints):
    Q = sp.corners.shape[2]
    Hs = [sp.corners[i].reshape(3 * Q, 4) for i in range(len(sp))]
    return [np.array(o) for o in f(x, u, sp.bary, sp.offset, *Hs)]


def test_numpy_twin_equals_forward_and_marker_positions(anny):
    rng = np.random.default_rng(3)
    model = anny
    betas = rng.normal(0, 1, 20)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    ms = plug_in_gait(model).with_offsets(rng.uniform(0.005, 0.03, 39))
    sp = skinned.surface_coeffs(model, rest, skel, skinned.SurfacePoints(ms.faces, ms.bary,
                                                                          ms.offsets))
    vids = rng.choice(model.num_vertices, 50, replace=False)
    sv = skinned.surface_coeffs(model, rest, skel,
                                skinned.SurfacePoints.at_vertices(model.faces, vids))
    for _ in range(3):
        x = rng.normal(0, 0.4, skel.n)
        out = forward(model, None, _pose(model, skel, x), rodrigues(x[:3])[None], x[3:6][None],
                      rest=rest)
        want = marker_positions(out.vertices[0], model.faces, ms)
        np.testing.assert_allclose(sp.positions(skel, u, x), want, atol=1e-10)
        np.testing.assert_allclose(sv.positions(skel, u, x), out.vertices[0, vids], atol=1e-10)


def test_graph_equals_twin_any_points_and_normals_follow_the_pose(anny):
    rng = np.random.default_rng(5)
    model = anny
    rest = rest_state(model, rng.normal(0, 1, 10))
    skel = skinned.fit_skeleton(model, [j for j in model.fit_joints if j < 30] or None)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    N = 6
    f, _ = _graph(skel, N)
    x = rng.normal(0, 0.4, skel.n)
    out = forward(model, None, _pose(model, skel, x), rodrigues(x[:3])[None], x[3:6][None],
                  rest=rest)
    for trial in range(2):  # the same graph, other points: only the parameters change
        faces = rng.choice(len(model.faces), N, replace=False)
        b = rng.dirichlet(np.ones(3), N)
        pts = skinned.SurfacePoints(faces, b, rng.uniform(-0.01, 0.03, N))
        sp = skinned.surface_coeffs(model, rest, skel, pts)
        got, cen, nrm, J = _call(f, x, u, sp)
        np.testing.assert_allclose(got, sp.positions(skel, u, x), atol=1e-12)
        # the facet form: posed centroid and posed unit normal of the mesh's own triangles
        tri = out.vertices[0][model.faces[faces]]
        np.testing.assert_allclose(cen, tri.mean(1), atol=1e-10)
        np.testing.assert_allclose(nrm, face_normals(out.vertices[0], model.faces[faces]),
                                   atol=1e-9)
        if trial == 0:
            rest_n = face_normals(rest.vertices[0], model.faces[faces])
            assert np.max(np.linalg.norm(nrm - rest_n, axis=1)) > 0.1  # not the rest normal
            eps = 1e-6
            for c in rng.choice(skel.n, 12, replace=False):
                dx = np.zeros(skel.n)
                dx[c] = eps
                fd = (sp.positions(skel, u, x + dx) - sp.positions(skel, u, x - dx)) / (2 * eps)
                np.testing.assert_allclose(J[:, c], fd.T.ravel(), atol=1e-7, err_msg=f"col {c}")


def test_bad_points_are_errors():
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    with pytest.raises(ValueError, match=r"vertices \[5\] belong to no face"):
        skinned.SurfacePoints.at_vertices(faces, [1, 5])
    sp = skinned.SurfacePoints.at_vertices(faces, [3, 0, 2])
    np.testing.assert_array_equal(sp.face, [1, 0, 0])
    np.testing.assert_array_equal(faces[sp.face][sp.bary.astype(bool)], [3, 0, 2])
    with pytest.raises(ValueError, match="2 faces, 3 bary rows"):
        skinned.SurfacePoints([0, 1], np.full((3, 3), 1 / 3), 0.0)


def test_fit_npz_reproduces_its_residuals_through_the_public_api(anny):
    """BodyFit's stored marker residuals = |marker_positions(forward(fit)) - observed| (1e-6 m):
    the fit, the API and the studio use one marker definition."""
    from artifacts import BodyFit
    from fitting import marker_fit, mocap, shape
    from fitting.marker_graph import template_placement
    from formats.c3d import Markers

    rng = np.random.default_rng(2)
    model = anny
    betas = rng.normal(0, 0.5, 10)
    tpl = template_placement(model, "plug-in-gait")
    pl = shape.Placement(tpl.names, tpl.face, tpl.bary, tpl.offset + rng.uniform(0, 0.01, 39))
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    F = 4
    pose = np.zeros((F, model.num_joints, 3))
    pose[:, skel.joints[1:]] = rng.normal(0, 0.3, (1, len(skel.joints) - 1, 3)) \
        + rng.normal(0, 0.05, (F, len(skel.joints) - 1, 3))
    R = rodrigues(np.array([0.1, -0.2, 1.0]))[None].repeat(F, 0)
    T = np.array([0.3, 0.2, 0.0]) + 0.01 * np.arange(F)[:, None]
    truth = forward(model, betas, pose, R, T)
    xyz = marker_positions(truth.vertices, model.faces, pl.markerset())
    xyz = xyz + rng.normal(0, 0.003, xyz.shape)  # residuals well above the 1e-6 check
    xyz[1:3, 5] = np.nan  # a gap
    capture = Markers(pl.names, xyz, 50.0)
    clock = mocap.VideoClock(50.0)
    opts = marker_fit.MarkerFitOptions(compile="interpreted", first_iters=15, max_iters=5)
    fit, _ = marker_fit.fit_markers(model, shape.to_shape_fit(betas, pl, "given", "given"), tpl,
                                    capture, clock, np.arange(F), opts=opts)
    fit.validate()
    assert isinstance(fit, BodyFit)
    out = forward(model, fit.betas, fit.body_pose, fit.global_orient, fit.transl)
    obs, vis = mocap.video_observations(capture, fit.frames, clock)
    again = np.linalg.norm(marker_positions(out.vertices, model.faces, pl.markerset()) - obs, axis=2)
    stored = fit.marker_residual_m
    np.testing.assert_array_equal(np.isnan(stored), ~vis)
    assert np.nanmedian(stored) > 1e-3  # a real fit, not a zero residual
    np.testing.assert_allclose(np.where(vis, again, np.nan), stored, atol=1e-6)
