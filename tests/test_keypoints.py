"""The keypoints stage: frame selection, marker timing, the videos' lengths and rates, and whole
runs through the engine on a small rendered two-person session (mediapipe) and on precomputed
OpenPose files."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from detect import layout
from fitting.mocap import VideoClock
from formats.c3d import Markers
from stages.keypoints import Options, frame_indices, markers_on_frames

FPS, HZ, OFFSET = 50.0, 100.0, -0.12
N_FRAMES = 4


def test_frame_indices():
    assert frame_indices(10, Options()).tolist() == list(range(10))
    assert frame_indices(10, Options(stride=3)).tolist() == [0, 3, 6, 9]
    assert frame_indices(10, Options(start=2, stop=8, stride=2)).tolist() == [2, 4, 6]
    assert frame_indices(5, Options(start=2, stop=50)).tolist() == [2, 3, 4]
    with pytest.raises(ValueError):
        Options(stride=0)
    with pytest.raises(ValueError):
        Options(start=5, stop=5)
    with pytest.raises(ValueError, match=r"chunk: must be >= 1, got 0"):
        Options(chunk=0)
    with pytest.raises(ValueError, match=r"pose_min_conf: must be in \[0, 1\], got 1.5"):
        Options(pose_min_conf=1.5)
    with pytest.raises(ValueError, match=r"cross_view_px: must be > 0 pixels"):
        Options(cross_view_px=-1.0)
    assert Options(workers=0).sequence_options().workers == (os.cpu_count() or 1)
    assert Options(workers=3, hands=False).sequence_options().people().hands is False


def _tiny_video(path: Path, n: int, fps: float) -> Path:
    from formats.video import write_mp4

    frames = [np.full((32, 48, 3), 40 * i, np.uint8) for i in range(n)]
    write_mp4(path, frames, fps)
    return path


def test_check_videos_names_a_wrong_rate_and_cuts_a_short_video(tmp_path):
    """One video at another rate than the recipe's: one message naming that video and both
    numbers; one video shorter than the others is not an error: the sequence is cut to the
    shortest, with a warning naming each longer video and both counts; good videos: no message."""
    from stages.common import check_videos, video_errors, video_length

    good = [_tiny_video(tmp_path / f"cam{i}" / "Test 1.mp4", 6, FPS) for i in range(3)]
    assert check_videos(good, FPS) == []
    short = _tiny_video(tmp_path / "cam3" / "Test 1.mp4", 4, FPS)
    slow = _tiny_video(tmp_path / "cam4" / "Test 1.mp4", 6, 25.0)
    msgs = check_videos(good + [short, slow], FPS)
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith(f"{slow}: fps: the video runs at 25 fps, the recipe says 50")
    errs = video_errors(good + [short, slow], FPS)
    assert [(e.file, e.field) for e in errs] == [(str(slow), "fps")]
    n, warnings = video_length(good + [short])
    assert n == 4 and len(warnings) == 3
    assert warnings[0].startswith(f"{good[0]}: frames: 6 frames, but {short} of the same "
                                  "sequence has 4")
    missing = tmp_path / "cam9" / "Test 1.mp4"
    assert check_videos(good + [missing], FPS) == [f"{missing}: <file>: missing"]


def test_markers_on_frames_follow_the_recipe_sync_convention():
    """The C3D's first sample is at video time OFFSET: video frame f is at mocap time
    f / fps - OFFSET. A marker moving at 1 m/s along x sits at x = mocap time."""
    t = np.arange(60) / HZ
    xyz = np.zeros((60, 2, 3))
    xyz[:, 0, 0] = t
    xyz[:, 1, 0] = t
    xyz[20:23, 1] = np.nan  # a gap
    frames = np.array([0, 1, 2, 5])
    mk = Markers(("a", "b"), xyz, HZ, 0, None)
    out = markers_on_frames(mk, frames, VideoClock(FPS, OFFSET))
    np.testing.assert_allclose(out[:, 0, 0], frames / FPS - OFFSET)
    # marker 1: frame 5 is at mocap time 0.22 -> inside the gap (samples 20..22): missing
    assert np.isnan(out[3, 1]).all() and np.isfinite(out[:3, 1]).all()
    # before the capture starts: missing
    out = markers_on_frames(mk, frames, VideoClock(FPS, 0.5))
    assert np.isnan(out[0]).all()


# --------------------------------------------------------------------------- a small session
def _write_session(root: Path) -> dict:
    """Two Anny people facing each other (person 0 wears Plug-in Gait markers) in the studio
    rig, N_FRAMES video frames at 50 fps, markers at 100 Hz starting 0.12 s before the video.
    Returns truth: kp65 (F, 2, 65, 3) world, cameras."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from body import forward, load_model
    from body.joints import keypoints
    from body.markers import marker_positions, plug_in_gait
    from calib.io import write_chi3d_camera
    from drawing.render import PersonMesh, Renderer
    from formats.c3d import Markers, write_c3d
    from formats.video import write_mp4
    from studio.rig import make_rig
    from studio.subjects import make_subjects

    rng = np.random.default_rng(7)
    m = load_model("anny")
    subs = make_subjects(m, ("s01a", "s01b"), rng)
    cams = make_rig(rng)
    names = list(m.joint_names)
    nj = len(names)

    def person(tv, who):
        """Forward kinematics at video times tv (s): facing each other 0.9 m apart."""
        bp = np.zeros((len(tv), nj, 3))
        s = np.sin(2 * np.pi * 0.8 * tv + who)
        bp[:, names.index("upperarm01.R"), 0] = 0.5 * s
        bp[:, names.index("lowerarm01.R"), 2] = 0.6 + 0.3 * s
        a = np.pi / 2 if who == 0 else -np.pi / 2
        R = np.array([[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]] * len(tv))
        T = np.zeros((len(tv), 3))
        T[:, 0] = (-0.45 if who == 0 else 0.45) + 0.2 * tv
        o = forward(m, subs[who].betas, bp, R, T)
        ref = forward(m, subs[who].betas, np.zeros((1, nj, 3)), np.eye(3)[None], np.zeros((1, 3)))
        lift = np.array([0.0, 0.0, -ref.vertices[0, :, 2].min()])
        return o.vertices + lift, keypoints(m, o, "kp65") + lift

    tv = np.arange(N_FRAMES) / FPS
    people = [person(tv, w) for w in (0, 1)]
    seq = root / "s01"
    with Renderer(cams) as r:
        views = [r.render([PersonMesh(people[w][0][f], np.asarray(m.faces), subs[w].colors)
                           for w in (0, 1)]) for f in range(N_FRAMES)]
    for c, cam in enumerate(cams):
        write_mp4(seq / "videos" / cam.name / "Test 1.mp4", [v[c] for v in views], FPS)
        write_chi3d_camera(seq / "camera_parameters" / cam.name / "Test 1.json", cam)
    tm = np.arange(int((N_FRAMES / FPS - OFFSET) * HZ) + 3) / HZ
    verts, _ = person(tm + OFFSET, 0)
    ms = plug_in_gait(m)
    xyz = marker_positions(verts, np.asarray(m.faces), ms)
    write_c3d(seq / "mocap" / "Test 1.c3d", Markers(tuple(ms.names), xyz, HZ, 0, "s01a"))
    recipe = {
        "session": "kp_test", "cameras": [c.name for c in cams],
        "subjects": {"s01a": {}, "s01b": {}},
        "sequences": {"s01/Test 1": {
            "markers_on": "s01a", "partner": "s01b", "c3d": "s01/mocap/Test 1.c3d",
            "videos": {c.name: f"s01/videos/{c.name}/Test 1.mp4" for c in cams},
            "calibration": {c.name: f"s01/camera_parameters/{c.name}/Test 1.json" for c in cams},
            "fps": FPS, "mocap": {"sync_offset_s": OFFSET}}},
    }
    (root / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    return {"kp65": np.stack([people[0][1], people[1][1]], 1), "cams": cams, "recipe": recipe}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("kp_session")
    truth = _write_session(root)
    return root, truth


def _run(root: Path, recipe: dict, outputs: Path, **stage_opts) -> Path:
    from pipeline.cli import main

    recipe = json.loads(json.dumps(recipe))
    recipe["stages"] = {"keypoints": stage_opts}
    path = root / f"recipe_{abs(hash(json.dumps(stage_opts, sort_keys=True)))}.yaml"
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    logs = []
    rc = main(["sequence", "s01/Test 1", "--recipe", str(path), "--outputs", str(outputs),
               "--until", "keypoints"], log=logs.append)
    assert rc == 0, "\n".join(logs)
    found = list(outputs.glob("kp_test/s01/*/keypoints/keypoints.npz"))
    assert len(found) == 1
    return found[0].parent


def _truth_uv(truth, frames):
    from calib import project

    return np.stack([project(cam, truth["kp65"][frames]) for cam in truth["cams"]])


@pytest.mark.slow
def test_stage_mediapipe_end_to_end(session, tmp_path):
    from detect.metrics import identity_swaps, keypoint_errors

    root, truth = session
    art = _run(root, truth["recipe"], tmp_path / "out", workers=2, chunk=2, stride=1)
    z = np.load(art / "keypoints.npz")
    C = len(truth["cams"])
    assert z["kp"].shape == (C, N_FRAMES, 2, layout.N, 3)
    assert z["boxes"].shape == (C, N_FRAMES, 2, 4) and z["hand_boxes"].shape == (C, N_FRAMES, 2, 2, 4)
    assert z["frames"].tolist() == list(range(N_FRAMES))
    uv = _truth_uv(truth, z["frames"])
    err = keypoint_errors(z["kp"], uv)
    for p in (0, 1):
        body = err[:, :, p, :17]
        assert np.isfinite(body).mean() > 0.8
        assert np.nanmedian(body) < 12.0, (p, np.nanmedian(body))
    assert not identity_swaps(z["kp"], uv).any()
    # the wearer's crop box holds its projected truth body
    b = z["boxes"][:, :, 0]
    inside = (uv[:, :, 0, :23] >= b[:, :, None, :2]) & (uv[:, :, 0, :23] <= b[:, :, None, 2:])
    assert inside.all(axis=-1).mean() > 0.95
    from artifacts.keypoints import Keypoints2D

    k2 = Keypoints2D.load(art)  # the stage's file passes the artifact's checks
    assert k2.camera_ids == [cam.name for cam in truth["cams"]]
    rep = json.loads((art / "report.json").read_text())
    assert rep["detector"] == "mediapipe" and rep["frames"] == N_FRAMES
    assert rep["fps_per_core"] > 0 and rep["detected"]["wearer.body"] > 0.8
    import cv2

    for cam in truth["cams"]:
        img = cv2.imread(str(art / f"overlay_{cam.name}.png"))
        assert img is not None and img.shape == (900, 900, 3)
    from formats.mcap_log import read_log

    log = read_log(art / "keypoints.mcap")
    names = [cam.name for cam in truth["cams"]]
    assert sorted(log) == sorted([f"/keypoints/{n}" for n in names] + [f"/boxes/{n}" for n in names])
    for c, n in enumerate(names):
        msgs = log[f"/keypoints/{n}"]
        assert [m["frame"] for _, m in msgs] == list(range(N_FRAMES))
        f = msgs[2][1]["frame"]
        np.testing.assert_allclose(np.array(msgs[2][1]["people"][1]["kp"]), z["kp"][c, f, 1], atol=1e-4)
        box = log[f"/boxes/{n}"][2][1]["body"][0]
        np.testing.assert_allclose(box, z["boxes"][c, f, 0], atol=0.06)


def test_stage_precomputed_openpose(session, tmp_path):
    """Precomputed detections (truth + noise, plus a spurious low-score person, shuffled
    order) go through the same rules: person 0 = the candidate matching the markers, person 1
    by the paper's rule; frames without files have no keypoints."""
    from formats.openpose import write_openpose_frame

    root, truth = session
    rng = np.random.default_rng(3)
    uv = _truth_uv(truth, np.arange(N_FRAMES))  # (C, F, 2, 65, 2)
    kp_dir = root / "openpose"
    covered = [0, 1, 3]
    for c, cam in enumerate(truth["cams"]):
        for f in covered:
            people = np.zeros((3, layout.N, 3))
            people[:2, :, :2] = uv[c, f] + rng.normal(0, 1.0, (2, layout.N, 2))
            people[:2, :, 2] = 0.8
            people[2, :, :2] = uv[c, f, 1] + [250.0, 0.0]
            people[2, :, 2] = 0.2
            people = people[rng.permutation(3)]
            write_openpose_frame(kp_dir / cam.name / f"Test_1_{f:012d}_keypoints.json", people)
    recipe = json.loads(json.dumps(truth["recipe"]))
    seq = recipe["sequences"]["s01/Test 1"]
    seq["keypoints"] = {cam.name: str(kp_dir / cam.name) for cam in truth["cams"]}
    seq["keypoints_format"] = "openpose"
    art = _run(root, recipe, tmp_path / "out", workers=1)
    z = np.load(art / "keypoints.npz")
    rep = json.loads((art / "report.json").read_text())
    assert rep["detector"] == "precomputed"
    kp = z["kp"]
    for f in covered:
        for p in (0, 1):
            ok = kp[:, f, p, :, 2] > 0
            assert ok[:, :23].mean() > 0.9
            d = np.linalg.norm(kp[:, f, p, :, :2] - uv[:, f, p], axis=-1)[ok]
            assert d.max() < 6.0
    assert not kp[:, 2, :, :, 2].any()  # frame 2 has no files
    from artifacts.keypoints import Keypoints2D

    k2 = Keypoints2D.load(art)
    assert k2.camera_ids == [cam.name for cam in truth["cams"]]
    np.testing.assert_array_equal(k2.kp, kp)


def _precomputed(session, edit):
    """The domain function's inputs on in-memory data: (cams, frames, the C3D's markers, their
    positions at the video frames, the projected truth uv, a precomputed detector whose
    per-view detections are the truth at confidence 0.9 after ``edit(c, people (F, 2, 65,
    3))``, an ArraySource that is never read)."""
    from detect.precomputed import PrecomputedDetector
    from detect.run import ArraySource
    from formats.c3d import read_c3d
    from formats.keypoints import KeypointFrames

    root, truth = session
    cams = truth["cams"]
    frames = np.arange(N_FRAMES)
    m = read_c3d(root / "s01" / "mocap" / "Test 1.c3d")
    xyz = markers_on_frames(m, frames, VideoClock(FPS, OFFSET))
    uv = _truth_uv(truth, frames)  # (C, F, 2, 65, 2)
    per_cam = []
    for c in range(len(cams)):
        people = np.zeros((N_FRAMES, 2, layout.N, 3), np.float32)
        people[..., :2] = uv[c]
        people[..., 2] = 0.9
        people = edit(c, people)
        per_cam.append(KeypointFrames(people, frames))
    source = ArraySource(np.zeros((len(cams), 0, 1, 1, 3), np.uint8), ())
    return cams, frames, m, xyz, uv, PrecomputedDetector.from_frames(per_cam), source


def test_detect_keypoints_is_pure_and_drops_what_other_views_disagree_with(session):
    """The domain function on in-memory inputs (cameras, markers at the video frames, a
    precomputed detector, an ArraySource that is never read): both people found; a view whose
    partner is shifted by 80 px is caught by the cross-view check (confidence 0 there,
    conf_raw keeps the detector's), and without the check it stays."""
    from detect.sequence import SequenceOptions, detect_keypoints

    def shift(c, people):
        if c == 1:
            people[:, 1, :, 0] += 80.0  # the partner shifted in one view
        return people[:, ::-1].copy()  # partner listed first

    cams, frames, m, xyz, uv, det, source = _precomputed(session, shift)
    out, rep = detect_keypoints(cams, source, xyz, list(m.names), frames, det, SequenceOptions())
    assert out.kp.shape == (len(cams), N_FRAMES, 2, layout.N, 3)
    assert out.camera_ids == [c.name for c in cams] and out.frames.tolist() == frames.tolist()
    ok = out.kp[..., 2] > 0
    good = np.ones(len(cams), bool)
    good[1] = False
    for p in (0, 1):
        d = np.linalg.norm(out.kp[good][:, :, p, :, :2] - uv[good][:, :, p], axis=-1)
        assert ok[good][:, :, p, :23].mean() > 0.9 and d[ok[good][:, :, p]].max() < 1.0
    body = slice(0, 17)
    moved = out.cross_view_outlier[1, :, 1, body]
    assert moved.mean() > 0.9, moved.mean()
    assert not out.kp[1, :, 1, body, 2][moved].any() and (out.conf_raw[1, :, 1, body][moved] > 0).all()
    assert not out.cross_view_outlier[good].any()
    assert rep["cross_view_outliers"]["partner"] == int(out.cross_view_outlier[:, :, 1].sum())
    assert rep["frames"] == N_FRAMES and rep["markers"] == len(m.names)
    out2, _ = detect_keypoints(cams, source, xyz, list(m.names), frames, det,
                               SequenceOptions(cross_view=False))
    assert not out2.cross_view_outlier.any()
    np.testing.assert_array_equal(out2.kp[..., 2], out.conf_raw)
    with pytest.raises(ValueError, match="no marker observed"):
        detect_keypoints(cams, source, np.full_like(xyz, np.nan), list(m.names), frames, det)


def test_detect_keypoints_drops_a_partner_slot_that_holds_somebody_far_away(session):
    """A bystander 2.5 m behind the pair in one view's partner slot (the detector found the
    operator, not the partner): with the floor given, that view's partner is dropped whole
    before the cross-view checks and counted; the other views keep the partner."""
    from calib import project
    from detect.sequence import SequenceOptions, detect_keypoints

    _, truth = session
    cam2 = truth["cams"][2]
    away = cam2.R[2] * np.array([1.0, 1.0, 0.0])  # along the view, on the floor
    bystander = truth["kp65"][np.arange(N_FRAMES)][:, 1] + 2.5 * away / np.linalg.norm(away)

    def operator(c, people):
        if c == 2:
            people[:, 1, :, :2] = project(cam2, bystander)
        return people

    cams, frames, m, xyz, uv, det, source = _precomputed(session, operator)
    ground = ((0.0, 0.0, 1.0), 0.0)
    out, rep = detect_keypoints(cams, source, xyz, list(m.names), frames, det, SequenceOptions(),
                                ground=ground)
    assert rep["partner_far_views"] == N_FRAMES
    assert not out.kp[2, :, 1, :, 2].any() and out.cross_view_outlier[2, :, 1].all()
    assert (out.conf_raw[2, :, 1] > 0).all()  # the detector's own confidences are kept
    others = np.ones(len(cams), bool)
    others[2] = False
    assert (out.kp[others][:, :, 1, :23, 2] > 0).mean() > 0.9  # the partner elsewhere stays
    _, rep0 = detect_keypoints(cams, source, xyz, list(m.names), frames, det, SequenceOptions())
    assert rep0["partner_far_views"] == 0  # no floor given: not judged


def _compute(path: Path, o: Options):
    from recipes import load_recipe
    from stages import view_for
    from stages.capture import capture_of
    from stages.keypoints import compute, raw_inputs

    rec = load_recipe(path)
    sid = "s01/Test 1"
    mk, cams, _ = capture_of(rec, sid)
    return compute(view_for(rec, "keypoints", sid), raw_inputs(rec, sid), o, unit=sid,
                   recipe_path=path, markers=mk, cams=cams)


def test_bad_inputs_name_the_file(session, tmp_path):
    """Markers that never overlap the video (wrong sync) and a precomputed detector without
    files are input errors naming the file and field, before any detection runs."""
    from formats.errors import InputError

    root, truth = session
    recipe = json.loads(json.dumps(truth["recipe"]))
    recipe["sequences"]["s01/Test 1"]["mocap"]["sync_offset_s"] = 100.0
    path = root / "recipe_badsync.yaml"
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    with pytest.raises(InputError, match=r"Test 1\.c3d: markers: no marker observed"):
        _compute(path, Options())
    with pytest.raises(InputError, match=r"recipe\.yaml: sequences\.s01/Test 1\.keypoints: "
                                         r"detector 'precomputed'"):
        _compute(root / "recipe.yaml", Options(detector="precomputed"))


def test_a_wrong_rate_stops_the_stage(session, tmp_path):
    """One view's video at another rate than the recipe's fps: an InputError naming that video
    and both numbers, before any detection runs. (A shorter view is cut to, with a warning:
    ``test_check_videos_names_a_wrong_rate_and_cuts_a_short_video``.)"""
    from formats.errors import InputError
    from formats.video import VideoReader, write_mp4

    root, truth = session
    cam = truth["cams"][2].name
    orig = root / truth["recipe"]["sequences"]["s01/Test 1"]["videos"][cam]
    with VideoReader(orig) as v:
        imgs = [v[i] for i in range(N_FRAMES)]
    for name, n, fps, pattern in (
            ("slow", N_FRAMES, FPS / 2, rf"fps: the video runs at {FPS / 2:g} fps, the recipe "
                                         rf"says {FPS:g}"),):
        video = write_mp4(tmp_path / name / cam / "Test 1.mp4", imgs[:n], fps)
        recipe = json.loads(json.dumps(truth["recipe"]))
        recipe["sequences"]["s01/Test 1"]["videos"][cam] = str(video)
        path = root / f"recipe_{name}.yaml"
        path.write_text(yaml.safe_dump(recipe, sort_keys=False))
        with pytest.raises(InputError, match=pattern) as e:
            _compute(path, Options(detector="mediapipe"))
        assert e.value.file == str(video)


@pytest.mark.slow
def test_stage_on_the_studio_small_session(small_session):
    """The stage's core on the shared studio test session (contact-driven handshake): both
    people found in most views, on the projected truth, never mixed up."""
    from body import load_model
    from body.joints import regress, regressor
    from calib import project
    from calib.io import read_chi3d_camera
    from detect.metrics import identity_swaps, keypoint_errors
    from recipes import load_recipe
    from stages import view_for
    from stages.capture import capture_of
    from stages.keypoints import compute, raw_inputs

    rec = load_recipe(small_session)
    sid = next(s for s in rec.sequences if "Handshake" in s)
    seq = rec.sequences[sid]
    mk, cams, _ = capture_of(rec, sid)
    c = compute(view_for(rec, "keypoints", sid), raw_inputs(rec, sid),
                Options(stride=8, workers=2), unit=sid, recipe_path=small_session,
                markers=mk, cams=cams)
    kp = c.keypoints
    fr = kp.frames
    group, action = sid.split("/")
    gt = np.load(Path(small_session).parent / "gt" / group / f"{action}.npz")
    reg = regressor(load_model("anny"), "kp65")
    kp3 = np.stack([regress(reg, gt["vertices"][p][fr].astype(float), gt["joints"][p][fr])
                    for p in (0, 1)], axis=1)
    uv = np.stack([project(read_chi3d_camera(seq.calibration[cam]), kp3) for cam in rec.cameras])
    err = keypoint_errors(kp.kp, uv)
    assert not identity_swaps(kp.kp, uv).any()
    for p in (0, 1):
        body = err[:, :, p, :17]
        assert np.isfinite(body).mean() > 0.6, (p, np.isfinite(body).mean())
        assert np.nanmedian(body) < 10.0, (p, np.nanmedian(body))
