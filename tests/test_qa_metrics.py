"""QA metrics, thresholds, flags and spans (``qa.metrics``) on small synthetic sequences: two
Anny bodies posed directly (no engine), three cameras, detections projected from the bodies."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from artifacts import BodyFit
from artifacts.keypoints import Keypoints2D
from qa.metrics import (
    Flags,
    QAMetrics,
    QAOptions,
    Span,
    flag_frames,
    sequence_metrics,
    threshold_name,
)

F = 12
FPS = 10.0  # 0.1 s per frame: the jerk step is one frame
WALK_M_S = 1.0  # the wearer slides along y at this speed, feet on the floor
PUSH = (4, 5)  # frames where the partner is pushed into the wearer
LOWER = (8,)  # frames where the wearer is lowered by 5 cm
ROTATED = (6, 7)  # frames where the partner's right elbow is rotated by 40 degrees
GROUND = (np.array([0.0, 0.0, 1.0]), 0.0)


@pytest.fixture(scope="module")
def model():
    from body import load_model

    return load_model("anny")


def _fit(model, transl, body_pose=None, markers=None) -> BodyFit:
    n = len(transl)
    bp = np.zeros((n, model.num_joints, 3)) if body_pose is None else body_pose
    kw = {}
    if markers is not None:
        M = markers.shape[1]
        kw = dict(marker_names=np.array([f"M{i}" for i in range(M)]), marker_residual_m=markers,
                  marker_weight=np.ones_like(markers), visible=np.ones(markers.shape, bool))
    return BodyFit(body_pose=bp, global_orient=np.tile(np.eye(3), (n, 1, 1)),
                   transl=np.asarray(transl, float), betas=np.zeros(10),
                   frames=np.arange(n), valid=np.ones(n, bool),
                   invalid_reason=np.zeros(n, np.int8), **kw)


def _cams():
    from calib.camera import look_at

    target = (0.7, 0.0, 0.0)
    out = []
    for i, ang in enumerate((-np.pi / 2, -np.pi / 2 + 0.9, -np.pi / 2 - 0.9)):
        c = (0.7 + 5 * np.cos(ang), 5 * np.sin(ang), 0.3)
        out.append(look_at(f"cam{i}", c, target, (1000.0, 1000.0), (640.0, 480.0), 1280, 960))
    return out


def _keypoints(model, fits, cams, delay=None, delayed=0) -> Keypoints2D:
    """Detections = the fits' KP65 projected (conf 1). delay (view, frames): that view's
    detections of person ``delayed`` (0: the wearer) of frame f show frame f + frames."""
    from body import forward
    from body.joints import keypoints as kp65
    from calib import project

    C = len(cams)
    kp = np.zeros((C, F, 2, 65, 3), np.float32)
    for p, fit in enumerate(fits):
        X = kp65(model, forward(model, fit.betas, fit.body_pose, fit.global_orient, fit.transl),
                 "kp65")
        for c, cam in enumerate(cams):
            kp[c, :, p, :, :2] = project(cam, X)
            kp[c, :, p, :, 2] = 1.0
            if delay is not None and delay[0] == c and p == delayed:
                s = delay[1]
                kp[c, :F - s, p] = kp[c, s:, p].copy()
                kp[c, F - s:, p, :, 2] = 0.0
    return Keypoints2D(kp=kp, boxes=np.full((C, F, 2, 4), np.nan, np.float32),
                       hand_boxes=np.full((C, F, 2, 2, 4), np.nan, np.float32),
                       frames=np.arange(F), wearer_retry=np.zeros((C, F), bool),
                       partner_mode=np.ones((C, F), np.int8),
                       cross_view_outlier=np.zeros((C, F, 2, 65), bool),
                       conf_raw=kp[..., 2].copy(), cameras=np.array([c.name for c in cams]))


@pytest.fixture(scope="module")
def scene(model):
    from body import forward

    rest = forward(model, np.zeros(10), np.zeros((1, model.num_joints, 3)),
                   np.eye(3)[None], np.zeros((1, 3))).vertices[0]
    z0 = -rest[:, 2].min() + 0.002  # soles 2 mm above the floor
    t = np.arange(F) / FPS
    wt = np.stack([np.zeros(F), WALK_M_S * t, np.full(F, z0)], 1)
    for f in LOWER:
        wt[f, 2] -= 0.05
    res = np.full((F, 4), 0.002)
    res[3:5, :2] = 0.12  # two markers swapped for two frames
    wearer = _fit(model, wt, markers=res)
    pt = np.tile([1.45, 0.0, z0], (F, 1))
    pt[:, 1] = wt[:, 1]  # side by side, moving together (arms out, 30 cm apart)
    for f in PUSH:
        pt[f, 0] = 0.65  # the wearer's hand and forearm in the partner's chest
    partner_clean = _fit(model, pt)
    bp = np.array(partner_clean.body_pose)
    j = model.joint_index("lowerarm01.R")
    for f in ROTATED:
        bp[f, j] = [0.0, 0.0, np.radians(40)]
    partner = dataclasses.replace(partner_clean, body_pose=bp)
    cams = _cams()
    kps = _keypoints(model, [wearer, partner_clean], cams)
    m = sequence_metrics(model, wearer, partner, kps, cams, None, GROUND, FPS)
    return dict(m=m, wearer=wearer, partner=partner, partner_clean=partner_clean, cams=cams)


def _other(frames_bad):
    return [f for f in range(F) if f not in frames_bad]


def test_penetration_and_volume_respond_to_a_limb_pushed_in(scene):
    m = scene["m"]
    pen, vol = m.values["penetration_mm"], m.values["penetration_volume_cm3"]
    assert m.units["penetration_mm"] == "mm" and m.units["penetration_volume_cm3"] == "cm3"
    for f in PUSH:
        assert pen[f] > 25.0, pen  # a forearm is ~8 cm thick: depth to the nearest surface
        assert vol[f] > 20.0, vol
    assert np.all(pen[_other(PUSH)] == 0.0) and np.all(vol[_other(PUSH)] == 0.0)
    fl = flag_frames(m, QAOptions(penetration_mm=25.0))
    r = fl.reasons.index("penetration_mm")
    assert fl.flagged[list(PUSH), r].all() and not fl.flagged[_other(PUSH), r].any()


def test_ground_penetration_of_a_lowered_body(scene):
    g = scene["m"].values["wearer.ground_penetration_mm"]
    for f in LOWER:
        assert 46.0 < g[f] < 50.0, g
    assert np.all(g[_other(LOWER)] < 1.0)
    assert np.all(scene["m"].values["partner.ground_penetration_mm"] < 1.0)


def test_foot_skate_of_a_dragged_foot(scene):
    m = scene["m"]
    sk = m.values["wearer.foot_skate_m_s"]
    ok = [f for f in range(1, F) if f not in LOWER and f - 1 not in LOWER]
    assert np.allclose(sk[ok], WALK_M_S, rtol=0.05), sk
    assert np.isnan(sk[0])  # no previous frame
    flags = flag_frames(m, QAOptions(foot_skate_m_s=0.5))
    assert flags.flagged[ok, flags.reasons.index("wearer.foot_skate_m_s")].all()


def test_rotated_limb_shows_in_jerk_and_reprojection(scene, model):
    m = scene["m"]
    jk = m.values["partner.jerk_m_s3"]
    def window_has(f, bad):  # jerk of frame f: fit frames f-2, f-1, f, f+1
        return any(f - 2 <= r <= f + 1 for r in bad)

    fin = [f for f in range(F) if np.isfinite(jk[f])]
    rot = [f for f in fin if window_has(f, ROTATED) and not window_has(f, PUSH)]
    far = [f for f in fin if not window_has(f, ROTATED + PUSH)]
    assert rot and far
    # 40 degrees at the elbow for 0.2 s: ~150-300 m/s3, far below the default threshold (which
    # the clean bench and demo fits reach: 660 m/s3), flagged by a tighter one
    assert jk[rot].min() > 100.0
    fl = flag_frames(m, QAOptions(jerk_m_s3=100.0))
    assert fl.flagged[rot, fl.reasons.index("partner.jerk_m_s3")].all()
    assert np.all(jk[far] < 1.0)  # constant velocity: no jerk
    wj = m.values["wearer.jerk_m_s3"]  # constant velocity but for the frame lowered by 5 cm
    assert np.nanmax(wj[[f for f in fin if not window_has(f, LOWER)]]) < 1.0
    assert np.nanmin(wj[[f for f in fin if window_has(f, LOWER)]]) > 40.0
    v = m.values["partner.reproj_views_body_px"]  # the wrist moves ~11 cm: ~22 px at 5 m
    assert v[list(ROTATED)].min() > 15.0 and v[_other(ROTATED)].max() < 1.0, v
    # per view: the worst limb's median. The arm's (shoulder, elbow, wrist) hides a wrist
    # alone, the hand (21 keypoints moving with the forearm) shows it
    arm = np.stack([m.values[f"partner.reproj_body_px.{c.name}"] for c in scene["cams"]])
    assert arm.max() < 1.0
    pv = np.stack([m.values[f"partner.reproj_hands_px.{c.name}"] for c in scene["cams"]])
    assert pv[:, list(ROTATED)].min() > 10.0 and pv[:, _other(ROTATED)].max() < 1.0
    for c in scene["cams"]:
        assert np.nanmax(m.values[f"wearer.reproj_body_px.{c.name}"]) < 1.0
    fl = flag_frames(m, QAOptions(reproj_views_body_px=10.0))
    assert fl.any[list(ROTATED)].all()
    span = next(s for s in fl.spans if s.start <= ROTATED[0] <= s.end)
    assert "partner.reproj_views_body_px" in span.reasons


def test_marker_burst_flags_marker_max(scene):
    m = scene["m"]
    mx = m.values["wearer.marker_max_mm"]
    assert np.allclose(mx[3:5], 120.0) and np.allclose(np.delete(mx, [3, 4]), 2.0)
    assert np.allclose(m.values["wearer.marker_median_mm"][3:5], 61.0)
    fl = flag_frames(m, QAOptions())
    r = fl.reasons.index("wearer.marker_max_mm")
    assert fl.flagged[3:5, r].all() and fl.flagged[:, r].sum() == 2


def test_outputs_cover_both_people(scene, model):
    m = scene["m"]
    assert m.people == ["wearer", "partner"]
    assert [v.shape for v in m.vertices] == [(F, model.num_vertices, 3)] * 2
    assert np.array_equal(m.frames, np.arange(F))
    assert np.all(m.values["partner.not_valid"] == 0.0)
    assert "partner.not_valid" in m.thresholds and m.thresholds["partner.not_valid"] == 0.5
    assert np.isnan(m.values["unexpected_contact_mm"]).all()  # no annotation: not applicable
    assert np.isnan(m.values["contact_gap_mm"]).all()
    json.dumps(m.sequence)
    for n, v in m.values.items():
        assert v.shape == (F,), n
        assert n in m.units


def test_sync_offset_of_a_delayed_view(scene, model):
    cams = scene["cams"]
    kps = _keypoints(model, [scene["wearer"], scene["partner_clean"]], cams, delay=(1, 2))
    m = sequence_metrics(model, scene["wearer"], None, kps, cams, None, GROUND, FPS)
    assert m.sequence["sync_offset_frames"] == {"cam0": 0, "cam1": 2, "cam2": 0}
    v = m.values["sync_offset_frames.cam1"]
    assert np.all(v == 2.0) and np.all(m.values["sync_offset_frames.cam0"] == 0.0)
    assert m.people == ["wearer"] and len(m.vertices) == 1
    assert np.isnan(m.values["penetration_mm"]).all()  # one person: not applicable
    fl = flag_frames(m, QAOptions())
    r = fl.reasons.index("sync_offset_frames.cam1")
    assert fl.flagged[:, r].all()
    assert not fl.flagged[:, fl.reasons.index("sync_offset_frames.cam0")].any()
    assert not flag_frames(m, QAOptions(sync_max_frames=2)).flagged[:, r].any()


def test_sync_offset_measured_on_the_partner_when_the_wearer_stands_still(scene, model):
    """A wearer standing still says nothing of time; the partner walking past does: a view
    whose both people are 2 frames late is found from the partner's detections (the wearer's
    alone leave it not measured)."""
    cams = scene["cams"]
    w = scene["wearer"]
    still = dataclasses.replace(w, transl=np.tile(np.asarray(w.transl)[:1], (F, 1)))
    pt = np.asarray(scene["partner_clean"].transl).copy()
    pt[:, 0] = 1.45  # no push: the partner walks along y past the wearer
    walker = dataclasses.replace(scene["partner_clean"], transl=pt)
    kps = _keypoints(model, [still, walker], cams, delay=(1, 2), delayed=1)
    both = sequence_metrics(model, still, walker, kps, cams, None, GROUND, FPS)
    assert both.sequence["sync_offset_frames"] == {"cam0": 0, "cam1": 2, "cam2": 0}
    assert both.sequence["sync_z"]["cam1"] >= 2.5
    json.dumps(both.sequence, allow_nan=False)  # the report is strict JSON (no infinity)
    alone = sequence_metrics(model, still, None, kps, cams, None, GROUND, FPS)
    assert alone.sequence["sync_offset_frames"] == {}  # nothing moved: too few points
    assert alone.sequence["sync_points"] == {"cam0": 0, "cam1": 0, "cam2": 0}


def test_a_view_whose_cost_does_not_move_with_the_shift_is_not_called_in_sync():
    """qa.metrics._sync_rise: the cost curve of session 32's bench view delayed by 2 frames
    (its detections did not follow the motion: 17.7-18.2 px from -3 to 0) is flat, so the
    view is not measurable, where it read 0 (in sync) before; a view that follows the motion
    (the clean views' V, 8 -> 11 px at 2 frames) rises on both sides, also around a best
    shift next to the range's end (one side then looks 1 frame away only)."""
    from qa import constants as K
    from qa.metrics import _sync_rise

    delayed = dict(zip(range(-3, 4), (17.929, 17.724, 17.838, 18.244, 18.878, 19.637, 20.366),
                       strict=True))
    assert _sync_rise(delayed, 0) < 0 < K.SYNC_MIN_RISE  # -2 is cheaper than the 0 it reads
    assert _sync_rise(delayed, -2) < K.SYNC_MIN_RISE  # and -2 itself is not told from -3
    v = dict(zip(range(-3, 4), (12.86, 11.06, 9.14, 7.97, 9.29, 11.27, 12.79), strict=True))
    assert _sync_rise(v, 0) == pytest.approx(11.06 / 7.97 - 1) and _sync_rise(v, 0) > 0.3
    shifted = {s: v[min(max(s + 2, -3), 3)] for s in range(-3, 4)}  # best at -2
    assert min(shifted, key=shifted.get) == -2
    assert _sync_rise(shifted, -2) == pytest.approx(9.14 / 7.97 - 1)  # -3: one frame away
    assert _sync_rise(shifted, -2) > K.SYNC_MIN_RISE


def test_a_view_that_reads_nobody_in_time_is_reported_not_measurable(scene, model):
    """Through sequence_metrics: a view whose partner detections stand still while the partner
    walks past (a detector locked on a poster) is not measurable, with its reason, and the
    views that see the walk are measured in sync; the report is strict JSON."""
    cams = scene["cams"]
    w = scene["wearer"]
    still = dataclasses.replace(w, transl=np.tile(np.asarray(w.transl)[:1], (F, 1)))
    pt = np.asarray(scene["partner_clean"].transl).copy()
    pt[:, 0] = 1.45
    walker = dataclasses.replace(scene["partner_clean"], transl=pt)
    kps = _keypoints(model, [still, walker], cams)
    kp = np.array(kps.kp)
    rng = np.random.default_rng(3)
    mid = kp[1, F // 2, 1, :, :2].copy()
    kp[1, :, 1, :, :2] = mid + rng.normal(0, 6.0, (F, 65, 2))  # cam1: the partner frozen
    kps = dataclasses.replace(kps, kp=kp)
    m = sequence_metrics(model, still, walker, kps, cams, None, GROUND, FPS)
    seq = m.sequence
    assert seq["sync_offset_frames"] == {"cam0": 0, "cam2": 0}
    assert "cam1" in seq["sync_not_measurable"]
    assert seq["sync_not_measurable_why"]["cam1"].startswith("flat")  # 0 (in sync) before
    assert seq["sync_rise"]["cam0"] > 0.1 and seq["sync_rise"]["cam2"] > 0.1
    json.dumps(seq, allow_nan=False)


def test_a_shift_that_wins_in_some_frames_only_is_not_kept():
    from qa.metrics import _paired_z

    frames = np.repeat(np.arange(10), 5)  # 10 person-frames of 5 detections
    steady = np.full(50, 1.5)  # every frame gains 1.5 px at the shift
    assert _paired_z(steady, frames) == np.inf
    rng = np.random.default_rng(0)
    noisy = rng.normal(1.5, 1.0, 50)
    assert _paired_z(noisy, frames) > 2.5
    # one frame gains 30 px (a wrong detection), the others lose a little: a larger mean gain
    # than ``steady``'s, but from one frame
    one = np.where(frames == 3, 30.0, -0.3)
    assert one.mean() > 2.0 and _paired_z(one, frames) < 2.5
    assert _paired_z(steady[:10], frames[:10]) == 0.0  # two person-frames: not judged


# ---------------------------------------------------------------------------- spans, options


def _metrics(frames, **values):
    frames = np.asarray(frames)
    vals = {k: np.asarray(v, float) for k, v in values.items()}
    thr = {k: 0.5 if k.endswith("not_valid") else 1.0 for k in vals}
    return QAMetrics(frames, vals, {k: "" for k in vals}, thr, {}, [], [])


def test_spans_merge_close_frames_and_split_far_ones():
    frames = np.arange(0, 60, 6)  # stride 6: gaps count in fit frames, not video frames
    pen = np.zeros(10)
    pen[[1, 2, 4]] = [50.0, 80.0, 45.0]  # rows 2 and 4: 2 fit frames apart -> merged
    pen[8] = 41.0  # 4 fit frames after row 4 -> its own span
    nv = np.zeros(10)
    nv[9] = 1.0
    m = _metrics(frames, penetration_mm=pen, **{"partner.not_valid": nv})
    opts = QAOptions(penetration_mm=40.0, merge_gap_frames=2)
    fl = flag_frames(m, opts)
    assert isinstance(fl, Flags)
    assert fl.reasons == ("penetration_mm", "partner.not_valid")
    assert fl.flagged.shape == (10, 2)
    assert [(s.start, s.end) for s in fl.spans] == [(6, 24), (48, 54)]
    a, b = fl.spans
    assert a.reasons == ["penetration_mm"] and a.peak_frame == 12 and a.worst == {"penetration_mm": 80.0}
    assert b.reasons == ["penetration_mm", "partner.not_valid"]
    assert b.peak_frame == 54  # not valid: 1.0 / 0.5 beats 41 / 40
    assert fl.rate == pytest.approx(5 / 10)
    assert np.array_equal(fl.any, np.isin(np.arange(10), [1, 2, 4, 8, 9]))
    j = json.loads(json.dumps(a.to_json()))
    assert j == {"start": 6, "end": 24, "reasons": ["penetration_mm"], "peak_frame": 12,
                 "worst": {"penetration_mm": 80.0}}
    # a smaller gap splits the first span
    fl1 = flag_frames(m, dataclasses.replace(opts, merge_gap_frames=1))
    assert [(s.start, s.end) for s in fl1.spans] == [(6, 12), (24, 24), (48, 54)]
    # a threshold only the peak beats
    fl2 = flag_frames(m, dataclasses.replace(opts, penetration_mm=60.0))
    assert [(s.start, s.end) for s in fl2.spans] == [(12, 12), (54, 54)]


def test_lower_is_bad_and_sync_flag_directions():
    frames = np.arange(5)
    m = _metrics(frames, unexpected_contact_mm=[100.0, 3.0, np.nan, 0.0, 6.0],
                 **{"sync_offset_frames.c": [2.0] * 5, "sync_offset_frames.d": [-1.0] * 5})
    fl = flag_frames(m, QAOptions(unexpected_contact_mm=5.0, sync_max_frames=1))
    r = fl.reasons.index("unexpected_contact_mm")
    assert fl.flagged[:, r].tolist() == [False, True, False, True, False]
    assert fl.flagged[:, fl.reasons.index("sync_offset_frames.c")].all()
    assert not fl.flagged[:, fl.reasons.index("sync_offset_frames.d")].any()
    assert fl.spans[0].worst["unexpected_contact_mm"] == 0.0


def test_no_flags_no_spans():
    m = _metrics(np.arange(4), penetration_mm=np.zeros(4))
    fl = flag_frames(m, QAOptions())
    assert fl.spans == [] and fl.rate == 0.0 and not fl.any.any()


def test_threshold_names():
    assert threshold_name("wearer.marker_max_mm") == "marker_max_mm"
    assert threshold_name("partner.marker_max_mm") is None
    assert threshold_name("partner.reproj_hands_px.50591643") == "reproj_hands_px"
    assert threshold_name("wearer.reproj_views_face_px") == "reproj_views_face_px"
    assert threshold_name("sync_offset_frames.58860488") == "sync_max_frames"
    assert threshold_name("partner.jerk_m_s3") == "jerk_m_s3"
    assert threshold_name("penetration_volume_cm3") == "penetration_volume_cm3"
    assert threshold_name("partner.not_valid") is None
    assert threshold_name("nonsense") is None


@pytest.mark.parametrize("field,value", [
    ("penetration_mm", -1.0), ("jerk_m_s3", 0.0), ("marker_max_mm", float("nan")),
    ("merge_gap_frames", -1), ("merge_gap_frames", 1.5), ("sync_max_frames", "2"),
    ("min_conf", 1.5), ("reproj_statistic", "mean"), ("contact_margin_frames", True),
])
def test_bad_options_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        QAOptions(**{field: value})


def test_span_dataclass_json_handles_nan():
    s = Span(3, 7, ["x"], 5, {"x": float("nan")})
    assert s.to_json()["worst"] == {"x": None}


def test_a_swap_burst_repaired_by_the_cleaning_is_flagged(small_session):
    """``marker_fit`` cleans its capture first: a label swap is un-swapped (or removed) and
    the fit looks fine, so QA flags the frames whose capture was repaired (and only those)."""
    import yaml

    from fitting.marker_clean import clean_markers
    from fitting.mocap import VideoClock
    from formats.c3d import read_c3d
    from qa.metrics import capture_repairs

    rec = yaml.safe_load(small_session.read_text())
    seq = next(iter(rec["sequences"].values()))
    raw = read_c3d(small_session.parent / seq["c3d"])
    i, j = raw.names.index("LKNE"), raw.names.index("RKNE")
    a = len(raw.xyz) // 3
    xyz = np.array(raw.xyz)
    xyz[a:a + 12, [i, j]] = xyz[a:a + 12, [j, i]]  # a burst of 12 samples, knees swapped
    bad = dataclasses.replace(raw, xyz=xyz)
    clock = VideoClock(float(seq.get("fps") or 50.0), 0.0, None)
    t_src = (raw.first_frame + np.arange(len(xyz))) / raw.rate_hz
    frames = np.arange(int(t_src[-1] * clock.fps))
    def changed(before):
        after = clean_markers(before)[0]
        a, b = np.asarray(before.xyz), np.asarray(after.xyz)
        return ~((a == b) | (np.isnan(a) & np.isnan(b))).all(axis=-1)

    assert not capture_repairs(changed(raw), raw.rate_hz, raw.first_frame, frames, clock).any()
    rep = capture_repairs(changed(bad), bad.rate_hz, bad.first_frame, frames, clock)
    t = frames / clock.fps
    inside = (t > t_src[a] + 0.5 / raw.rate_hz) & (t < t_src[a + 11] - 0.5 / raw.rate_hz)
    assert inside.any() and (rep[inside] >= 2).all(), rep
    far = (t < t_src[a] - 0.1) | (t > t_src[a + 11] + 0.1)
    assert (rep[far] == 0).all(), rep
    m = _metrics(frames, **{"wearer.markers_repaired": rep})
    fl = flag_frames(m, QAOptions())
    assert np.array_equal(fl.flagged[:, fl.reasons.index("wearer.markers_repaired")], rep > 0)
