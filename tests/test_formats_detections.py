"""OpenPose and COCO keypoint readers -> KP65, and their bad-input errors."""
import json

import numpy as np
import pytest

from formats.coco import read_coco
from formats.errors import InputError
from formats.openpose import read_openpose, read_openpose_frame, write_openpose_frame
from formats.skeletons import KP65, OPENPOSE_BODY25

OP_TO_NAME = {"Nose": "nose", "RShoulder": "r_shoulder", "RElbow": "r_elbow", "RWrist": "r_wrist",
              "LShoulder": "l_shoulder", "LElbow": "l_elbow", "LWrist": "l_wrist", "RHip": "r_hip",
              "RKnee": "r_knee", "RAnkle": "r_ankle", "LHip": "l_hip", "LKnee": "l_knee",
              "LAnkle": "l_ankle", "REye": "r_eye", "LEye": "l_eye", "REar": "r_ear",
              "LEar": "l_ear", "LBigToe": "l_big_toe", "LSmallToe": "l_small_toe",
              "LHeel": "l_heel", "RBigToe": "r_big_toe", "RSmallToe": "r_small_toe",
              "RHeel": "r_heel"}
COCO17 = ["nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder", "l_elbow",
          "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle",
          "r_ankle"]  # the COCO keypoint order, written out independently of the code


def openpose_person(rng, hands=True):
    """BODY_25 with x = 10 * index + 1, so each keypoint is identifiable; hands random."""
    body = np.c_[10.0 * np.arange(25) + 1, rng.uniform(0, 900, 25), rng.uniform(0.2, 1, 25)]
    lh, rh = rng.uniform(0, 900, (21, 3)), rng.uniform(0, 900, (21, 3))
    lh[:, 2] = rh[:, 2] = 0.7
    p = {"person_id": [-1], "pose_keypoints_2d": body.ravel().tolist(), "face_keypoints_2d": []}
    p["hand_left_keypoints_2d"] = lh.ravel().tolist() if hands else []
    p["hand_right_keypoints_2d"] = rh.ravel().tolist() if hands else []
    return p, body, lh, rh


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def test_openpose_maps_body25_and_hands_by_name(tmp_path, rng):
    folder = tmp_path / "op"
    folder.mkdir()
    truth = {}
    for fr, n in ((12, 2), (10, 1), (11, 0)):
        people = [openpose_person(rng, hands=(i == 0)) for i in range(n)]
        truth[fr] = people
        (folder / f"cam1_{fr:012d}_keypoints.json").write_text(
            json.dumps({"version": 1.3, "people": [p[0] for p in people]}))
    kf = read_openpose(folder)
    assert kf.frames.tolist() == [10, 11, 12] and kf.kp.shape == (3, 2, 65, 3)
    assert np.all(kf.kp[1] == 0) and np.all(kf.kp[0, 1] == 0)  # empty frame, padding person
    _, body, lh, rh = truth[12][0]
    got = kf.kp[2, 0]
    for i, name in enumerate(OPENPOSE_BODY25):
        if name in OP_TO_NAME:
            assert np.allclose(got[KP65.index(OP_TO_NAME[name])], body[i], atol=1e-4), name
    assert np.allclose(got[KP65.index("l_hand_wrist")], lh[0], atol=1e-4)
    assert np.allclose(got[KP65.index("r_hand_pinky4")], rh[20], atol=1e-4)
    assert np.all(kf.kp[2, 1, 23:, 2] == 0)  # second person had no hands
    # Neck (x = 11) and MidHip (x = 81) are not KP65 points: they appear nowhere.
    assert not np.any(np.isin(np.round(kf.kp[..., 0]), [11.0, 81.0]))


def test_openpose_write_read_round_trip(tmp_path, rng):
    people = rng.uniform(0, 900, (2, 65, 3)).astype(np.float32)
    people[..., 2] = rng.uniform(0.1, 1, (2, 65))
    people[1, 30] = 0
    back = read_openpose_frame(write_openpose_frame(tmp_path / "f_000000000004_keypoints.json", people))
    assert np.allclose(back, people, atol=1e-4)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.pop("people"), "people"),
    (lambda d: d["people"][0].pop("pose_keypoints_2d"), "people[0].pose_keypoints_2d"),
    (lambda d: d["people"][0].__setitem__("pose_keypoints_2d", [1.0] * 54), "people[0].pose_keypoints_2d"),
    (lambda d: d["people"][0]["hand_left_keypoints_2d"].__setitem__(4, float("nan")),
     "people[0].hand_left_keypoints_2d"),
    (lambda d: d["people"][0].__setitem__("hand_right_keypoints_2d", [[1, 2, 3]] * 21),
     "people[0].hand_right_keypoints_2d"),
])
def test_openpose_bad_input(tmp_path, rng, mutate, field):
    d = {"version": 1.3, "people": [openpose_person(rng)[0]]}
    mutate(d)
    path = tmp_path / "x_000000000042_keypoints.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        read_openpose(path)
    assert (e.value.file, e.value.field, e.value.frame) == (str(path), field, 42)


