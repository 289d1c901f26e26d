"""mediapipe behind the detector interface, on a rendered Anny body (pyrender, EGL): keypoints
land on the projected truth, crops map back to the full image, left/right are anatomical, the
hand label flip is right, and nothing is downloaded or printed."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib import look_at, project, world_to_cam
from detect import layout
from detect.crops import box_from_points, expand_box, hand_box_from_3d
from detect.mediapipe_detector import MediapipeDetector, hand_side

REPO = Path(__file__).resolve().parents[1]

@pytest.fixture(scope="module")
def scene():
    """One Anny body (reference pose, turned 25 degrees) in a 900 x 900 view with lens
    distortion; truth = body.joints KP65 keypoints projected with calib.project."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from body import forward, load_model
    from body.joints import keypoints
    from drawing.render import PersonMesh, Renderer

    m = load_model("anny")
    yaw = np.radians(25)
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    nj = len(m.joint_names)
    out = forward(m, np.zeros(10), np.zeros((1, nj, 3)), Rz[None], np.zeros((1, 3)))
    lift = np.array([0.0, 0.0, -out.vertices[0, :, 2].min()])
    V = out.vertices[0] + lift
    kp3 = keypoints(m, out, "kp65")[0] + lift
    names = list(m.joint_names)
    J = out.joints[0] + lift
    hands3 = [(J[names.index(f"wrist.{s}")], J[names.index(f"finger3-1.{s}")]) for s in "LR"]
    cam = look_at("c", (0.4, -3.4, 1.4), (0, 0, 0.9), (1100, 1100), (450, 450), 900, 900,
                  k=(-0.05, 0.01, 0.0))
    col = np.tile([[190, 110, 90]], (len(V), 1)).astype(np.uint8)
    with Renderer([cam]) as r:
        img = r.render([PersonMesh(V, np.asarray(m.faces), col)])[0]
    return dict(img=img, cam=cam, truth_uv=project(cam, kp3), V=V, hands3=hands3)


@pytest.fixture(scope="module")
def mp_detector():
    d = MediapipeDetector()
    yield d
    d.close()


def test_body_in_a_crop_lands_on_projected_truth(scene, mp_detector):
    img, cam, truth = scene["img"], scene["cam"], scene["truth_uv"]
    box = expand_box(box_from_points(project(cam, scene["V"][::37])), 0.15, square=True)
    crop = mp_detector.detect(img, kind="body", box=box)
    assert len(crop) == 1
    kp = crop.kp[0]
    ok = kp[:, 2] > 0
    assert ok[layout.BODY].sum() == 21  # all mapped pose keypoints (no small toes)
    assert not ok[23:].any()  # hands come from the hand detector only
    err = np.linalg.norm(kp[ok, :2] - truth[ok], axis=1)
    assert np.median(err) < 8.0, np.round(err, 1)
    assert np.all(kp[ok, 2] > 0.5)
    # left/right are the person's own (no mirroring): each shoulder/hip/knee is nearer its
    # own truth than the other side's
    for a, b in (("l_shoulder", "r_shoulder"), ("l_hip", "r_hip"), ("l_knee", "r_knee")):
        ia, ib = layout.IDX[a], layout.IDX[b]
        assert np.linalg.norm(kp[ia, :2] - truth[ia]) < np.linalg.norm(kp[ia, :2] - truth[ib])
    # the same person over the whole image: same keypoints within a few pixels (the crop map)
    whole = mp_detector.detect(img, kind="body")
    d = np.linalg.norm(whole.kp[0, ok, :2] - kp[ok, :2], axis=1)
    assert np.median(d) < 4.0
    # an empty crop finds nobody
    assert len(mp_detector.detect(img, kind="body", box=np.array([0.0, 0, 120, 120]))) == 0


def test_hands_in_hand_crops_get_the_anatomical_side(scene, mp_detector):
    img, cam = scene["img"], scene["cam"]
    for side, (w3, f3) in enumerate(scene["hands3"]):
        centre = w3 + 1.2 * (f3 - w3)
        box = hand_box_from_3d(project(cam, centre), world_to_cam(cam, centre)[2], float(np.mean(cam.f)))
        found = mp_detector.detect(img, kind="hands", box=box)
        assert len(found) >= 1
        wrist_uv = project(cam, w3)
        blocks = [(s, c[layout.HANDS[s]]) for c in found.kp for s in (0, 1)
                  if c[layout.HANDS[s].start, 2] > 0]
        s, hand = min(blocks, key=lambda t: np.linalg.norm(t[1][0, :2] - wrist_uv))
        assert s == side
        assert np.linalg.norm(hand[0, :2] - wrist_uv) < 12.0
        truth = scene["truth_uv"][layout.HANDS[side]]
        assert np.median(np.linalg.norm(hand[:, :2] - truth, axis=1)) < 10.0
        assert np.all((hand[:, :2] >= box[:2] - 5) & (hand[:, :2] <= box[2:] + 5))


def test_hand_label_flip():
    assert hand_side("Left") == 1 and hand_side("Right") == 0
    with pytest.raises(ValueError):
        hand_side("left")


def test_offline_and_quiet():
    """In a process without network (``unshare -rn``), building the graphs and detecting
    needs no download, and the native logging noise does not reach stderr."""
    code = ("import numpy as np; from detect.mediapipe_detector import MediapipeDetector; "
            "d = MediapipeDetector(); img = np.full((200, 200, 3), 127, np.uint8); "
            "print(len(d.detect(img, kind='body')), len(d.detect(img, kind='hands'))); d.close()")
    cmd = [sys.executable, "-c", code]
    unshare = shutil.which("unshare")
    if unshare and subprocess.run([unshare, "-rn", "true"], capture_output=True).returncode == 0:
        cmd = [unshare, "-rn"] + cmd
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "0 0"
    assert done.stderr == ""
