"""studio.truth: the studio's ground truth in the CHI3D layout, and the evaluate stage on a
tiny hand-made release/truth pair (no pipeline run)."""
from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from body import forward, load_model
from body.rotations import rodrigues
from calib.io import write_chi3d_cameras
from formats.anny_json import read_anny
from formats.chi3d import write_contact_signatures, write_joints3d_25
from studio.truth import ensure_truth, truth_files, write_chi3d_truth
from tests.test_evaluate import camera, people, signature

F = 3
ACTION = "Push 1"


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


def fake_session(root, model, subjects=("s01a", "s01b"), markers_on="s01b"):
    """A generated session's files that the truth writer reads: gt/<group>/<action>.npz (the
    studio's keys), gt/session.json, the session's calibration and contact file."""
    rng = np.random.default_rng(0)
    pose = 0.1 * rng.normal(size=(2, F, model.num_joints, 3))
    pose[:, :, 0] = 0
    R = rodrigues(rng.normal(0, 0.2, (2, F, 3)))
    T = np.array([[[-0.75, 0, 0.95]], [[0.75, 0, 0.95]]]) + rng.normal(0, 0.01, (2, F, 3))
    betas = rng.normal(0, 0.5, (2, 4))
    verts = np.stack([forward(model, betas[p], pose[p], R[p], T[p]).vertices for p in range(2)])
    (root / "gt" / "s01").mkdir(parents=True)
    np.savez(root / "gt" / "s01" / f"{ACTION}.npz", subjects=np.array(subjects), betas=betas,
             body_pose=pose, global_orient=R, transl=T, vertices=verts.astype(np.float32),
             frames=np.arange(F), contact_start=0, contact_end=2, contact_frame=1)
    write_joints3d_25(root / "gt" / "s01" / "joints3d_25" / f"{ACTION}.json", people(rng, F))
    (root / "gt" / "session.json").write_text(json.dumps(
        {"sequences": {f"s01/{ACTION}": {"markers_on": markers_on}}}))
    write_chi3d_cameras(root / "s01", ACTION, [camera()])
    write_contact_signatures(root / "s01" / "interaction_contact_signature.json",
                             {ACTION: signature(1, 0, 2)})
    return verts


def test_truth_in_chi3d_layout_person0_wears_markers(tmp_path, model):
    verts = fake_session(tmp_path, model)              # npz order s01a, s01b; wearer s01b
    written = write_chi3d_truth(tmp_path, model)
    g = tmp_path / "gt" / "s01"
    assert set(written) == set(truth_files(tmp_path)) and len(written) == 4
    a = read_anny(g / "anny" / f"{ACTION}.json")
    assert a["body_pose"].shape == (2, F, model.num_joints, 3, 3)
    assert a["betas"].shape == (2, F, 4)
    # person 0 = the wearer = the npz's person 1: posing it gives that person's mesh
    from body.rotations import rotmat_to_rotvec
    pose, orient = rotmat_to_rotvec(a["body_pose"]), a["global_orient"]
    v0 = forward(model, a["betas"][0, 0], pose[0], orient[0], a["transl"][0]).vertices
    np.testing.assert_allclose(v0, verts[1], atol=1e-5)
    valid = json.loads((g / "valid" / f"{ACTION}.json").read_text())
    assert np.array(valid["valid"]).all() and np.shape(valid["valid"]) == (2, F)
    assert (g / "camera_parameters" / "50591643" / f"{ACTION}.json").read_bytes() == \
        (tmp_path / "s01" / "camera_parameters" / "50591643" / f"{ACTION}.json").read_bytes()
    assert (g / "interaction_contact_signature.json").is_file()
    # idempotent: nothing rewritten; ensure_truth restores only what is missing
    assert write_chi3d_truth(tmp_path, model) == []
    assert ensure_truth(tmp_path) == []
    (g / "valid" / f"{ACTION}.json").unlink()
    assert ensure_truth(tmp_path) == [g / "valid" / f"{ACTION}.json"]
    assert not list(g.rglob(".*tmp*")) and not list(g.rglob("*.build"))


