"""CasADi slot LBS against the numpy forward (atol 1e-10) and its Jacobian against finite
differences of the numpy forward."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from body import forward, load_model, rest_state
from body.lbs import marker_lbs_cs, marker_params, slot_lbs_cs, slot_params, slot_spec
from body.markers import marker_positions, plug_in_gait
from body.rotations import rodrigues


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


def _full_pose(model, spec, pose_q):
    pose = np.zeros((1, model.num_joints, 3))
    pose[0, list(spec.fit_joints)] = pose_q
    return pose


def _call(f, args: dict):
    return f.call({k: ca.DM(v) for k, v in args.items()})


def test_fit_skeleton_is_compact(model):
    assert len(model.fit_joints) == 52 and model.fit_joints[0] == 0
    names = [model.joint_names[j] for j in model.fit_joints]
    assert not any(n.startswith(("toe", "metacarpal", "eye")) for n in names)


@pytest.mark.parametrize("num_betas", [0, 10])
def test_slots_match_numpy(model, num_betas):
    rng = np.random.default_rng(num_betas)
    spec = slot_spec(model, num_slots=16, num_betas=num_betas)
    f = slot_lbs_cs(model, spec)
    ids = rng.choice(model.num_vertices, 13, replace=False)  # 3 slots left unused
    betas = rng.normal(size=10)
    rest = rest_state(model, betas)
    p = slot_params(model, spec, ids, rest=rest)
    Q = len(spec.fit_joints)
    pose_q = rng.normal(0, 0.4, (Q, 3))
    rg, T = rng.normal(size=3), rng.normal(size=3)
    args = dict(p, pose=pose_q, global_orient=rg, transl=T)
    if num_betas:
        args["betas"] = betas
    r = _call(f, args)
    out = forward(model, betas, _full_pose(model, spec, pose_q), rodrigues(rg)[None], T[None], rest=rest)
    np.testing.assert_allclose(np.array(r["slots"])[:13], out.vertices[0, ids], atol=1e-10)
    np.testing.assert_allclose(np.array(r["joints"]), out.joints[0], atol=1e-10)
    # the same graph serves other vertices: only the parameters change
    ids2 = rng.choice(model.num_vertices, 16, replace=False)
    r2 = _call(f, dict(args, **slot_params(model, spec, ids2, rest=rest)))
    np.testing.assert_allclose(np.array(r2["slots"]), out.vertices[0, ids2], atol=1e-10)


def test_markers_and_jacobian_vs_finite_differences(model):
    rng = np.random.default_rng(7)
    ms = plug_in_gait(model).subset(["LFHD", "C7", "LELB", "RWRA", "LKNE", "RTOE"])
    S = 6
    spec = slot_spec(model, num_slots=3 * len(ms), num_betas=S)
    f = marker_lbs_cs(model, spec)
    betas = rng.normal(size=S)
    rest = rest_state(model, betas)
    p = marker_params(model, spec, ms, rest=rest)
    Q = len(spec.fit_joints)
    pose_q = rng.normal(0, 0.3, (Q, 3))
    rg, T = rng.normal(size=3), rng.normal(size=3)
    args = dict(p, pose=pose_q, global_orient=rg, transl=T, betas=betas)
    r = _call(f, args)

    def numpy_markers(pq, rgv, Tv, b):
        out = forward(model, b, _full_pose(model, spec, pq), rodrigues(rgv)[None], Tv[None],
                      rest=None if b is not betas else rest)
        return marker_positions(out.vertices[0], model.faces, ms)

    np.testing.assert_allclose(np.array(r["markers"]), numpy_markers(pose_q, rg, T, betas), atol=1e-10)

    # Jacobian w.r.t. (pose, global_orient, transl, betas) against central differences
    sym = {k: ca.SX.sym(k, *np.atleast_2d(v).shape) if np.ndim(v) == 2 else ca.SX.sym(k, np.size(v))
           for k, v in args.items()}
    outm = f.call(sym)["markers"]
    unknowns = ca.vertcat(ca.vec(sym["pose"]), sym["global_orient"], sym["transl"], sym["betas"])
    jac = ca.Function("jac_markers", list(sym.values()), [ca.jacobian(ca.vec(outm), unknowns)], list(sym.keys()), ["J"])
    Jc = np.array(jac.call({k: ca.DM(v) for k, v in args.items()})["J"])
    # the bind rotations are frozen in the graph: differentiate numpy with them frozen too
    def num(u):
        pq = u[: 3 * Q].reshape(3, Q).T  # ca.vec is column-major
        rgv, Tv, b = u[3 * Q: 3 * Q + 3], u[3 * Q + 3: 3 * Q + 6], u[3 * Q + 6:]
        rs = rest_state(model, b)
        rs = type(rs)(rs.vertices, rs.joints, rest.bind_rot, rs.offsets)
        par = model.parents
        off = rs.joints - rs.joints[:, np.maximum(par, 0)]
        Ap = rest.bind_rot[:, np.maximum(par, 0)].copy()
        Ap[:, par == 0] = np.eye(3)
        off = np.einsum("njxy,njy->njx", Ap, off)
        off[:, 0] = rs.joints[:, 0]
        rs = type(rs)(rs.vertices, rs.joints, rest.bind_rot, off)
        out = forward(model, b, _full_pose(model, spec, pq), rodrigues(rgv)[None], Tv[None], rest=rs)
        return marker_positions(out.vertices[0], model.faces, ms).T.ravel()  # column-major vec

    u0 = np.concatenate([pose_q.T.ravel(), rg, T, betas])
    eps = 1e-6
    cols = rng.choice(len(u0), 40, replace=False)
    for c in cols:
        du = np.zeros_like(u0)
        du[c] = eps
        fd = (num(u0 + du) - num(u0 - du)) / (2 * eps)
        np.testing.assert_allclose(Jc[:, c], fd, atol=2e-7, err_msg=f"column {c}")
