"""Calibration files labs have (Qualisys .qca.txt, Pose2Sim/anipose/caliscope .toml, EasyMocap,
CHI3D, Vicon) read through one entry point, ``calib.io.read_camera``.

Each synthetic file is written from a known camera in the format's own convention, and the
reader's camera (``calib.project``) is compared with an independent projection computed from
the file's own numbers (cv2.projectPoints on the file's K, distortion and pose). The real
Pose2Sim demo calibration (4 Qualisys Miqus Video cameras) is checked for consistency: the
optical axes meet, image "up" is world up, the image size is the videos', and the coloured cap
triangulated from three views reprojects into the fourth.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib import Camera, look_at, project
from calib.camera import normalized_from_pixels
from calib.io import (
    calibration_format,
    read_camera,
    write_chi3d_camera,
    write_easymocap,
    write_opencv_camera,
)
from calib.lab_formats import QCA_SUBPIXELS, read_qualisys, read_toml
from formats.errors import InputError

# ------------------------------------------------------------------------------------ constants
PX_TOL = 1e-6                       # reader vs the format's own projection, pixels
REAL = Path("/work/shared/real/video/pose2sim_demo")
REAL_QCA = REAL / "calibration" / "Calib.qca.txt"
REAL_SIZE = (1088, 1920)            # the qca's fov_video window: portrait
AXES_MISS_M = 0.15                  # the 4 optical axes pass this close to one point (0.11 m)
AXES_RANGE_M = (2.5, 4.5)           # ... that far in front of each camera (3.3-3.8 m)
UP_MIN_Z = 0.8                      # image "up" (-y of the camera) . world z
CAP_FRAMES = range(0, 100, 5)
CAP_HUE = (85, 100)                 # the cyan cap, OpenCV hue 0..180
CAP_MIN_SAT, CAP_MIN_VAL, CAP_MIN_AREA = 140, 60, 300
CAP_MAX_ROW = 1100                  # the cap is in the upper part of the portrait frames
CAP_MEDIAN_PX = 30.0                # leave-one-view-out reprojection of the cap centroid (18 px:
                                    # the centroid of the visible cap is not one 3D point)
CAP_WRONG_PX = 150.0                # a wrong rotation convention is this far off (180+ px)
LEFT, TOP = 16, 40                  # a video window inside the sensor (qca fov_video)

RNG_SEED = 3


def _points(n=60, seed=RNG_SEED):
    rng = np.random.default_rng(seed)
    return rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 2.0], size=(n, 3))


def _cams():
    """Two known portrait cameras, OpenCV lenses, around the volume at the origin."""
    a = look_at("cam01", (3.2, -1.5, 1.8), (0, 0, 1), (1680.5, 1679.2), (530.3, 951.7), 1088, 1920,
                k=(-0.046, 0.14, 0.01), p=(6e-4, 7e-4), model="opencv")
    b = look_at("cam02", (-2.9, 2.4, 2.1), (0.2, 0, 0.9), (1402.0, 1401.0), (545.0, 940.0), 1088,
                1920, k=(0.03, -0.02, 0.0), p=(-5e-4, 2e-4), model="opencv")
    return [a, b]


def _cv2_pixels(X, rvec, tvec, K, dist):
    uv, _ = cv2.projectPoints(np.asarray(X, float).reshape(-1, 1, 3), np.asarray(rvec, float),
                              np.asarray(tvec, float), np.asarray(K, float), np.asarray(dist, float))
    return uv.reshape(-1, 2)


# -------------------------------------------------------------------------------------- Qualisys
def _qca_camera_xml(cam: Camera, drop: str = "", resolution: str | None = None) -> str:
    """``cam`` in Qualisys' convention: sub-pixel f and c of the full sensor, the video window
    at (LEFT, TOP), camera centre in mm, r = rows of Qualisys' camera axes (y up, z back)."""
    r = np.diag([1.0, -1.0, -1.0]) @ cam.R
    x, y, z = cam.T * 1000
    tr = " ".join(f'r{i + 1}{j + 1}="{r[i, j]!r}"' for i in range(3) for j in range(3))
    intr = {"focalLengthU": cam.f[0] * QCA_SUBPIXELS, "focalLengthV": cam.f[1] * QCA_SUBPIXELS,
            "centerPointU": (cam.c[0] + LEFT) * QCA_SUBPIXELS,
            "centerPointV": (cam.c[1] + TOP) * QCA_SUBPIXELS, "focallength": 9.3,
            "radialDistortion1": cam.k[0], "radialDistortion2": cam.k[1],
            "radialDistortion3": cam.k[2], "tangentalDistortion1": cam.p[0],
            "tangentalDistortion2": cam.p[1], "skew": 0.0,
            "sensorMaxU": 69568, "sensorMaxV": 122816, "sensorMinU": 0, "sensorMinV": 0}
    intr_s = " ".join(f'{k}="{v!r}"' for k, v in intr.items() if k != drop)
    fov = (f'left="{LEFT}" top="{TOP}" right="{LEFT + cam.width - 1}" '
           f'bottom="{TOP + cam.height - 1}"')
    res = f' video_resolution="{resolution}"' if resolution else ""
    return (f'    <camera active="1" avg-residual="0.4" model="Miqus Video" serial="{cam.name}"{res}>\n'
            f'      <fov_marker {fov}/>\n      <fov_video {fov}/>\n'
            f'      <transform x="{x!r}" y="{y!r}" z="{z!r}" {tr}/>\n'
            f'      <intrinsic {intr_s}/>\n    </camera>\n')


