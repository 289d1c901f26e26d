"""The partner fit's numpy ``L_2d`` residual (fitting/reprojection.py) against its peer, the
CasADi graph of the marker fit (``fitting.marker_graph.MarkerGraph`` with keypoint slots, the
same ``fitting.terms.L_2d``), and against finite differences."""
from __future__ import annotations

import numpy as np


def test_numpy_reprojection_equals_the_casadi_graph(anny):
    from body.joints import regressor
    from body.lbs import rest_state
    from calib import camera_vector, look_at
    from fitting import compiled, skinned
    from fitting.marker_graph import GraphSpec, MarkerGraph, body_joints
    from fitting.reprojection import Reprojection

    rng = np.random.default_rng(5)
    cams = [look_at(f"c{k}", [4 * np.cos(a), 4 * np.sin(a), 2.0], [0, 0, 1.0], (1100, 1050),
                    (450, 440), 900, 900, k=(-0.2, 0.1, 0.01), p=(1e-3, -5e-4), model=m)
            for k, (a, m) in enumerate([(0.5, "h36m"), (2.1, "h36m"), (3.7, "h36m")])]
    skel = skinned.fit_skeleton(anny, body_joints(anny))
    rest = rest_state(anny, rng.normal(0, 0.5, 10))
    u, _ = skinned.reduced_offsets(anny, rest, skel)
    Hk = skinned.regressed_coeffs(anny, rest, skel, regressor(anny, "kp65")[:23])
    C, K = len(cams), len(Hk)
    uv = rng.uniform(200, 700, (C, K, 2))
    conf = rng.uniform(0.3, 1.0, (C, K)) * (rng.random((C, K)) > 0.2)
    x = rng.normal(0, 0.2, skel.n)
    x[3:6] = [0.1, -0.2, 0.0]

    spec = GraphSpec(skel.topology, (), skinned.support_of(Hk), C, cams[0].model)
    graph = MarkerGraph(spec, compiled.CompileOptions(mode="interpreted"))
    empty = skinned.SkinnedPoints(np.zeros((0, 3, spec.Q, 4)), np.zeros((0, 3)), np.zeros(0))
    p = graph.params(u, empty, np.zeros((0, 3)), np.zeros(0), Hk,
                     np.stack([camera_vector(c) for c in cams]), uv, conf)
    r_cs, j_cs = graph.fun(x, p)
    J_cs = np.zeros((graph.fun.n_r, graph.fun.n_x))
    J_cs.ravel()[graph.fun._flat] = j_cs

    rep = Reprojection(skel, u, Hk, cams)
    rep.set_observations(uv, conf)
    r, j = rep(x)
    J = j.reshape(rep.n_r, rep.n_x)
    assert r.shape == r_cs.shape and J.shape == J_cs.shape
    assert np.abs(r - r_cs).max() < 1e-8 * max(1.0, np.abs(r_cs).max())
    assert np.abs(J - J_cs).max() < 1e-7 * np.abs(J_cs).max()
    assert np.all(r.reshape(C, K, 2)[conf == 0] == 0)  # a missing keypoint has no rows

    h = 1e-6
    Jfd = np.stack([(rep(x + h * e)[0] - rep(x - h * e)[0]) / (2 * h) for e in np.eye(rep.n_x)], 1)
    assert np.abs(J - Jfd).max() < 1e-5 * np.abs(Jfd).max()
