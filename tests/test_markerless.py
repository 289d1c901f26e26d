"""Markerless sequences (issue #28 items 1 and 3): the recipe schema, the people found across
views with a bystander rejected, the held-out view figure on cases with a known answer, and a
two-person markerless studio sequence through the fit, the export and the QA report."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from calib.camera import look_at
from detect.markerless import MarkerlessOptions, detect_markerless, volume_centre
from fitting.heldout import group_stats, pixel_errors, triangulated
from recipes import RecipeError, load_recipe

CAMS = ["c1", "c2", "c3"]


# ------------------------------------------------------------------------------ the recipe


def _recipe(folder: Path, **seq) -> Path:
    (folder / "d").mkdir(exist_ok=True)
    for n in ["c1.mp4", "c2.mp4", "c3.mp4", "cal.qca.txt", "x.c3d"]:
        (folder / "d" / n).write_text("x")
    base = {"videos": {c: f"d/{c}.mp4" for c in CAMS},
            "calibration": {c: "d/cal.qca.txt" for c in CAMS},
            "calibration_format": "qualisys"}
    base.update(seq)
    base = {k: v for k, v in base.items() if v is not None}
    r = {"session": "lab", "cameras": CAMS, "subjects": {"a": {}, "b": {}},
         "sequences": {"s01/Walk 1": base}}
    p = folder / "r.yaml"
    p.write_text(yaml.safe_dump(r, sort_keys=False))
    return p


def test_schema_accepts_markerless_sequences(tmp_path):
    s = load_recipe(_recipe(tmp_path, people=["a"]))
    seq = s.sequence("s01/Walk 1")
    assert seq.markerless and seq.markers_on is None and seq.c3d is None
    assert seq.persons == ["a"] and s.sequences_of("a") == ["s01/Walk 1"]
    s2 = load_recipe(_recipe(tmp_path, people=["b", "a"]))
    assert s2.sequence("s01/Walk 1").persons == ["b", "a"]
    from stages import applies, recipe_view

    # the marker stages leave the DAG, the video ones and the held-out view stay
    assert not applies(s2, "capture", "s01/Walk 1") and not applies(s2, "marker_fit", "s01/Walk 1")
    assert not applies(s2, "marker_loo", "s01/Walk 1")
    assert applies(s2, "partner_fit", "s01/Walk 1") and applies(s2, "heldout", "s01/Walk 1")
    assert recipe_view(s2, "s01/Walk 1", "sequence.markers_on") == "b"  # person 0's slot
    assert recipe_view(s2, "s01/Walk 1", "sequence.partner") == "a"
    assert recipe_view(s2, "s01/Walk 1", "sequence.markerless") is True


@pytest.mark.parametrize("fields, says", [
    ({"people": ["a"], "c3d": "d/x.c3d"}, "c3d: a C3D is given but no subject wears the markers"),
    ({}, "people: a sequence without a marker wearer"),
    ({"people": ["a", "b"], "partner": "b"}, "partner: a markerless sequence names everyone"),
    ({"people": ["a", "a"]}, "people: the same subject twice"),
    ({"people": ["a", "b", "a"]}, "people: one or two people are fitted, got 3"),
    ({"people": ["zz"]}, "people: unknown subject 'zz'"),
    ({"people": ["a"], "videos": None, "calibration": None}, "videos: a markerless sequence"),
    ({"markers_on": "a", "people": ["b"], "c3d": "d/x.c3d"}, "people: a sequence with a marker"),
    ({"markers_on": "a"}, "c3d: missing required field"),
])
def test_schema_rejects_contradictory_sequences(tmp_path, fields, says):
    with pytest.raises(RecipeError) as e:
        load_recipe(_recipe(tmp_path, **fields))
    msg = str(e.value)
    assert msg.startswith(str(tmp_path / "r.yaml") + ": sequences.s01/Walk 1."), msg
    assert says in msg, msg


# ------------------------------------------------------------------------------ people


def _rig(n=4, radius=5.0, size=(640, 480)):
    w, h = size
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        cams.append(look_at(f"v{i}", (radius * np.cos(a), radius * np.sin(a), 1.5), (0, 0, 1.0),
                            (500.0, 500.0), (w / 2, h / 2), w, h))
    return cams


def _skeleton(centre) -> np.ndarray:
    """(65, 3) a standing person's KP65 points at ``centre`` on the floor (body only; the hands
    at the wrists)."""
    from detect import layout

    x, y = centre
    pts = {"nose": (0, 0.08, 1.65), "l_eye": (0.03, 0.07, 1.68), "r_eye": (-0.03, 0.07, 1.68),
           "l_ear": (0.07, 0, 1.66), "r_ear": (-0.07, 0, 1.66), "l_shoulder": (0.19, 0, 1.45),
           "r_shoulder": (-0.19, 0, 1.45), "l_elbow": (0.25, 0, 1.15), "r_elbow": (-0.25, 0, 1.15),
           "l_wrist": (0.27, 0.05, 0.88), "r_wrist": (-0.27, 0.05, 0.88), "l_hip": (0.1, 0, 0.95),
           "r_hip": (-0.1, 0, 0.95), "l_knee": (0.11, 0.02, 0.5), "r_knee": (-0.11, 0.02, 0.5),
           "l_ankle": (0.12, 0, 0.08), "r_ankle": (-0.12, 0, 0.08),
           "l_big_toe": (0.13, 0.15, 0.02), "r_big_toe": (-0.13, 0.15, 0.02),
           "l_small_toe": (0.17, 0.12, 0.02), "r_small_toe": (-0.17, 0.12, 0.02),
           "l_heel": (0.12, -0.05, 0.02), "r_heel": (-0.12, -0.05, 0.02)}
    X = np.full((layout.N, 3), np.nan)
    for n, p in pts.items():
        X[layout.IDX[n]] = (p[0] + x, p[1] + y, p[2])
    return X


def _view(cam, X) -> np.ndarray:
    from fitting.heldout import project_front

    uv = project_front(cam, X)
    ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    kp = np.zeros((len(X), 3), np.float32)
    kp[ok, :2] = uv[ok]
    kp[ok, 2] = 0.9
    return kp


def test_people_found_across_views_and_bystander_rejected():
    """Two people near the volume centre and an operator 4 m off it, seen by two cameras:
    the two are associated across all four views and kept in their slots frame after frame;
    the operator, a consistent person in 3D but far from the centre, is rejected and counted
    in every frame; the candidates' order in a view does not matter."""
    cams = _rig()
    rng = np.random.default_rng(0)
    F = 5
    cands, truth = [], []
    for f in range(F):
        a, b = _skeleton((-0.4 + 0.02 * f, 0.0)), _skeleton((0.45, 0.1 - 0.02 * f))
        op = _skeleton((-2.2, -2.2))  # 3.1 m off the centre, in the field of v0 and v1 only
        truth.append((a, b))
        per_view = []
        for c, cam in enumerate(cams):
            ks = [_view(cam, a), _view(cam, b)]
            if c in (0, 1):  # the operator stands where only these two views see him
                ks.append(_view(cam, op))
            ks = [k for k in ks if (k[:23, 2] > 0).sum() >= 8]
            order = rng.permutation(len(ks))
            per_view.append(np.stack([ks[i] for i in order]))
        cands.append(per_view)
    o = MarkerlessOptions(people=2, max_candidates=3, volume_radius_m=2.5)
    kp, facts = detect_markerless(cams, None, np.arange(F), None, o, candidates=cands)
    assert facts["people_found_frames"] == [F, F]
    assert facts["bystanders"]["frames_with"] == F and facts["bystanders"]["far_from_volume"] == F
    # slot 0 is the same person in every frame and every view (the left one: x < 0)
    for f in range(F):
        X = triangulated(cams, kp.kp[:, f:f + 1, 0], 0.5)[0]
        Y = triangulated(cams, kp.kp[:, f:f + 1, 1], 0.5)[0]
        ok = np.isfinite(X[:, 0])
        assert np.nanmax(np.linalg.norm(X[ok] - truth[f][0][ok], axis=1)) < 1e-4
        assert np.nanmax(np.linalg.norm(Y[ok] - truth[f][1][ok], axis=1)) < 1e-4
    assert np.allclose(volume_centre(cams)[:2], 0, atol=1e-9)


