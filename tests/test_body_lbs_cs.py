"""The fit's symbolic skinning (one primitive: fitting/skinned.py surface points in
fitting/marker_graph.py's compiled graph) on Anny against the numpy peer body.lbs.forward +
body.markers.marker_positions: residuals (atol 1e-10) and Jacobian (central differences)."""
from __future__ import annotations

import numpy as np
import pytest

from body import forward, load_model, rest_state
from body.markers import marker_positions, plug_in_gait
from body.rotations import rodrigues
from fitting import compiled, skinned, terms
from fitting.marker_graph import (
    GraphSpec,
    MarkerGraph,
    marker_coeffs,
    marker_support,
    template_placement,
)


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


def test_fit_skeleton_is_compact(model):
    assert len(model.fit_joints) == 52 and model.fit_joints[0] == 0
    names = [model.joint_names[j] for j in model.fit_joints]
    assert not any(n.startswith(("toe", "metacarpal", "eye")) for n in names)


def test_marker_graph_equals_forward_and_its_jacobian(model):
    rng = np.random.default_rng(7)
    names = ["LFHD", "C7", "LELB", "RWRA", "LKNE", "RTOE"]
    ms = plug_in_gait(model).subset(names).with_offsets(rng.uniform(0.005, 0.02, 6))
    pl = template_placement(model, ms)
    betas = rng.normal(size=10)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    g = MarkerGraph(GraphSpec(skel.topology, marker_support(model, skel, pl)),
                    compiled.CompileOptions(mode="interpreted"))
    obs = rng.normal(0, 0.5, (6, 3))
    p = g.params(u, marker_coeffs(model, rest, skel, pl), obs, np.ones(6))
    assert g.dropped_weight < 1e-12

    def numpy_r(x):
        pose = np.zeros((1, model.num_joints, 3))
        pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
        out = forward(model, None, pose, rodrigues(x[:3])[None], x[3:6][None], rest=rest)
        return terms.L_3d(marker_positions(out.vertices[0], model.faces, ms), obs, np.ones(6))

    x = rng.normal(0, 0.3, skel.n)
    r, J = g.fun.dense(x, p)
    np.testing.assert_allclose(r, numpy_r(x), atol=1e-10)
    eps = 1e-6
    for c in rng.choice(skel.n, 40, replace=False):
        dx = np.zeros(skel.n)
        dx[c] = eps
        fd = (numpy_r(x + dx) - numpy_r(x - dx)) / (2 * eps)
        np.testing.assert_allclose(J[:, c], fd, atol=2e-7, err_msg=f"column {c}")
