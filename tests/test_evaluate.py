"""The CHI3D benchmark evaluator (`evaluate/`) on small hand-made folders written with the
`formats.chi3d` / `calib.io` writers."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import procrustes
from scipy.spatial.transform import Rotation

from calib.camera import look_at
from calib.io import write_chi3d_cameras
from evaluate import evaluate_folders
from evaluate import metrics as M
from evaluate.__main__ import main
from formats.chi3d import ContactSignature, write_contact_signatures, write_joints3d_25
from formats.errors import InputError

F = 10
ACTION = "Hug 1"
NON_PELVIS = slice(1, None)


def camera():
    return look_at("50591643", centre=(0.0, -5.0, 1.2), target=(0.0, 0.0, 1.0),
                   f=(1000.0, 1000.0), c=(450.0, 450.0), width=900, height=900)


def people(rng, frames=F) -> np.ndarray:
    """(2, F, 25, 3): two distinct random skeletons 1.5 m apart, moving a little."""
    out = []
    for x in (-0.75, 0.75):
        base = rng.uniform([-0.25, -0.15, 0.0], [0.25, 0.15, 1.7], (25, 3)) + [x, 0.0, 0.0]
        base[0] = [x, 0.0, 0.95]
        drift = np.cumsum(rng.normal(0, 0.01, (frames, 1, 3)), axis=0)
        out.append(base[None] + drift + rng.normal(0, 0.005, (frames, 25, 3)))
    return np.stack(out)


def write_seq(root, joints, action=ACTION, subject="s01", contact=None, valid=None,
              vertices=None, cams=True):
    d = root / subject
    write_joints3d_25(d / "joints3d_25" / f"{action}.json", joints)
    if cams:
        write_chi3d_cameras(d, action, [camera()])
    if contact is not None:
        write_contact_signatures(d / "interaction_contact_signature.json", contact)
    if valid is not None:
        (d / "valid").mkdir(parents=True, exist_ok=True)
        (d / "valid" / f"{action}.json").write_text(json.dumps({"valid": valid.tolist()}))
    if vertices is not None:
        (d / "vertices").mkdir(parents=True, exist_ok=True)
        np.savez(d / "vertices" / f"{action}.npz", vertices=vertices[0], root=vertices[1])
    return d


def signature(fr_id, start=None, end=None):
    return ContactSignature(fr_id=fr_id, smplx_regions=np.zeros((0, 2), np.int64),
                            smplx_faces=np.zeros((0, 2), np.int64), start_fr=start, end_fr=end)


def meshes(rng, joints):
    """Fake posed meshes (P, F, 40, 3) riding on each person's pelvis, and their root."""
    local = rng.normal(0, 0.3, (2, 1, 40, 3))
    root = joints[:, :, 0] + [0.0, 0.0, 0.05]
    return local + root[:, :, None, :], root


def seq_figures(result, name=f"s01/{ACTION}"):
    return result["sequences"][name]


# ------------------------------------------------------------------------------------ metrics
def test_procrustes_matches_scipy_and_refuses_reflections():
    rng = np.random.default_rng(0)
    Y = rng.normal(size=(14, 3))
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    X = (0.7 * Y @ R.T + [1.0, 2.0, -0.5]) + rng.normal(0, 0.02, Y.shape)
    Xh = M.similarity_procrustes(X, Y)
    sse = ((Xh - Y) ** 2).sum()
    _, _, disparity = procrustes(Y, X)          # scipy standardises both: SSE / |Y - mean|^2
    assert sse == pytest.approx(disparity * ((Y - Y.mean(0)) ** 2).sum(), rel=1e-9)
    # exact similarity -> exact recovery, batched over leading axes
    Xs = np.stack([2.0 * Y @ R + 3.0, 0.5 * Y @ R.T - 1.0])
    np.testing.assert_allclose(M.similarity_procrustes(Xs, np.stack([Y, Y])), np.stack([Y, Y]),
                               atol=1e-12)
    # a mirror image is not a similarity: scipy (reflections allowed) gets 0, we do not
    mirror = Y * [-1.0, 1.0, 1.0]
    assert procrustes(Y, mirror)[2] < 1e-20
    assert M.mean_distance(M.similarity_procrustes(mirror, Y), Y) > 0.1


