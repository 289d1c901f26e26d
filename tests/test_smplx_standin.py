"""The SMPL-X-schema stand-in target (body/smplx_standin.py): a mesh of its own, rigged like
SMPL-X, read by the smplx package exactly as by our forward, and still Anny's body."""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.spatial import cKDTree

from body import forward, load_model
from body.rotations import rodrigues
from body.smplfamily import SMPLX_JOINTS, SMPLX_PARENTS, read_model_file, smplx_betas, smplx_pose
from body.smplx_from_anny import ANNY_TO_SMPLX, smplx_from_anny_path
from body.smplx_standin import FILE_NAME, builder_stamp, is_stale, main, standin_path, surface_map


@pytest.fixture(scope="module")
def path(anny):
    return standin_path()  # cached in assets/build/smplx_standin/


@pytest.fixture(scope="module")
def model(path):
    return load_model("smplx", path)


def _anny_rest(anny):
    out = forward(anny, np.zeros(1), np.zeros((1, anny.num_joints, 3)), np.eye(3)[None], np.zeros((1, 3)))
    return out.vertices[0], np.asarray(anny.faces, dtype=np.int64)


def _dense(W):
    return W.toarray() if sp.issparse(W) else np.asarray(W)


def _random_inputs(rng, F):
    return dict(
        betas=rng.normal(size=(F, 10)), expression=rng.normal(size=(F, 10)),
        global_orient=rng.normal(0, 1, (F, 3)), transl=rng.normal(0, 1, (F, 3)),
        body_pose=rng.normal(0, 0.4, (F, 21, 3)), jaw_pose=rng.normal(0, 0.2, (F, 3)),
        leye_pose=rng.normal(0, 0.2, (F, 3)), reye_pose=rng.normal(0, 0.2, (F, 3)),
        left_hand_pose=rng.normal(0, 0.4, (F, 15, 3)), right_hand_pose=rng.normal(0, 0.4, (F, 15, 3)),
    )


def _ours(model, x):
    b = smplx_betas(model, x["betas"], x["expression"])
    pose = smplx_pose(x["body_pose"], x["jaw_pose"], x["leye_pose"], x["reye_pose"],
                      x["left_hand_pose"], x["right_hand_pose"])
    return forward(model, b, pose, rodrigues(x["global_orient"]), x["transl"])


