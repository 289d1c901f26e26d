"""Stage ``capture``: the C3D read, unit-checked and cleaned once into typed artifacts
(``artifacts.capture.Markers``, ``CameraRig``), and what that boundary guarantees downstream:
a ghost marker, a C3D in the wrong unit and a 150-sample label swap through a sequence with
video (the faults a lab's real data showed)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_marker_fit_stage import FakeWriter, _session

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ the artifacts on their own


def _markers(**over):
    from artifacts.capture import Markers

    F, M = 6, 3
    xyz = np.random.default_rng(0).normal(0, 0.3, (F, M, 3)) + [0, 0, 1]
    kw = dict(names=np.array(["A", "B", "C"]), labels=np.array(["s:A", "s:B", ""]), xyz=xyz,
              raw_observed=np.ones((F, M), bool), repair=np.zeros((F, M), np.int8),
              repair_codes=np.array(["none", "ghost", "unswapped"]), rate_hz=100.0,
              first_frame=4, unit_scale=1e-3, source="take.c3d")
    kw.update(over)
    return Markers(**kw)


def test_markers_artifact_round_trip_and_refuses_what_is_not_a_cleaned_capture(tmp_path):
    from artifacts import ArtifactError
    from artifacts.capture import Markers

    m = _markers()
    m.save(FakeWriter(tmp_path / "ok"))
    back = Markers.load(tmp_path / "ok")
    np.testing.assert_array_equal(back.xyz, m.xyz)
    assert back.marker_names == ("A", "B", "C") and int(back.first_frame) == 4
    c = back.capture()  # what the fits take
    assert c.names == ("A", "B", "C") and c.rate_hz == 100.0 and c.first_frame == 4
    with pytest.raises(ArtifactError, match=r"xyz \[frame 0\]: .*not metres"):
        _markers(xyz=m.xyz * 1000).validate("x.npz")  # millimetres
    with pytest.raises(ArtifactError, match="repair: codes outside"):
        _markers(repair=np.full((6, 3), 7, np.int8)).validate("x.npz")
    ro = np.ones((6, 3), bool)
    ro[2, 1] = False  # the file had no sample there, the artifact does: invented
    with pytest.raises(ArtifactError, match=r"xyz \[frame 2\]: .*never invents"):
        _markers(raw_observed=ro).validate("x.npz")
    rep = np.zeros((6, 3), np.int8)
    rep[1:3, 0] = 1
    rep[4, 2] = 2
    assert _markers(repair=rep).repairs_by_code() == {"ghost": 2, "unswapped": 1}


def test_camera_rig_round_trip_projects_as_the_cameras_it_was_made_from(tmp_path):
    from artifacts import ArtifactError
    from artifacts.capture import CameraRig
    from calib import look_at, project

    cams = [look_at(f"c{k}", [3 * np.cos(a), 3 * np.sin(a), 1.8], [0, 0, 1.0], (1000, 1010),
                    (440, 455), 900, 900) for k, a in enumerate([0.3, 1.9, 3.5])]
    CameraRig.from_cameras(cams, ["a.json", "b.json", "c.json"]).save(FakeWriter(tmp_path))
    rig = CameraRig.load(tmp_path)
    X = np.random.default_rng(1).normal(0, 0.4, (20, 3)) + [0, 0, 1]
    for a, b in zip(cams, rig.cameras(), strict=True):
        np.testing.assert_allclose(project(b, X), project(a, X), atol=1e-9)
    assert [c.name for c in rig.cameras(["c2", "c0"])] == ["c2", "c0"]
    with pytest.raises(ArtifactError, match="no camera 'c9'"):
        rig.cameras(["c9"])


def test_prepare_capture_repairs_a_ghost_and_says_where(tmp_path, anny):
    """A marker 5 m off for 0.1 s: removed (NaN) exactly there, coded as repaired per sample,
    named in the report; every other sample is the file's, untouched."""
    import dataclasses

    from fitting.capture import CaptureOptions, prepare_capture, read_capture

    s = _session(tmp_path, anny, np.random.default_rng(5), F=30, swap=False)
    names = tuple(s.shape.names)
    raw, labels, scale = read_capture(s.raw["c3d"], names)
    x = np.array(raw.xyz)
    k = names.index("RKNE")
    ok = np.flatnonzero(np.isfinite(x[:, k, 0]))
    a = int(ok[len(ok) // 2])
    n = int(0.1 * raw.rate_hz)
    ghost = np.zeros(len(x), bool)
    ghost[a:a + n] = np.isfinite(x[a:a + n, k, 0])
    x[ghost, k] += [5.0, 0.0, 0.0]
    art, rep = prepare_capture(dataclasses.replace(raw, xyz=x), labels, scale, "take.c3d",
                               CaptureOptions())
    assert np.isnan(art.xyz[ghost, k]).all()
    assert art.raw_observed[ghost, k].all() and art.repaired[ghost, k].all()
    codes = [str(c) for c in art.repair_codes]
    assert {codes[c] for c in art.repair[ghost, k]} <= {"ghost", "spike", "implausible_speed"}
    untouched = ~art.repaired & art.raw_observed
    np.testing.assert_array_equal(art.xyz[untouched], x[untouched])
    assert art.repaired.sum() - ghost.sum() <= 0.002 * art.raw_observed.sum()  # no false alarms
    assert rep["per_marker"]["RKNE"]["repaired"] and rep["repaired_frames"] >= ghost.sum()
    assert any("RKNE" in w and "repaired" in w for w in rep["warnings"]), rep["warnings"]
    off = prepare_capture(dataclasses.replace(raw, xyz=x), labels, scale, "take.c3d",
                          CaptureOptions(clean_enabled=False))[0]
    assert not off.repaired.any() and np.isfinite(off.xyz[ghost, k]).all()  # taken as read


# ---------------------------------------------------- through the engine, with video


def _small_copy(small_session: Path, tmp: Path, c3d: Path, stages: dict | None = None) -> tuple[Path, str]:
    """The small studio session's recipe, every path absolute, the handshake sequence alone,
    its C3D replaced by ``c3d``; returns (recipe path, sequence id)."""
    rec = yaml.safe_load(small_session.read_text())
    base = small_session.parent

    def absolute(v):
        if isinstance(v, dict):
            return {k: absolute(x) for k, x in v.items()}
        if isinstance(v, list):
            return [absolute(x) for x in v]
        if isinstance(v, str) and (base / v).exists():
            return str((base / v).resolve())
        return v

    rec = absolute(rec)
    sid = next(s for s in rec["sequences"] if "Handshake" in s)
    rec["sequences"] = {sid: {**rec["sequences"][sid], "c3d": str(c3d)}}
    rec["session"] = "capture_test"
    rec.setdefault("stages", {})
    rec["stages"].update(stages or {})
    p = tmp / "recipe.yaml"
    p.write_text(yaml.safe_dump(rec, sort_keys=False))
    return p, sid


def _pipeline(recipe: Path, sid: str, out: Path, until: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", "sequence", sid, "--recipe",
                           str(recipe), "--until", until, "--outputs", str(out)],
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True,
                          text=True, timeout=1500)


def _c3d_of(small_session: Path):
    rec = yaml.safe_load(small_session.read_text())
    sid = next(s for s in rec["sequences"] if "Handshake" in s)
    return small_session.parent / rec["sequences"][sid]["c3d"]


@pytest.mark.slow
def test_a_capture_in_metres_labelled_mm_stops_at_capture_with_one_line(small_session, tmp_path):
    """Before anything is detected or fitted: exit 2, one line naming the file and
    POINT:UNITS, no complete artifact of any stage."""
    from formats.c3d import read_c3d, write_c3d

    m = read_c3d(_c3d_of(small_session))
    bad = tmp_path / "metres.c3d"
    write_c3d(bad, type(m)(m.names, m.xyz / 1000.0, m.rate_hz, m.first_frame))  # m under "mm"
    recipe, sid = _small_copy(small_session, tmp_path, bad)
    done = _pipeline(recipe, sid, tmp_path / "out", "keypoints")
    assert done.returncode == 2, done.stderr[-3000:]
    lines = [ln for ln in done.stderr.splitlines() if "metres.c3d" in ln and "POINT:UNITS" in ln]
    assert lines, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    assert list((tmp_path / "out").rglob("manifest.json")) == []


@pytest.mark.slow
def test_a_ghost_and_a_150_sample_swap_through_a_sequence_with_video(small_session, tmp_path):
    """The studio capture at 500 Hz (resampled) with a wrist-marker label swap of 150 samples
    and a knee marker 5 m off for 0.1 s: the capture stage un-swaps the one and removes the
    other, keypoints find the wearer as on clean data (no crash on the ghost's crop), and the
    marker fit holds every marker within 15 mm."""
    from formats.c3d import read_c3d, write_c3d

    m = read_c3d(_c3d_of(small_session))
    rate = 500.0
    t0 = np.arange(len(m.xyz)) / m.rate_hz
    t = np.arange(0, t0[-1] + 1e-9, 1 / rate)
    x = np.stack([np.stack([np.interp(t, t0, m.xyz[:, j, d]) for d in range(3)], -1)
                  for j in range(len(m.names))], axis=1)
    assert len(t) >= 200, len(t)
    clean = x.copy()
    names = list(m.names)
    wa = next(i for i, n in enumerate(names) if n.endswith("LWRA"))
    wb = next(i for i, n in enumerate(names) if n.endswith("LWRB"))
    kn = next(i for i, n in enumerate(names) if n.endswith("RKNE"))
    s0 = (len(t) - 150) // 2
    x[s0:s0 + 150, [wa, wb]] = x[s0:s0 + 150, [wb, wa]]
    g0 = len(t) // 5
    x[g0:g0 + 50, kn] += [5.0, 0.0, 0.0]
    path = tmp_path / "faults.c3d"
    write_c3d(path, type(m)(m.names, x, rate, round(m.first_frame * rate / m.rate_hz)))
    recipe, sid = _small_copy(small_session, tmp_path, path)
    out = tmp_path / "out"
    done = _pipeline(recipe, sid, out, "marker_fit")
    assert done.returncode == 0, done.stderr[-4000:]
    seq = next(out.rglob("capture/markers.npz")).parent
    from artifacts.capture import Markers

    cap = Markers.load(seq)
    codes = [str(c) for c in cap.repair_codes]
    rep = json.loads((seq / "report.json").read_text())
    order = [names.index(n) if n in names else next(i for i, x in enumerate(names)
                                                     if x.endswith(":" + n))
             for n in cap.marker_names]
    a, b = cap.marker_names.index("LWRA"), cap.marker_names.index("LWRB")
    k = cap.marker_names.index("RKNE")
    swapped = slice(s0, s0 + 150)
    assert {codes[c] for c in cap.repair[swapped, a]} == {"unswapped"}, rep["cleaning"]
    np.testing.assert_allclose(cap.xyz[swapped][:, [a, b]], clean[swapped][:, [order[a], order[b]]],
                               atol=1e-6)
    assert np.isnan(cap.xyz[g0:g0 + 50, k]).all() and cap.repaired[g0:g0 + 50, k].all()
    # the keypoints found the wearer in the views as usual: the ghost did not move its crop
    kp = np.load(next(out.rglob("keypoints/keypoints.npz")))["kp"]
    found = (kp[:, :, 0, :23, 2] > 0).any(axis=-1).mean()
    assert found > 0.8, found
    fit = json.loads(next(out.rglob("marker_fit/report.json")).read_text())
    res = np.load(next(out.rglob("marker_fit/fit.npz")))["marker_residual_m"]
    assert np.nanmax(res) * 1000 < 15.0, (np.nanmax(res), fit.get("warnings"))


@pytest.mark.slow
def test_marker_loo_refits_with_the_options_marker_fit_used(tmp_path, anny):
    """marker_fit writes the options it ran with; marker_loo's refits use them (not the
    defaults), hands off, and its report says which."""
    from test_marker_fit_stage import _ctx, view

    import stages.marker_loo as loo
    from fitting.marker_fit import MarkerFitOptions
    from stages.marker_fit import run

    s = _session(tmp_path, anny, np.random.default_rng(9), F=16, swap=False)
    opts = MarkerFitOptions(sigma_marker_mm=12.0, max_iters=6, weights={"L_theta": 0.3})
    ctx = _ctx(s, tmp_path / "mf", opts)
    run(ctx)
    saved = MarkerFitOptions.load(ctx.out.dir)
    assert saved == opts
    from formats.video import write_mp4

    video = tmp_path / "v.mp4"  # marker_loo counts the video's frames
    write_mp4(video, np.zeros((16, 16, 16, 3), np.uint8), s.values["sequence.fps"])
    lctx = type(ctx)(**{**vars(ctx), "stage": "marker_loo", "recipe": view(loo, s.values),
                        "raw": {**ctx.raw, "video": video},
                        "params": loo.Options(markers=["LWRA", "RKNE"], stride=4),
                        "out": FakeWriter(tmp_path / "loo"),
                        "inputs": {**ctx.inputs, "marker_fit": ctx.out.dir}})
    loo.run(lctx)
    rep = json.loads((tmp_path / "loo" / "report.json").read_text())
    fo = rep["fit_options"]
    assert fo["sigma_marker_mm"] == 12.0 and fo["max_iters"] == 6 and fo["use_hands"] is False
    assert fo["weights"]["L_theta"] == 0.3
    assert set(rep["per_marker"]) == {"LWRA", "RKNE"}
    (ctx.out.dir / "options.json").unlink()  # an artifact of older code: recompute, said plainly
    from formats.errors import InputError

    with pytest.raises(InputError, match=r"options\.json: <file>: missing"):
        loo.run(lctx)


def test_fit_summary_is_what_the_export_republishes(tmp_path):
    """A fit's headline figures travel as a typed FitSummary (no report keys read by name):
    round trip, and counts that do not add up are refused naming the field."""
    from artifacts import ArtifactError, FitSummary

    s = FitSummary(fit="marker_fit", subject="s1", frames=10, frames_valid=8,
                   frames_not_valid={"held_before_first_marker": 2, "too_few_markers": 0},
                   warnings=("marker RWRA: 30 mm",), figures={"residual_mm": {"median": 2.1}})
    s.save(FakeWriter(tmp_path))
    back = FitSummary.load(tmp_path)
    assert back.published() == {"subject": "s1", "frames": 10, "frames_valid": 8,
                                "frames_not_valid": {"held_before_first_marker": 2,
                                                     "too_few_markers": 0},
                                "residual_mm": {"median": 2.1},
                                "warnings": ["marker RWRA: 30 mm"]}
    bad = FitSummary(fit="marker_fit", subject="s1", frames=10, frames_valid=9,
                     frames_not_valid={"too_few_markers": 2})
    with pytest.raises(ArtifactError, match="summary.json: frames_not_valid"):
        bad.save(FakeWriter(tmp_path / "bad"))
    assert not (tmp_path / "bad" / "summary.json").exists()
    doc = json.loads((tmp_path / "summary.json").read_text())
    doc["fit"] = "keypoints"
    (tmp_path / "summary.json").write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match="summary.json: fit"):
        FitSummary.load(tmp_path)
