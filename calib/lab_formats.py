"""Calibration files labs have, as project cameras: Qualisys ``.qca.txt`` and the TOML of
Pose2Sim / anipose / caliscope. (Vicon ``.xcp``: :mod:`calib.xcp`; CHI3D JSON, EasyMocap and
OpenCV FileStorage: :mod:`calib.io`; one entry point for all: :func:`calib.io.read_camera`.)

Qualisys ``.qca.txt`` (QTM's calibration export, XML)::

    <calibration ...><cameras>
      <camera serial="cam01" model="Miqus Video" [video_resolution="1080p"] ...>
        <fov_video left="0" top="0" right="1087" bottom="1919"/>
        <transform x y z (mm) r11 r12 r13 r21 r22 r23 r31 r32 r33/>
        <intrinsic focalLengthU focalLengthV centerPointU centerPointV (sub-pixel units)
                   radialDistortion1 2 3 tangentalDistortion1 2 skew .../>
      </camera> ...

Conventions, and how they were checked:

- Sub-pixel units: ``focalLength*`` and ``centerPoint*`` are in 1/64 pixel of the full sensor
  (``QCA_SUBPIXELS``; ``sensorMaxU`` = 64 x (sensor width - 1) in the files we have).
  ``f = focalLength / 64``; the video is the window ``fov_video`` of the sensor (pixels,
  inclusive bounds), so ``c = centerPoint / 64 - (left, top)`` and the image is
  ``(right - left + 1) x (bottom - top + 1)``. A ``video_resolution="<n>p"`` attribute (a
  video recorded below the 1080p sensor mode, as Pose2Sim reads it) scales f, c and the size
  by ``n / 1080``.
- Pose: ``x y z`` is the camera centre in the world, millimetres (``Camera.T = xyz / 1000``).
  The rows of ``r`` are the camera's axes in the world (``r`` = cam_from_world) in Qualisys'
  camera frame, x right, y up, z backwards (the camera looks along -z); the OpenCV frame
  (x right, y down, z forward) is that turned half a turn about x:
  ``Camera.R = diag(1, -1, -1) r``. Checked on the 4 cameras of the Pose2Sim demo: their
  optical axes ``-r[2]`` pass within 0.11 m of one point 3.3-3.8 m in front of each, and
  image "up" (``r[1]``) points to world +z (``tests/test_calib_lab_formats.py``). This is also
  Pose2Sim's ``calib_qca_to_toml`` (transpose twice, then rotate by pi about x).
- Lens: ``radialDistortion1..3`` and ``tangentalDistortion1..2`` are OpenCV's
  ``k1 k2 k3 p1 p2`` on normalized coordinates (dimensionless, hence not in sub-pixels,
  although Pose2Sim divides them by 64 too): ``model="opencv"``. On the Pose2Sim demo the two
  readings differ by at most 5-8 px, in the image corners (k1 and k2 nearly cancel there), which
  the cap triangulation of the tests cannot tell apart. ``skew`` must be 0.

TOML (Pose2Sim, anipose / aniposelib, caliscope)::

    [cam_1]                      # one table per camera; other tables ([metadata]) are skipped
    name = "cam01"               # optional (the table name is used)
    size = [ 1088.0, 1920.0,]    # width, height, pixels
    matrix = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    distortions = [k1, k2, p1, p2]   # or 5 (k3 last), OpenCV
    rotation = [rx, ry, rz]          # Rodrigues, cam_from_world
    translation = [tx, ty, tz]       # metres: X_cam = R X_world + t
    fisheye = false                  # true (OpenCV fisheye lens) is refused

Camera choice in a file of several cameras (:func:`qualisys_camera`, :func:`toml_camera`):
the recipe's camera id is matched to the file's id (qca ``serial``; TOML ``name``), then to
the TOML table name (``cam_1``), then without case; a 1-camera file needs no id. The Camera
keeps the recipe's id as its name. Every reader raises :class:`formats.errors.InputError`
naming the file and the field (``cameras.camera[2].intrinsic.focalLengthU: missing``).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from calib.camera import Camera
from formats.errors import InputError

# ------------------------------------------------------------------------------------ constants
#: Qualisys stores focal lengths and principal points in 1/64 pixel.
QCA_SUBPIXELS = 64.0
#: The sensor mode ``video_resolution`` scales from (Pose2Sim's reading of the attribute).
QCA_REFERENCE_RESOLUTION = 1080
#: Largest |skew| (sub-pixels) taken as zero.
QCA_SKEW_TOL = 1e-9
#: Qualisys camera frame (y up, z backwards) -> OpenCV camera frame: half a turn about x.
QCA_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
#: Tolerance of a rotation matrix read from a file (orthonormal, det +1).
ROTATION_TOL = 1e-4

_QCA_INTRINSIC = ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV")
_QCA_LENS = ("radialDistortion1", "radialDistortion2", "radialDistortion3",
             "tangentalDistortion1", "tangentalDistortion2")
_QCA_FOV = ("left", "top", "right", "bottom")


# --------------------------------------------------------------------------------------- shared
def pick_camera(path, cams: dict[str, Camera], name: str | None, field: str,
                aliases: dict[str, str] | None = None) -> Camera:
    """The camera ``name`` of a file holding ``cams`` (``{file id: Camera}``): its id, else an
    alias (``{alias: file id}``, e.g. the TOML table name), else the id without case; no name
    for a 1-camera file. The Camera is renamed to ``name``. InputError naming ``field``."""
    if name is None:
        if len(cams) != 1:
            raise InputError(path, field, f"{len(cams)} cameras {sorted(cams)}: name one")
        return next(iter(cams.values()))
    want = str(name).strip()
    key = want if want in cams else (aliases or {}).get(want)
    if key is None:
        hits = [k for k in cams if k.lower() == want.lower()]
        if len(hits) > 1:
            raise InputError(path, field, f"{want!r} matches {hits} without case")
        key = hits[0] if hits else None
    if key is None:
        raise InputError(path, field, f"no camera {want!r} (the file has {sorted(cams)})")
    cam = cams[key]
    return cam if cam.name == want else replace(cam, name=want)


def _rotation(path, field: str, R: np.ndarray) -> np.ndarray:
    if not np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOL) or np.linalg.det(R) < 0:
        raise InputError(path, field, f"not a rotation (R R^T != I or det < 0): {R.tolist()}")
    u, _, vt = np.linalg.svd(R)  # snap to the nearest rotation (files print ~16 digits)
    return u @ vt


def _make(path, field: str, **kw) -> Camera:
    try:
        return Camera(**kw)
    except ValueError as e:
        raise InputError(path, field, str(e)) from None


# -------------------------------------------------------------------------------------- Qualisys
def _qca_float(path, el, where: str, attr: str, default: str | None = None) -> float:
    text = el.get(attr, default)
    if text is None:
        raise InputError(path, f"{where}.{attr}", "missing")
    try:
        v = float(text)
    except ValueError:
        raise InputError(path, f"{where}.{attr}", f"not a number: {text!r}") from None
    if not np.isfinite(v):
        raise InputError(path, f"{where}.{attr}", f"not finite: {text!r}")
    return v


def _qca_child(path, el, where: str, tag: str):
    child = el.find(tag)
    if child is None:
        raise InputError(path, f"{where}.{tag}", "missing")
    return child


def _qca_scale(path, el, where: str) -> float:
    res = el.get("video_resolution")
    if res is None or res.strip() in ("", "N/A"):
        return 1.0
    text = res.strip().lower().rstrip("p")
    if not text.isdigit() or int(text) <= 0:
        raise InputError(path, f"{where}.video_resolution", f"expected '<n>p', got {res!r}")
    return int(text) / QCA_REFERENCE_RESOLUTION


def _qca_camera(path: Path, el, i: int) -> Camera:
    where = f"cameras.camera[{i}]"
    serial = (el.get("serial") or "").strip()
    if not serial:
        raise InputError(path, f"{where}.serial", "missing")
    scale = _qca_scale(path, el, where)
    fov_el = _qca_child(path, el, where, "fov_video")
    left, top, right, bottom = (_qca_float(path, fov_el, f"{where}.fov_video", a) for a in _QCA_FOV)
    if right < left or bottom < top:
        raise InputError(path, f"{where}.fov_video", f"empty window left={left} right={right} "
                         f"top={top} bottom={bottom}")
    intr = _qca_child(path, el, where, "intrinsic")
    w_in = f"{where}.intrinsic"
    fu, fv, cu, cv = (_qca_float(path, intr, w_in, a) / QCA_SUBPIXELS for a in _QCA_INTRINSIC)
    if fu <= 0 or fv <= 0:
        raise InputError(path, f"{w_in}.focalLengthU", f"focal lengths must be positive, got "
                         f"{fu * QCA_SUBPIXELS} {fv * QCA_SUBPIXELS}")
    k1, k2, k3, p1, p2 = (_qca_float(path, intr, w_in, a, "0") for a in _QCA_LENS)
    skew = _qca_float(path, intr, w_in, "skew", "0")
    if abs(skew) > QCA_SKEW_TOL:
        raise InputError(path, f"{w_in}.skew", f"{skew}: skewed pixels are not supported")
    tr = _qca_child(path, el, where, "transform")
    w_tr = f"{where}.transform"
    r = np.array([[_qca_float(path, tr, w_tr, f"r{a}{b}") for b in (1, 2, 3)] for a in (1, 2, 3)])
    r = _rotation(path, w_tr, r)
    centre = np.array([_qca_float(path, tr, w_tr, a) for a in "xyz"]) / 1000.0
    f = np.array([fu, fv]) * scale
    c = (np.array([cu, cv]) - (left, top)) * scale
    w, h = round((right - left + 1) * scale), round((bottom - top + 1) * scale)
    return _make(path, where, name=serial, f=f, c=c, k=(k1, k2, k3), p=(p1, p2),
                 R=QCA_TO_OPENCV @ r, T=centre, width=w, height=h, model="opencv")


def read_qualisys(path: str | Path) -> dict[str, Camera]:
    """Every camera of a Qualisys ``.qca.txt``: ``{serial: Camera}`` (file order,
    ``model="opencv"``, metres; conventions in the module doc)."""
    import xml.etree.ElementTree as ET

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "missing")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(path, "<xml>", f"not a .qca.txt (XML) file: {e}") from None
    els = root.findall("cameras/camera")
    if not els:
        raise InputError(path, "cameras.camera", "no camera")
    out: dict[str, Camera] = {}
    for i, el in enumerate(els):
        cam = _qca_camera(path, el, i)
        if cam.name in out:
            raise InputError(path, f"cameras.camera[{i}].serial", f"{cam.name!r} appears twice")
        out[cam.name] = cam
    return out


def qualisys_camera(path: str | Path, name: str | None = None) -> Camera:
    """One camera of a ``.qca.txt`` by its ``serial`` (see the module doc's matching rule)."""
    return pick_camera(Path(path), read_qualisys(path), name, "cameras.camera.serial")


# ------------------------------------------------------------------------------------------ TOML
def _toml_array(path, field: str, value, shape: tuple) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(path, field, f"not a numeric array ({e})") from None
    if a.shape != shape:
        raise InputError(path, field, f"expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(path, field, "contains NaN or inf")
    return a


def _toml_camera(path: Path, key: str, t: dict) -> Camera:
    import cv2

    for field in ("size", "matrix", "distortions", "rotation", "translation"):
        if field not in t:
            raise InputError(path, f"{key}.{field}", "missing")
    if t.get("fisheye", False):
        raise InputError(path, f"{key}.fisheye", "an OpenCV fisheye lens is not supported "
                         "(the camera model is OpenCV's pinhole k1 k2 p1 p2 k3)")
    size = _toml_array(path, f"{key}.size", t["size"], (2,))
    if np.any(size <= 0) or np.any(size != np.round(size)):
        raise InputError(path, f"{key}.size", f"expected positive whole width, height, got "
                         f"{size.tolist()}")
    K = _toml_array(path, f"{key}.matrix", t["matrix"], (3, 3))
    if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or K[1, 0] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise InputError(path, f"{key}.matrix", f"expected [[fx,0,cx],[0,fy,cy],[0,0,1]], got "
                         f"{K.tolist()}")
    n = len(t["distortions"]) if isinstance(t["distortions"], list) else 0
    if n not in (4, 5):
        raise InputError(path, f"{key}.distortions", "expected a list of 4 or 5 values (k1 k2 p1 "
                         f"p2 [k3]), got {t['distortions']!r}")
    d = _toml_array(path, f"{key}.distortions", t["distortions"], (n,))
    rvec = _toml_array(path, f"{key}.rotation", t["rotation"], (3,))
    tvec = _toml_array(path, f"{key}.translation", t["translation"], (3,))
    R = cv2.Rodrigues(rvec.reshape(3, 1))[0]
    k3 = d[4] if d.size == 5 else 0.0
    name = str(t.get("name", key)).strip() or key
    return _make(path, key, name=name, f=(K[0, 0], K[1, 1]), c=(K[0, 2], K[1, 2]),
                 k=(d[0], d[1], k3), p=(d[2], d[3]), R=R, T=-R.T @ tvec,
                 width=int(size[0]), height=int(size[1]), model="opencv")


def _read_toml(path: str | Path) -> tuple[dict[str, Camera], dict[str, str]]:
    import tomllib

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "missing")
    try:
        d = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(path, "<toml>", f"not a TOML file: {e}") from None
    cams: dict[str, Camera] = {}
    tables: dict[str, str] = {}
    for key, t in d.items():
        if not isinstance(t, dict) or "matrix" not in t:
            continue  # [metadata] and friends
        cam = _toml_camera(path, key, t)
        if cam.name in cams:
            raise InputError(path, f"{key}.name", f"{cam.name!r} appears twice")
        cams[cam.name] = cam
        tables[key] = cam.name
    if not cams:
        raise InputError(path, "[<camera>].matrix", "no camera table (one with a matrix)")
    return cams, tables


def read_toml(path: str | Path) -> dict[str, Camera]:
    """Every camera of a Pose2Sim / anipose / caliscope ``.toml``: ``{name: Camera}`` (the
    ``name`` field, else the table name; ``model="opencv"``, metres)."""
    return _read_toml(path)[0]


def toml_camera(path: str | Path, name: str | None = None) -> Camera:
    """One camera of a calibration ``.toml`` by its ``name``, else its table name (``cam_1``)."""
    cams, tables = _read_toml(path)
    return pick_camera(Path(path), cams, name, "name", aliases=tables)