def test_mesh_is_its_own(path, model, anny):
    """Own vertex count and triangulation, vertices off Anny's, a closed oriented surface with
    Anny's components (no finger welded to another), lying on Anny's surface."""
    Va, Fa = _anny_rest(anny)
    Vs, Fs = model.v_template, np.asarray(model.faces, dtype=np.int64)
    assert len(Vs) != len(Va) and len(Fs) != len(Fa)
    assert 9930 <= len(Vs) <= 11000  # smplx.SMPLX picks extra joints by vertex ids up to 9929
    d, _ = cKDTree(Va).query(Vs)
    assert (d > 5e-4).mean() >= 0.99, np.percentile(d, 1)
    m = trimesh.Trimesh(Vs, Fs, process=False)
    ma = trimesh.Trimesh(Va, Fa, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert abs(m.volume - ma.volume) < 0.01 * ma.volume, (m.volume, ma.volume)
    n_comp = len(trimesh.graph.connected_components(m.edges, nodes=np.arange(len(Vs))))
    assert n_comp == len(trimesh.graph.connected_components(ma.edges, nodes=np.arange(len(Va))))
    # on Anny's surface: vertices and facet centroids (a facet bridging two fingers would not be)
    _, _, dv = surface_map(Vs, Va, Fa)
    _, _, dc = surface_map(m.triangles_center, Va, Fa)
    assert np.median(dv) < 1e-3 and dv.max() < 5e-3 and dc.max() < 5e-3, (dv.max(), dc.max())
    W = _dense(model.weights)
    finger = np.isin(np.argmax(W, 1), np.arange(25, 55))
    in_hand = np.isin(Fs, np.flatnonzero(finger)).all(1)
    assert in_hand.sum() > 500 and dc[in_hand].max() < 2.5e-3, dc[in_hand].max()
    # no edge joins two different fingers beyond their first segments (those meet at the web)
    dom = np.argmax(W, 1)
    chain = np.where(finger, (dom - 25) // 3, -1)
    level = np.where(finger, (dom - 25) % 3, -1)
    e = m.edges_unique
    other = (chain[e[:, 0]] >= 0) & (chain[e[:, 1]] >= 0) & (chain[e[:, 0]] != chain[e[:, 1]])
    assert other.any()  # the webs: the test sees edges between fingers
    assert not np.any(other & (level[e].max(1) >= 1)), "an edge bridges two fingers"


def test_schema_joints_and_parents(path, model):
    raw = read_model_file(path)
    for k in ("v_template", "f", "weights", "J_regressor", "kintree_table", "shapedirs", "posedirs",
              "hands_componentsl", "hands_componentsr", "hands_meanl", "hands_meanr",
              "lmk_faces_idx", "lmk_bary_coords"):
        assert k in raw, k
    assert path.name == "SMPLX_NEUTRAL.npz"
    assert raw["shapedirs"].shape[1:] == (3, 20) and raw["posedirs"].shape[1:] == (3, 486)
    assert model.joint_names == SMPLX_JOINTS and len(model.joint_names) == 55
    assert tuple(model.parents) == SMPLX_PARENTS
    np.testing.assert_allclose(_dense(model.weights).sum(1), 1, atol=1e-5)
    assert np.abs(model.posedirs).max() > 1e-4  # pose correctives carried over


def test_smplx_package_equals_our_forward(path, model):
    torch = pytest.importorskip("torch")
    smplx = pytest.importorskip("smplx")
    rng = np.random.default_rng(0)
    F = 3
    x = _random_inputs(rng, F)
    layer = smplx.SMPLX(model_path=str(path.parent), ext="npz", use_pca=False, flat_hand_mean=True,
                        num_betas=10, num_expression_coeffs=10, dtype=torch.float64, batch_size=F)
    assert layer.v_template.shape[0] == model.num_vertices
    assert layer.parents.numpy().tolist()[1:] == list(SMPLX_PARENTS[1:])
    with torch.no_grad():
        ref = layer(**{k: torch.as_tensor(v.reshape(F, -1)) for k, v in x.items()})
    out = _ours(model, x)
    ev = np.abs(out.vertices - ref.vertices.numpy()).max()
    ej = np.abs(out.joints - ref.joints[:, :55].numpy()).max()
    assert ev < 1e-5 and ej < 1e-5, (ev, ej)
    assert np.abs(out.vertices - out.vertices.mean(1, keepdims=True)).max() > 0.3  # a real body


def test_build_layer_rotation_matrices(path, model, tmp_path):
    """``smplx.build_layer`` (SMPLXLayer: rotation matrices) from the file, and from a folder
    in smplx's ``<root>/smplx/SMPLX_NEUTRAL.npz`` layout."""
    torch = pytest.importorskip("torch")
    smplx = pytest.importorskip("smplx")
    (tmp_path / "smplx").mkdir()
    os.symlink(path, tmp_path / "smplx" / FILE_NAME)
    rng = np.random.default_rng(1)
    F = 2
    x = _random_inputs(rng, F)
    out = _ours(model, x)
    rot = {k: torch.as_tensor(rodrigues(v)) for k, v in x.items()
           if k not in ("betas", "expression", "transl")}
    kw = dict(num_betas=10, num_expression_coeffs=10, dtype=torch.float64)
    for where in (str(path), str(tmp_path)):
        layer = smplx.build_layer(where, model_type="smplx", ext="npz", **kw)
        assert type(layer).__name__ == "SMPLXLayer"
        with torch.no_grad():
            ref = layer(betas=torch.as_tensor(x["betas"]), expression=torch.as_tensor(x["expression"]),
                        transl=torch.as_tensor(x["transl"]), **rot)
        ev = np.abs(out.vertices - ref.vertices.numpy()).max()
        assert ev < 1e-5, (where, ev)


def test_standin_is_anny_rerigged(model, anny):
    """Posed like Anny (same joint rotations on the anchored joints), the stand-in lies on the
    posed Anny surface; its joints follow betas as the Anny-vertex SMPL-X file's do."""
    Fa = np.asarray(anny.faces, dtype=np.int64)
    rng = np.random.default_rng(5)
    n = 3
    px = np.zeros((n, 55, 3))
    pa = np.zeros((n, anny.num_joints, 3))
    for j, name in enumerate(SMPLX_JOINTS):
        anchor = ANNY_TO_SMPLX[name][0]
        if j > 0 and anchor is not None:
            px[:, j] = rng.normal(0, 0.35 if j < 22 else 0.3, (n, 3))
            pa[:, anny.joint_index(anchor)] = px[:, j]
    I, O = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    va = forward(anny, np.zeros(1), pa, I, O).vertices
    vs = forward(model, np.zeros(20), px, I, O).vertices
    med = []
    for i in range(n):
        _, _, d = surface_map(vs[i], va[i], Fa)
        med.append(np.median(d))
        assert np.percentile(d, 95) < 0.015, np.percentile(d, 95)
    assert max(med) < 0.010, med
    # a real pose: the posed body is far from the rest body
    assert np.abs(vs - model.v_template[None]).max() > 0.1
    # joints under random betas as in smplx_from_anny's file (the regressor follows shape)
    ref = load_model("smplx", smplx_from_anny_path(anny))
    b = rng.normal(size=(4, 20))
    for bi in b:
        js = forward(model, bi, np.zeros((1, 55, 3)), np.eye(3)[None], np.zeros((1, 3))).joints[0]
        jr = forward(ref, bi, np.zeros((1, 55, 3)), np.eye(3)[None], np.zeros((1, 3))).joints[0]
        assert np.abs(js - jr).max() < 1e-3, np.abs(js - jr).max()


def test_stale_file_is_rebuilt(path, tmp_path):
    """A file with another stamp is rebuilt (atomically, no temporary left); ``--if-stale``
    leaves a current one alone."""
    shutil.copy(path, tmp_path / FILE_NAME)
    assert not is_stale(tmp_path / FILE_NAME)
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d["build_stamp"] = np.array("0" * 16)
    np.savez(tmp_path / FILE_NAME, **d)
    assert is_stale(tmp_path / FILE_NAME)
    p = standin_path(tmp_path)
    with np.load(p) as z:
        assert str(z["build_stamp"]) == builder_stamp()
        np.testing.assert_array_equal(z["f"], read_model_file(path)["f"])  # deterministic build
    assert sorted(q.name for q in tmp_path.iterdir()) == [FILE_NAME]
    mtime = p.stat().st_mtime_ns
    assert main(["--if-stale", "--out", str(tmp_path)]) == 0
    assert p.stat().st_mtime_ns == mtime
