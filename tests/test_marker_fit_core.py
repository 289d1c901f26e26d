"""fitting.marker_fit on a small random body: a known motion recovered from its own markers,
with gaps, noise and a swapped label; re-wrapping; the first-frame rigid initialisation."""
from __future__ import annotations

import numpy as np
import pytest
from test_fitting_skinned import random_model

from body.lbs import rest_state
from body.rotations import rodrigues
from fitting import compiled, marker_fit, priors, skinned
from fitting.marker_graph import GraphSpec, MarkerGraph


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(7)
    model = random_model(rng, V=80, bind=False)
    rest = rest_state(model, np.zeros(4))
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    M = 24
    vm = rng.choice(model.num_vertices, M, replace=False)
    Hm = skinned.surface_coeffs(model, rest, skel,
                                skinned.SurfacePoints.at_vertices(model.faces, vm))
    graph = MarkerGraph(GraphSpec(skel.topology, skinned.points_support(Hm)),
                        compiled.CompileOptions(mode="interpreted"))
    prior = priors.default_prior(skel.names[1:])
    return skel, u, Hm, graph, prior


def motion(rng, skel, F=25):
    """A smooth random motion: (F, n) unknowns."""
    n = skel.n
    a = rng.normal(0, 0.5, n)
    b = rng.normal(0, 0.5, n)
    t = np.linspace(0, 1, F)[:, None]
    X = a * np.sin(2 * t) * 0.8 + b * t * 0.5
    X[:, 3:6] = np.array([0.3, -0.2, 0.9]) + t * np.array([0.4, 0.1, 0.0])
    X[:, :3] = np.array([0.2, -0.1, 1.5]) + t * np.array([0.0, 0.0, 0.4])
    return X


def markers_of(skel, u, Hm, X):
    return np.stack([Hm.positions(skel, u, x) for x in X])


def test_known_motion_recovered_from_its_own_markers(setup):
    skel, u, Hm, graph, prior = setup
    rng = np.random.default_rng(0)
    X = motion(rng, skel)
    obs = markers_of(skel, u, Hm, X)
    vis = np.ones(obs.shape[:2])
    opts = marker_fit.MarkerFitOptions(weights={"L_theta": 1e-12, "L_s": 1e-12})
    fit = marker_fit.fit_sequence(marker_fit.FrameSolver(graph, skel, u, Hm, prior, opts), obs, vis)
    got = markers_of(skel, u, Hm, fit.x)
    assert np.abs(got - obs).max() < 1e-5
    assert np.nanmax(fit.marker_residual_m) < 1e-5
    # the global rotation and translation are recovered exactly
    np.testing.assert_allclose(rodrigues(fit.x[:, :3]), rodrigues(X[:, :3]), atol=1e-5)
    np.testing.assert_allclose(fit.x[:, 3:6], X[:, 3:6], atol=1e-5)


def test_gaps_noise_and_a_swapped_label(setup):
    skel, u, Hm, graph, prior = setup
    rng = np.random.default_rng(1)
    X = motion(rng, skel)
    clean = markers_of(skel, u, Hm, X)
    obs = clean + rng.normal(0, 0.001 / np.sqrt(3), clean.shape)
    vis = np.ones(obs.shape[:2])
    vis[5:15, 3] = 0
    vis[10:20, 11] = 0
    obs[vis == 0] = np.nan
    swapped = obs.copy()
    swapped[8:, [2, 9]] = obs[8:, [9, 2]]  # labels of two markers swapped from frame 8 on
    solver = marker_fit.FrameSolver(graph, skel, u, Hm, prior, marker_fit.MarkerFitOptions())
    fit = marker_fit.fit_sequence(solver, swapped, vis)
    got = markers_of(skel, u, Hm, fit.x)
    good = np.ones(vis.shape, bool)
    good[:, [2, 9]] = False
    err = np.linalg.norm(got - clean, axis=2)
    assert np.median(err[good]) < 0.002, np.median(err[good])
    assert np.percentile(err[good], 95) < 0.006
    # the swapped markers are flagged: large residual, small robust weight
    assert np.all(fit.robust_weight[8:, [2, 9]] < 0.2)
    assert np.nanmedian(fit.robust_weight[:, good[0]]) > 0.9
    assert np.all(np.isnan(fit.marker_residual_m[vis == 0]))


def test_rewrap_keeps_rotation_and_bounds_angle():
    rng = np.random.default_rng(2)
    x = rng.normal(0, 3, 3 + 3 + 3 * 5)
    y = marker_fit.rewrap(x)
    rv_x = np.concatenate([x[:3], x[6:]]).reshape(-1, 3)
    rv_y = np.concatenate([y[:3], y[6:]]).reshape(-1, 3)
    assert np.all(np.linalg.norm(rv_y, axis=1) <= np.pi + 1e-12)
    np.testing.assert_allclose(rodrigues(rv_y), rodrigues(rv_x), atol=1e-12)
    np.testing.assert_array_equal(y[3:6], x[3:6])


def test_kabsch_initialisation(setup):
    skel, u, Hm, _, _ = setup
    rng = np.random.default_rng(3)
    x = np.zeros(skel.n)
    x[:3] = rng.normal(0, 1, 3)
    x[3:6] = rng.normal(0, 1, 3)
    obs = Hm.positions(skel, u, x)
    vis = np.ones(len(obs))
    x0 = marker_fit.initial_pose(skel, u, Hm, obs, vis)
    np.testing.assert_allclose(Hm.positions(skel, u, x0), obs, atol=1e-10)
    with pytest.raises(ValueError, match="fewer than 3"):
        marker_fit.initial_pose(skel, u, Hm, obs, np.r_[1, 1, np.zeros(len(obs) - 2)])
