"""Calibration files: CHI3D JSON, EasyMocap yml, OpenCV FileStorage; round trips and bad input."""
import json
from dataclasses import replace

import numpy as np
import pytest
from test_calib_camera import chi3d_reference, random_camera, random_points

from calib import project
from calib.io import (
    chi3d_camera_path,
    read_chi3d_camera,
    read_chi3d_cameras,
    read_easymocap,
    read_opencv_camera,
    write_chi3d_camera,
    write_chi3d_cameras,
    write_easymocap,
    write_opencv_camera,
)
from formats.errors import InputError


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def test_chi3d_round_trip_and_public_loader_shapes(tmp_path, rng):
    cams = [random_camera(rng, "h36m", name=n) for n in ("50591643", "58860488")]
    paths = write_chi3d_cameras(tmp_path / "s03", "Hug 1", cams)
    assert paths[0] == tmp_path / "s03/camera_parameters/50591643/Hug 1.json"
    back = read_chi3d_cameras(tmp_path / "s03", "Hug 1")
    assert list(back) == ["50591643", "58860488"]
    for c in cams:
        assert back[c.name].allclose(c, atol=1e-15)
    # Load the way the public tools do (np.array of each leaf) and project with their formula.
    d = json.loads(paths[0].read_text())
    a = {k1: {k2: np.array(v) for k2, v in d[k1].items()} for k1 in d}
    assert a["intrinsics_w_distortion"]["p"].shape == (1, 2)
    assert a["intrinsics_w_distortion"]["k"].shape == (1, 3)
    X = random_points(rng, cams[0], 50)
    Xc = (X - a["extrinsics"]["T"]) @ a["extrinsics"]["R"].T
    iw = a["intrinsics_w_distortion"]
    ref = chi3d_reference(Xc, iw["f"], iw["c"], iw["k"], iw["p"])
    assert np.abs(ref - project(cams[0], X)).max() < 1e-9


def test_chi3d_reads_flat_lists(tmp_path, rng):
    cam = random_camera(rng, "h36m", name="60457274")
    d = {"extrinsics": {"R": cam.R.tolist(), "T": cam.T.tolist()},
         "intrinsics_w_distortion": {"f": cam.f.tolist(), "c": cam.c.tolist(),
                                     "k": cam.k.tolist(), "p": cam.p.tolist()}}
    path = tmp_path / "60457274" / "Grab 4.json"
    path.parent.mkdir()
    path.write_text(json.dumps(d))
    assert read_chi3d_camera(path).allclose(cam, atol=1e-15)
    assert read_chi3d_camera(path).name == "60457274"


def test_chi3d_refuses_opencv_lens_with_tangential(tmp_path, rng):
    cam = random_camera(rng, "opencv")
    with pytest.raises(ValueError, match="convert_distortion"):
        write_chi3d_camera(tmp_path / "x.json", cam)
    write_chi3d_camera(tmp_path / "x.json", replace(cam, p=(0, 0)))  # identical lens: allowed


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["extrinsics"].pop("R"), "extrinsics.R"),
    (lambda d: d["extrinsics"].__setitem__("R", [[1, 0, 0], [0, 1, 0]]), "extrinsics.R"),
    (lambda d: d["extrinsics"].__setitem__("R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "extrinsics.R"),
    (lambda d: d["extrinsics"].__setitem__("T", [[0, "a", 1]]), "extrinsics.T"),
    (lambda d: d["intrinsics_w_distortion"].__setitem__("k", [[0.1, float("nan"), 0]]),
     "intrinsics_w_distortion.k"),
    (lambda d: d["intrinsics_w_distortion"].__setitem__("p", [[0.1]]), "intrinsics_w_distortion.p"),
    (lambda d: d.pop("intrinsics_w_distortion"), "intrinsics_w_distortion.f"),
    (lambda d: d["intrinsics_wo_distortion"].__setitem__("f", [1.0]), "intrinsics_wo_distortion.f"),
])
def test_chi3d_bad_input(tmp_path, rng, mutate, field):
    path = write_chi3d_camera(tmp_path / "c" / "a.json", random_camera(rng))
    d = json.loads(path.read_text())
    mutate(d)
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        read_chi3d_camera(path)
    assert e.value.field == field and e.value.file == str(path)


