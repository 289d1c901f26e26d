"""The SMPL-family loader and the SMPL-X-schema file built from Anny, against the smplx package."""
from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse as sp

from body import forward, load_model, rest_state
from body.rotations import rodrigues
from body.smplfamily import (
    SMPLX_JOINTS,
    SMPLX_PARENTS,
    load_smpl_family,
    read_model_file,
    smplx_betas,
    smplx_pose,
)
from body.smplx_from_anny import ANNY_TO_SMPLX, smplx_from_anny_path
from formats.errors import InputError


@pytest.fixture(scope="module")
def smplx_path(anny):
    return smplx_from_anny_path(anny)  # cached in assets/build/smplx_from_anny/


@pytest.fixture(scope="module")
def model(smplx_path):
    return load_model("smplx", smplx_path)


def _random_inputs(rng, F):
    return dict(
        betas=rng.normal(size=(F, 10)), expression=rng.normal(size=(F, 10)),
        global_orient=rng.normal(0, 1, (F, 3)), transl=rng.normal(0, 1, (F, 3)),
        body_pose=rng.normal(0, 0.4, (F, 21, 3)), jaw_pose=rng.normal(0, 0.2, (F, 3)),
        leye_pose=rng.normal(0, 0.2, (F, 3)), reye_pose=rng.normal(0, 0.2, (F, 3)),
        left_hand_pose=rng.normal(0, 0.4, (F, 15, 3)), right_hand_pose=rng.normal(0, 0.4, (F, 15, 3)),
    )


@pytest.mark.slow
def test_forward_equals_smplx_package(model, smplx_path):
    torch = pytest.importorskip("torch")
    smplx = pytest.importorskip("smplx")
    rng = np.random.default_rng(0)
    F = 3
    x = _random_inputs(rng, F)
    layer = smplx.SMPLX(str(smplx_path.parent), ext="npz", use_pca=False, flat_hand_mean=True,
                        num_betas=10, num_expression_coeffs=10, dtype=torch.float64, batch_size=F)
    with torch.no_grad():
        ref = layer(**{k: torch.as_tensor(v.reshape(F, -1)) for k, v in x.items()})
    b = smplx_betas(model, x["betas"], x["expression"])
    pose = smplx_pose(x["body_pose"], x["jaw_pose"], x["leye_pose"], x["reye_pose"],
                      x["left_hand_pose"], x["right_hand_pose"])
    out = forward(model, b, pose, rodrigues(x["global_orient"]), x["transl"])
    ev = np.abs(out.vertices - ref.vertices.numpy()).max()
    ej = np.abs(out.joints - ref.joints[:, :55].numpy()).max()
    assert ev < 1e-6 and ej < 1e-6, (ev, ej)
    # the pose correctives matter here (the test would not see a posedirs bug otherwise)
    assert np.abs(model.posedirs).max() > 1e-4


