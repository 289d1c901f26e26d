"""The keypoints stage: frame selection, marker timing, and whole runs through the engine on a
small rendered two-person session (mediapipe) and on precomputed OpenPose files."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from detect import layout
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


def test_markers_on_frames_follow_the_recipe_sync_convention():
    """The C3D's first sample is at video time OFFSET: video frame f is at mocap time
    f / fps - OFFSET. A marker moving at 1 m/s along x sits at x = mocap time."""
    t = np.arange(60) / HZ
    xyz = np.zeros((60, 2, 3))
    xyz[:, 0, 0] = t
    xyz[:, 1, 0] = t
    xyz[20:23, 1] = np.nan  # a gap
    frames = np.array([0, 1, 2, 5])
    out = markers_on_frames(t, xyz, frames, FPS, OFFSET)
    np.testing.assert_allclose(out[:, 0, 0], frames / FPS - OFFSET)
    # marker 1: frame 5 is at mocap time 0.22 -> inside the gap (samples 20..22): missing
    assert np.isnan(out[3, 1]).all() and np.isfinite(out[:3, 1]).all()
    # before the capture starts: missing
    out = markers_on_frames(t, xyz, frames, FPS, 0.5)
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
    from formats.c3d import Markers, write_c3d
    from formats.video import write_mp4
    from studio.render import PersonMesh, Renderer
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


def test_bad_inputs_name_the_file(session, tmp_path):
    """Markers that never overlap the video (wrong sync) and a precomputed detector without
    files are input errors naming the file and field, before any detection runs."""
    from formats.errors import InputError
    from recipes import load_recipe
    from stages.keypoints import compute, raw_inputs

    root, truth = session
    recipe = json.loads(json.dumps(truth["recipe"]))
    recipe["sequences"]["s01/Test 1"]["mocap"]["sync_offset_s"] = 100.0
    path = root / "recipe_badsync.yaml"
    path.write_text(yaml.safe_dump(recipe, sort_keys=False))
    rec = load_recipe(path)
    with pytest.raises(InputError, match=r"Test 1\.c3d: markers: no marker observed"):
        compute(rec, "s01/Test 1", raw_inputs(rec, "s01/Test 1"), Options())
    rec = load_recipe(root / "recipe.yaml")
    with pytest.raises(InputError, match=r"sequences\.s01/Test 1\.keypoints"):
        compute(rec, "s01/Test 1", raw_inputs(rec, "s01/Test 1"), Options(detector="precomputed"))


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
    from stages.keypoints import compute, raw_inputs

    rec = load_recipe(small_session)
    sid = next(s for s in rec.sequences if "Handshake" in s)
    seq = rec.sequences[sid]
    c = compute(rec, sid, raw_inputs(rec, sid), Options(stride=8, workers=2))
    fr = c.res.frames
    group, action = sid.split("/")
    gt = np.load(Path(small_session).parent / "gt" / group / f"{action}.npz")
    reg = regressor(load_model("anny"), "kp65")
    kp3 = np.stack([regress(reg, gt["vertices"][p][fr].astype(float), gt["joints"][p][fr])
                    for p in (0, 1)], axis=1)
    uv = np.stack([project(read_chi3d_camera(seq.calibration[cam]), kp3) for cam in rec.cameras])
    err = keypoint_errors(c.res.kp, uv)
    assert not identity_swaps(c.res.kp, uv).any()
    for p in (0, 1):
        body = err[:, :, p, :17]
        assert np.isfinite(body).mean() > 0.6, (p, np.isfinite(body).mean())
        assert np.nanmedian(body) < 10.0, (p, np.nanmedian(body))