def test_match_people_hungarian_three_people():
    gt = np.array([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10]], float)
    perm = [2, 0, 1]
    pred = gt[perm] + 1.0                             # pred person i is true person perm[i]
    order = M.match_people(pred[None], gt[None])
    assert order[0].tolist() == [1, 2, 0]             # true g <- predicted order[g]
    np.testing.assert_allclose(M.reorder_people(pred[:, None], order)[:, 0], gt + 1.0)
    assert M.box_iou(gt[0], gt[0] + [5, 0, 5, 0]) == pytest.approx(50 / 150)


# ---------------------------------------------------------------------------- folder protocol
def test_identical_folders_score_zero(tmp_path):
    rng = np.random.default_rng(1)
    j = people(rng)
    v = meshes(rng, j)
    for side in ("gt", "pred"):
        write_seq(tmp_path / side, j, contact={ACTION: signature(4, 2, 6)}, vertices=v)
    r = evaluate_folders(tmp_path / "pred", tmp_path / "gt")
    s = seq_figures(r)
    for g in ("all", "contact", "fr_id_person0"):
        assert all(s[g][m] == pytest.approx(0, abs=1e-9) for m in s[g]), (g, s[g])
    assert s["swapped_frames"] == 0 and s["frames"] == F and s["contact_frames"] == 5


def test_known_offsets(tmp_path):
    rng = np.random.default_rng(2)
    j = people(rng)
    write_seq(tmp_path / "gt", j, contact={ACTION: signature(4)})
    d = np.array([0.03, -0.04, 0.0])                   # 50 mm
    write_seq(tmp_path / "shift", j + d)               # a pure translation of everything
    s = seq_figures(evaluate_folders(tmp_path / "shift", tmp_path / "gt"))["all"]
    assert s["mpjpe"] == pytest.approx(0, abs=1e-9) and s["pa_mpjpe"] == pytest.approx(0, abs=1e-9)
    assert s["transl_err"] == pytest.approx(50.0)
    k = j.copy()
    k[:, :, NON_PELVIS] += [0.0, 0.0, 0.02]            # every joint but the pelvis: 20 mm
    write_seq(tmp_path / "limbs", k)
    s = seq_figures(evaluate_folders(tmp_path / "limbs", tmp_path / "gt"))["all"]
    assert s["mpjpe"] == pytest.approx(20.0) and s["transl_err"] == pytest.approx(0, abs=1e-9)
    assert 0 < s["pa_mpjpe"] < 20.0


def test_pa_removes_a_similarity_transform(tmp_path):
    rng = np.random.default_rng(3)
    j = people(rng)
    v, root = meshes(rng, j)
    write_seq(tmp_path / "gt", j, vertices=(v, root))
    R = Rotation.from_rotvec([0.0, 0.2, 0.4]).as_matrix()
    # per person about its own pelvis (keeps the two people apart, so matching is unchanged)
    c = j[:, :, :1]
    pj = 1.1 * (j - c) @ R.T + c + [0.05, 0.0, 0.0]
    pv = 1.1 * (v - c) @ R.T + c + [0.05, 0.0, 0.0]
    proot = 1.1 * (root - c[:, :, 0]) @ R.T + c[:, :, 0] + [0.05, 0.0, 0.0]
    write_seq(tmp_path / "pred", pj, vertices=(pv, proot))
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["swapped_frames"] == 0
    assert s["all"]["pa_mpjpe"] == pytest.approx(0, abs=1e-6)
    assert s["all"]["pa_mpvpe"] == pytest.approx(0, abs=1e-6)
    assert s["all"]["mpjpe"] > 10 and s["all"]["mpvpe"] > 10
    assert s["all"]["transl_err"] == pytest.approx(50.0)


