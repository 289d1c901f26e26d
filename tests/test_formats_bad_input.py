"""One matrix over every reader: truncated file, wrong shape, NaN, missing key -> InputError
whose message names the file, the field and (where it applies) the frame."""
import json
import re

import numpy as np
import pytest
from test_calib_camera import random_camera

from calib.io import (
    read_chi3d_camera,
    read_easymocap,
    read_opencv_camera,
    write_chi3d_camera,
    write_easymocap,
    write_opencv_camera,
)
from formats.c3d import Markers, read_c3d, write_c3d
from formats.chi3d import read_contact_signatures, read_joints3d_25, read_smplx
from formats.coco import read_coco
from formats.errors import InputError
from formats.mcap_log import SequenceLog, read_log
from formats.openpose import read_openpose


def truncate(path, frac=0.5):
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * frac)])
    return path


def edit_json(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))
    return path


def edit_text(path, old, new):
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return path


def nan_first_value(path):
    """Replace the first matrix's first number in an OpenCV YAML file by .nan."""
    text = path.read_text()
    new = re.sub(r"data: \[ *[-0-9.e+]+", "data: [ .nan", text, count=1)
    assert new != text
    path.write_text(new)
    return path


def chi3d_cam(tmp):
    return write_chi3d_camera(tmp / "50591643" / "Hug 1.json", random_camera(np.random.default_rng(0)))


def easymocap(tmp):
    write_easymocap(tmp / "intri.yml", tmp / "extri.yml", [random_camera(np.random.default_rng(0), "opencv")])
    return tmp / "intri.yml"


def opencv_cam(tmp):
    return write_opencv_camera(tmp / "cam.yml", random_camera(np.random.default_rng(0)))


def c3d_file(tmp):
    rng = np.random.default_rng(0)
    return write_c3d(tmp / "t.c3d", Markers(["A", "B"], rng.normal(size=(300, 2, 3)), 100.0))


def openpose_file(tmp):
    p = tmp / "op" / "v_000000000007_keypoints.json"
    p.parent.mkdir()
    p.write_text(json.dumps({"people": [{"pose_keypoints_2d": [1.0] * 75}]}))
    return p


def coco_file(tmp):
    p = tmp / "c.json"
    p.write_text(json.dumps({"images": [{"id": 1, "file_name": "000007.jpg"}],
                             "annotations": [{"image_id": 1, "keypoints": [1.0] * 51}]}))
    return p


def joints_file(tmp):
    p = tmp / "j.json"
    p.write_text(json.dumps({"joints3d_25": np.zeros((2, 9, 25, 3)).tolist()}))
    return p


def smplx_file(tmp):
    from test_formats_chi3d import random_smplx

    from formats.chi3d import write_smplx

    return write_smplx(tmp / "smplx.json", random_smplx(np.random.default_rng(0)))


def contact_file(tmp):
    p = tmp / "s.json"
    p.write_text(json.dumps({"Hug 1": {"fr_id": 7, "smplx_signature": {"region_id": [[1, 2]],
                                                                         "face_id": [[3, 4]]}}}))
    return p


def mcap_file(tmp):
    with SequenceLog(tmp / "l.mcap", fps=50) as log:
        for j in range(50):
            log.log_metrics(j, {"x": float(j)})
    return tmp / "l.mcap"


def _nan_at_frame(d, f):
    d["joints3d_25"][1][f][3][2] = float("nan")


