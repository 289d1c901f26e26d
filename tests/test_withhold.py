"""Frames are ground truth only when they are (issue #27 items 3 and 5): a frame whose QA flags
say the fit is wrong (``stages.export.withhold``, default ``qa.constants.FIT_WRONG``) is
published not valid with a ``qa:<reason>`` in ``valid/<action>.json``, for the person the
metric is about (both for a pair metric); input-side reasons (a repaired capture, a camera out
of sync) withhold nothing; ``export.json`` and the release's datasheet count what was withheld
and why.

The end-to-end test plants a 15 cm limb error into one frame of the partner on the small
studio session and runs the ``qa``, ``export`` and ``release`` stages' ``run`` functions on
it. The fits are the studio's truth (the fitted poses of a perfect fit: the stages' fits
would take minutes to compute) and the detections their KP65 keypoints projected into the
session's four cameras; the capture (markers, camera rig) comes from the ``capture`` stage
through the engine."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from test_export_release import _Art, _writer

# constants of the planted fault
PLANT_JOINT = "upperarm01.R"  # the limb turned (as bench/cases/qa.py's limb_rotation)
PLANT_ERROR_M = 0.15  # the wrist moves at least this far
PLANT_DEGREES = tuple(range(10, 95, 5))  # turns tried about the joint's local x, smallest first:
# the first that moves the wrist PLANT_ERROR_M is planted (an error of about 15 cm, not more)
QA_DRAWING_OFF = {"overlay_sample": 0, "overlay_max": 0, "video": False, "scene": False}


# ------------------------------------------------------------------------------- unit
def _metrics(frames, reasons, flags: dict):
    """A QAMetrics-like object: ``flags`` {reason: [frames flagged]}."""
    frames = np.asarray(frames)
    fl = np.zeros((len(frames), len(reasons)), bool)
    for r, fs in flags.items():
        for f in fs:
            fl[np.flatnonzero(frames == f)[0], reasons.index(r)] = True
    return SimpleNamespace(metrics=SimpleNamespace(frames=frames, reasons=np.array(reasons),
                                                   flagged=fl))


def test_partner_flags_withhold_the_partner_only_and_input_flags_nobody():
    from stages.export import DEFAULT_WITHHOLD, qa_withheld, validity

    frames = np.arange(10)
    qa = _metrics(frames, ["partner.reproj_views_body_px", "wearer.markers_repaired"],
                  {"partner.reproj_views_body_px": [3, 7], "wearer.markers_repaired": [5]})
    held = qa_withheld(qa, frames, ["wearer", "partner"], DEFAULT_WITHHOLD)
    valid, reason = validity(np.ones((2, 10), bool), np.zeros((2, 10), np.int8), None, held)
    assert valid[0].all(), reason[0]
    assert np.flatnonzero(~valid[1]).tolist() == [3, 7]
    assert reason[1, 3] == reason[1, 7] == "qa:reproj_views_body_px"
    assert set(reason[:, 5]) == {"fitted"}
    # listing the input-side reason withholds the wearer at 5 too; an empty list nothing
    held = qa_withheld(qa, frames, ["wearer", "partner"], ("markers_repaired",))
    assert np.argwhere(held != "").tolist() == [[0, 5]] and held[0, 5] == "qa:markers_repaired"
    assert (qa_withheld(qa, frames, ["wearer", "partner"], ()) == "").all()


def test_pair_reasons_withhold_both_and_the_fit_reason_comes_first():
    from artifacts import INVALID_REASONS
    from stages.export import DEFAULT_WITHHOLD, qa_withheld, validity

    frames = np.array([10, 12, 14, 16])
    qa = _metrics(frames, ["penetration_mm", "wearer.jerk_m_s3", "sync_offset_frames.cam1"],
                  {"penetration_mm": [12], "wearer.jerk_m_s3": [12, 16],
                   "sync_offset_frames.cam1": [10, 12, 14, 16]})
    held = qa_withheld(qa, frames, ["wearer", "partner"], DEFAULT_WITHHOLD)
    # frame 12: both (pair), the wearer's first reason in withhold's order; 16: the wearer only
    assert held[:, 1].tolist() == ["qa:penetration_mm", "qa:penetration_mm"]
    assert held[:, 3].tolist() == ["qa:jerk_m_s3", ""]
    assert (held[:, [0, 2]] == "").all()  # sync is input side
    later = ("jerk_m_s3",) + tuple(r for r in DEFAULT_WITHHOLD if r != "jerk_m_s3")
    assert qa_withheld(qa, frames, ["wearer", "partner"], later)[0, 1] == "qa:jerk_m_s3"
    # a frame the fit holds keeps the fit's reason; QA's reason before not_converted
    code = INVALID_REASONS.index("too_few_markers")
    valid, reason = validity(np.array([[True, False, True, True], [True] * 4]),
                             np.array([[0, code, 0, 0], [0] * 4]),
                             np.array([[True] * 4, [True, False, False, True]]), held)
    assert reason.tolist() == [["fitted", "too_few_markers", "fitted", "qa:jerk_m_s3"],
                               ["fitted", "qa:penetration_mm", "not_converted", "fitted"]]
    assert valid.tolist() == [[True, False, True, False], [True, False, False, True]]
    # frames QA did not measure are not withheld
    assert (qa_withheld(qa, np.array([11, 13]), ["wearer"], DEFAULT_WITHHOLD) == "").all()


def test_a_marker_fitted_wearer_is_withheld_by_its_own_reasons_not_the_video_fits():
    """trust_markers: the pair reasons and the cross-view reprojection fall on the person
    fitted from the video; the wearer's marker reasons and its other fit reasons still hold it
    back; with no video-fitted person (or trust_markers off) every reason withholds as before."""
    from types import SimpleNamespace as NS

    from qa import constants as K
    from stages.export import DEFAULT_WITHHOLD, Options, marker_fitted, qa_withheld

    frames = np.arange(6)
    qa = _metrics(frames, ["penetration_mm", "wearer.reproj_views_body_px",
                           "wearer.marker_max_mm", "wearer.self_penetration_mm",
                           "partner.reproj_views_body_px"],
                  {"penetration_mm": [1], "wearer.reproj_views_body_px": [2],
                   "wearer.marker_max_mm": [3], "wearer.self_penetration_mm": [4],
                   "partner.reproj_views_body_px": [5]})
    roles = ["wearer", "partner"]
    fits = [NS(marker_names=np.array(["LFHD", "RFHD"])), NS(marker_names=None)]
    assert marker_fitted(fits, roles) == ("wearer",)
    held = qa_withheld(qa, frames, roles, DEFAULT_WITHHOLD, marker_fitted(fits, roles))
    assert held[0].tolist() == ["", "", "", "qa:marker_max_mm", "qa:self_penetration_mm", ""]
    assert held[1].tolist() == ["", "qa:penetration_mm", "", "", "", "qa:reproj_views_body_px"]
    # the old rule: everyone a reason is about
    old = qa_withheld(qa, frames, roles, DEFAULT_WITHHOLD)
    assert old[0].tolist() == ["", "qa:penetration_mm", "qa:reproj_views_body_px",
                               "qa:marker_max_mm", "qa:self_penetration_mm", ""]
    assert (old[1] == held[1]).all()
    # nobody fitted from the video alone: nothing is spared
    assert (qa_withheld(qa, frames, roles, DEFAULT_WITHHOLD, ("wearer", "partner")) == old).all()
    assert Options().trust_markers and not Options(trust_markers=False).trust_markers
    assert set(K.MARKER_FIT_SPARED) <= set(K.FIT_WRONG)
    assert not {"marker_max_mm", "marker_median_mm"} & set(K.MARKER_FIT_SPARED)


def test_every_qa_reason_is_classified_once_with_why():
    import dataclasses as dc

    from qa import constants as K
    from qa.metrics import QAOptions, threshold_name

    assert not set(K.FIT_WRONG) & set(K.NOT_FIT_WRONG)
    reasons = {threshold_name(n) for n in (
        "wearer.marker_max_mm", "wearer.marker_median_mm", "wearer.markers_repaired",
        "partner.reproj_body_px.c", "partner.reproj_hands_px.c", "partner.reproj_face_px.c",
        "partner.reproj_views_body_px", "partner.reproj_views_hands_px",
        "partner.reproj_views_face_px", "sync_offset_frames.c", "penetration_mm",
        "penetration_volume_cm3", "partner.self_penetration_mm", "partner.ground_penetration_mm",
        "partner.foot_skate_m_s", "contact_gap_mm", "unexpected_contact_mm",
        "partner.jerk_m_s3")}
    assert reasons == set(K.FIT_WRONG) | set(K.NOT_FIT_WRONG)
    assert reasons <= {f.name for f in dc.fields(QAOptions)}
    assert all(len(why) > 20 for why in {**K.FIT_WRONG, **K.NOT_FIT_WRONG}.values())
    assert {"markers_repaired", "sync_max_frames"} <= set(K.NOT_FIT_WRONG)
    assert set(K.PAIR_REASONS) <= set(K.FIT_WRONG)


@pytest.mark.parametrize("value,msg", [(["reproj_views_body_px", "nonsense"], "nonsense"),
                                       (["jerk_m_s3", "jerk_m_s3"], "twice")])
def test_withhold_option_names_the_bad_reason(value, msg):
    from pipeline.plan import PlanError, validate_params
    from stages import export as E

    with pytest.raises(PlanError, match=rf"stages\.export.*withhold.*{msg}"):
        validate_params(E.STAGE, {"withhold": value}, "r.yaml: stages.export")
    ok, _ = validate_params(E.STAGE, {"withhold": ["penetration_mm"]}, "r.yaml: stages.export")
    assert ok.withhold == ("penetration_mm",)


def test_valid_file_lists_its_qa_reasons_and_old_files_still_read(tmp_path):
    from formats import release as R
    from formats.errors import InputError

    reason = [["fitted", "qa:jerk_m_s3"], ["fitted", "fitted"]]
    valid = [[True, False], [True, True]]
    p = R.write_valid(tmp_path / "a.json", valid, reason, [4, 5], qa_withhold=["jerk_m_s3"])
    v = R.read_valid(p)
    assert v["qa_withhold"] == ("jerk_m_s3",) and v["reason"][0, 1] == "qa:jerk_m_s3"
    assert R.withheld_counts(v["reason"]) == {"qa:jerk_m_s3": 1}
    # a QA reason the file does not list: refused, naming file, field and frame
    d = json.loads(p.read_text())
    d["qa_withhold"] = ["penetration_mm"]
    (tmp_path / "b.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"b\.json.*reason.*frame 1.*qa:jerk_m_s3"):
        R.read_valid(tmp_path / "b.json")
    with pytest.raises(InputError, match="qa_withhold"):
        R.write_valid(tmp_path / "c.json", valid, reason, [4, 5])
    # a file written before (no QA reasons, no list) reads as before
    old = R.write_valid(tmp_path / "old.json", [[True, False]], [["fitted", "too_few_markers"]],
                        [0, 1])
    assert "qa_withhold" not in json.loads(old.read_text()) and "qa_withhold" not in R.read_valid(old)


# ------------------------------------------------------------------------- end to end
def _ctx(stage, unit, recipe, params, inputs, raw, out: Path):
    from pipeline.spec import StageContext
    from stages import view_for

    return StageContext(stage=stage, unit=unit, recipe=view_for(recipe, stage, unit),
                        params=params, inputs=inputs, raw=raw, out=_writer(out),
                        progress=lambda it, total=None, desc="": it, log=lambda s: None)


def _save_fit(fit, role: str, subject: str, d: Path) -> _Art:
    from artifacts import FitSummary

    w = _writer(d)
    fit.save(w)
    FitSummary(fit=role, subject=subject, frames=len(fit.frames),
               frames_valid=int(np.sum(fit.valid)), frames_not_valid={}).save(w)
    return _Art(d)


def _plant(model, fit, row: int):
    """The fit with ``PLANT_JOINT`` turned at ``row`` until the wrist moves by
    ``PLANT_ERROR_M``; returns (planted fit, wrist displacement m)."""
    from body import forward
    from body.joints import keypoints
    from body.rotations import rodrigues, rotmat_to_rotvec
    from formats.skeletons import kp65_index

    j = model.joint_index(PLANT_JOINT)
    w = kp65_index("r_wrist")

    def wrist(pose):
        out = forward(model, fit.betas, pose[row:row + 1], fit.global_orient[row:row + 1],
                      fit.transl[row:row + 1])
        return keypoints(model, out, "kp65")[0, w]

    before = wrist(np.asarray(fit.body_pose))
    for deg in PLANT_DEGREES:
        pose = np.array(fit.body_pose)
        pose[row, j] = rotmat_to_rotvec(rodrigues(pose[row, j])
                                        @ rodrigues(np.array([np.deg2rad(deg), 0.0, 0.0])))
        moved = float(np.linalg.norm(wrist(pose) - before))
        if moved >= PLANT_ERROR_M:
            return dataclasses.replace(fit, body_pose=pose), moved
    raise AssertionError(f"{PLANT_JOINT}: no turn in {PLANT_DEGREES} moves the wrist "
                         f"{PLANT_ERROR_M} m (last {moved:.3f} m)")


@pytest.fixture(scope="module")
def planted(small_session, tmp_path_factory, anny):
    """The small session's handshake: capture through the engine, truth fits with the partner's
    right upper arm turned in the middle frame, qa, export and release run on them."""
    import yaml

    from artifacts import BodyFit, ShapeFit
    from artifacts.capture import CameraRig, Markers
    from artifacts.keypoints import Keypoints2D
    from bench.cases.partner_fit import absolute_paths
    from body import forward
    from body.joints import keypoints
    from calib import project
    from pipeline.cli import main
    from recipes import load_recipe
    from stages import export as E
    from stages import qa as Q
    from stages import release as REL

    tmp = tmp_path_factory.mktemp("withhold")
    root = Path(small_session).parent
    rec = absolute_paths(yaml.safe_load(Path(small_session).read_text()), root)
    sid = next(s for s in rec["sequences"] if "Handshake" in s)
    rec["sequences"] = {sid: rec["sequences"][sid]}
    path = tmp / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    logs: list[str] = []
    rc = main(["sequence", sid, "--recipe", str(path), "--outputs", str(tmp / "out"), "--until",
               "capture", "--executor", "serial"], log=logs.append)
    assert rc == 0, "\n".join(logs[-30:])
    recipe = load_recipe(path)
    seq = recipe.sequences[sid]
    cap = _Art(next((tmp / "out").glob("*/*/*/capture")))
    group, action = sid.split("/", 1)
    gt = np.load(root / "gt" / group / f"{action}.npz")
    subjects = [seq.markers_on, seq.partner]
    assert [str(s) for s in gt["subjects"]] == subjects  # truth person 0 = the marker wearer
    model = anny
    F = len(gt["frames"])
    fits = [BodyFit(body_pose=gt["body_pose"][p], global_orient=gt["global_orient"][p],
                    transl=gt["transl"][p], betas=gt["betas"][p],
                    frames=np.asarray(gt["frames"], np.int64), valid=np.ones(F, bool),
                    invalid_reason=np.zeros(F, np.int8)) for p in range(2)]
    row = F // 2
    bad, moved = _plant(model, fits[1], row)
    # detections: the truth's KP65 projected into the rig's cameras (the clean partner)
    cams = CameraRig.load(cap).cameras(list(recipe.cameras))
    kp = np.zeros((len(cams), F, 2, 65, 3), np.float32)
    for p, fit in enumerate(fits):
        X = keypoints(model, forward(model, fit.betas, fit.body_pose, fit.global_orient,
                                     fit.transl), "kp65")
        for c, cam in enumerate(cams):
            kp[c, :, p, :, :2] = project(cam, X)
            kp[c, :, p, :, 2] = 1.0
    C = len(cams)
    Keypoints2D(kp=kp, boxes=np.full((C, F, 2, 4), np.nan, np.float32),
                hand_boxes=np.full((C, F, 2, 2, 4), np.nan, np.float32),
                frames=np.asarray(gt["frames"], np.int64), wearer_retry=np.zeros((C, F), bool),
                partner_mode=np.ones((C, F), np.int8),
                cross_view_outlier=np.zeros((C, F, 2, 65), bool), conf_raw=kp[..., 2].copy(),
                cameras=np.array([c.name for c in cams])).save(_writer(tmp / "keypoints"))
    names = Markers.load(cap).marker_names
    M = len(names)
    shape = {}
    for p, s in enumerate(subjects):
        ShapeFit(betas=gt["betas"][p], marker_names=np.array(names), marker_face=np.zeros(M, int),
                 marker_bary=np.tile([1.0, 0.0, 0.0], (M, 1)), marker_offset=np.zeros(M),
                 shape_source="given", placement_source="given").save(_writer(tmp / f"shape_{s}"))
        shape[s] = _Art(tmp / f"shape_{s}")
    inputs = {"capture": cap, "shape_fit": shape, "keypoints": _Art(tmp / "keypoints"),
              "marker_fit": _save_fit(fits[0], "marker_fit", subjects[0], tmp / "marker_fit"),
              "partner_fit": _save_fit(bad, "partner_fit", subjects[1], tmp / "partner_fit")}
    Q.run(_ctx("qa", sid, recipe, Q.Options(**QA_DRAWING_OFF), inputs, Q.raw_inputs(recipe, sid),
               tmp / "qa"))
    inputs["qa"] = _Art(tmp / "qa")
    E.run(_ctx("export", sid, recipe, E.Options(), inputs,
               {"body_model": E.raw_inputs(recipe, sid)["body_model"]}, tmp / "export"))
    REL.run(_ctx("release", "session", recipe, None, {"export": {sid: _Art(tmp / "export")},
                                                      "qa": {sid: inputs["qa"]}}, {},
                 tmp / "release"))
    return {"tmp": tmp, "sid": sid, "group": group, "action": action, "row": row,
            "frame": int(gt["frames"][row]), "moved": moved, "frames": gt["frames"]}


@pytest.mark.slow
def test_a_planted_limb_error_is_published_not_valid(planted):
    from artifacts import QAResult, SequenceExport
    from artifacts.release import Release
    from formats import release as R
    from qa.constants import FIT_WRONG, PAIR_REASONS
    from qa.metrics import threshold_name
    from stages.export import DEFAULT_WITHHOLD

    assert PLANT_ERROR_M <= planted["moved"] < PLANT_ERROR_M + 0.05
    f, row = planted["frame"], planted["row"]
    qa = QAResult.load(planted["tmp"] / "qa")
    # QA flags the planted frame for the partner with a reason that says the fit is wrong
    flagged = qa.frame_reasons.get(f, ())
    assert any(r.startswith("partner.") and threshold_name(r) in FIT_WRONG for r in flagged), \
        qa.frame_reasons
    v = R.read_valid(planted["tmp"] / "export" / planted["group"] / "valid" /
                     f"{planted['action']}.json")
    np.testing.assert_array_equal(v["frames"], planted["frames"])
    # the partner at the planted frame: not valid, with the QA reason; its neighbours valid
    first = next(r for r in DEFAULT_WITHHOLD if any(threshold_name(x) == r and
                                                     "wearer" not in x for x in flagged))
    assert not v["valid"][1, row] and v["reason"][1, row] == R.QA_REASON_PREFIX + first, \
        (v["reason"][1, row], flagged)
    assert v["valid"][1, [row - 1, row + 1]].all(), v["reason"][1, row - 1:row + 2]
    # the wearer: valid around it; at it only a pair reason (the turned arm is the hand the
    # two shake: the annotated contact opens) may withhold it too
    assert v["valid"][0, [row - 1, row + 1]].all(), v["reason"][0, row - 1:row + 2]
    assert v["valid"][0, row] or v["reason"][0, row][len(R.QA_REASON_PREFIX):] in PAIR_REASONS, \
        v["reason"][0, row]
    assert not (v["joints_valid"][1, row]).any()
    assert v["qa_withhold"] == DEFAULT_WITHHOLD
    # the evaluator reads the same mask: it does not score the withheld frame
    from evaluate.folders import read_valid as eval_valid

    assert not eval_valid(planted["tmp"] / "export" / planted["group"] / "valid" /
                          f"{planted['action']}.json", 2, len(planted["frames"]))[1, row]
    # export.json and the datasheet count it, per reason, per sequence and in total
    exp = SequenceExport.load(planted["tmp"] / "export")
    held = R.withheld_counts(v["reason"])
    assert held and exp.withheld == held and sum(held.values()) >= 1
    assert exp.person_frames_not_valid == int((~v["valid"]).sum())
    rel = Release.load(planted["tmp"] / "release")
    s = rel.sheet.sequences[planted["sid"]]
    assert s["withheld"] == held
    assert rel.sheet.totals.withheld == held
    assert rel.sheet.totals.not_valid_by_reason[v["reason"][1, row]] >= 1
    assert f in [a for a, b in s["not_valid_frames"][s["persons"][1]][v["reason"][1, row]]
                 for a in range(a, b + 1)]
    print(f"planted {planted['moved'] * 100:.0f} cm at frame {f}: QA flags {flagged}, "
          f"withheld {held}")
    md = (planted["tmp"] / "release" / "datasheet.md").read_text()
    assert "withheld for QA flags" in md and v["reason"][1, row] in md


def test_export_and_datasheet_counts_must_agree(tmp_path):
    from artifacts.base import ArtifactError, JsonFields
    from artifacts.export import SequenceExport
    from artifacts.release import DatasheetTotals

    files = ("g/valid/A 1.json",)
    for f in files:
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_text("{}")
    kw = dict(sequence="g/A 1", group="g", action="A 1", persons=("a", "b"), model="anny",
              frames=4, first_frame=0, last_frame=3, video_fps=None, person_frames_not_valid=2,
              not_valid_by_reason=({"subject": "a", "qa:jerk_m_s3": 1},
                                   {"subject": "b", "qa:jerk_m_s3": 1}),
              cameras={}, contact=None, absent={}, files=files, valid_file=files[0])
    ok = SequenceExport(**kw, withhold=("jerk_m_s3",), withheld={"qa:jerk_m_s3": 2})
    ok.validate(tmp_path / "export.json", tmp_path)
    back = SequenceExport.from_json(JsonFields(ok.to_json(), tmp_path / "export.json",
                                               folder=tmp_path))
    assert back.withhold == ("jerk_m_s3",) and back.withheld == {"qa:jerk_m_s3": 2}
    for bad, msg in (({"withhold": ("jerk_m_s3",), "withheld": {"qa:jerk_m_s3": 1}},
                      r"export\.json: withheld\.qa:jerk_m_s3: 1 person-frames"),
                     ({"withhold": None, "withheld": {"qa:jerk_m_s3": 2}},
                      r"withheld\.qa:jerk_m_s3: not among the reasons withheld")):
        with pytest.raises(ArtifactError, match=msg):
            SequenceExport(**kw, **bad).validate(tmp_path / "export.json", tmp_path)
    # an export.json written before (no withhold / withheld) reads as nothing withheld
    old = {k: v for k, v in ok.to_json().items() if k not in ("withhold", "withheld")}
    back = SequenceExport.from_json(JsonFields(old, tmp_path / "export.json", folder=tmp_path))
    assert back.withhold is None and back.withheld == {}
    t = {"sequences": 1, "frames": 4, "person_frames": 8, "person_frames_not_valid": 2,
         "not_valid_by_reason": {"qa:jerk_m_s3": 2}}
    assert DatasheetTotals.from_json(JsonFields({**t, "withheld": {"qa:jerk_m_s3": 2}},
                                                "datasheet.json", "totals")).withheld
    with pytest.raises(ArtifactError, match=r"datasheet\.json: totals\.withheld\.qa:jerk_m_s3"):
        DatasheetTotals.from_json(JsonFields({**t, "withheld": {"qa:jerk_m_s3": 3}},
                                             "datasheet.json", "totals"))
