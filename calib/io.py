"""Calibration files: CHI3D camera JSON, EasyMocap ``intri.yml``/``extri.yml``, OpenCV FileStorage;
:func:`read_camera` reads one camera of any calibration format (also Vicon ``.xcp``,
Qualisys ``.qca.txt``, Pose2Sim / anipose / caliscope ``.toml``: :mod:`calib.lab_formats`).

- CHI3D: ``<subject>/camera_parameters/<camera>/<action>.json``::

      {"extrinsics": {"R": 3x3, "T": [[x, y, z]]},          # X_cam = (X - T) @ R.T, metres
       "intrinsics_w_distortion": {"f": [[fx, fy]], "c": [[cx, cy]],
                                   "k": [[k1, k2, k3]], "p": [[p1, p2]]},
       "intrinsics_wo_distortion": {"f": [[fx, fy]], "c": [[cx, cy]]}}

  Written as 1xN nested lists because the public CHI3D tools index ``p[:, [1, 0]]`` and
  ``k @ [r2, r2^2, r2^3]`` (both need 2-D arrays). Read accepts flat or nested. The file has
  no image size: CHI3D frames are 900 x 900 (``constants.CHI3D_IMAGE_SIZE``).
  ``intrinsics_wo_distortion`` is read for validation only (the Camera uses the
  ``w_distortion`` f and c for both projections, as the release does).
- EasyMocap: ``intri.yml`` (``names``, ``K_<cam>`` 3x3, ``dist_<cam>`` 1x5, optional ``H_<cam>``,
  ``W_<cam>``) and ``extri.yml`` (``names``, ``R_<cam>`` Rodrigues 3x1, ``Rot_<cam>`` 3x3,
  ``T_<cam>`` 3x1 with ``X_cam = Rot X + T``, metres). OpenCV distortion only.
- OpenCV FileStorage, one camera per file (.yml/.yaml/.xml/.json): ``camera_name``,
  ``image_width``, ``image_height``, ``camera_matrix``, ``distortion_coefficients`` (5, or the
  exact 12-coefficient form of a Human3.6M camera), ``rotation_matrix`` (cam_from_world),
  ``translation_vector`` (``X_cam = R X + t``). On read, ``rvec``/``R`` and ``tvec``/``T`` are
  accepted too.

Every reader raises :class:`formats.errors.InputError` naming the file and the field.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib import constants
from calib.camera import Camera
from calib.convert import from_opencv, opencv_dist
from formats.errors import InputError
from formats.keypoints import load_json


# --------------------------------------------------------------------------------------- helpers
def _array(file, field: str, value, n: int | tuple) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(file, field, f"not a numeric array ({e})") from None
    if isinstance(n, tuple):
        if a.shape != n:
            raise InputError(file, field, f"expected shape {n}, got {a.shape}")
    else:
        if a.size != n:
            raise InputError(file, field, f"expected {n} values, got shape {a.shape}")
        a = a.reshape(n)
    if not np.all(np.isfinite(a)):
        raise InputError(file, field, "contains NaN or inf")
    return a


def _get(file, d: dict, dotted: str):
    cur = d
    for part in dotted.split("."):
        if not isinstance(cur, dict) or part not in cur:
            raise InputError(file, dotted, "missing")
        cur = cur[part]
    return cur


def _camera(file, field: str, **kw) -> Camera:
    try:
        return Camera(**kw)
    except ValueError as e:
        raise InputError(file, field, str(e)) from None


def _nested(a) -> list:
    return [np.asarray(a, dtype=float).reshape(-1).tolist()]


# ----------------------------------------------------------------------------------------- CHI3D
def read_chi3d_camera(path: str | Path, name: str | None = None,
                      size: tuple[int, int] = constants.CHI3D_IMAGE_SIZE) -> Camera:
    """Read one CHI3D camera JSON. name: defaults to the parent folder (the camera serial);
    size: (width, height) pixels. Returns a ``model="h36m"`` Camera.

    A Vicon ``.xcp`` path is read by :func:`calib.xcp.xcp_camera` instead: ``name`` is the
    camera's DEVICEID, USERID or NAME (optional for a one-camera file), the size comes from the
    file, and the Camera is ``model="opencv"``."""
    path = Path(path)
    if path.suffix.lower() == ".xcp":
        from calib.xcp import xcp_camera

        return xcp_camera(path, name)
    d = load_json(path)
    if not isinstance(d, dict):
        raise InputError(path, "<json>", f"expected an object, got {type(d).__name__}")
    R = _array(path, "extrinsics.R", _get(path, d, "extrinsics.R"), (3, 3))
    T = _array(path, "extrinsics.T", _get(path, d, "extrinsics.T"), 3)
    vals = {}
    for key, n in (("f", 2), ("c", 2), ("k", 3), ("p", 2)):
        field = f"intrinsics_w_distortion.{key}"
        vals[key] = _array(path, field, _get(path, d, field), n)
    if "intrinsics_wo_distortion" in d:
        for key in ("f", "c"):
            field = f"intrinsics_wo_distortion.{key}"
            _array(path, field, _get(path, d, field), 2)
    if np.any(vals["f"] <= 0):
        raise InputError(path, "intrinsics_w_distortion.f", f"must be positive, got {vals['f']}")
    return _camera(path, "extrinsics.R", name=name or path.parent.name, R=R, T=T,
                   width=size[0], height=size[1], model="h36m", **vals)


def write_chi3d_camera(path: str | Path, cam: Camera) -> Path:
    """Write ``cam`` as a CHI3D camera JSON (parents created). The camera must use the h36m
    model, or have ``p = 0`` (then both models agree): convert with
    ``calib.convert.convert_distortion`` first otherwise."""
    if cam.model != "h36m" and np.any(cam.p):
        raise ValueError(f"write_chi3d_camera({cam.name}): model {cam.model!r} with tangential "
                         "distortion; convert_distortion(cam, 'h36m') first")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = {
        "extrinsics": {"R": cam.R.tolist(), "T": _nested(cam.T)},
        "intrinsics_w_distortion": {"f": _nested(cam.f), "c": _nested(cam.c),
                                    "k": _nested(cam.k), "p": _nested(cam.p)},
        "intrinsics_wo_distortion": {"f": _nested(cam.f), "c": _nested(cam.c)},
    }
    path.write_text(json.dumps(d))
    return path


def chi3d_camera_path(subject_dir: str | Path, camera: str, action: str) -> Path:
    """``<subject_dir>/camera_parameters/<camera>/<action>.json``."""
    return Path(subject_dir) / "camera_parameters" / camera / f"{action}.json"


def read_chi3d_cameras(subject_dir: str | Path, action: str,
                       size: tuple[int, int] = constants.CHI3D_IMAGE_SIZE) -> dict[str, Camera]:
    """All cameras of one action: ``{serial: Camera}`` sorted by serial."""
    root = Path(subject_dir) / "camera_parameters"
    if not root.is_dir():
        raise InputError(root, "camera_parameters", "folder missing")
    out = {}
    for cam_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        f = cam_dir / f"{action}.json"
        if f.exists():
            out[cam_dir.name] = read_chi3d_camera(f, cam_dir.name, size)
    if not out:
        raise InputError(root, f"<camera>/{action}.json", "no camera file for this action")
    return out


def write_chi3d_cameras(subject_dir: str | Path, action: str, cams) -> list[Path]:
    """Write each camera of ``cams`` (iterable of Camera) to its CHI3D path."""
    return [write_chi3d_camera(chi3d_camera_path(subject_dir, c.name, action), c) for c in cams]


# ------------------------------------------------------------------------------- OpenCV storage
def _fs_open(path: Path, write: bool):
    import cv2

    if not write and not path.exists():
        raise InputError(path, "<file>", "missing")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE if write else cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # a parse error can surface as SystemError
        msg = getattr(e, "err", None) or getattr(e.__cause__, "err", None) or str(e)
        raise InputError(path, "<filestorage>", f"unreadable or truncated: {msg}") from None
    if not fs.isOpened():
        raise InputError(path, "<filestorage>", "cannot open")
    return fs


def _fs_mat(fs, path: Path, key: str, required: bool = True):
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        if required:
            raise InputError(path, key, "missing")
        return None
    if node.isInt() or node.isReal():
        return np.array([node.real()])
    import cv2

    try:
        m = node.mat()
    except cv2.error:
        m = None
    if m is None:
        raise InputError(path, key, "not a matrix")
    return np.asarray(m, dtype=np.float64)


def _fs_int(fs, path: Path, key: str):
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if not (node.isInt() or node.isReal()):
        raise InputError(path, key, "expected an integer")
    return int(node.real())


def _fs_names(fs, path: Path) -> list[str]:
    node = fs.getNode("names")
    if node.empty() or node.isNone():
        raise InputError(path, "names", "missing")
    if not node.isSeq():
        raise InputError(path, "names", "expected a sequence of camera names")
    return [node.at(i).string() for i in range(node.size())]


def _fs_write_names(fs, names):
    import cv2

    fs.startWriteStruct("names", cv2.FileNode_SEQ)
    for n in names:
        fs.write("", n)
    fs.endWriteStruct()


def read_easymocap(intri: str | Path, extri: str | Path,
                   size: tuple[int, int] | None = None) -> dict[str, Camera]:
    """Read EasyMocap ``intri.yml`` + ``extri.yml`` -> ``{name: Camera}`` (``model="opencv"``).

    size: (width, height) used when the file has no ``W_<cam>``/``H_<cam>``; if neither gives
    a size, InputError on ``H_<cam>``.
    """
    intri, extri = Path(intri), Path(extri)
    fi, fe = _fs_open(intri, False), _fs_open(extri, False)
    try:
        names = _fs_names(fi, intri)
        names_e = _fs_names(fe, extri)
        out = {}
        for n in names:
            if n not in names_e:
                raise InputError(extri, f"R_{n}", f"camera {n} listed in {intri.name} only")
            K = _array(intri, f"K_{n}", _fs_mat(fi, intri, f"K_{n}"), (3, 3))
            dist = _fs_mat(fi, intri, f"dist_{n}", required=False)
            dist = np.zeros(5) if dist is None else _array(intri, f"dist_{n}", dist, dist.size)
            w, h = _fs_int(fi, intri, f"W_{n}"), _fs_int(fi, intri, f"H_{n}")
            if w is None or h is None:
                if size is None:
                    raise InputError(intri, f"H_{n}", "no image size in the file and none given")
                w, h = size
            rot = _fs_mat(fe, extri, f"Rot_{n}", required=False)
            if rot is not None:
                rot = _array(extri, f"Rot_{n}", rot, (3, 3))
            else:
                rot = _array(extri, f"R_{n}", _fs_mat(fe, extri, f"R_{n}"), 3)
            t = _array(extri, f"T_{n}", _fs_mat(fe, extri, f"T_{n}"), 3)
            try:
                out[n] = from_opencv(n, rot, t, K, dist, w, h)
            except ValueError as e:
                raise InputError(intri, f"K_{n}/dist_{n}", str(e)) from None
        return out
    finally:
        fi.release()
        fe.release()


def _dist5(cam: Camera, who: str) -> np.ndarray:
    """(5,) OpenCV k1 k2 p1 p2 k3 of ``cam``; an h36m lens qualifies only with p = 0."""
    if cam.model == "h36m" and not np.any(cam.p):
        return np.array([cam.k[0], cam.k[1], 0.0, 0.0, cam.k[2]])
    d = opencv_dist(cam)
    if d.size != 5:
        raise ValueError(f"{who}({cam.name}): Human3.6M tangential distortion needs 12 OpenCV "
                         "coefficients; convert_distortion(cam, 'opencv') first")
    return d


def write_easymocap(intri: str | Path, extri: str | Path, cams) -> None:
    """Write cameras (iterable of Camera; OpenCV model, or h36m with ``p = 0``) as EasyMocap
    ``intri.yml`` / ``extri.yml``, including ``W_<cam>``/``H_<cam>``."""
    import cv2

    cams = list(cams)
    dists = [_dist5(c, "write_easymocap") for c in cams]
    intri, extri = Path(intri), Path(extri)
    intri.parent.mkdir(parents=True, exist_ok=True)
    extri.parent.mkdir(parents=True, exist_ok=True)
    fi, fe = _fs_open(intri, True), _fs_open(extri, True)
    try:
        names = [c.name for c in cams]
        _fs_write_names(fi, names)
        _fs_write_names(fe, names)
        for c, d in zip(cams, dists, strict=True):
            fi.write(f"K_{c.name}", c.K)
            fi.write(f"dist_{c.name}", d.reshape(1, 5))
            fi.write(f"H_{c.name}", c.height)
            fi.write(f"W_{c.name}", c.width)
            fe.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
            fe.write(f"Rot_{c.name}", c.R)
            fe.write(f"T_{c.name}", c.t.reshape(3, 1))
    finally:
        fi.release()
        fe.release()


def read_opencv_camera(path: str | Path, name: str | None = None) -> Camera:
    """Read one camera from an OpenCV FileStorage file (see module doc for the keys)."""
    path = Path(path)
    fs = _fs_open(path, False)
    try:
        node = fs.getNode("camera_name")
        cname = name or (node.string() if not node.empty() and node.isString() else path.stem)
        K = _array(path, "camera_matrix", _fs_mat(fs, path, "camera_matrix"), (3, 3))
        dist = _fs_mat(fs, path, "distortion_coefficients", required=False)
        dist = np.zeros(5) if dist is None else _array(path, "distortion_coefficients", dist,
                                                       dist.size)
        w, h = _fs_int(fs, path, "image_width"), _fs_int(fs, path, "image_height")
        if w is None:
            raise InputError(path, "image_width", "missing")
        if h is None:
            raise InputError(path, "image_height", "missing")
        rot = None
        for key in ("rotation_matrix", "R", "rvec"):
            m = _fs_mat(fs, path, key, required=False)
            if m is not None:  # a 3x3 matrix, or a Rodrigues vector (rvec, or R given as 3x1)
                rot = _array(path, key, m, (3, 3) if m.size == 9 else 3)
                break
        if rot is None:
            raise InputError(path, "rotation_matrix", "missing (also looked for R, rvec)")
        t = None
        for key in ("translation_vector", "tvec", "T"):
            m = _fs_mat(fs, path, key, required=False)
            if m is not None:
                t = _array(path, key, m, 3)
                break
        if t is None:
            raise InputError(path, "translation_vector", "missing (also looked for tvec, T)")
        try:
            return from_opencv(cname, rot, t, K, dist, w, h)
        except ValueError as e:
            raise InputError(path, "camera_matrix/distortion_coefficients", str(e)) from None
    finally:
        fs.release()


def write_opencv_camera(path: str | Path, cam: Camera) -> Path:
    """Write ``cam`` to an OpenCV FileStorage file; exact for both models (a Human3.6M lens is
    written as 12 coefficients, see calib.convert)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fs = _fs_open(path, True)
    try:
        fs.write("camera_name", cam.name)
        fs.write("image_width", cam.width)
        fs.write("image_height", cam.height)
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", opencv_dist(cam).reshape(1, -1))
        fs.write("rotation_matrix", cam.R)
        fs.write("translation_vector", cam.t.reshape(3, 1))
    finally:
        fs.release()
    return path