CASES = {
    # reader name: (make, read, {kind: (corrupt, field, frame)})
    "chi3d_camera": (chi3d_cam, read_chi3d_camera, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d["extrinsics"].__setitem__("T", [1, 2])), "extrinsics.T", None),
        "nan": (lambda p: edit_json(p, lambda d: d["intrinsics_w_distortion"].__setitem__("f", [[float("nan"), 1]])),
                "intrinsics_w_distortion.f", None),
        "missing": (lambda p: edit_json(p, lambda d: d["intrinsics_w_distortion"].pop("c")),
                    "intrinsics_w_distortion.c", None)}),
    "easymocap": (easymocap, lambda p: read_easymocap(p, p.parent / "extri.yml"), {
        "truncated": (lambda p: truncate(p, 0.3), "<filestorage>", None),
        "shape": (lambda p: edit_text(p, "rows: 3\n   cols: 3", "rows: 1\n   cols: 9"), "K_cam", None),
        "nan": (nan_first_value, "K_cam", None),
        "missing": (lambda p: edit_text(p, "dist_cam", "distortion_cam") and edit_text(p, "K_cam", "KK_cam"),
                    "K_cam", None)}),
    "opencv_camera": (opencv_cam, read_opencv_camera, {
        "truncated": (lambda p: truncate(p, 0.4), "<filestorage>", None),
        "shape": (lambda p: edit_text(p, "rows: 3\n   cols: 3", "rows: 1\n   cols: 9"), "camera_matrix", None),
        "nan": (nan_first_value, "camera_matrix", None),
        "missing": (lambda p: edit_text(p, "camera_matrix", "cam_matrix"), "camera_matrix", None)}),
    "c3d": (c3d_file, lambda p: read_c3d(p, markers=["A", "B"]), {
        "truncated": (truncate, "<data>", ...),  # ...: some frame, named
        "missing": (lambda p: p, "POINT:LABELS", None)}),  # read with a marker the file lacks
    "openpose": (openpose_file, read_openpose, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d["people"][0].__setitem__("pose_keypoints_2d", [1.0] * 74)),
                  "people[0].pose_keypoints_2d", 7),
        "nan": (lambda p: edit_json(p, lambda d: d["people"][0]["pose_keypoints_2d"].__setitem__(9, float("nan"))),
                "people[0].pose_keypoints_2d", 7),
        "missing": (lambda p: edit_json(p, lambda d: d["people"][0].pop("pose_keypoints_2d")),
                    "people[0].pose_keypoints_2d", 7)}),
    "coco": (coco_file, read_coco, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d["annotations"][0].__setitem__("keypoints", [1.0] * 52)),
                  "annotations[0].keypoints", 7),
        "nan": (lambda p: edit_json(p, lambda d: d["annotations"][0]["keypoints"].__setitem__(0, float("nan"))),
                "annotations[0].keypoints", 7),
        "missing": (lambda p: edit_json(p, lambda d: d["annotations"][0].pop("keypoints")),
                    "annotations[0].keypoints", 7)}),
    "joints3d_25": (joints_file, read_joints3d_25, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d.__setitem__("joints3d_25", np.zeros((2, 9, 25, 2)).tolist())),
                  "joints3d_25", None),
        "nan": (lambda p: edit_json(p, lambda d: _nan_at_frame(d, 6)), "joints3d_25", 6),
        "missing": (lambda p: edit_json(p, lambda d: d.pop("joints3d_25")), "joints3d_25", None)}),
    "smplx": (smplx_file, read_smplx, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d.__setitem__("betas", np.zeros((2, 4, 11)).tolist())),
                  "betas", None),
        "nan": (lambda p: edit_json(p, lambda d: d["transl"][0][2].__setitem__(1, float("nan"))), "transl", 2),
        "missing": (lambda p: edit_json(p, lambda d: d.pop("jaw_pose")), "jaw_pose", None)}),
    "contact": (contact_file, read_contact_signatures, {
        "truncated": (truncate, "<json>", None),
        "shape": (lambda p: edit_json(p, lambda d: d["Hug 1"]["smplx_signature"].__setitem__("face_id", [[1]])),
                  "Hug 1.smplx_signature.face_id", 7),
        "nan": (lambda p: edit_json(p, lambda d: d["Hug 1"]["smplx_signature"].__setitem__("face_id", [[1, float("nan")]])),
                "Hug 1.smplx_signature.face_id", 7),
        "missing": (lambda p: edit_json(p, lambda d: d["Hug 1"].pop("fr_id")), "Hug 1.fr_id", None)}),
    "mcap": (mcap_file, read_log, {"truncated": (truncate, "<mcap>", None)}),
}
PARAMS = [(name, kind) for name, (_, _, kinds) in CASES.items() for kind in kinds]


@pytest.mark.parametrize("name, kind", PARAMS, ids=[f"{n}-{k}" for n, k in PARAMS])
def test_bad_input_names_file_field_frame(tmp_path, name, kind):
    make, read, kinds = CASES[name]
    corrupt, field, frame = kinds[kind]
    path = make(tmp_path)
    read(path)  # the intact file reads
    if name == "c3d" and kind == "missing":
        read = lambda p: read_c3d(p, markers=["A", "STRN"])  # noqa: E731
    path = corrupt(path)
    with pytest.raises(InputError) as e:
        read(path)
    err = e.value
    assert err.file == str(path) and str(path) in str(err)
    if field is not None:
        assert err.field == field and field in str(err)
    if frame is ...:
        assert isinstance(err.frame, int)
    else:
        assert err.frame == frame
    if frame is not None:
        frame = err.frame
        assert f"[frame {frame}]" in str(err)