def test_one_person_sequence_keeps_the_subject_not_the_nearer_operator():
    """One person fitted: the person at the centre is chosen over an operator farther off
    even when the operator is the first candidate of every view that sees him."""
    cams = _rig()
    subj, op = _skeleton((0.2, 0.0)), _skeleton((-2.2, -2.2))
    cands = [[np.stack(([_view(c, op)] if i in (0, 1) else []) + [_view(c, subj)])
              for i, c in enumerate(cams)]]
    o = MarkerlessOptions(people=1, max_candidates=3)
    kp, facts = detect_markerless(cams, None, np.arange(1), None, o, candidates=cands)
    X = triangulated(cams, kp.kp[:, :, 0], 0.5)[0]
    ok = np.isfinite(X[:, 0])
    assert np.allclose(X[ok], subj[ok], atol=1e-4)
    assert facts["bystanders"]["groups"] == 1


# ------------------------------------------------------------------------------ held-out view


def _person_frames(F=3):
    return np.stack([_skeleton((0.1 * f, -0.05 * f)) for f in range(F)])


def test_heldout_exact_keypoints_zero_and_a_shifted_camera_its_shift():
    """Detections that are the exact projections: the fit's keypoints projected into the
    held-out view and the baseline triangulated from the other three both land on them
    (~0 px); a held-out camera whose principal point is off by (3, 4) px (its detections
    made by the true camera): every error is the 5 px shift, in every group."""
    import dataclasses

    cams = _rig()
    X = _person_frames()  # (F, 65, 3)
    det = np.stack([[_view(c, x) for x in X] for c in cams])  # (C, F, 65, 3)
    held = 3
    e = pixel_errors(cams[held], X, det[held], 0.5)
    assert np.nanmax(e) < 1e-3 and np.isfinite(e[:, :23]).all()  # float32 detections
    base = triangulated(cams[:held], det[:held], 0.5)
    assert np.nanmax(pixel_errors(cams[held], base, det[held], 0.5)) < 1e-3
    moved = dataclasses.replace(cams[held], c=np.asarray(cams[held].c) + (3.0, 4.0))
    e2 = pixel_errors(moved, X, det[held], 0.5)
    fin = e2[np.isfinite(e2)]
    assert len(fin) > 50 and np.allclose(fin, 5.0, atol=1e-3)
    st = group_stats(np.round(e2, 6))
    assert st["body"]["median_px"] == 5.0 and st["face"]["p90_px"] == 5.0
    assert st["hands"]["n"] == 0 and st["hands"]["median_px"] is None  # no hand detected
    assert st["all"]["n"] == int(np.isfinite(e2).sum())