def test_swapped_people_are_matched_back(tmp_path):
    rng = np.random.default_rng(4)
    j = people(rng)
    v = meshes(rng, j)
    write_seq(tmp_path / "gt", j, vertices=v)
    swap = np.zeros(F, bool)
    swap[[1, 2, 5, 9]] = True
    pj = np.where(swap[None, :, None, None], j[::-1], j)
    pv = (np.where(swap[None, :, None, None], v[0][::-1], v[0]),
          np.where(swap[None, :, None], v[1][::-1], v[1]))
    write_seq(tmp_path / "pred", pj, vertices=pv)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["swapped_frames"] == 4
    assert all(s["all"][m] == pytest.approx(0, abs=1e-9) for m in s["all"])
    # the swap was real: unmatched, the error would be the people's 1.5 m distance
    assert M.translation_error(pj, j).mean() > 0.5


def test_contact_frames_use_only_the_interval(tmp_path):
    rng = np.random.default_rng(5)
    j = people(rng)
    write_seq(tmp_path / "gt", j, contact={ACTION: signature(4, 3, 5)})
    k = j.copy()
    k[:, 3:6, NON_PELVIS] += [0.02, 0.0, 0.0]           # error inside the interval only
    k[1, 4, NON_PELVIS] += [0.01, 0.0, 0.0]             # person 1 at fr_id: +10 mm more
    write_seq(tmp_path / "in", k)
    s = seq_figures(evaluate_folders(tmp_path / "in", tmp_path / "gt"))
    assert s["contact"]["mpjpe"] == pytest.approx((5 * 20 + 30) / 6)
    assert s["all"]["mpjpe"] == pytest.approx((5 * 20 + 30) / (2 * F))
    assert s["fr_id_person0"]["mpjpe"] == pytest.approx(20.0)   # the public *_c convention
    k = j.copy()
    k[:, [0, 1, 7, 8], NON_PELVIS] += [0.0, 0.03, 0.0]  # error outside only
    write_seq(tmp_path / "out", k)
    s = seq_figures(evaluate_folders(tmp_path / "out", tmp_path / "gt"))
    assert s["contact"]["mpjpe"] == pytest.approx(0, abs=1e-9)
    assert s["all"]["mpjpe"] == pytest.approx(30.0 * 4 / F)


def test_invalid_frames_are_excluded_and_counted(tmp_path):
    rng = np.random.default_rng(6)
    j = people(rng)
    valid = np.ones((2, F), bool)
    valid[1, [2, 3]] = False
    valid[0, 3] = False
    write_seq(tmp_path / "gt", j, valid=valid)
    k = j.copy()
    k[1, [2, 3], NON_PELVIS] += 0.5                    # garbage where the truth is not valid
    k[0, 3, NON_PELVIS] += 0.5
    k[0, 6, NON_PELVIS] += [0.0, 0.0, 0.017]
    write_seq(tmp_path / "pred", k)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["frames_not_valid"] == 2 and s["person_frames_not_valid"] == 3
    assert s["all"]["mpjpe"] == pytest.approx(17.0 / 17)


def test_sequences_weigh_the_same(tmp_path):
    rng = np.random.default_rng(7)
    ja, jb = people(rng, 10), people(rng, 30)
    write_seq(tmp_path / "gt", ja, action="Grab 1")
    write_seq(tmp_path / "gt", jb, action="Push 2", subject="s02")
    write_seq(tmp_path / "pred", ja + [0.01, 0, 0], action="Grab 1")
    write_seq(tmp_path / "pred", jb + [0.03, 0, 0], action="Push 2", subject="s02")
    r = evaluate_folders(tmp_path / "pred", tmp_path / "gt")
    assert set(r["sequences"]) == {"s01/Grab 1", "s02/Push 2"}
    assert r["overall"]["all"]["transl_err"] == pytest.approx(20.0)  # not 25 (frame-weighted)
    assert r["overall"]["frames"] == 40
    assert r["overall"]["all"]["mpvpe"] is None
    assert all("vertex metrics not computed" in s["notes"][0] for s in r["sequences"].values())
    assert all(s["contact"]["mpjpe"] is None for s in r["sequences"].values())


