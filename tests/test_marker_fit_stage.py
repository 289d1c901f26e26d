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

from formats.errors import InputError


class FakeArtifact:
    def __init__(self, folder: Path, arrays: dict[str, dict]):
        self.dir = folder
        self._arrays = arrays

    def arrays(self, name):
        return self._arrays[name]

    def json(self, name):
        return json.loads((self.dir / f"{name}.json").read_text())

    def path(self, filename):
        return self.dir / filename


class FakeWriter:
    def __init__(self, folder: Path):
        self.dir = folder
        folder.mkdir(parents=True, exist_ok=True)

    def save_arrays(self, name, **arrays):
        np.savez(self.dir / f"{name}.npz", **arrays)
        return self.dir / f"{name}.npz"

    def save_json(self, name, obj):
        (self.dir / f"{name}.json").write_text(json.dumps(obj))
        return self.dir / f"{name}.json"

    def path(self, filename):
        return self.dir / filename


@pytest.fixture(scope="module")
def anny():
    from body import load_model

    try:
        return load_model("anny")
    except InputError as e:
        pytest.skip(f"Anny not exported: {e}")


def _session(tmp: Path, model, rng, F=40, fps=50.0, rate=240.0, swap=True, fingers=False):
    """Truth motion, its markers as a Vicon C3D, cameras, and the stage context pieces."""

    from bench import fitting_synth as S
    from body.lbs import rest_state
    from calib import look_at
    from calib.io import write_chi3d_camera
    from fitting import shape, skinned
    from formats.c3d import read_c3d
    from stages.marker_fit import template_placement

    betas = S.subject_betas(model, rng)[:80]
    pl = template_placement(model, "plug-in-gait")
    skel = skinned.fit_skeleton(model, None if fingers else shape.body_joints(model))
    # mocap at 240 Hz covering the video (sync offset -0.1 s), motion defined per mocap sample
    sync = -0.1
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
    gaps = write_vicon_pig(tmp / "take.c3d", markers, rate, rng, first_frame=0, n_gaps=10,
                           gap_len=(10, 80))
    assert read_c3d(tmp / "take.c3d", markers=pl.names).rate_hz == rate
    cams = {}
    for k, a in enumerate([0.5, 2.1, 3.7, 5.3]):
        name = f"cam{k}"
        cam = look_at(name, [4 * np.cos(a), 4 * np.sin(a), 2.0], [0, 0, 1.0], (1100, 1100),
                      (450, 450), 900, 900)
        cams[name] = write_chi3d_camera(tmp / "cams" / name / "take.json", cam)
    t_video = np.arange(F) / fps - sync
    sample = np.round(t_video * rate).astype(int)  # video frames fall on mocap samples
    art = FakeArtifact(tmp, {"shape": {
        "betas": betas, "marker_names": np.array(pl.names), "marker_face": pl.face,
        "marker_bary": pl.bary, "marker_offset": pl.offset}})
    kp = np.zeros((4, F, 2, 65, 3), np.float32)  # detections without hands (conf 0)
    if fingers:  # person 0's hand keypoints: the truth projected, 2 px noise
        from body.joints import regressor
        from calib import project
        from calib.io import read_chi3d_camera

        R = regressor(model, "kp65")
        pts = np.stack([R @ np.concatenate([truth.vertices[s], truth.joints[s]])
                        for s in np.round((np.arange(F) / fps - sync) * rate).astype(int)])
        for c, p in enumerate(cams.values()):
            uv = project(read_chi3d_camera(p), pts) + rng.normal(0, 2.0, pts.shape[:2] + (2,))
            kp[c, :, 0, 23:65, :2] = uv[:, 23:65]
            kp[c, :, 0, 23:65, 2] = 0.9
    kp_art = FakeArtifact(tmp, {"keypoints": {"kp": kp, "frames": np.arange(F)}})
    seq = SimpleNamespace(markers_on="s1", partner="s2", fps=fps,
                          mocap=SimpleNamespace(sync_offset_s=sync, rate_hz=None))
    recipe = SimpleNamespace(
        body_model=SimpleNamespace(kind="anny", path=None), cameras=list(cams),
        subjects={"s1": SimpleNamespace(markerset="plug-in-gait")},
        sequence=lambda unit: seq)
    raw = {"c3d": tmp / "take.c3d", **{f"calibration:{c}": p for c, p in cams.items()}}
    truth_video = SimpleNamespace(joints=truth.joints[sample], vertices=truth.vertices[sample],
                                  skel=skel, gaps=gaps)
    return recipe, raw, art, kp_art, truth_video


@pytest.mark.slow
def test_stage_recovers_motion_from_vicon_export(tmp_path, anny):
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(21)
    F = 40
    recipe, raw, art, kp_art, truth = _session(tmp_path, anny, rng, F=F)
    out = FakeWriter(tmp_path / "out")
    logs = []
    ctx = SimpleNamespace(stage="marker_fit", unit="g/take", recipe=recipe, params=Options(),
                          inputs={"shape_fit": {"s1": art}, "keypoints": kp_art}, raw=raw,
                          out=out, progress=lambda it, **k: it, log=logs.append)
    run(ctx)
    fit = dict(np.load(out.dir / "fit.npz"))
    rep = json.loads((out.dir / "report.json").read_text())
    assert (out.dir / "residuals.png").stat().st_size > 1000
    assert fit["body_pose"].shape == (F, anny.num_joints, 3)
    assert fit["global_orient"].shape == (F, 3, 3) and fit["transl"].shape == (F, 3)
    assert rep["hands"] is False and rep["frames"] == F
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
def test_stage_uses_hand_keypoints_when_present(tmp_path, anny):
    """Fingers move in the truth; the markers can't see them, person 0's hand keypoints can."""
    from stages.marker_fit import Options, run

    rng = np.random.default_rng(5)
    F = 12
    recipe, raw, art, kp_art, truth = _session(tmp_path, anny, rng, F=F, swap=False, fingers=True)
    errs = {}
    for hands in (True, False):
        out = FakeWriter(tmp_path / f"out{hands}")
        ctx = SimpleNamespace(stage="marker_fit", unit="g/take", recipe=recipe,
                              params=Options(use_hands=hands, compile="interpreted"),
                              inputs={"shape_fit": {"s1": art}, "keypoints": kp_art}, raw=raw,
                              out=out, progress=lambda it, **k: it, log=lambda s: None)
        run(ctx)
        rep = json.loads((out.dir / "report.json").read_text())
        assert rep["hands"] is hands
        fit = dict(np.load(out.dir / "fit.npz"))
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
    recipe, raw, art, kp_art, truth = _session(tmp_path, anny, rng, F=F, swap=False)
    frames = np.arange(0, F, stride)
    kp = kp_art.arrays("keypoints")["kp"][:, frames]
    strided = FakeArtifact(tmp_path, {"keypoints": {"kp": kp, "frames": frames}})
    out = FakeWriter(tmp_path / "out")
    ctx = SimpleNamespace(stage="marker_fit", unit="g/take", recipe=recipe, params=Options(),
                          inputs={"shape_fit": {"s1": art}, "keypoints": strided}, raw=raw,
                          out=out, progress=lambda it, **k: it, log=lambda s: None)
    run(ctx)
    fit = dict(np.load(out.dir / "fit.npz"))
    assert np.array_equal(fit["frames"], frames)
    est = forward(anny, fit["betas"], fit["body_pose"], fit["global_orient"], fit["transl"])
    jerr = np.linalg.norm(est.joints - truth.joints[frames], axis=2)[:, truth.skel.joints] * 1000
    assert jerr.mean() < 8.0, jerr.mean()