def test_openpose_bad_files(tmp_path, rng):
    good = json.dumps({"people": [openpose_person(rng)[0]]})
    (tmp_path / "a_000000000001_keypoints.json").write_text(good[: len(good) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_openpose(tmp_path)
    (tmp_path / "a_000000000001_keypoints.json").write_text(good)
    (tmp_path / "b_000000000001_keypoints.json").write_text(good)
    with pytest.raises(InputError, match="also given"):
        read_openpose(tmp_path)
    (tmp_path / "nonumber.json").write_text(good)
    with pytest.raises(InputError, match="no frame number"):
        read_openpose([tmp_path / "nonumber.json"])
    with pytest.raises(InputError, match="no OpenPose"):
        (tmp_path / "empty").mkdir()
        read_openpose(tmp_path / "empty")


def test_coco_dataset_form_with_wholebody_parts(tmp_path, rng):
    def ann(img, n_body=17):
        kp = np.c_[rng.uniform(0, 900, (n_body, 2)), rng.integers(0, 3, n_body)]
        return {"image_id": img, "category_id": 1, "keypoints": kp.ravel().tolist(),
                "foot_kpts": np.c_[rng.uniform(0, 900, (6, 2)), np.full(6, 2)].ravel().tolist(),
                "lefthand_kpts": np.c_[rng.uniform(0, 900, (21, 2)), np.ones(21)].ravel().tolist(),
                "righthand_kpts": [], "face_kpts": [0.0] * 204}, kp
    a0, k0 = ann(7)
    a1, _ = ann(7)
    a2, _ = ann(9)
    a2["category_id"] = 2  # not a person
    d = {"images": [{"id": 7, "file_name": "frames/000120.jpg"}, {"id": 9, "file_name": "000121.jpg"}],
         "annotations": [a0, a1, a2], "categories": [{"id": 1, "name": "person"}]}
    (tmp_path / "c.json").write_text(json.dumps(d))
    kf = read_coco(tmp_path / "c.json")
    assert kf.frames.tolist() == [120, 121] and kf.kp.shape == (2, 2, 65, 3)
    assert np.all(kf.kp[1] == 0)
    got = kf.kp[0, 0]
    for i, name in enumerate(COCO17):
        j = KP65.index(name)
        if k0[i, 2] > 0:
            assert np.allclose(got[j], [k0[i, 0], k0[i, 1], 1.0], atol=1e-3), name
        else:
            assert np.all(got[j] == 0), name
    foot = np.array(a0["foot_kpts"]).reshape(6, 3)
    assert np.allclose(got[KP65.index("l_big_toe"), :2], foot[0, :2], atol=1e-3)
    assert np.allclose(got[KP65.index("r_heel"), :2], foot[5, :2], atol=1e-3)
    lh = np.array(a0["lefthand_kpts"]).reshape(21, 3)
    assert np.allclose(got[KP65.index("l_hand_index1"), :2], lh[5, :2], atol=1e-3)
    assert np.all(got[44:, 2] == 0)


def test_coco_results_form_133(tmp_path, rng):
    wb = np.c_[rng.uniform(0, 900, (133, 2)), rng.uniform(0, 1, 133)]
    res = [{"image_id": 5, "category_id": 1, "keypoints": wb.ravel().tolist(), "score": 0.9}]
    (tmp_path / "r.json").write_text(json.dumps(res))
    kf = read_coco(tmp_path / "r.json")
    assert kf.frames.tolist() == [5]
    got = kf.kp[0, 0]
    assert np.allclose(got[:23], wb[:23], atol=1e-3)
    assert np.allclose(got[KP65.index("l_hand_wrist")], wb[91], atol=1e-3)
    assert np.allclose(got[KP65.index("r_hand_pinky4")], wb[132], atol=1e-3)


@pytest.mark.parametrize("mutate, field, frame", [
    (lambda d: d["annotations"][0].pop("image_id"), "annotations[0].image_id", None),
    (lambda d: d["annotations"][0].__setitem__("image_id", 99), "annotations[0].image_id", None),
    (lambda d: d["annotations"][0].__setitem__("keypoints", [1.0] * 50), "annotations[0].keypoints", 3),
    (lambda d: d["annotations"][0]["keypoints"].__setitem__(0, float("nan")), "annotations[0].keypoints", 3),
    (lambda d: d["annotations"][0].__setitem__("lefthand_kpts", [1.0] * 60),
     "annotations[0].lefthand_kpts", 3),
    (lambda d: d.pop("annotations"), "annotations", None),
    (lambda d: d["images"][0].pop("id"), "images[0].id", None),
])
def test_coco_bad_input(tmp_path, mutate, field, frame):
    d = {"images": [{"id": 1, "file_name": "img_0003.png"}],
         "annotations": [{"image_id": 1, "category_id": 1, "keypoints": [1.0, 2.0, 2] * 17}]}
    mutate(d)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        read_coco(path)
    assert (e.value.file, e.value.field, e.value.frame) == (str(path), field, frame)
    path.write_text(json.dumps(d)[:20])
    with pytest.raises(InputError, match="truncated"):
        read_coco(path)