def test_chi3d_truncated_and_missing(tmp_path, rng):
    path = write_chi3d_camera(tmp_path / "c" / "a.json", random_camera(rng))
    path.write_text(path.read_text()[:100])
    with pytest.raises(InputError, match="truncated"):
        read_chi3d_camera(path)
    with pytest.raises(InputError, match="cannot read"):
        read_chi3d_camera(tmp_path / "nope.json")
    (tmp_path / "s/camera_parameters/50591643").mkdir(parents=True)
    with pytest.raises(InputError, match="no camera file"):
        read_chi3d_cameras(tmp_path / "s", "Hug 1")
    assert chi3d_camera_path("s", "1", "Hug 1").as_posix() == "s/camera_parameters/1/Hug 1.json"


def test_easymocap_round_trip(tmp_path, rng):
    cams = [random_camera(rng, "opencv", name=f"{i:02d}") for i in range(4)]
    cams.append(replace(random_camera(rng, "h36m", name="h"), p=(0, 0)))  # p = 0: same lens
    write_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml", cams)
    back = read_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert list(back) == [c.name for c in cams]
    for c in cams:
        X = random_points(rng, c, 30)
        assert np.abs(project(back[c.name], X) - project(c, X)).max() < 1e-9
    with pytest.raises(ValueError, match="12 OpenCV"):
        write_easymocap(tmp_path / "i2.yml", tmp_path / "e2.yml", [random_camera(rng, "h36m")])


def test_easymocap_written_by_hand_with_rodrigues_only(tmp_path):
    # EasyMocap-style file without Rot_ and without size: R from Rodrigues, size from argument.
    (tmp_path / "intri.yml").write_text(
        "%YAML:1.0\n---\nnames:\n  - \"1\"\nK_1: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n"
        "  data: [1000., 0., 450., 0., 1000., 450., 0., 0., 1.]\n"
        "dist_1: !!opencv-matrix\n  rows: 1\n  cols: 5\n  dt: d\n  data: [0.1, 0., 0., 0., 0.]\n")
    (tmp_path / "extri.yml").write_text(
        "%YAML:1.0\n---\nnames:\n  - \"1\"\nR_1: !!opencv-matrix\n  rows: 3\n  cols: 1\n  dt: d\n"
        "  data: [0., 0., 1.5707963267948966]\nT_1: !!opencv-matrix\n  rows: 3\n  cols: 1\n"
        "  dt: d\n  data: [0., 0., 5.]\n")
    with pytest.raises(InputError) as e:
        read_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert e.value.field == "H_1"
    cam = read_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml", size=(900, 900))["1"]
    assert np.allclose(cam.R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert np.allclose(cam.T, cam.R.T @ [0, 0, -5.0])
    assert cam.model == "opencv" and np.isclose(cam.k[0], 0.1)


def test_easymocap_bad_input(tmp_path, rng):
    write_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml", [random_camera(rng, "opencv")])
    text = (tmp_path / "intri.yml").read_text()
    (tmp_path / "intri.yml").write_text(text.replace("K_cam", "Kx_cam"))
    with pytest.raises(InputError) as e:
        read_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml")
    assert e.value.field == "K_cam"
    (tmp_path / "intri.yml").write_text(text[: len(text) // 2])
    with pytest.raises(InputError):
        read_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml")
    with pytest.raises(InputError, match="missing"):
        read_easymocap(tmp_path / "none.yml", tmp_path / "extri.yml")


@pytest.mark.parametrize("suffix", ["yml", "xml", "json"])
@pytest.mark.parametrize("model", ["h36m", "opencv"])
def test_opencv_filestorage_round_trip(tmp_path, rng, suffix, model):
    cam = random_camera(rng, model, name="65906101")
    path = write_opencv_camera(tmp_path / f"cam.{suffix}", cam)
    back = read_opencv_camera(path)
    assert back.name == "65906101" and back.allclose(cam, atol=1e-12)


def test_opencv_filestorage_bad_input(tmp_path, rng):
    path = write_opencv_camera(tmp_path / "cam.yml", random_camera(rng))
    text = path.read_text()
    path.write_text(text.replace("image_height", "img_h"))
    with pytest.raises(InputError) as e:
        read_opencv_camera(path)
    assert e.value.field == "image_height"
    path.write_text(text.replace("rotation_matrix", "rot"))
    with pytest.raises(InputError, match="rotation_matrix"):
        read_opencv_camera(path)
    nan_text = text.replace("distortion_coefficients: !!opencv-matrix", "distortion_coefficients: "
                            "!!opencv-matrix", 1)
    i = nan_text.index("data:", nan_text.index("distortion_coefficients"))
    path.write_text(nan_text[: i + 7] + ".nan, " + nan_text[i + 7:].split(",", 1)[1])
    with pytest.raises(InputError) as e:
        read_opencv_camera(path)
    assert e.value.field == "distortion_coefficients"