@pytest.mark.slow
def test_file_schema_and_rerig(model, smplx_path, anny):
    raw = read_model_file(smplx_path)
    for k in ("v_template", "f", "weights", "J_regressor", "kintree_table", "shapedirs", "posedirs",
              "hands_componentsl", "hands_componentsr", "hands_meanl", "hands_meanr",
              "lmk_faces_idx", "lmk_bary_coords"):
        assert k in raw, k
    assert smplx_path.name.startswith("SMPLX_")
    assert raw["shapedirs"].shape[2] == 20 and raw["posedirs"].shape[2] == 486
    assert model.joint_names == SMPLX_JOINTS and len(model.fit_joints) == 52
    assert tuple(model.parents[:4]) == (-1, 0, 0, 0) and model.parents[15] == 12
    # J_regressor puts each joint at its Anny anchor joint (reference posture, betas 0)
    a0 = forward(anny, np.zeros(1), np.zeros((1, anny.num_joints, 3)), np.eye(3)[None], np.zeros((1, 3)))
    for name in ("left_knee", "right_wrist", "spine3", "left_index2"):
        anchor = ANNY_TO_SMPLX[name][0]
        np.testing.assert_allclose(model.joint_template[model.joint_index(name)],
                                   a0.joints[0, anny.joint_index(anchor)], atol=1e-5)
    # the re-rigged model follows Anny's own skinning; the fitted correctives help
    rng = np.random.default_rng(5)
    px = np.zeros((4, 55, 3))
    px[:, 1:22] = rng.normal(0, 0.35, (4, 21, 3))
    pa = np.zeros((4, anny.num_joints, 3))
    for j, n in enumerate(SMPLX_JOINTS):
        if ANNY_TO_SMPLX[n][0] is not None:
            pa[:, anny.joint_index(ANNY_TO_SMPLX[n][0])] = px[:, j]
    I4, O4 = np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3))
    va = forward(anny, np.zeros(1), pa, I4, O4).vertices
    vx = forward(model, np.zeros(1), px, I4, O4).vertices
    from dataclasses import replace

    vn = forward(replace(model, posedirs=np.zeros_like(model.posedirs)), np.zeros(1), px, I4, O4).vertices
    e_with = np.linalg.norm(va - vx, axis=-1).mean()
    e_without = np.linalg.norm(va - vn, axis=-1).mean()
    assert e_with < 0.01 and e_with < 0.8 * e_without, (e_with, e_without)


def _write_pkl(path, z, chumpy_keys=(), sparse_keys=()):
    """A .pkl as distributed: some arrays as chumpy objects, J_regressor as scipy.sparse."""
    mod = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

        def __reduce__(self):
            return (object.__new__, (Ch,), {"x": self.x})

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    mod.Ch = Ch
    sys.modules["chumpy"] = types.ModuleType("chumpy")
    sys.modules["chumpy.ch"] = mod
    try:
        d = {k: (Ch(v) if k in chumpy_keys else sp.csc_matrix(v) if k in sparse_keys else v)
             for k, v in z.items()}
        with open(path, "wb") as f:
            pickle.dump(d, f, protocol=2)
    finally:
        del sys.modules["chumpy.ch"], sys.modules["chumpy"]


@pytest.fixture()
def tiny(tmp_path):
    """A small random but valid SMPL-X-schema model (60 vertices) as a dict of arrays."""
    rng = np.random.default_rng(9)
    V = 60
    W = rng.uniform(size=(V, 55)) ** 8
    Jr = rng.uniform(size=(55, V))
    return {
        "v_template": rng.normal(size=(V, 3)), "f": rng.integers(0, V, (80, 3)),
        "weights": W / W.sum(1, keepdims=True), "J_regressor": Jr / Jr.sum(1, keepdims=True),
        "kintree_table": np.stack([np.array(SMPLX_PARENTS) % 2 ** 32, np.arange(55)]).astype(np.uint32),
        "shapedirs": rng.normal(0, 0.01, (V, 3, 20)), "posedirs": rng.normal(0, 0.01, (V, 3, 486)),
        "hands_componentsl": np.eye(45), "hands_componentsr": np.eye(45),
        "hands_meanl": np.zeros(45), "hands_meanr": np.zeros(45),
        "lmk_faces_idx": np.zeros(0, dtype=np.int64), "lmk_bary_coords": np.zeros((0, 3)),
    }


def test_pkl_with_chumpy_and_sparse_loads_the_same(tiny, tmp_path):
    (tmp_path / "a").mkdir()
    np.savez(tmp_path / "a" / "SMPLX_NEUTRAL.npz", **tiny)
    p = tmp_path / "SMPLX_NEUTRAL.pkl"
    _write_pkl(p, tiny, chumpy_keys=("shapedirs", "posedirs", "v_template"), sparse_keys=("J_regressor",))
    assert "chumpy" not in sys.modules
    m1 = load_smpl_family(tmp_path / "a" / "SMPLX_NEUTRAL.npz")
    m2 = load_smpl_family(p)
    rng = np.random.default_rng(2)
    pose = rng.normal(0, 0.3, (1, 55, 3))
    b = rng.normal(size=20)
    o1 = forward(m1, b, pose, np.eye(3)[None], np.zeros((1, 3)))
    o2 = forward(m2, b, pose, np.eye(3)[None], np.zeros((1, 3)))
    np.testing.assert_allclose(o1.vertices, o2.vertices, atol=1e-12)
    assert np.abs(o1.vertices).max() > 0.1
    # a folder finds the file
    assert load_model("smplx", tmp_path).source == str(p)