# ------------------------------------------------------------------------------- one entry point
#: Calibration formats :func:`read_camera` reads (the recipe's ``calibration_format``), and
#: other names labs use for them.
CALIBRATION_FORMATS = ("chi3d", "vicon", "qualisys", "pose2sim", "easymocap", "opencv")
FORMAT_ALIASES = {"xcp": "vicon", "qca": "qualisys", "toml": "pose2sim", "anipose": "pose2sim",
                  "caliscope": "pose2sim"}


def calibration_format(path: str | Path, fmt: str | None = None) -> str:
    """The format of a calibration file: ``fmt`` (a name of ``CALIBRATION_FORMATS`` or an
    alias), else from the suffix: ``.json`` chi3d, ``.xcp`` vicon, ``.qca.txt`` qualisys,
    ``.toml`` pose2sim, ``.yml``/``.yaml``/``.xml`` easymocap when the file lists ``names``
    (an EasyMocap ``intri.yml``/``extri.yml``), else opencv (one camera per file)."""
    path = Path(path)
    if fmt is not None:
        f = FORMAT_ALIASES.get(fmt.lower(), fmt.lower())
        if f not in CALIBRATION_FORMATS:
            raise InputError(path, "calibration_format", f"{fmt!r}: expected one of "
                             f"{list(CALIBRATION_FORMATS)} (or {sorted(FORMAT_ALIASES)})")
        return f
    name = path.name.lower()
    if name.endswith(".qca.txt") or name.endswith(".qca"):
        return "qualisys"
    by_suffix = {".json": "chi3d", ".xcp": "vicon", ".toml": "pose2sim"}
    if path.suffix.lower() in by_suffix:
        return by_suffix[path.suffix.lower()]
    if path.suffix.lower() in (".yml", ".yaml", ".xml"):
        fs = _fs_open(path, False)
        try:
            node = fs.getNode("names")
            return "opencv" if node.empty() or node.isNone() else "easymocap"
        finally:
            fs.release()
    raise InputError(path, "calibration_format", f"unknown suffix {path.suffix!r}: name the "
                     f"format, one of {list(CALIBRATION_FORMATS)}")