def test_vertices_from_smplx_without_a_model_are_not_faked(tmp_path, monkeypatch):
    monkeypatch.delenv("SMPLX_MODEL_PATH", raising=False)
    from formats.chi3d import SMPLX_SHAPES, write_smplx
    rng = np.random.default_rng(8)
    j = people(rng, 4)  # F = 3 trips formats.chi3d (transl (2, 3, 3) taken for rotations)
    params = {k: np.broadcast_to(np.eye(3) if t[-2:] == (3, 3) else np.zeros(t), (2, 4, *t))
              for k, t in SMPLX_SHAPES.items()}
    for side in ("gt", "pred"):
        write_seq(tmp_path / side, j)
        write_smplx(tmp_path / side / "s01" / "smplx" / f"{ACTION}.json", params)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["all"]["mpvpe"] is None and s["all"]["pa_mpvpe"] is None
    assert "no SMPL-X model file" in s["notes"][0] and "smplx/Hug 1.json" in s["notes"][0]


# ---------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("case", ["missing_action", "wrong_shape", "one_person", "frames",
                                  "vertices_shape"])
def test_bad_prediction_names_file_and_field(tmp_path, case):
    rng = np.random.default_rng(9)
    j = people(rng)
    write_seq(tmp_path / "gt", j)
    write_seq(tmp_path / "gt", j, action="Kick 3")
    pred = tmp_path / "pred"
    bad = pred / "s01" / "joints3d_25" / f"{ACTION}.json"
    field, match = "joints3d_25", None
    write_seq(pred, j, action="Kick 3", cams=False)
    if case == "missing_action":
        bad.parent.mkdir(parents=True, exist_ok=True)
        match = "missing: the truth has action 'Hug 1'"
    elif case == "wrong_shape":
        bad.write_text(json.dumps({"joints3d_25": j[:, :, :24].tolist()}))
        match = r"expected shape \(P, F, 25, 3\)"
    elif case == "one_person":
        write_seq(pred, j[:1], cams=False)
        match = "person axis of 1, the truth has 2 people"
    elif case == "frames":
        write_seq(pred, j[:, :7], cams=False)
        match = "7 frames, the truth has 10"
    else:
        v, root = meshes(rng, j)
        write_seq(pred, j, vertices=(v[:, :4], root), cams=False)
        bad, field, match = pred / "s01" / "vertices" / f"{ACTION}.npz", "vertices", "expected shape"
    with pytest.raises(InputError, match=match) as e:
        evaluate_folders(pred, tmp_path / "gt")
    assert e.value.file == str(bad) and e.value.field == field


def test_cli_table_json_and_errors(tmp_path, capsys):
    rng = np.random.default_rng(10)
    j = people(rng)
    write_seq(tmp_path / "gt", j, contact={ACTION: signature(4, 2, 6)})
    write_seq(tmp_path / "pred", j + [0.0, 0.0, 0.012])
    assert main([str(tmp_path / "pred"), str(tmp_path / "gt")]) == 0
    out = capsys.readouterr().out
    assert "| s01/Hug 1 | 10 | 20/20 | 0 | 0 | 0 | 0.0 | 0.0 | 12.0 | n/c | n/c |" in out
    assert "fr_id of person 0 only" in out
    assert "mean over sequences" in out
    r = json.loads((tmp_path / "pred" / "evaluation.json").read_text())
    assert r["overall"]["contact"]["transl_err"] == pytest.approx(12.0)
    assert r["protocol"]["units"] == "mm"
    (tmp_path / "pred" / "s01" / "joints3d_25" / f"{ACTION}.json").unlink()
    assert main([str(tmp_path / "pred"), str(tmp_path / "gt"), "--json", str(tmp_path / "e.json")]) == 2
    err = capsys.readouterr().err
    assert "pred/s01/joints3d_25/Hug 1.json: joints3d_25: missing" in err
    assert not (tmp_path / "e.json").exists()