@pytest.mark.slow
def test_smpl_and_smplh_files(model, smplx_path, tmp_path):
    """SMPL (24 joints) and SMPL+H (52) files derived from the SMPL-X one load as such."""
    z = read_model_file(smplx_path)
    W, Jr, par = z["weights"], z["J_regressor"], z["kintree_table"][0].astype(np.int64)
    keep = [j for j in range(55) if j not in (22, 23, 24)]  # SMPL+H: drop jaw and eyes
    Wh = W[:, keep].copy()
    Wh[:, 15] += W[:, 22:25].sum(1)  # their skin goes to the head
    idx = {j: i for i, j in enumerate(keep)}
    parh = np.array([par[j] if j == 0 else idx[par[j]] for j in keep])
    pd = z["posedirs"].reshape(-1, 3, 54, 9)[:, :, [j - 1 for j in keep[1:]]].reshape(-1, 3, 51 * 9)
    zh = dict(z, weights=Wh, J_regressor=Jr[keep], kintree_table=np.stack([parh, np.arange(52)]),
              posedirs=pd, shapedirs=z["shapedirs"][:, :, :10])
    np.savez(tmp_path / "SMPLH_NEUTRAL.npz", **zh)
    mh = load_smpl_family(tmp_path / "SMPLH_NEUTRAL.npz")
    assert mh.name == "smplh" and mh.num_joints == 52 and mh.num_expression == 0
    ps = np.zeros((1, 52, 3))
    ps[0, 1:22] = np.random.default_rng(3).normal(0, 0.3, (21, 3))
    px = np.zeros((1, 55, 3))
    px[0, 1:22] = ps[0, 1:22]
    # no jaw/eye pose: the SMPL+H body equals the SMPL-X one
    oh = forward(mh, np.zeros(10), ps, np.eye(3)[None], np.zeros((1, 3)))
    ox = forward(model, np.zeros(20), px, np.eye(3)[None], np.zeros((1, 3)))
    np.testing.assert_allclose(oh.vertices, ox.vertices, atol=1e-6)
    with pytest.raises(InputError, match="smplh model, not smplx"):
        load_smpl_family(tmp_path / "SMPLH_NEUTRAL.npz", kind="smplx")


def test_load_model_dispatches_by_kind(tiny, tmp_path):
    """body.loaders.load_model: an exact kind must match the file, 'smpl-family' takes the
    file's own, an unknown kind is refused by name."""
    p = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(p, **tiny)
    assert load_model("SMPLX", p).name == "smplx"
    assert load_model("smpl-family", p).name == "smplx"
    with pytest.raises(InputError, match="smplx model, not smplh") as e:
        load_model("smplh", p)
    assert e.value.field == "kintree_table" and str(p) in str(e.value)
    with pytest.raises(ValueError, match="unknown body model kind 'ghum'"):
        load_model("ghum", p)


def test_a_model_file_is_read_once_per_process_until_it_changes(tiny, tmp_path):
    """body.loaders.load_model keeps what it read: the same file again is the same (frozen,
    read-only) object, whether named by its path or its folder; a file rewritten in place (same
    name, same size) is read anew, and so is a copy elsewhere."""
    p = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(p, **tiny)
    a = load_model("smplx", p)
    assert load_model("smplx", tmp_path) is a
    assert not a.v_template.flags.writeable
    z = dict(tiny, v_template=tiny["v_template"] + 0.5)
    size = p.stat().st_size
    np.savez(p, **z)
    assert p.stat().st_size == size
    b = load_model("smplx", p)
    assert b is not a
    np.testing.assert_allclose(b.v_template, a.v_template + 0.5)
    (tmp_path / "copy").mkdir()
    np.savez(tmp_path / "copy" / "SMPLX_NEUTRAL.npz", **z)
    c = load_model("smplx", tmp_path / "copy")
    assert c is not b and c.source != b.source


