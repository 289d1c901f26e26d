"""The ``export`` and ``release`` stages on small fake upstream artifacts (a filmed two-person
sequence on a stride, a marker-only one): every exported file read back through its reader
equals what was written, frames that are not valid are marked with their reason, the SMPL-X
contact facets come from convert's correspondence (regions from ours or the official map),
the release's manifest verifies (``sha256sum -c`` too), its datasheet lists the frames that
are not valid and why, and a tampered file is caught by the re-read pass."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

CAMS = ("50591643", "58860488")
NT = 60  # facets of the fake SMPL-X target mesh


def _rot(rng, *shape):
    from body.rotations import rodrigues

    return rodrigues(rng.normal(0, 0.3, shape + (3,)))


class _Art:
    """A completed artifact in a folder (what the engine hands a stage)."""

    def __init__(self, d: Path):
        from pipeline.store import StoredArtifact

        self._a = StoredArtifact(Path(d), "k", "u", "s", {})
        self.dir = Path(d)

    def arrays(self, name):
        return self._a.arrays(name)

    def json(self, name):
        return self._a.json(name)

    def path(self, f):
        return self._a.path(f)


def _writer(d: Path):
    from pipeline.store import Writer

    d.mkdir(parents=True, exist_ok=True)
    return Writer(d)


def _fit(model, rng, frames, reasons, d: Path, markers=False) -> _Art:
    from artifacts import BodyFit

    F, J = len(frames), model.num_joints
    reasons = np.asarray(reasons, np.int8)
    pose = rng.normal(0, 0.05, (F, J, 3))
    pose[:, 0] = 0
    M = 3
    fit = BodyFit(body_pose=pose, global_orient=_rot(rng, F), transl=rng.normal(0, 0.3, (F, 3)),
                  betas=rng.normal(0, 0.5, 12), frames=np.asarray(frames, np.int64),
                  valid=reasons == 0, invalid_reason=reasons,
                  **({} if not markers else dict(
                      marker_names=np.array(["A", "B", "C"]),
                      marker_residual_m=np.full((F, M), 0.001), marker_weight=np.ones((F, M)),
                      visible=np.ones((F, M), bool))))
    w = _writer(d)
    fit.save(w)
    from artifacts import INVALID_REASONS, FitSummary

    FitSummary(fit="marker_fit" if markers else "partner_fit", subject="x", frames=F,
               frames_valid=int((reasons == 0).sum()),
               frames_not_valid={r: int((reasons == c).sum()) for c, r in enumerate(INVALID_REASONS)
                                 if c},
               figures={"residual_mm": {"median": 1.5, "p90": 3.0}, "fit_cpu_s": 1.0,
                        "reprojection_px": {"median": 4.0}}).save(w)
    return _Art(d)


def _convert(rng, frames, P, valid, d: Path, n_src_faces: int) -> _Art:
    F = len(frames)
    w = _writer(d)
    sm = {"transl": rng.normal(0, 0.3, (P, F, 3)), "global_orient": _rot(rng, P, F),
          "body_pose": _rot(rng, P, F, 21), "left_hand_pose": _rot(rng, P, F, 15),
          "right_hand_pose": _rot(rng, P, F, 15), "jaw_pose": _rot(rng, P, F),
          "leye_pose": _rot(rng, P, F), "reye_pose": _rot(rng, P, F),
          "betas": rng.normal(0, 1, (P, 10)), "expression": rng.normal(0, 1, (P, 10)),
          "frames": np.asarray(frames, np.int64), "valid": np.asarray(valid, bool),
          "v2s_mm": np.full((P, F), 2.0), "subjects": np.array(["a", "b"][:P])}
    from artifacts import ConversionReport, SMPLXFit, SurfaceCorrespondence
    from artifacts.smplx_fit import PersonConversion, TargetInfo

    SMPLXFit(**sm).save(w)

    def bary(n):
        b = rng.uniform(0.1, 1, (n, 3))
        return b / b.sum(1, keepdims=True)

    Vt, Vs = 40, 30  # vertices of the fake target and source meshes
    SurfaceCorrespondence(
        tgt_vert_face=rng.integers(0, n_src_faces, Vt), tgt_vert_bary=bary(Vt),
        src_vert_face=rng.integers(0, NT, Vs), src_vert_bary=bary(Vs),
        src_face_tgt_face=rng.integers(0, NT, n_src_faces),
        tgt_face_src_face=rng.integers(0, n_src_faces, NT), tgt_faces=rng.integers(0, Vt, (NT, 3)),
        src_faces=rng.integers(0, Vs, (n_src_faces, 3))).save(w)
    ConversionReport(
        sequence="g/a", target=TargetInfo("SMPLX_NEUTRAL.npz", "0" * 64, "smplx", Vt, True,
                                          "stand-in"),
        correspondence_key="k", registered_now=False,
        per_person=tuple(PersonConversion(s, 2.0, 3.0, 5.0, F) for s in ["a", "b"][:P]),
        fps_per_core=F * P / 0.1, cpu_s=0.1, registration_cpu_s=0.0).save(w)
    return _Art(d)


def _video(path: Path, n: int) -> Path:
    from formats.video import write_mp4

    # frame i: a flat grey of level 40 * i + 20 (survives mp4v compression as a mean)
    return write_mp4(path, [np.full((32, 32, 3), 40 * i + 20, np.uint8) for i in range(n)], 10.0)


def _ctx(stage, unit, tree, params, inputs, raw, out: Path):
    from pipeline.spec import RecipeView, StageContext

    return StageContext(stage=stage, unit=unit, recipe=RecipeView(tree, stage), params=params,
                        inputs=inputs, raw=raw, out=_writer(out),
                        progress=lambda it, total=None, desc="": it, log=lambda s: None)


@pytest.fixture(scope="module")
def world(tmp_path_factory, anny):
    """Two exported sequences: ``g1/Hug 1`` (two persons, two cameras, partner on a stride of
    2: frames 0, 2, 4 of 5; frames not valid in both persons, one not converted) and
    ``g2/Walk 1`` (marker-only, P = 1, no video, no contact, no text)."""
    from body.regions import region_map
    from calib.camera import Camera
    from stages import export as E

    tmp = tmp_path_factory.mktemp("exp")
    rng = np.random.default_rng(3)
    model = anny
    bm = Path(__file__).resolve().parents[1] / "assets" / "build" / "anny_model.npz"
    # ---- sequence 1: filmed, two persons
    mf = _fit(model, rng, range(5), [0, 0, 2, 0, 0], tmp / "mf1", markers=True)
    pf = _fit(model, rng, [0, 2, 4], [0, 0, 5], tmp / "pf1")
    cv = _convert(rng, [0, 2, 4], 2, [[False, True, True], [True, True, True]], tmp / "cv1",
                  len(model.faces))
    raw = {"body_model": bm}
    cams = {}
    for i, c in enumerate(CAMS):
        cams[c] = Camera(name=c, f=np.array([500.0, 510]), c=np.array([16.0, 15]),
                         k=np.array([0.01, -0.002, 0.0]), p=np.array([0.001, 0.0005]),
                         R=_rot(rng), T=np.array([1.0 + i, 2.0, 1.5]), width=32, height=32)
        raw[f"video:{c}"] = _video(tmp / "vid" / c / "Hug 1.mp4", 5)
    from artifacts.capture import CameraRig

    cap = tmp / "capture1"  # the cameras as the capture stage hands them on
    CameraRig.from_cameras(list(cams.values()), [f"{c}.json" for c in cams]).save(_writer(cap))
    rmap = region_map(model)
    faces = np.array([[100, 2000], [5000, 7000]])
    regions = rmap.region_of(faces)
    sig = {"Hug 1": {"fr_id": 2, "start_fr": 1, "end_fr": 3,
                     "smplx_signature": {"region_id": [], "face_id": []},
                     "anny_signature": {"region_id": regions.tolist(), "face_id": faces.tolist()}},
           "Other 2": {"fr_id": 0, "smplx_signature": {"region_id": [], "face_id": []}}}
    raw["contact"] = tmp / "contact.json"
    raw["contact"].write_text(json.dumps(sig))
    tree = {"body_model": {"kind": "anny"}, "cameras": list(CAMS),
            "sequence": {"fps": 10.0, "text": "A hugs B.", "markers_on": "a", "partner": "b",
                         "has_video": True}}
    ex1 = tmp / "ex1"
    E.run(_ctx("export", "g1/Hug 1", tree, E.Options(), {
        "marker_fit": mf, "partner_fit": pf, "convert": cv, "shape_fit": {}, "capture": cap},
        raw, ex1))
    # ---- sequence 2: marker-only
    mf2 = _fit(model, rng, range(10, 14), [1, 0, 0, 2], tmp / "mf2", markers=True)
    cv2 = _convert(rng, range(10, 14), 1, [[True] * 4], tmp / "cv2", len(model.faces))
    tree2 = {"body_model": {"kind": "anny"}, "cameras": list(CAMS),
             "sequence": {"fps": None, "text": "", "markers_on": "c", "partner": None,
                          "has_video": False}}
    ex2 = tmp / "ex2"
    E.run(_ctx("export", "g2/Walk 1", tree2, E.Options(), {
        "marker_fit": mf2, "convert": cv2, "shape_fit": {}}, {"body_model": bm}, ex2))
    return {"tmp": tmp, "model": model, "mf": mf, "pf": pf, "cv": cv, "raw": raw, "cams": cams,
            "faces": faces, "regions": regions, "rmap": rmap, "tree": tree, "ex1": ex1,
            "ex2": ex2, "mf2": mf2, "cv2": cv2, "bm": bm}


def test_export_round_trip_of_every_file(world):
    from artifacts import BodyFit
    from body import forward
    from body.joints import keypoints
    from body.rotations import rodrigues
    from calib.io import read_chi3d_cameras
    from formats import anny_json, chi3d
    from formats import release as R
    from formats.video import VideoReader
    from stages.export import smplx_release

    g = world["ex1"] / "g1"
    model = world["model"]
    fits = [BodyFit.load(world["mf"]), BodyFit.load(world["pf"])]
    idx = [np.array([0, 2, 4]), np.array([0, 1, 2])]
    # SMPL-X: convert's parameters in the CHI3D shapes, betas repeated per frame
    sm = chi3d.read_smplx(g / "smplx" / "Hug 1.json")
    want = smplx_release(world["cv"].arrays("smplx"), 2)
    for k, v in want.items():
        np.testing.assert_allclose(sm[k], v, atol=1e-12, err_msg=k)
    assert sm["betas"].shape == (2, 3, 10) and sm["global_orient"].shape == (2, 3, 1, 3, 3)
    np.testing.assert_allclose(sm["betas"][:, 2], world["cv"].arrays("smplx")["betas"])
    # Anny: the fits at the exported frames, rotation matrices
    an = anny_json.read_anny(g / "anny" / "Hug 1.json")
    for p, (f, i) in enumerate(zip(fits, idx, strict=True)):
        np.testing.assert_allclose(an["transl"][p], f.transl[i], atol=1e-12)
        np.testing.assert_allclose(an["global_orient"][p], f.global_orient[i], atol=1e-12)
        np.testing.assert_allclose(an["body_pose"][p], rodrigues(f.body_pose[i]), atol=1e-12)
        np.testing.assert_allclose(an["betas"][p, 1], f.betas, atol=1e-12)
    assert list(an["joint_names"]) == list(model.joint_names)
    # joints3d_25 from the fitted mesh, person 0 = the marker wearer
    j = chi3d.read_joints3d_25(g / "joints3d_25" / "Hug 1.json")
    assert j.shape == (2, 3, 25, 3)
    for p, (f, i) in enumerate(zip(fits, idx, strict=True)):
        out = forward(model, f.betas, f.body_pose[i], f.global_orient[i], f.transl[i])
        np.testing.assert_allclose(j[p], keypoints(model, out, "joints3d_25"), atol=1e-9)
    # cameras as given
    cams = read_chi3d_cameras(g, "Hug 1", size=(32, 32))
    assert sorted(cams) == sorted(CAMS)
    for c, cam in cams.items():
        ref = world["cams"][c]
        for a in ("R", "T", "f", "c", "k", "p"):
            np.testing.assert_allclose(getattr(cam, a), getattr(ref, a), atol=1e-12, err_msg=a)
    # videos cut to the exported frames 0, 2, 4 of the source, at the stride's rate
    for c in CAMS:
        with VideoReader(world["raw"][f"video:{c}"]) as v:
            src = np.array([float(v[i].mean()) for i in range(5)])
        with VideoReader(g / "videos" / c / "Hug 1.mp4") as v:
            assert len(v) == 3 and v.info.fps == pytest.approx(5.0)
            cut = np.array([float(v[i].mean()) for i in range(3)])
        assert np.argmin(np.abs(cut[:, None] - src[None]), axis=1).tolist() == [0, 2, 4]
    # validity: reasons of the fits at the exported frames, and the frame not converted
    va = R.read_valid(g / "valid" / "Hug 1.json")
    np.testing.assert_array_equal(va["frames"], [0, 2, 4])
    assert va["reason"].tolist() == [["not_converted", "too_few_markers", "fitted"],
                                     ["fitted", "fitted", "poor_reprojection"]]
    np.testing.assert_array_equal(va["valid"], [[False, False, True], [True, True, False]])
    # text and contact: only this action
    assert R.read_text_annotations(g / "text_annotations.json") == {"Hug 1": "A hugs B."}
    sigs = chi3d.read_contact_signatures(g / "interaction_contact_signature.json")
    assert list(sigs) == ["Hug 1"]
    # frames 1..3 with contact at 2 on the exported frames [0, 2, 4]: interval 1..1, frame 1
    s = sigs["Hug 1"]
    assert (s.fr_id, s.start_fr, s.end_fr) == (1, 1, 1)
    np.testing.assert_array_equal(s.anny_faces, world["faces"])
    np.testing.assert_array_equal(s.anny_regions, world["regions"])
    rep = json.loads((world["ex1"] / "export.json").read_text())
    assert rep["contact"]["original_frames"] == {"fr_id": 2, "start_fr": 1, "end_fr": 3}
    assert rep["person_frames_not_valid"] == 3 and rep["frames"] == 3
    fig = json.loads((world["ex1"] / "figures.json").read_text())
    assert fig["marker_fit"]["residual_mm"]["median"] == 1.5
    assert fig["convert"]["per_person"][1]["v2s_median_mm"] == 2.0


def test_marker_only_export_has_one_person_and_says_what_is_absent(world):
    from formats import chi3d
    from formats import release as R

    g = world["ex2"] / "g2"
    assert chi3d.read_joints3d_25(g / "joints3d_25" / "Walk 1.json").shape == (1, 4, 25, 3)
    assert chi3d.read_smplx(g / "smplx" / "Walk 1.json")["transl"].shape == (1, 4, 3)
    va = R.read_valid(g / "valid" / "Walk 1.json")
    assert va["reason"].tolist() == [["held_before_first_marker", "fitted", "fitted",
                                      "too_few_markers"]]
    np.testing.assert_array_equal(va["frames"], [10, 11, 12, 13])
    assert not (g / "videos").exists() and not (g / "camera_parameters").exists()
    assert not (g / "text_annotations.json").exists()
    absent = json.loads((world["ex2"] / "export.json").read_text())["absent"]
    assert {"videos", "camera_parameters", "person 1", "interaction_contact_signature",
            "text_annotations"} <= set(absent)


def test_smplx_contact_facets_come_from_the_correspondence(world, tmp_path):
    from formats import chi3d
    from stages import export as E

    m = world["cv"].arrays("correspondence")["src_face_tgt_face"]
    s = chi3d.read_contact_signatures(world["ex1"] / "g1" / "interaction_contact_signature.json")
    s = s["Hug 1"]
    np.testing.assert_array_equal(s.smplx_faces, m[world["faces"]])
    # without the official map: the region of each Anny facet (our 75-region map)
    np.testing.assert_array_equal(s.smplx_regions, world["rmap"].region_of(world["faces"]))
    # with the official contact_regions.json: the region of each mapped SMPL-X facet
    official = np.arange(NT) % 5  # region r holds the facets with id % 5 == r
    cr = tmp_path / "contact_regions.json"
    cr.write_text(json.dumps({"rid_to_smplx_fids": [np.flatnonzero(official == r).tolist()
                                                   for r in range(5)]}))
    out = tmp_path / "ex"
    E.run(_ctx("export", "g1/Hug 1", world["tree"], E.Options(contact_regions=str(cr)), {
        "marker_fit": world["mf"], "partner_fit": world["pf"], "convert": world["cv"],
        "shape_fit": {}}, {**world["raw"], "contact_regions": cr}, out))
    s2 = chi3d.read_contact_signatures(out / "g1" / "interaction_contact_signature.json")["Hug 1"]
    np.testing.assert_array_equal(s2.smplx_faces, m[world["faces"]])
    np.testing.assert_array_equal(s2.smplx_regions, official[m[world["faces"]]])
    assert not np.array_equal(s2.smplx_regions, s.smplx_regions)


def _release(world, out: Path, exports=None):
    from stages import release as Rel

    tree = {"session": {"name": "lab", "subjects": ["a", "b", "c"], "sequences": {
        "g1/Hug 1": {"group": "g1", "action": "Hug 1", "has_video": True, "text": "A hugs B."},
        "g2/Walk 1": {"group": "g2", "action": "Walk 1", "has_video": False, "text": ""}}}}
    exports = exports or {"g1/Hug 1": _Art(world["ex1"]), "g2/Walk 1": _Art(world["ex2"])}
    Rel.run(_ctx("release", "session", tree, None, {"export": exports}, {}, out))
    return out


def test_release_manifest_verifies_and_datasheet_lists_invalid_frames(world, tmp_path):
    from formats import release as R
    from stages.release import verify_release

    rel = _release(world, tmp_path / "rel")
    assert R.verify_manifest(rel) == []
    listed = R.read_manifest(rel / R.MANIFEST_FILE)
    on_disk = {p.relative_to(rel).as_posix() for p in rel.rglob("*") if p.is_file()}
    assert set(listed) == on_disk - {R.MANIFEST_FILE}
    if shutil.which("sha256sum"):
        done = subprocess.run(["sha256sum", "-c", "--quiet", R.MANIFEST_FILE], cwd=rel,
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stdout + done.stderr
    ver = json.loads((rel / "verification.json").read_text())
    assert ver["ok"] and ver["problems"] == []
    assert ver["files"]["g1/videos/50591643/Hug 1.mp4"].endswith("(3 frames)")
    assert ver["files"]["g1/anny/Hug 1.json"] == "formats.anny_json.read_anny"
    assert verify_release(rel)["ok"]
    sheet = json.loads((rel / "datasheet.json").read_text())
    assert sheet["subjects"] == ["a", "b", "c"]
    assert sheet["interaction_classes"] == {"Hug": ["g1/Hug 1"], "Walk": ["g2/Walk 1"]}
    assert sheet["contact_events"] == 1
    t = sheet["totals"]
    assert (t["sequences"], t["frames"], t["person_frames"]) == (2, 7, 10)
    assert t["person_frames_not_valid"] == 5
    assert t["not_valid_by_reason"] == {"held_before_first_marker": 1, "not_converted": 1,
                                        "poor_reprojection": 1, "too_few_markers": 2}
    hug = sheet["sequences"]["g1/Hug 1"]
    assert hug["not_valid_frames"] == {"a": {"not_converted": [[0, 0]],
                                             "too_few_markers": [[2, 2]]},
                                       "b": {"poor_reprojection": [[4, 4]]}}
    assert sheet["sequences"]["g2/Walk 1"]["not_valid_frames"] == {
        "c": {"held_before_first_marker": [[10, 10]], "too_few_markers": [[13, 13]]}}
    assert hug["figures"]["marker_fit"]["residual_mm"]["median"] == 1.5
    md = (rel / "datasheet.md").read_text()
    assert "g1/Hug 1, b: poor_reprojection: 4" in md and "too_few_markers 2" in md
    # the groups' merged files
    assert json.loads((rel / "g1" / "text_annotations.json").read_text()) == {"Hug 1": "A hugs B."}


def test_tampered_files_are_caught_by_the_re_read_pass(world, tmp_path):
    from formats import release as R
    from formats.errors import InputError
    from stages.release import verify_release

    rel = _release(world, tmp_path / "rel")
    # a tampered release file: the manifest and the reader both say so, naming the file
    j = rel / "g1" / "joints3d_25" / "Hug 1.json"
    j.write_text(j.read_text()[:-40])
    res = verify_release(rel)
    assert not res["ok"]
    assert any(str(j) in p and "sha256" in p for p in res["problems"])
    assert any(str(j) in p and "JSON" in p for p in res["problems"])
    # an export whose file is corrupt: the release stage fails naming that file
    bad = tmp_path / "ex1"
    shutil.copytree(world["ex1"], bad)
    v = bad / "g1" / "valid" / "Hug 1.json"
    d = json.loads(v.read_text())
    d["valid"][0][0] = True  # valid, but the reason says not_converted
    v.write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        _release(world, tmp_path / "rel2", {"g1/Hug 1": _Art(bad), "g2/Walk 1": _Art(world["ex2"])})
    assert "valid" in str(e.value) and "Hug 1.json" in str(e.value)
    # a video whose frame count disagrees with its joints
    bad2 = tmp_path / "ex1b"
    shutil.copytree(world["ex1"], bad2)
    _video(bad2 / "g1" / "videos" / CAMS[0] / "Hug 1.mp4", 5)
    with pytest.raises(InputError, match="5 video frames, its joints3d_25 has 3"):
        _release(world, tmp_path / "rel3", {"g1/Hug 1": _Art(bad2), "g2/Walk 1": _Art(world["ex2"])})
    assert R.MANIFEST_FILE  # (the names are the module's)


def test_valid_mask_reader_rejects_bad_files(tmp_path):
    from formats import release as R
    from formats.errors import InputError

    p = R.write_valid(tmp_path / "v.json", [[True, False]], [["fitted", "too_few_markers"]], [3, 5])
    assert R.read_valid(p)["frames"].tolist() == [3, 5]
    for d, field in (({"valid": [[True, 1]], "reason": [["fitted", "x"]], "frames": [0, 1]},
                      "valid"),
                     ({"valid": [[True, False]], "reason": [["fitted", "fitted"]],
                       "frames": [0, 1]}, "reason"),
                     ({"valid": [[True, True]], "reason": [["fitted", "fitted"]],
                       "frames": [1, 1]}, "frames"),
                     ({"valid": [[True]], "reason": [["fitted"]]}, "frames")):
        p.write_text(json.dumps(d))
        with pytest.raises(InputError) as e:
            R.read_valid(p)
        assert e.value.field == field and e.value.file == str(p)


def test_export_and_release_are_registered():
    from stages import PLANNED, _stage

    st = {p[0]: _stage(*p) for p in PLANNED if p[0] in ("export", "release")}
    assert st["export"].implemented and st["release"].implemented
    assert st["release"].per == "session" and st["release"].upstream == ("export", "qa")


def test_release_into_a_relative_store_path(world, tmp_path, monkeypatch):
    """The engine's store root is relative by default (``outputs``): the release and its
    manifest are written and verified the same (the demo's path)."""
    from formats import release as R

    monkeypatch.chdir(tmp_path)
    rel = _release(world, Path("relative") / "rel")
    assert R.verify_manifest(rel) == []
    assert json.loads((rel / "verification.json").read_text())["ok"]


def test_typed_outputs_feed_release_and_evaluate(world, tmp_path, monkeypatch):
    """export's and release's outputs read back through their classes; ``evaluate`` scores
    the folder ``artifacts.Release`` names and refuses a release whose re-read pass failed."""
    import evaluate
    from artifacts import ArtifactError, Release, SequenceExport
    from stages import evaluate as Ev

    ex = SequenceExport.load(_Art(world["ex1"]))
    assert ex.persons == ("a", "b") and ex.valid_file == "g1/valid/Hug 1.json"
    assert ex.contact.event and ex.figures.marker_residual_median_mm() == 1.5
    assert all(p.is_file() for p in ex.paths().values())
    rel = _release(world, tmp_path / "rel")
    r = Release.load(_Art(rel))
    assert r.verified and r.root == rel and r.sheet.totals.frames == 7
    assert r.files_checked == len(r.files) > 0
    seen = []
    monkeypatch.setattr(evaluate, "evaluate_folders",
                        lambda pred, gt, **kw: seen.append((pred, gt)) or {"sequences": {}})
    monkeypatch.setattr(evaluate, "markdown", lambda result: "| table |")
    raw = {"truth:s01/joints3d_25/Hug 1.json": rel / "g1" / "joints3d_25" / "Hug 1.json"}
    Ev.run(_ctx("evaluate", "session", {"body_model": {"kind": "anny"}}, Ev.Options(truth="x"),
                {"release": _Art(rel)}, raw, tmp_path / "ev"))
    assert seen == [(rel, rel)]  # the release folder, and the truth root of the raw inputs
    v = json.loads((rel / "verification.json").read_text())
    v.update(ok=False, problems=["g1/x.json: broken"])
    (rel / "verification.json").write_text(json.dumps(v))
    with pytest.raises(ArtifactError, match="re-read pass"):
        Ev.run(_ctx("evaluate", "session", {"body_model": {"kind": "anny"}}, Ev.Options(truth="x"),
                    {"release": _Art(rel)}, raw, tmp_path / "ev2"))