@pytest.mark.slow
def test_vertices_from_smplx_match_the_smplx_layer_and_score(tmp_path):
    """The public evaluator poses SMPL-X with ``smplx.build_layer``; our posing of a CHI3D
    ``smplx/<action>.json`` must give its vertices; then MPVPE through the model folder path."""
    smplx = pytest.importorskip("smplx")
    torch = pytest.importorskip("torch")
    from body import load_model
    from body.smplx_from_anny import smplx_from_anny_path
    from evaluate.folders import vertices_from_smplx
    from formats.chi3d import SMPLX_SHAPES, write_smplx

    path = smplx_from_anny_path()
    rng = np.random.default_rng(11)
    P, Fs = 2, 4
    params = {}
    for k, t in SMPLX_SHAPES.items():
        if t[-2:] == (3, 3):
            params[k] = Rotation.from_rotvec(rng.normal(0, 0.2, (P * Fs * t[0], 3))).as_matrix() \
                .reshape(P, Fs, *t)
        else:
            params[k] = rng.normal(0, 0.5, (P, Fs, *t))
    params["transl"][1] += [1.5, 0.0, 0.0]
    ours = vertices_from_smplx(load_model("smplx", path), params, "memory")
    layer = smplx.build_layer(str(path), model_type="smplx", num_betas=10,
                              num_expression_coeffs=10, ext="npz", dtype=torch.float64)
    for p in range(P):
        with torch.no_grad():
            ref = layer(**{k: torch.as_tensor(v[p]) for k, v in params.items()})
        np.testing.assert_allclose(ours.vertices[p], ref.vertices.numpy(), atol=1e-6)
        np.testing.assert_allclose(ours.root[p], ref.joints[:, 0].numpy(), atol=1e-6)
    # folders: truth and prediction as smplx/ files; a translated prediction has MPVPE 0
    j = people(rng, Fs)
    shifted = dict(params, transl=params["transl"] + [0.0, 0.04, 0.0])
    for side, prm in (("gt", params), ("pred", shifted)):
        write_seq(tmp_path / side, j)
        write_smplx(tmp_path / side / "s01" / "smplx" / f"{ACTION}.json", prm)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt", smplx_model=path))
    assert s["all"]["mpvpe"] == pytest.approx(0, abs=1e-6)
    assert s["vertices"]["truth"].endswith("smplx/Hug 1.json")
    write_smplx(tmp_path / "pred" / "s01" / "smplx" / f"{ACTION}.json",
                dict(params, betas=params["betas"] + 0.5))
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt", smplx_model=path))
    assert s["all"]["mpvpe"] > 1.0 and s["all"]["pa_mpvpe"] < s["all"]["mpvpe"]


def test_cameras_from_the_prediction_when_the_truth_has_none(tmp_path):
    rng = np.random.default_rng(12)
    j = people(rng)
    write_seq(tmp_path / "gt", j, cams=False)
    write_seq(tmp_path / "pred", j[::-1], cams=False)
    with pytest.raises(InputError, match="matching needs a camera") as e:
        evaluate_folders(tmp_path / "pred", tmp_path / "gt")
    assert e.value.field == "camera_parameters"
    write_seq(tmp_path / "pred", j[::-1])
    r = evaluate_folders(tmp_path / "pred", tmp_path / "gt")
    s = seq_figures(r)
    assert s["swapped_frames"] == F and s["all"]["mpjpe"] == pytest.approx(0, abs=1e-9)


# ----------------------------------------------------------------- release-side additions (#17)
def anny_params(model, rng, F_, P=2):
    from body.rotations import rodrigues
    J = model.num_joints
    pose = 0.1 * rng.normal(size=(P, F_, J, 3))
    pose[:, :, 0] = 0.0
    return dict(transl=rng.normal(0, 0.3, (P, F_, 3)) + [[[-0.75, 0, 0.95]], [[0.75, 0, 0.95]]][:P],
                global_orient=rodrigues(rng.normal(0, 0.2, (P, F_, 3))),
                body_pose=rodrigues(pose), betas=np.zeros((P, F_, 4)),
                joint_names=list(model.joint_names))