def _write_qca(path: Path, cams, drop_in: int = -1, drop: str = "", resolution=None) -> Path:
    body = "".join(_qca_camera_xml(c, drop if i == drop_in else "", resolution)
                   for i, c in enumerate(cams))
    path.write_text("<?xml version='1.0' encoding='ASCII'?>\n<calibration type=\"regular\">\n"
                    f"  <cameras>\n{body}  </cameras>\n</calibration>\n")
    return path


def _qca_own_pixels(path: Path, serial: str, X: np.ndarray) -> np.ndarray:
    """Pixels from the file's numbers, independently: Qualisys camera frame ``r (X - C)``
    (looking along -z, y up), to OpenCV's by flipping y and z, then cv2.projectPoints with
    K = sub-pixels / 64 minus the window origin."""
    import xml.etree.ElementTree as ET

    el = next(e for e in ET.parse(path).getroot().iter("camera") if e.get("serial") == serial)
    t, i, fov = el.find("transform"), el.find("intrinsic"), el.find("fov_video")
    r = np.array([[float(t.get(f"r{a}{b}")) for b in "123"] for a in "123"])
    C = np.array([float(t.get(a)) for a in "xyz"]) / 1000
    Xq = (X - C) @ r.T
    Xcv = Xq * [1, -1, -1]
    K = np.array([[float(i.get("focalLengthU")) / 64, 0,
                   float(i.get("centerPointU")) / 64 - float(fov.get("left"))],
                  [0, float(i.get("focalLengthV")) / 64,
                   float(i.get("centerPointV")) / 64 - float(fov.get("top"))], [0, 0, 1]])
    dist = [float(i.get(a)) for a in ("radialDistortion1", "radialDistortion2",
                                      "tangentalDistortion1", "tangentalDistortion2",
                                      "radialDistortion3")]
    return _cv2_pixels(Xcv, np.zeros(3), np.zeros(3), K, dist)