def easymocap_pair(path: str | Path) -> tuple[Path, Path]:
    """``(intri.yml, extri.yml)`` from either file of an EasyMocap pair: the other is the
    sibling whose name has ``extri`` for ``intri`` (or the reverse)."""
    path = Path(path)
    n = path.name
    if "intri" in n:
        return path, path.with_name(n.replace("intri", "extri"))
    if "extri" in n:
        return path.with_name(n.replace("extri", "intri")), path
    raise InputError(path, "<file>", "an EasyMocap calibration is named intri.yml / extri.yml "
                     "(the pair is found by the name)")


def read_camera(path: str | Path, name: str | None = None, fmt: str | None = None) -> Camera:
    """One camera from any calibration file the project reads, as a :class:`Camera` named
    ``name`` (the recipe's camera id).

    fmt: the recipe's ``calibration_format`` (:func:`calibration_format`; None: from the
    suffix). Files of one camera: CHI3D JSON (h36m lens, 900 x 900; ``name`` defaults to the
    folder), OpenCV FileStorage. Files of several cameras (the recipe may give the same file
    for every camera): the camera whose id is ``name`` (Vicon: DEVICEID, USERID or NAME;
    Qualisys: ``serial``; TOML: ``name`` or the table name; EasyMocap: an entry of ``names``),
    else the id without case; a 1-camera file needs no name. InputError naming the file and
    the field otherwise."""
    from calib import lab_formats

    path = Path(path)
    f = calibration_format(path, fmt)
    if f == "chi3d":
        if path.suffix.lower() == ".xcp":
            raise InputError(path, "calibration_format", "chi3d given for a Vicon .xcp")
        return read_chi3d_camera(path, name)
    if f == "vicon":
        from calib.xcp import xcp_camera

        return xcp_camera(path, name)
    if f == "qualisys":
        return lab_formats.qualisys_camera(path, name)
    if f == "pose2sim":
        return lab_formats.toml_camera(path, name)
    if f == "opencv":
        return read_opencv_camera(path, name)
    intri, extri = easymocap_pair(path)
    return lab_formats.pick_camera(intri, read_easymocap(intri, extri), name, "names")