def test_vertices_from_anny_files_on_both_sides(tmp_path):
    from body import load_model
    from formats.anny_json import write_anny
    model = load_model("anny")
    rng = np.random.default_rng(11)
    j = people(rng, 3)
    a = anny_params(model, rng, 3)
    for side in ("gt", "pred"):
        write_seq(tmp_path / side, j)
        write_anny(tmp_path / side / "s01" / "anny" / f"{ACTION}.json", **a)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["vertices"]["mesh"] == "anny"
    assert s["all"]["mpvpe"] == pytest.approx(0, abs=1e-9)
    b = dict(a, transl=a["transl"] + [0.1, 0.0, 0.0])  # centred on joint 0: no vertex error
    write_anny(tmp_path / "pred" / "s01" / "anny" / f"{ACTION}.json", **b)
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["all"]["mpvpe"] == pytest.approx(0, abs=1e-6)
    bp = a["body_pose"].copy()
    bp[:, :, 1:] = np.swapaxes(bp[:, :, 1:], -1, -2)   # inverted local rotations
    write_anny(tmp_path / "pred" / "s01" / "anny" / f"{ACTION}.json", **dict(a, body_pose=bp))
    r = evaluate_folders(tmp_path / "pred", tmp_path / "gt")
    assert seq_figures(r)["all"]["mpvpe"] > 5.0
    assert "vertex metrics on: anny" in __import__("evaluate").markdown(r)
    # the prediction without an anny file: not compared across meshes
    (tmp_path / "pred" / "s01" / "anny" / f"{ACTION}.json").unlink()
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["all"]["mpvpe"] is None and s["vertices"]["mesh"] is None


def test_frames_not_published_by_the_prediction_are_counted_not_scored(tmp_path):
    rng = np.random.default_rng(12)
    j = people(rng)
    write_seq(tmp_path / "gt", j, contact={ACTION: signature(4, 2, 6)})
    frames = np.arange(2, 9)                           # the release holds truth frames 2..8
    k = j[:, frames].copy()
    pub = np.ones((2, len(frames)), bool)
    pub[1, 0] = False                                  # truth frame 2, person 1: not published
    k[1, 0, NON_PELVIS] += 0.5                         # garbage there
    k[0, 3, NON_PELVIS] += [0.0, 0.0, 0.013]           # truth frame 5, person 0: 13 mm
    d = write_seq(tmp_path / "pred", k)
    (d / "valid").mkdir()
    (d / "valid" / f"{ACTION}.json").write_text(json.dumps(
        {"valid": pub.tolist(), "reason": [[""] * 7] * 2, "frames": frames.tolist()}))
    s = seq_figures(evaluate_folders(tmp_path / "pred", tmp_path / "gt"))
    assert s["frames"] == 7 and s["person_frames_scored"] == 13
    assert s["frames_not_published"] == 1 and s["person_frames_not_published"] == 1
    assert s["all"]["mpjpe"] == pytest.approx(13.0 / 13)
    assert s["contact_frames"] == 5                   # truth frames 2..6
    assert s["fr_id_person0"]["mpjpe"] == pytest.approx(0, abs=1e-9)  # truth frame 4
    assert any("not published" in n for n in s["notes"])
    bad = write_seq(tmp_path / "late", j[:, :3])
    (bad / "valid").mkdir()
    (bad / "valid" / f"{ACTION}.json").write_text(json.dumps({"valid": [[True] * 3] * 2,
                                                              "frames": [8, 9, 10]}))
    with pytest.raises(InputError, match="beyond the truth's 10 frames") as e:
        evaluate_folders(tmp_path / "late", tmp_path / "gt")
    assert e.value.field == "frames" and e.value.frame == 2