def test_qualisys_reader_projects_as_the_file_says(tmp_path):
    cams = _cams()
    path = _write_qca(tmp_path / "Calib.qca.txt", cams)
    got = read_qualisys(path)
    assert list(got) == ["cam01", "cam02"]
    X = _points()
    for cam in cams:
        c = got[cam.name]
        assert (c.width, c.height, c.model) == (1088, 1920, "opencv")
        assert c.allclose(cam, atol=1e-9)
        np.testing.assert_allclose(project(c, X), _qca_own_pixels(path, cam.name, X),
                                   atol=PX_TOL, rtol=0)
        # one file for every camera: picked by serial, renamed to the recipe's id
        one = read_camera(path, cam.name.upper())
        assert one.name == cam.name.upper() and one.allclose(
            Camera(one.name, c.f, c.c, c.k, c.p, c.R, c.T, c.width, c.height, c.model))


def test_qualisys_video_resolution_scales_the_camera(tmp_path):
    cams = _cams()
    full = read_qualisys(_write_qca(tmp_path / "a.qca.txt", cams))["cam01"]
    half = read_qualisys(_write_qca(tmp_path / "b.qca.txt", cams, resolution="540p"))["cam01"]
    assert (half.width, half.height) == (544, 960)
    np.testing.assert_allclose(half.f, full.f / 2)
    np.testing.assert_allclose(half.c, full.c / 2)
    X = _points()
    np.testing.assert_allclose(project(half, X), project(full, X) / 2, atol=PX_TOL)


@pytest.mark.parametrize("drop,field", [
    ("focalLengthU", "cameras.camera[1].intrinsic.focalLengthU: missing"),
    ("centerPointV", "cameras.camera[1].intrinsic.centerPointV: missing"),
])
def test_qualisys_bad_files_name_file_and_field(tmp_path, drop, field):
    path = _write_qca(tmp_path / "Calib.qca.txt", _cams(), drop_in=1, drop=drop)
    with pytest.raises(InputError, match=re.escape(f"Calib.qca.txt: {field}")):
        read_qualisys(path)
    text = path.read_text()
    (tmp_path / "x.qca.txt").write_text(text.replace('r22="', 'r22="abc'))
    with pytest.raises(InputError, match=r"x.qca.txt: cameras.camera\[0\].transform.r22: not a number"):
        read_qualisys(tmp_path / "x.qca.txt")
    (tmp_path / "y.qca.txt").write_text(text.replace("<transform", "<transformX"))
    with pytest.raises(InputError, match=r"y.qca.txt: cameras.camera\[0\].transform: missing"):
        read_qualisys(tmp_path / "y.qca.txt")
    (tmp_path / "z.qca.txt").write_text(text[:200])
    with pytest.raises(InputError, match=r"z.qca.txt: <xml>: not a .qca.txt"):
        read_qualisys(tmp_path / "z.qca.txt")
    good = _write_qca(tmp_path / "good.qca.txt", _cams())
    with pytest.raises(InputError, match=r"good.qca.txt: cameras.camera.serial: no camera 'cam07' "
                                         r"\(the file has \['cam01', 'cam02'\]\)"):
        read_camera(good, "cam07")
    with pytest.raises(InputError, match="2 cameras"):
        read_camera(good)


# ------------------------------------------------------------------------------------------ TOML
def _toml_text(cams, n_dist=4, names=True, extra="") -> str:
    out = []
    for i, c in enumerate(cams):
        rvec = cv2.Rodrigues(c.R)[0].ravel()
        d = [c.k[0], c.k[1], c.p[0], c.p[1]] + ([c.k[2]] if n_dist == 5 else [])
        K = c.K
        out.append(f"[cam_{i + 1}]\n" + (f'name = "{c.name}"\n' if names else "")
                   + f"size = [ {float(c.width)}, {float(c.height)},]\n"
                   + "matrix = [ " + ", ".join("[ " + ", ".join(repr(float(v)) for v in row) + ",]"
                                               for row in K) + ",]\n"
                   + "distortions = [ " + ", ".join(repr(float(v)) for v in d) + ",]\n"
                   + "rotation = [ " + ", ".join(repr(float(v)) for v in rvec) + ",]\n"
                   + "translation = [ " + ", ".join(repr(float(v)) for v in c.t) + ",]\n"
                   + "fisheye = false\n" + extra + "\n")
    out.append("[metadata]\nadjusted = false\nerror = 0.0\n")
    return "".join(out)


