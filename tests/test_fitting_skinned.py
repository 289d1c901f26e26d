"""Slot skinning on the reduced fit skeleton vs body.lbs.forward (the peer), surface points
(markers: face corners + bary + offset along the posed normal) vs forward +
body.markers.marker_positions, and the marker graph's residuals and Jacobian vs numpy and
finite differences. A small random body model with Anny-style bind rotations stands in for
the real one (fast, no export needed)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from body.lbs import forward, rest_state
from body.model import BodyModel
from body.rotations import rodrigues
from calib import camera_vector, look_at, project
from fitting import compiled, marker_graph, skinned, terms


def random_model(rng, V=60, bind=True, S=4):
    parents = np.array([-1, 0, 1, 2, 3, 1, 5, 6, 1, 8, 9, 0, 11, 12])
    J = len(parents)
    joints = np.zeros((J, 3))
    for j in range(1, J):
        joints[j] = joints[parents[j]] + rng.normal(0, 0.15, 3)
    owner = rng.integers(0, J, V)
    verts = joints[owner] + rng.normal(0, 0.05, (V, 3))
    W = np.zeros((V, J))
    for v in range(V):
        js = [owner[v], parents[owner[v]] if owner[v] else 0, rng.integers(J)]
        W[v, js] += rng.random(3)
    W /= W.sum(1, keepdims=True)
    kw = {}
    if bind:
        q = rng.normal(0, 0.3, (J, 3))
        kw = dict(orient_template=rodrigues(q) + rng.normal(0, 0.01, (J, 3, 3)),
                  orient_shapedirs=rng.normal(0, 0.01, (J, 3, 3, S)),
                  ref_orient=rodrigues(rng.normal(0, 0.3, (J, 3))))
    return BodyModel(
        name="toy", v_template=verts, faces=np.arange(V - V % 3).reshape(-1, 3),
        shapedirs=rng.normal(0, 0.01, (V, 3, S)), joint_template=joints,
        joint_shapedirs=rng.normal(0, 0.01, (J, 3, S)), parents=parents,
        joint_names=tuple(f"j{j}" for j in range(J)), weights=sp.csr_matrix(W),
        fit_joints=(0, 1, 2, 4, 5, 7, 8, 11, 12), **kw)


@pytest.mark.parametrize("bind", [True, False])
def test_slots_on_reduced_skeleton_equal_full_forward(bind):
    rng = np.random.default_rng(0)
    model = random_model(rng, bind=bind)
    betas = rng.normal(0, 1, 4)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    H = skinned.vertex_coeffs(model, rest, skel, model.weights, rest.vertices[0])
    for _ in range(3):
        x = rng.normal(0, 0.6, skel.n)
        pose = np.zeros((1, model.num_joints, 3))
        pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
        out = forward(model, betas, pose, rodrigues(x[:3])[None], x[3:6][None], rest=rest)
        got = skinned.slot_positions_np(skel, u, H, x)
        np.testing.assert_allclose(got, out.vertices[0], atol=1e-12)


def _fd(f, x, h=1e-6):
    J = np.zeros((len(f(x)), len(x)))
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (f(x + e) - f(x - e)) / (2 * h)
    return J


def test_marker_graph_residuals_and_jacobian(tmp_path):
    rng = np.random.default_rng(1)
    model = random_model(rng)
    rest = rest_state(model, np.zeros(4))
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    M, K = 6, 4
    rng.choice(model.num_vertices, M, replace=False)  # (keeps the draws of the cases below)
    vk = rng.choice(model.num_vertices, K, replace=False)
    fm = rng.choice(len(model.faces), M, replace=False)
    pts = skinned.SurfacePoints(fm, rng.dirichlet(np.ones(3), M), rng.uniform(0, 0.02, M))
    Hm = skinned.surface_coeffs(model, rest, skel, pts)
    Hk = skinned.vertex_coeffs(model, rest, skel, model.weights[vk], rest.vertices[0, vk])
    cams = [look_at(f"c{i}", [3 * np.cos(a), 3 * np.sin(a), 1.2], [0, 0, 0.3], (1000, 1000),
                    (450, 450), 900, 900, k=(-0.1, 0.05, 0.0), p=(1e-4, -2e-4))
            for i, a in enumerate([0.3, 2.0])]
    spec = marker_graph.GraphSpec(skel.topology, skinned.points_support(Hm), skinned.support_of(Hk),
                                  len(cams), "h36m")
    g = marker_graph.MarkerGraph(spec, compiled.CompileOptions(mode="interpreted"))
    obs = rng.normal(0, 0.3, (M, 3))
    vis = np.array([1, 1, 0, 1, 1, 1.0])
    uv = rng.uniform(0, 900, (2, K, 2))
    conf = rng.uniform(0, 1, (2, K))
    conf[0, 1] = 0
    p = g.params(u, Hm, obs, vis, Hk, np.stack([camera_vector(c) for c in cams]), uv, conf)

    def numpy_r(x):
        m = Hm.positions(skel, u, x)
        kp = skinned.slot_positions_np(skel, u, Hk, x)
        uvm = np.concatenate([project(c, kp) for c in cams])
        return np.concatenate([terms.L_3d(m, np.where(vis[:, None] > 0, obs, 0), vis),
                               terms.L_2d(uvm, uv.reshape(-1, 2), conf.reshape(-1))])

    x = rng.normal(0, 0.3, spec.n_x)
    r, Jd = g.fun.dense(x, p)
    np.testing.assert_allclose(r, numpy_r(x), atol=1e-9)
    np.testing.assert_allclose(Jd, _fd(numpy_r, x), atol=1e-5, rtol=1e-6)
    # near zero pose: the small-angle branch keeps derivatives finite and right
    x0 = np.zeros(spec.n_x)
    r0, J0 = g.fun.dense(x0, p)
    assert np.all(np.isfinite(J0))
    np.testing.assert_allclose(J0, _fd(numpy_r, x0, h=1e-7), atol=1e-4, rtol=1e-5)


def test_support_restriction_is_exact_when_it_covers_the_weights():
    rng = np.random.default_rng(2)
    model = random_model(rng, bind=False)
    rest = rest_state(model, np.zeros(4))
    skel = skinned.fit_skeleton(model)
    vm = rng.choice(model.num_vertices, 5, replace=False)
    H = skinned.vertex_coeffs(model, rest, skel, model.weights[vm], rest.vertices[0, vm])
    sup = skinned.support_of(H)
    assert all(len(s) < len(skel.joints) for s in sup)
    flat, dropped = skinned.restrict(H, sup)
    assert dropped < 1e-12 and len(flat) == 4 * sum(len(s) for s in sup)
    big = skinned.neighbourhood_support(model, rest, skel, rest.vertices[0, vm], 0.05)
    assert all(set(a) <= set(b) for a, b in zip(sup, big, strict=True))
    # a support missing a joint drops its weight and rescales the rest to sum 1
    cut = tuple(s[1:] if len(s) > 1 else s for s in sup)
    flat2, dropped2 = skinned.restrict(H, cut)
    assert dropped2 > 0
    o = 0
    for s in cut:
        blk = flat2[o:o + 4 * len(s)].reshape(len(s), 4)
        assert np.isclose(blk[:, 3].sum(), 1.0)
        o += 4 * len(s)


def test_regressed_coeffs_match_regressing_the_full_forward():
    rng = np.random.default_rng(3)
    model = random_model(rng)
    betas = rng.normal(0, 1, 4)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    V, J = model.num_vertices, model.num_joints
    R = sp.random(5, V + J, density=0.05, random_state=3, format="csr")
    H = skinned.regressed_coeffs(model, rest, skel, R)
    x = rng.normal(0, 0.5, skel.n)
    pose = np.zeros((1, J, 3))
    pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
    out = forward(model, betas, pose, rodrigues(x[:3])[None], x[3:6][None], rest=rest)
    want = R @ np.concatenate([out.vertices[0], out.joints[0]])
    np.testing.assert_allclose(skinned.slot_positions_np(skel, u, H, x), want, atol=1e-12)


def test_surface_points_equal_forward_and_marker_positions():
    from body.markers import make_markerset, marker_positions

    rng = np.random.default_rng(4)
    model = random_model(rng)
    betas = rng.normal(0, 1, 4)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    T = len(model.faces)
    ms = make_markerset([f"m{i}" for i in range(T)], np.arange(T), rng.dirichlet(np.ones(3), T),
                        rng.uniform(-0.01, 0.05, T))
    Hm = skinned.surface_coeffs(model, rest, skel, skinned.SurfacePoints(ms.faces, ms.bary,
                                                                          ms.offsets))
    X, wants = rng.normal(0, 0.6, (3, skel.n)), []
    for x in X:
        pose = np.zeros((1, model.num_joints, 3))
        pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
        out = forward(model, betas, pose, rodrigues(x[:3])[None], x[3:6][None], rest=rest)
        wants.append(marker_positions(out.vertices[0], model.faces, ms))
        np.testing.assert_allclose(Hm.positions(skel, u, x), wants[-1], atol=1e-12)
    # frames batched on a leading axis: the same positions in one call
    np.testing.assert_allclose(Hm.positions(skel, u, X), np.stack(wants), atol=1e-12)
    np.testing.assert_allclose(Hm.positions(skel, u, X.reshape(3, 1, -1))[:, 0], np.stack(wants),
                               atol=1e-12)
