"""The marker_fit stage adapter on a Vicon-like Plug-in Gait C3D (240 Hz, Subject: prefixes,
model outputs and angles stored as points, gaps, a swapped label): a known motion recovered
from its own markers; without hand keypoints."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from test_marker_fit_vicon import write_vicon_pig

from pipeline.store import Writer


def FakeWriter(folder: Path) -> Writer:
    """The engine's own writer, into a folder of the test's (created)."""
    folder.mkdir(parents=True, exist_ok=True)
    return Writer(folder)


def view(stage_module, values: dict):
    """The recipe view the engine hands the stage: exactly the module's declared READS
    (a KeyError here means the stage declares a field the test does not provide)."""
    from pipeline.spec import RecipeView, build_view_tree

    return RecipeView(build_view_tree({k: values[k] for k in stage_module.STAGE.reads}),
                      stage_module.STAGE.name)


def keypoints_artifact(folder: Path, kp: np.ndarray, frames: np.ndarray, cams) -> Path:
    """A keypoints artifact folder holding ``kp (C, F, 2, 65, 3)`` at video ``frames``."""
    from artifacts.keypoints import Keypoints2D

    C, F = kp.shape[:2]
    Keypoints2D(kp=kp, boxes=np.full((C, F, 2, 4), np.nan, np.float32),
                hand_boxes=np.full((C, F, 2, 2, 4), np.nan, np.float32),
                frames=np.asarray(frames, np.int64), wearer_retry=np.zeros((C, F), bool),
                partner_mode=np.zeros((C, F), np.int8),
                cross_view_outlier=np.zeros((C, F, 2, 65), bool),
                conf_raw=kp[..., 2].copy(), cameras=np.array(list(cams))).save(FakeWriter(folder))
    return folder


def capture_artifact(folder: Path, values: dict, raw: dict, unit: str = "g/take") -> Path:
    """Stage ``capture`` run on ``raw`` (body_model, c3d, calibration:<cam>) into ``folder``:
    the cleaned markers and camera rig the marker stages read."""
    import stages.capture as cap

    keep = {k: v for k, v in raw.items() if k in ("body_model", "c3d", "markerset")
            or k.startswith("calibration:")}
    values = {"sequence.calibration_format": None, **values}  # null: from the files' suffix
    ctx = SimpleNamespace(stage="capture", unit=unit, recipe=view(cap, values),
                          params=cap.Options(), raw=keep, out=FakeWriter(folder),
                          inputs={}, log=lambda m: None, progress=lambda it, **k: it)
    cap.run(ctx)
    return folder


def _session(tmp: Path, model, rng, F=40, fps=50.0, rate=240.0, swap=True, fingers=False,
             sync=-0.1, hole_frames=(), first_frame=0):
    """Truth motion, its markers as a Vicon C3D, cameras, and the stage context pieces.
    sync: the recipe's mocap.sync_offset_s (video frame f at mocap time f / fps - sync; > 0
    leaves the first video frames before the capture); hole_frames: video frames at which no
    marker is recorded (every marker in a gap)."""

    from bench import fitting_synth as S
    from body.lbs import rest_state
    from calib import look_at
    from calib.io import write_chi3d_camera
    from fitting import shape, skinned
    from fitting.marker_graph import template_placement, to_shape_fit
    from formats.c3d import read_c3d
    from stages import common

    betas = S.subject_betas(model, rng)[:80]
    pl = template_placement(model, "plug-in-gait")
    skel = skinned.fit_skeleton(model, None if fingers else shape.body_joints(model))
    # mocap at 240 Hz covering the video, motion defined per mocap sample
    n_mocap = int((F / fps - sync + 0.05) * rate)
    X = S.motion(skel, n_mocap, rate, rng)
    X[:, 6:] *= 0.7
    rest = rest_state(model, betas)
    truth = S.posed(model, betas, skel, X, rest)
    markers = S.true_markers(model, truth.vertices, pl)
    markers += rng.normal(0, S.MARKER_NOISE_SD_M, markers.shape)
    if swap:
        i, j = pl.names.index("LTHI"), pl.names.index("LTIB")
        markers[n_mocap // 2:, [i, j]] = markers[n_mocap // 2:, [j, i]]
    t_mocap = np.arange(n_mocap) / rate
    for f in hole_frames:  # the samples around video frame f
        markers[np.abs(t_mocap - (f / fps - sync)) < 1.5 / rate] = np.nan
    gaps = write_vicon_pig(tmp / "take.c3d", markers, rate, rng, first_frame=first_frame,
                           n_gaps=10, gap_len=(10, 80))
    assert read_c3d(tmp / "take.c3d", markers=pl.names).rate_hz == rate
    cams = {}
    for k, a in enumerate([0.5, 2.1, 3.7, 5.3]):
        name = f"cam{k}"
        cam = look_at(name, [4 * np.cos(a), 4 * np.sin(a), 2.0], [0, 0, 1.0], (1100, 1100),
                      (450, 450), 900, 900)
        cams[name] = write_chi3d_camera(tmp / "cams" / name / "take.json", cam)
    t_video = np.arange(F) / fps - sync
    sample = np.clip(np.round(t_video * rate).astype(int), 0, None)  # video frames on samples
    sf = to_shape_fit(betas, pl, "given", "given")
    sf.save(FakeWriter(tmp / "shape_fit"))
    kp = np.zeros((4, F, 2, 65, 3), np.float32)  # detections without hands (conf 0)
    if fingers:  # person 0's hand keypoints: the truth projected, 2 px noise
        from body.joints import regressor
        from calib import project
        from calib.io import read_chi3d_camera

        R = regressor(model, "kp65")
        pts = np.stack([R @ np.concatenate([truth.vertices[s], truth.joints[s]]) for s in sample])
        for c, p in enumerate(cams.values()):
            uv = project(read_chi3d_camera(p), pts) + rng.normal(0, 2.0, pts.shape[:2] + (2,))
            kp[c, :, 0, 23:65, :2] = uv[:, 23:65]
            kp[c, :, 0, 23:65, 2] = 0.9
    values = {"body_model.kind": "anny", "cameras": list(cams), "sequence.fps": fps,
              "sequence.mocap": {"sync_offset_s": sync, "rate_hz": None},
              "sequence.markers_on": "s1", "sequence.has_video": True,
              "wearer.markerset": "plug-in-gait", "wearer.label_prefix": None,
              "wearer.marker_labels": {},
              "subject.markerset": "plug-in-gait", "subject.label_prefix": None,
              "subject.marker_labels": {}, "subject.static_frames": []}
    body_file = common.body_model_file(SimpleNamespace(body_model=SimpleNamespace(kind="anny",
                                                                                  path=None)))
    raw = {"body_model": body_file, "c3d": tmp / "take.c3d",
           **{f"calibration:{c}": p for c, p in cams.items()}}
    truth_video = SimpleNamespace(joints=truth.joints[sample], vertices=truth.vertices[sample],
                                  skel=skel, gaps=gaps, mocap_joints=truth.joints)
    return SimpleNamespace(values=values, raw=raw, shape=sf, shape_dir=tmp / "shape_fit",
                           kp=kp, cams=list(cams), truth=truth_video,
                           capture_dir=capture_artifact(tmp / "capture", values, raw),
                           kp_dir=keypoints_artifact(tmp / "keypoints", kp, np.arange(F), cams))


def _ctx(s, out: Path, params, keypoints=None, log=lambda m: None):
    import stages.marker_fit as stage

    return SimpleNamespace(stage="marker_fit", unit="g/take", recipe=view(stage, s.values),
                           params=params, raw=s.raw, out=FakeWriter(out), log=log,
                           inputs={"shape_fit": {"s1": s.shape_dir}, "capture": s.capture_dir,
                                   "keypoints": s.kp_dir if keypoints is None else keypoints},
                           progress=lambda it, **k: it)


@pytest.mark.slow
def test_stage_recovers_motion_from_vicon_export(tmp_path, anny):
    from artifacts import BodyFit
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(21)
    F = 40
    s = _session(tmp_path, anny, rng, F=F)
    truth = s.truth
    logs = []
    ctx = _ctx(s, tmp_path / "out", Options(), log=logs.append)
    run(ctx)
    out = ctx.out
    fit = dict(np.load(out.dir / "fit.npz"))
    assert BodyFit.load(out.dir).valid.all()
    rep = json.loads((out.dir / "report.json").read_text())
    assert (out.dir / "residuals.png").stat().st_size > 1000
    assert fit["body_pose"].shape == (F, anny.num_joints, 3)
    assert fit["global_orient"].shape == (F, 3, 3) and fit["transl"].shape == (F, 3)
    assert rep["hands"] is False and rep["frames"] == F
    assert rep["frames_not_valid"] == {"held_before_first_marker": 0, "too_few_markers": 0}
    from body.lbs import forward

    est = forward(anny, fit["betas"], fit["body_pose"], fit["global_orient"], fit["transl"])
    jerr = np.linalg.norm(est.joints - truth.joints, axis=2)[:, truth.skel.joints] * 1000
    assert jerr.mean() < 6.0, jerr.mean()
    # the swapped labels (second half) are flagged as outliers, the others are not
    names = list(fit["marker_names"])
    i, j = names.index("LTHI"), names.index("LTIB")
    w = fit["marker_weight"]
    late = slice(F // 2 + 5, F)
    assert np.nanmax(w[late][:, [i, j]]) < 0.2
    others = np.delete(np.arange(len(names)), [i, j])
    assert np.nanmedian(w[:, others]) > 0.9
    # gaps are masked: NaN residuals exactly where markers are not visible
    assert np.array_equal(np.isnan(fit["marker_residual_m"]), ~fit["visible"])
    assert not fit["visible"].all()


@pytest.mark.slow
def test_frames_without_markers_are_held_and_not_valid(tmp_path, anny):
    """The video starts 0.1 s (5 frames) before the capture, and 3 frames later on record no
    marker: those frames are held (before the first marker: at the first solution) and
    marked not valid with their reason in fit.npz and in the report; the others match the
    truth."""
    from artifacts import INVALID_REASONS, BodyFit
    from body.lbs import forward
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(3)
    F = 30
    s = _session(tmp_path, anny, rng, F=F, swap=False, sync=0.1, hole_frames=(15, 16, 17))
    logs = []
    ctx = _ctx(s, tmp_path / "out", Options(), log=logs.append)
    run(ctx)
    fit = BodyFit.load(ctx.out.dir)
    rep = json.loads((ctx.out.dir / "report.json").read_text())
    reason = [INVALID_REASONS[c] for c in fit.invalid_reason]
    assert reason[:5] == ["held_before_first_marker"] * 5
    assert reason[15:18] == ["too_few_markers"] * 3
    assert np.flatnonzero(~fit.valid).tolist() == [0, 1, 2, 3, 4, 15, 16, 17]
    assert rep["first_fitted_frame"] == 5 and rep["frames_valid"] == F - 8
    assert rep["frames_not_valid"] == {"held_before_first_marker": 5, "too_few_markers": 3}
    assert any("< 3 markers from frame 15" in m for m in logs), logs
    # held at the first solution, no residuals there
    np.testing.assert_array_equal(fit.body_pose[:5], np.broadcast_to(fit.body_pose[5], (5,) +
                                                                     fit.body_pose.shape[1:]))
    assert np.isnan(fit.marker_residual_m[:5]).all()
    est = forward(anny, fit.betas, fit.body_pose, fit.global_orient, fit.transl)
    jerr = np.linalg.norm(est.joints - s.truth.joints, axis=2)[:, s.truth.skel.joints] * 1000
    assert jerr[fit.valid].mean() < 6.0, jerr[fit.valid].mean()


@pytest.mark.slow
def test_stage_uses_hand_keypoints_when_present(tmp_path, anny):
    """Fingers move in the truth; the markers can't see them, person 0's hand keypoints can."""
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(5)
    F = 12
    s = _session(tmp_path, anny, rng, F=F, swap=False, fingers=True)
    truth = s.truth
    errs = {}
    for hands in (True, False):
        ctx = _ctx(s, tmp_path / f"out{hands}", Options(use_hands=hands, compile="interpreted"))
        run(ctx)
        rep = json.loads((ctx.out.dir / "report.json").read_text())
        assert rep["hands"] is hands
        fit = dict(np.load(ctx.out.dir / "fit.npz"))
        from body.lbs import forward

        est = forward(anny, fit["betas"], fit["body_pose"], fit["global_orient"], fit["transl"])
        finger = [j for j in truth.skel.joints if "finger" in anny.joint_names[j]]
        errs[hands] = (np.linalg.norm(est.joints - truth.joints, axis=2)[:, finger] * 1000).mean()
    assert errs[True] < 0.5 * errs[False], errs


@pytest.mark.slow
def test_stage_fits_the_keypoints_frames_when_strided(tmp_path, anny):
    """With a frame stride in the keypoints stage, the fit is made at exactly those video
    frames (not at 0..F-1), and matches the truth there."""
    from body.lbs import forward
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(8)
    F, stride = 40, 4
    s = _session(tmp_path, anny, rng, F=F, swap=False)
    frames = np.arange(0, F, stride)
    strided = keypoints_artifact(tmp_path / "strided", s.kp[:, frames], frames, s.cams)
    ctx = _ctx(s, tmp_path / "out", Options(), keypoints=strided)
    run(ctx)
    fit = dict(np.load(ctx.out.dir / "fit.npz"))
    assert np.array_equal(fit["frames"], frames)
    est = forward(anny, fit["betas"], fit["body_pose"], fit["global_orient"], fit["transl"])
    jerr = np.linalg.norm(est.joints - s.truth.joints[frames], axis=2)[:, s.truth.skel.joints]
    assert jerr.mean() * 1000 < 8.0, jerr.mean() * 1000


def test_stage_options_name_the_bad_field():
    from stages.marker_fit import Options

    with pytest.raises(ValueError, match=r"weights\.L_foo: unknown term \(known: L_3d, L_2d, "
                                         r"L_theta, L_s\)"):
        Options(weights={"L_foo": 1.0})
    with pytest.raises(ValueError, match=r"max_frames: must be >= 1, got -2"):
        Options(max_frames=-2)
    with pytest.raises(ValueError, match=r"sigma_marker_mm: must be > 0"):
        Options(sigma_marker_mm=0)
    assert Options(weights={"L_s": 0.5}).weights == {"L_3d": 1.0, "L_2d": 1e-6, "L_theta": 2e-7,
                                                      "L_s": 0.5}


def test_marker_only_sequence_fits_every_sample_at_the_capture_rate(tmp_path, anny):
    """No videos, no cameras, no keypoints: every sample of the C3D is fitted at its own rate
    (240 Hz, not a video rate), from its first frame (C3D frame 118, not 1): fit.npz frames are
    the capture's 0-based frame numbers, and the report says whose frames they are."""
    from artifacts import BodyFit
    from body.lbs import forward
    from formats.c3d import read_c3d
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(4)
    s = _session(tmp_path, anny, rng, F=6, swap=False, first_frame=117)
    mk = read_c3d(s.raw["c3d"], markers=list(s.shape.names))
    assert mk.first_frame == 117
    s.values.update({"cameras": [], "sequence.has_video": False, "sequence.fps": None})
    s.raw = {k: v for k, v in s.raw.items() if not k.startswith("calibration:")}
    ctx = _ctx(s, tmp_path / "out", Options(compile="interpreted"))
    ctx.inputs.pop("keypoints")
    run(ctx)
    fit = BodyFit.load(ctx.out.dir)
    rep = json.loads((ctx.out.dir / "report.json").read_text())
    n = len(mk.xyz)
    np.testing.assert_array_equal(fit.frames, 117 + np.arange(n))
    assert rep["frames"] == n and rep["fit_rate_hz"] == 240.0
    assert rep["capture_first_frame"] == 118 and rep["capture"] == "take.c3d"
    assert fit.valid.all()
    est = forward(anny, fit.betas, fit.body_pose, fit.global_orient, fit.transl)
    jerr = np.linalg.norm(est.joints - s.truth.mocap_joints[:n], axis=2)[:, s.truth.skel.joints]
    assert jerr.mean() * 1000 < 6.0, jerr.mean() * 1000