def test_toml_reader_projects_as_opencv_does(tmp_path):
    import tomllib

    cams = _cams()
    cams[1] = Camera("cam02", cams[1].f, cams[1].c, (0.03, -0.02, 0.0), cams[1].p, cams[1].R,
                     cams[1].T, 1088, 1920, "opencv")
    for n_dist in (4, 5):
        use = cams if n_dist == 5 else [Camera(c.name, c.f, c.c, (c.k[0], c.k[1], 0.0), c.p, c.R,
                                               c.T, c.width, c.height, "opencv") for c in cams]
        path = tmp_path / f"Calib_{n_dist}.toml"
        path.write_text(_toml_text(use, n_dist))
        got = read_toml(path)
        assert list(got) == ["cam01", "cam02"]
        raw = tomllib.loads(path.read_text())
        X = _points()
        for i, cam in enumerate(use):
            t = raw[f"cam_{i + 1}"]
            d = t["distortions"] + ([0.0] if n_dist == 4 else [])
            ref = _cv2_pixels(X, t["rotation"], t["translation"], t["matrix"],
                              [d[0], d[1], d[2], d[3], d[4]])
            np.testing.assert_allclose(project(got[cam.name], X), ref, atol=PX_TOL, rtol=0)
            assert got[cam.name].allclose(cam, atol=1e-9)
    # no name field: the table name; the recipe's id is kept as the camera's name
    path = tmp_path / "anipose.toml"
    path.write_text(_toml_text(cams, 5, names=False))
    assert list(read_toml(path)) == ["cam_1", "cam_2"]
    c = read_camera(path, "cam_2")
    assert c.name == "cam_2" and c.allclose(Camera("cam_2", *(getattr(cams[1], a) for a in
                                                              ("f", "c", "k", "p", "R", "T")),
                                                   1088, 1920, "opencv"))


def test_toml_bad_files_name_file_and_field(tmp_path):
    cams = _cams()
    text = _toml_text(cams)
    cases = {
        "cam_2.rotation: missing": text.replace("rotation = ", "rotationX = ", 2)
                                       .replace("rotationX = ", "rotation = ", 1),
        "cam_1.fisheye: an OpenCV fisheye": text.replace("fisheye = false", "fisheye = true", 1),
        "cam_1.distortions: expected a list of 4 or 5": text.replace("distortions = [ ",
                                                           "distortions = [ 0.0, 0.0, ", 1),
        "cam_1.matrix: not a numeric array": text.replace("matrix = [ [", "matrix = [ [ 1.0, ], [", 1),
        "<toml>: not a TOML file": text.replace("[cam_1]", "[cam_1", 1),
    }
    for i, (msg, bad) in enumerate(cases.items()):
        p = tmp_path / f"bad{i}.toml"
        p.write_text(bad)
        with pytest.raises(InputError, match=f"bad{i}.toml: {msg}"):
            read_toml(p)