def test_heldout_refit_from_three_views_lands_on_the_fourth(anny):
    """The whole held-out path on a posed Anny: its KP65 keypoints projected into four views
    are the detections; each person refitted from three views (the partner fit) projects into
    the fourth within a few pixels, and the per-keypoint triangulation of three exact views
    within ~0 px."""
    from artifacts.keypoints import Keypoints2D
    from fitting.heldout import fitted_keypoints, held_out_view, summarise
    from fitting.partner_fit import PartnerFitOptions

    cams = _rig(size=(800, 600))
    F = 2
    rng = np.random.default_rng(3)
    from artifacts import BodyFit

    J = anny.num_joints
    pose = rng.normal(0, 0.05, (F, J, 3))
    R = np.stack([np.eye(3)] * F)
    truth = BodyFit(body_pose=pose, global_orient=R, transl=np.zeros((F, 3)),
                    betas=np.zeros(anny.num_betas), frames=np.arange(F), valid=np.ones(F, bool),
                    invalid_reason=np.zeros(F, np.int8))
    X = fitted_keypoints(anny, truth)
    assert 1.0 < np.ptp(X[0, :23, 2]) < 2.2  # a standing person in the views
    det = np.stack([[_view(c, x) for x in X] for c in cams])  # (C, F, 65, 3)
    kp = np.zeros((len(cams), F, 2, 65, 3), np.float32)
    kp[:, :, 1] = det
    k2 = Keypoints2D(kp=kp, boxes=np.full((len(cams), F, 2, 4), np.nan, np.float32),
                     hand_boxes=np.full((len(cams), F, 2, 2, 4), np.nan, np.float32),
                     frames=np.arange(F), wearer_retry=np.zeros((len(cams), F), bool),
                     partner_mode=np.zeros((len(cams), F), np.int8),
                     cross_view_outlier=np.zeros((len(cams), F, 2, 65), bool),
                     conf_raw=kp[..., 2].copy(), cameras=np.array([c.name for c in cams]))
    res = held_out_view(anny, [k2], [np.zeros(anny.num_betas)], cams, 3, np.arange(F),
                        PartnerFitOptions(check_views=False), min_conf=0.5)
    rep = summarise(res)
    assert rep["all"]["baseline"]["body"]["median_px"] < 0.01
    assert rep["all"]["fit"]["body"]["median_px"] < 3.0, rep["all"]