def test_truth_scores_zero_against_itself_on_the_anny_mesh(tmp_path, model):
    from evaluate import evaluate_folders
    fake_session(tmp_path, model)
    write_chi3d_truth(tmp_path, model)
    s = evaluate_folders(tmp_path / "gt", tmp_path / "gt")["sequences"][f"s01/{ACTION}"]
    assert s["vertices"]["mesh"] == "anny"
    assert all(v == pytest.approx(0, abs=1e-9) for v in s["all"].values())
    assert s["contact_frames"] == 3


def test_truth_missing_wearer_is_an_error(tmp_path, model):
    from formats.errors import InputError
    fake_session(tmp_path, model, markers_on="s09x")
    with pytest.raises(InputError, match="marker wearer 's09x'") as e:
        write_chi3d_truth(tmp_path, model)
    assert e.value.field == "subjects"


def test_evaluate_stage_on_a_hand_made_release(tmp_path, model):
    from pipeline.store import Writer
    from stages import evaluate as E
    fake_session(tmp_path, model)
    write_chi3d_truth(tmp_path, model)
    g = tmp_path / "gt" / "s01"
    rel = tmp_path / "release" / "s01"
    for sub in ("joints3d_25", "anny", "camera_parameters"):
        shutil.copytree(g / sub, rel / sub)
    j = json.loads((g / "joints3d_25" / f"{ACTION}.json").read_text())["joints3d_25"]
    write_joints3d_25(rel / "joints3d_25" / f"{ACTION}.json", np.array(j) + [0.0, 0.0, 0.02])
    (rel / "valid").mkdir()
    (rel / "valid" / f"{ACTION}.json").write_text(json.dumps(
        {"valid": [[True, True, False], [True, True, True]], "reason": [[""] * 3] * 2,
         "frames": [0, 1, 2]}))
    # what the release stage adds: manifest, datasheet and its verified re-read record
    # (evaluate scores only a verified release: artifacts.Release)
    from artifacts import Release

    root = tmp_path / "release"
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    (root / "MANIFEST.sha256").write_text("")
    (root / "datasheet.md").write_text("# hand-made\n")
    (root / "datasheet.json").write_text(json.dumps({
        "session": "s", "subjects": ["a", "b"], "sequences_not_exported": [],
        "sequences": {f"s01/{ACTION}": {"frames": 3, "persons": ["a", "b"]}},
        "totals": {"sequences": 1, "frames": 3, "person_frames": 6, "person_frames_not_valid": 1,
                   "not_valid_by_reason": {"too_few_markers": 1}}}))
    Release(ok=True, files_checked=len(files), files={f: "hand" for f in files}).save(Writer(root))
    recipe = SimpleNamespace(stages={"evaluate": {"truth": "gt"}}, source=tmp_path / "r.yaml",
                             body_model=SimpleNamespace(kind="anny", path=None))
    raw = E.raw_inputs(recipe, "session")
    assert f"truth:s01/anny/{ACTION}.json" in raw and "body_model" in raw
    assert not any(k.endswith(".npz") or "session.json" in k for k in raw)  # npz truth not read
    out = tmp_path / "art"
    out.mkdir()
    logs = []
    ctx = SimpleNamespace(inputs={"release": tmp_path / "release"}, raw=raw,
                          out=Writer(out), log=logs.append, params=E.Options(truth="gt"))
    E.run(ctx)
    r = json.loads((out / "evaluation.json").read_text())
    s = r["sequences"][f"s01/{ACTION}"]
    assert s["all"]["transl_err"] == pytest.approx(20.0)
    assert s["all"]["mpvpe"] == pytest.approx(0, abs=1e-6) and s["vertices"]["mesh"] == "anny"
    assert r["scored"][f"s01/{ACTION}"] == {
        "frames": 3, "frames_scored": 3, "frames_excluded": 0, "frames_not_published": 1,
        "frames_not_valid": 0, "person_frames_scored": 5, "person_frames_excluded": 1}
    md = (out / "evaluation.md").read_text()
    assert "| s01/Push 1 | 3 | 5/6 | 0 | 1 | 0 |" in md and "fr_id of person 0 only" in md
    assert any("1 not published" in x for x in logs)
    with pytest.raises(Exception, match="stages.evaluate.truth"):
        E.raw_inputs(SimpleNamespace(stages={"evaluate": {"truth": "nope"}}, source=recipe.source,
                                     body_model=recipe.body_model), "session")
