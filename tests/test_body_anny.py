"""Our numpy Anny forward against anny's own (torch) forward, and the exported shape space."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from body import forward, load_model, rest_state
from body.anny import betas_from_anny, coefficients
from body.rotations import rodrigues


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


@pytest.fixture(scope="module")
def anny_model():
    """anny itself, rebuilt from the compact-model file the exporter keeps in ANNY_CACHE_DIR."""
    torch = pytest.importorskip("torch")
    from body import anny_export, anny_paths

    os.environ.setdefault("ANNY_CACHE_DIR", str(anny_paths.DEFAULT_CACHE_DIR))
    import anny.paths

    anny.paths.set_anny_cache_path(os.environ["ANNY_CACHE_DIR"])
    from pathlib import Path

    if not anny_export.compact_cache_file(Path(os.environ["ANNY_CACHE_DIR"])).exists():
        pytest.skip("anny's compact-model cache is missing (run `make setup`)")
    t = time.time()
    m = anny_export.build_anny()
    if time.time() - t > 60:
        pytest.fail("anny was rebuilt from scratch: the exporter should keep its compact cache")
    torch.set_default_dtype(torch.float64)
    return m


def _random_body(model, rng, n):
    z = model.extras
    phen = rng.uniform(0, 1, (n, len(z["pheno_labels"])))
    local = rng.uniform(-1, 1, (n, len(z["local_change_labels"]))) * (rng.uniform(size=(n, 1)) < 0.7)
    return phen, local


def test_forward_matches_anny(model, anny_model):
    import torch

    rng = np.random.default_rng(0)
    n = 4
    phen, local = _random_body(model, rng, n)
    all_sliders = list(anny_model.local_change_labels)
    ours = [str(s) for s in model.extras["local_change_labels"]]
    local_full = np.zeros((n, len(all_sliders)))
    for i, s in enumerate(ours):
        local_full[:, all_sliders.index(s)] = local[:, i]
    J = model.num_joints
    pose = rng.normal(0, 0.35, (n, J, 3))
    pose[:, 0] = rng.normal(0, 0.3, (n, 3))
    Rg = rodrigues(rng.normal(0, 1.0, (n, 3)))
    T = rng.normal(0, 1.0, (n, 3))

    betas = betas_from_anny(model, phen, local)
    rest = rest_state(model, betas)
    out = forward(model, betas, pose, Rg, T)

    D = np.tile(np.eye(4), (n, J, 1, 1))
    D[:, :, :3, :3] = rodrigues(pose)
    D[:, 0, :3, :3] = Rg @ D[:, 0, :3, :3]
    D[:, 0, :3, 3] = rest.joints[:, 0] + T
    with torch.no_grad():
        ref = anny_model(
            pose_parameters=torch.as_tensor(D),
            phenotype_kwargs=torch.as_tensor(phen),
            local_changes_kwargs=torch.as_tensor(local_full),
        )
    np.testing.assert_allclose(rest.vertices, ref["rest_vertices"].numpy(), atol=1e-7)
    np.testing.assert_allclose(rest.joints, ref["rest_bone_heads"].numpy(), atol=1e-7)
    err_v = np.abs(out.vertices - ref["vertices"].numpy()).max()
    err_j = np.abs(out.joints - ref["bone_poses"][..., :3, 3].numpy()).max()
    assert err_v < 1e-6 and err_j < 1e-6, (err_v, err_j)
    # world rotations: anny's bone pose orientation = G_j U_j
    np.testing.assert_allclose(out.joint_rot @ model.ref_orient[None], ref["bone_poses"][..., :3, :3].numpy(), atol=1e-9)


def test_smpl_convention_global_orient(model):
    """v_world = R (v_local - J0) + J0 + T for any shape and pose."""
    rng = np.random.default_rng(1)
    b = rng.normal(size=20)
    pose = rng.normal(0, 0.2, (1, model.num_joints, 3))
    R = rodrigues(rng.normal(size=(1, 3)))
    T = rng.normal(size=(1, 3))
    loc = forward(model, b, pose, np.eye(3)[None], np.zeros((1, 3)))
    w = forward(model, b, pose, R, T)
    J0 = rest_state(model, b).joints[0, 0]
    np.testing.assert_allclose(w.vertices[0], (loc.vertices[0] - J0) @ R[0].T + J0 + T[0], atol=1e-12)
    np.testing.assert_allclose(w.joints[0, 0], J0 + T[0], atol=1e-12)


def test_shape_space_exact_and_linear(model):
    """betas_from_anny is exact: c(betas) reproduces anny's coefficients; shapes are linear."""
    z = model.extras
    rng = np.random.default_rng(2)
    phen, local = _random_body(model, rng, 5)
    c = coefficients(phen, local, z)
    b = betas_from_anny(model, phen, local)
    np.testing.assert_allclose(z["coeff_mean"] + b @ z["coeff_basis"].T, c, atol=1e-9)
    # rest joints and vertices are affine in betas
    r = rest_state(model, np.stack([b[0], b[1], 0.3 * b[0] + 0.7 * b[1]]))
    np.testing.assert_allclose(r.vertices[2], 0.3 * r.vertices[0] + 0.7 * r.vertices[1], atol=1e-9)
    np.testing.assert_allclose(r.joints[2], 0.3 * r.joints[0] + 0.7 * r.joints[1], atol=1e-12)
    # the default phenotype (0.5 everywhere) is a plausible adult: 1.5 - 2.0 m tall
    v = rest_state(model, betas_from_anny(model, np.full(6, 0.5))).vertices[0]
    assert 1.5 < np.ptp(v[:, 2]) < 2.0


def test_export_stamp_and_bad_file(tmp_path, model):
    from body import anny_export, anny_paths
    from formats.errors import InputError

    assert not anny_export.is_stale(anny_paths.model_path())
    p = tmp_path / "anny_model.npz"
    np.savez(p, stamp=np.array("old"))
    assert anny_export.is_stale(p) and anny_export.is_stale(tmp_path / "missing.npz")
    assert anny_export.main(["--if-stale"]) == 0  # current file: no-op
    np.savez(p, v_template=model.v_template, faces=model.faces)
    with pytest.raises(InputError) as e:
        load_model("anny", p)
    assert e.value.field == "shapedirs" and str(p) in str(e.value)
    np.savez(p, v_template=model.v_template[:, :2])
    with pytest.raises(InputError, match="v_template"):
        load_model("anny", p)