# ------------------------------------------------------------------------- the other formats
def test_read_camera_dispatches_every_format(tmp_path):
    from calib.convert import to_opencv

    cams = _cams()
    X = _points()
    # EasyMocap: either file of the pair, the camera by name
    write_easymocap(tmp_path / "intri.yml", tmp_path / "extri.yml", cams)
    for f in ("intri.yml", "extri.yml"):
        assert calibration_format(tmp_path / f) == "easymocap"
        c = read_camera(tmp_path / f, "cam02")
        assert c.allclose(cams[1], atol=1e-9)
        np.testing.assert_allclose(project(c, X), _cv2_pixels(X, *to_opencv(cams[1])), atol=PX_TOL)
    # OpenCV FileStorage: one camera per file
    write_opencv_camera(tmp_path / "one.yml", cams[0])
    assert calibration_format(tmp_path / "one.yml") == "opencv"
    assert read_camera(tmp_path / "one.yml").allclose(cams[0], atol=1e-9)
    # CHI3D JSON (h36m lens, 900 x 900)
    chi = look_at("50591643", (3, -1, 1.5), (0, 0, 1), (1145.0, 1144.0), (450.0, 452.0), 900, 900,
                  k=(-0.2, 0.1, 0.0), p=(1e-3, -2e-3))
    write_chi3d_camera(tmp_path / "50591643" / "Hug 1.json", chi)
    assert read_camera(tmp_path / "50591643" / "Hug 1.json").allclose(chi)
    # the recipe's format wins over the suffix; aliases; unknown ones are named
    p = tmp_path / "calib.txt"
    p.write_text(_toml_text(cams, 5))
    assert read_camera(p, "cam01", fmt="anipose").allclose(cams[0], atol=1e-9)
    with pytest.raises(InputError, match=r"calib.txt: calibration_format: unknown suffix"):
        read_camera(p, "cam01")
    with pytest.raises(InputError, match=r"calibration_format: 'bundler': expected one of"):
        read_camera(p, "cam01", fmt="bundler")
    assert calibration_format("a/Calib.qca.txt") == "qualisys"
    assert calibration_format("a/b.xcp") == "vicon"
    assert calibration_format("a/b.toml") == "pose2sim"
    with pytest.raises(InputError, match=r"names: no camera 'cam09'"):
        read_camera(tmp_path / "intri.yml", "cam09")


# -------------------------------------------------------------------------- the real Qualisys file
needs_real = pytest.mark.skipif(not REAL_QCA.is_file(), reason="no ../shared/real pose2sim demo")


@needs_real
def test_real_qca_cameras_look_at_one_volume():
    cams = read_qualisys(REAL_QCA)
    assert list(cams) == ["cam01", "cam02", "cam03", "cam04"]
    for c in cams.values():
        assert (c.width, c.height) == REAL_SIZE
        assert 0 < c.c[0] < c.width and 0 < c.c[1] < c.height
        assert -c.R[1] @ [0, 0, 1] > UP_MIN_Z  # image up is world up
    # the optical axes (camera z) pass close to one point in front of every camera
    M, v = np.zeros((3, 3)), np.zeros(3)
    for c in cams.values():
        P = np.eye(3) - np.outer(c.R[2], c.R[2])
        M += P
        v += P @ c.T
    X = np.linalg.solve(M, v)
    for c in cams.values():
        w = X - c.T
        assert AXES_RANGE_M[0] < w @ c.R[2] < AXES_RANGE_M[1]
        assert np.linalg.norm(w - (w @ c.R[2]) * c.R[2]) < AXES_MISS_M


def _cap_centroids(videos) -> np.ndarray:
    from formats.video import VideoReader

    out = np.full((len(videos), len(CAP_FRAMES), 2), np.nan)
    for ci, path in enumerate(videos):
        with VideoReader(path) as v:
            for j, f in enumerate(CAP_FRAMES):
                hsv = cv2.cvtColor(v[f], cv2.COLOR_RGB2HSV)
                m = ((hsv[..., 0] >= CAP_HUE[0]) & (hsv[..., 0] <= CAP_HUE[1])
                     & (hsv[..., 1] > CAP_MIN_SAT) & (hsv[..., 2] > CAP_MIN_VAL)).astype(np.uint8)
                m[CAP_MAX_ROW:] = 0
                n, _, st, cen = cv2.connectedComponentsWithStats(m)
                if n > 1:
                    k = 1 + int(np.argmax(st[1:, 4]))
                    if st[k, 4] > CAP_MIN_AREA:
                        out[ci, j] = cen[k]
    return out