@pytest.mark.parametrize("edit,key", [
    (lambda z: z.pop("weights"), "weights"),
    (lambda z: z.__setitem__("J_regressor", z["J_regressor"][:, :50]), "J_regressor"),
    (lambda z: z.__setitem__("shapedirs", z["shapedirs"][:, :, :15]), "shapedirs"),
    (lambda z: z.__setitem__("posedirs", z["posedirs"][:, :, :400]), "posedirs"),
    (lambda z: z.__setitem__("v_template", z["v_template"][:, :2]), "v_template"),
])
def test_bad_files_name_file_and_key(tiny, tmp_path, edit, key):
    z = dict(tiny)
    edit(z)
    p = tmp_path / "SMPLX_NEUTRAL.npz"
    np.savez(p, **z)
    with pytest.raises(InputError) as e:
        load_smpl_family(p)
    assert str(p) in str(e.value) and e.value.field == key


def test_missing_path(monkeypatch, tmp_path):
    monkeypatch.delenv("SMPLX_MODEL_PATH", raising=False)
    with pytest.raises(InputError, match="SMPLX_MODEL_PATH"):
        load_model("smplx")
    monkeypatch.setenv("SMPLX_MODEL_PATH", str(tmp_path))
    with pytest.raises(InputError, match="no model file"):
        load_model("smplx")
    (tmp_path / "SMPLX_NEUTRAL.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read"):
        load_model("smplx")


@pytest.mark.slow
def test_surface_points_on_smplx(model):
    """The fit's surface points (fitting/skinned.py) on an SMPL-X model equal the numpy forward
    without pose correctives exactly (the reduced fit graph leaves them out, a documented
    approximation) and stay within a few mm of the forward with them."""
    import dataclasses

    from body.markers import make_markerset, marker_positions
    from fitting import skinned

    rng = np.random.default_rng(4)
    b = rng.normal(size=20)
    rest = rest_state(model, b)
    skel = skinned.fit_skeleton(model)
    assert len(skel.joints) == 52
    u, _ = skinned.reduced_offsets(model, rest, skel)
    faces = rng.choice(len(model.faces), 8, replace=False)
    ms = make_markerset([f"m{i}" for i in range(8)], faces, rng.dirichlet(np.ones(3), 8), 0.0095)
    pts = skinned.surface_coeffs(model, rest, skel,
                                 skinned.SurfacePoints(ms.faces, ms.bary, ms.offsets))
    x = rng.normal(0, 0.2, skel.n)
    pose = np.zeros((1, 55, 3))
    pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
    R, T = rodrigues(x[:3])[None], x[3:6][None]
    flat = dataclasses.replace(model, posedirs=None)
    want = marker_positions(forward(flat, b, pose, R, T).vertices[0], model.faces, ms)
    np.testing.assert_allclose(pts.positions(skel, u, x), want, atol=1e-10)
    full = marker_positions(forward(model, b, pose, R, T).vertices[0], model.faces, ms)
    assert 0 < np.abs(full - want).max() < 0.02


@pytest.mark.slow
def test_smplx_joint_sets(model):
    from body.joints import keypoints, regressor
    from formats.skeletons import H36M17

    out = forward(model, np.zeros(20), np.zeros((1, 55, 3)), np.eye(3)[None], np.zeros((1, 3)))
    h36 = keypoints(model, out, "joints3d_25")[0]
    j = out.joints[0]
    np.testing.assert_allclose(h36[H36M17.index("l_knee")], j[model.joint_index("left_knee")])
    np.testing.assert_allclose(h36[0], j[0])
    assert np.argmax(h36[:17, 2]) == H36M17.index("head")
    with pytest.raises(ValueError, match="not defined on this mesh"):
        regressor(model, "kp65")  # nose, eyes, ... need SMPL-X's own topology