# ------------------------------------------------------------------------------ end to end


@pytest.mark.slow
def test_markerless_two_person_studio_sequence_fit_export_qa(small_session, tmp_path):
    """The studio's handshake with nobody's markers and no scans (the same videos): both
    people found in the views, fitted (shape from the views), held-out view measured,
    converted, QA'd and exported as two persons; no marker stage in its DAG."""
    import json

    from artifacts import BodyFit
    from bench.cases.real_video import markerless_recipe
    from pipeline.cli import main

    seq = "s01/Handshake 1"
    rec = markerless_recipe(small_session, tmp_path / "ml.yaml", [seq], stages={
        "keypoints": {"stop": 8, "hands": False},
        "heldout": {"stride": 4},
        "qa": {"video": False, "scene": False, "overlay_sample": 1, "overlay_max": 2}})
    logs: list[str] = []
    rc = main(["sequence", seq, "--recipe", str(rec), "--outputs", str(tmp_path / "out")],
              log=logs.append)
    assert rc == 0, "\n".join(logs[-30:])
    text = "\n".join(logs)
    for stage in ("capture", "marker_fit", "marker_loo"):
        assert f" {stage} " not in text, f"{stage} ran on a markerless sequence"
    session = yaml.safe_load(rec.read_text())["session"]
    base = tmp_path / "out" / session / "s01" / "Handshake 1"
    kr = json.loads((base / "keypoints" / "report.json").read_text())
    assert kr["markerless"] and kr["people_found_frames"] == [8, 8]
    p0, p1 = BodyFit.load(base / "partner_fit" / "person0"), BodyFit.load(base / "partner_fit")
    assert p0.valid.sum() >= 6 and p1.valid.sum() >= 6
    pr = json.loads((base / "partner_fit" / "report.json").read_text())
    for r in pr["people"].values():  # the shape from the views fits the bones it saw
        assert r["shape"]["source"] == "views"
        assert r["shape"]["bone_rms_mm"] < r["shape"]["bone_rms_mean_shape_mm"]
    # the two are different people a person's width apart, not one fitted twice
    d = np.linalg.norm(p0.transl - p1.transl, axis=1)
    assert np.all(d > 0.2), d
    ho = json.loads((base / "heldout" / "report.json").read_text())
    assert set(ho["cameras"]) == {"50591643", "58860488", "60457274", "65906101"}
    assert ho["all"]["fit"]["body"]["n"] > 0
    html = (base / "qa" / "report.html").read_text()
    assert "Held-out view" in html
    ex = json.loads((base / "export" / "export.json").read_text())
    smplx = [f for f in ex["files"] if "/smplx/" in f]
    assert smplx, ex["files"]
    valid = json.loads(next((base / "export").rglob("valid/*.json")).read_text())
    assert len(valid["valid"] if isinstance(valid, dict) and "valid" in valid else valid) == 2