def _loo_errors(cams, det) -> np.ndarray:
    """Each view left out: the cap triangulated (DLT on undistorted rays) from the others,
    reprojected into it; pixels."""
    errs = []
    for j in range(det.shape[1]):
        ok = [i for i in range(len(cams)) if np.isfinite(det[i, j, 0])]
        if len(ok) < 3:
            continue
        for lo in ok:
            A = []
            for i in ok:
                if i == lo:
                    continue
                xy = normalized_from_pixels(cams[i], det[i, j][None])[0]
                P = np.hstack([cams[i].R, cams[i].t[:, None]])
                A += [xy[0] * P[2] - P[0], xy[1] * P[2] - P[1]]
            Xh = np.linalg.svd(np.array(A))[2][-1]
            errs.append(np.linalg.norm(project(cams[lo], Xh[:3] / Xh[3]) - det[lo, j]))
    return np.array(errs)


@needs_real
def test_real_qca_reprojects_the_cap_across_views():
    from dataclasses import replace

    from formats.video import video_info

    videos = [REAL / "videos" / f"cam0{i}.mp4" for i in range(1, 5)]
    cams = [read_camera(REAL_QCA, f"cam0{i}") for i in range(1, 5)]
    for c, v in zip(cams, videos, strict=True):  # the sizes: portrait; two encoded 8 px narrower
        info = video_info(v)
        assert info.height == c.height and 0 <= c.width - info.width <= 8
    det = _cap_centroids(videos)
    assert np.isfinite(det[..., 0]).sum() >= 3 * len(CAP_FRAMES)
    errs = _loo_errors(cams, det)
    assert len(errs) >= 40 and np.median(errs) < CAP_MEDIAN_PX
    # the rotation read the other way round (no half turn to OpenCV's frame) does not fit
    wrong = [replace(c, R=np.diag([1.0, -1.0, -1.0]) @ c.R) for c in cams]
    assert np.median(_loo_errors(wrong, det)) > CAP_WRONG_PX


# ------------------------------------------------------------------------------------ the recipe
def test_recipe_names_the_calibration_format():
    import typing

    from pydantic import ValidationError

    from calib.io import CALIBRATION_FORMATS
    from recipes.schema import CalibrationFormat, SequenceSpec

    assert typing.get_args(CalibrationFormat) == CALIBRATION_FORMATS
    s = SequenceSpec(markers_on="a", c3d="x.c3d", calibration_format="qualisys")
    assert s.calibration_format == "qualisys"
    assert SequenceSpec(markers_on="a", c3d="x.c3d").calibration_format is None
    with pytest.raises(ValidationError, match="calibration_format"):
        SequenceSpec(markers_on="a", c3d="x.c3d", calibration_format="bundler")


def test_capture_reads_both_files_of_an_easymocap_pair(tmp_path):
    """The capture stage's raw inputs hold extri.yml beside intri.yml (keyed by content), and
    one .qca.txt given for every camera is one file."""
    from types import SimpleNamespace

    import stages.capture as cap

    cams = ["c1", "c2"]
    seq = SimpleNamespace(c3d=tmp_path / "x.c3d", markers_on="sa", calibration_format=None,
                          calibration={c: tmp_path / "intri.yml" for c in cams})
    recipe = SimpleNamespace(cameras=cams, sequence=lambda u: seq,
                             subjects={"sa": SimpleNamespace(markerset="plug-in-gait")},
                             body_model=SimpleNamespace(path=tmp_path / "m.npz", kind="anny"))
    raw = cap.raw_inputs(recipe, "g/a")
    assert raw["calibration:c1"] == tmp_path / "intri.yml"
    assert raw["calibration_pair:c2"] == tmp_path / "extri.yml"
    seq.calibration = {c: tmp_path / "Calib.qca.txt" for c in cams}
    raw = cap.raw_inputs(recipe, "g/a")
    assert raw["calibration:c2"] == tmp_path / "Calib.qca.txt"
    assert not any(k.startswith("calibration_pair:") for k in raw)
