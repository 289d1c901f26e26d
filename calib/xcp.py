"""Vicon ``.xcp`` camera calibrations (Nexus / Shogun / Tracker / CaraLive) as project cameras.

The .xcp is XML: a ``<Cameras>`` root with one ``<Camera>`` per device::

    <Camera DEVICEID="2107" USERID="1" NAME="Vue #2107" SENSOR="..." SENSOR_SIZE="1920 1080"
            PIXEL_ASPECT_RATIO="1" SKEW="0" DISPLAY_TYPE="Vue" ...>
      <KeyFrames>
        <KeyFrame FRAME="0" FOCAL_LENGTH="1650.2" PRINCIPAL_POINT="958.1 541.7"
                  ORIENTATION="qx qy qz qw" POSITION="x y z"
                  VICON_RADIAL2="Vicon3Parameter cx cy k1 k2 k3" WORLD_ERROR="..." .../>
      </KeyFrames>
    </Camera>

Conventions (Vicon's CaraPost reference, "About calibration data (XCP) files", and Vicon's
own open-source GRIP ``IO.loadXCP``, which builds ``RT = [R(q) | -R(q) POSITION]``):

- ``ORIENTATION``: unit quaternion ``qx qy qz qw`` (the real part last) of the rotation
  cam_from_world: ``X_cam = R(q) (X_world - POSITION)``; camera axes x right, y down,
  z forward (OpenCV's), so ``R(q)`` is this project's ``Camera.R`` directly.
- ``POSITION``: camera centre, world, millimetres (``Camera.T`` = POSITION / 1000).
- ``FOCAL_LENGTH``: pixels, horizontal; ``fy = FOCAL_LENGTH / PIXEL_ASPECT_RATIO``.
  ``PRINCIPAL_POINT``: pixels. ``SENSOR_SIZE``: width height, pixels. ``SKEW`` must be 0.
- Lens: Vicon's radial model maps an observed (distorted) pixel ``p_d`` to the ideal pinhole
  pixel ``p_u`` (the inverse direction of this project's and OpenCV's models)::

      d = (p_d.x - cx, a (p_d.y - cy)),   r2 = |d|^2   (pixels^2, a = PIXEL_ASPECT_RATIO)
      p_u = (cx, cy) + (1 + k1 r2 + k2 r2^2 + k3 r2^3) (d.x, d.y / a)

  ``VICON_RADIAL2="<model> cx cy k1 k2 k3"`` gives the distortion centre and 3 coefficients;
  the older ``VICON_RADIAL="k1 k2"`` uses the principal point as centre (GRIP: "k1 =
  VICON_RADIAL[0] * hsx^2"; its ``solve_camera_distortion_from_3d`` fits exactly this map).

The project model (``calib.camera``) maps undistorted normalized coordinates to distorted
ones, so no closed form converts one into the other. :func:`read_xcp` fits the project's
``k1 k2 k3 p1 p2`` (``model="opencv"``; the tangential terms absorb a distortion centre away
from the principal point) by linear least squares over a grid of pixels covering the sensor,
exactly as :func:`calib.convert.convert_distortion` does between the project's own models, and
raises InputError when the fit is worse than ``XCP_FIT_MAX_PX`` anywhere on the sensor.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calib import constants
from calib.camera import Camera, distort
from formats.errors import InputError

#: Default largest pixel distance, anywhere on the sensor, between Vicon's lens model and the
#: fitted project model. Half a pixel: below the noise of the 2D keypoints the fits use. A
#: centred lens with |k1| r^2 up to 0.2 at the corners fits to ~0.04 px; a distortion centre
#: 18 px from the principal point with |k1| r^2 = 0.1 to ~0.1 px (tangential terms absorb it).
XCP_FIT_MAX_PX = 0.5

_KEYFRAME_REQUIRED = ("FOCAL_LENGTH", "PRINCIPAL_POINT", "ORIENTATION", "POSITION")


def vicon_undistort_pixels(uv_d: np.ndarray, centre, k, aspect: float = 1.0) -> np.ndarray:
    """Vicon's radial model: observed pixels ``uv_d`` (..., 2) -> ideal pinhole pixels.

    centre: (2,) distortion centre, pixels; k: (k1, k2[, k3]) in pixels^-2, ^-4, ^-6;
    aspect: PIXEL_ASPECT_RATIO (the y offset is scaled by it before the radius is taken)."""
    uv_d = np.asarray(uv_d, dtype=np.float64)
    k = np.concatenate([np.asarray(k, dtype=np.float64).reshape(-1), np.zeros(3)])[:3]
    dx = uv_d[..., 0] - centre[0]
    dy = aspect * (uv_d[..., 1] - centre[1])
    r2 = dx * dx + dy * dy
    s = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    return np.stack([centre[0] + s * dx, centre[1] + s * dy / aspect], axis=-1)


def _floats(path, where: str, attr: str, text: str | None, n: int) -> np.ndarray:
    if text is None:
        raise InputError(path, f"{where}.{attr}", "missing")
    try:
        a = np.array([float(t) for t in text.split()], dtype=np.float64)
    except ValueError:
        raise InputError(path, f"{where}.{attr}", f"not numbers: {text!r}") from None
    if a.size != n:
        raise InputError(path, f"{where}.{attr}", f"expected {n} values, got {a.size}: {text!r}")
    if not np.all(np.isfinite(a)):
        raise InputError(path, f"{where}.{attr}", f"not finite: {text!r}")
    return a


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of the unit quaternion ``q = (qx, qy, qz, qw)``."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _fit_lens(path, where: str, f: np.ndarray, c: np.ndarray, centre: np.ndarray, kv: np.ndarray,
              aspect: float, width: int, height: int,
              max_px: float = XCP_FIT_MAX_PX) -> tuple[np.ndarray, np.ndarray, float]:
    """Fit the project's opencv-model ``k (3,), p (2,)`` to Vicon's lens over the sensor;
    returns them and the largest pixel error of the fit."""
    g = constants.CONVERSION_GRID
    u, v = np.meshgrid(np.linspace(0, width - 1, g), np.linspace(0, height - 1, g))
    uv_d = np.stack([u.ravel(), v.ravel()], axis=-1)
    # Vicon's map must be monotonic in the radius over the sensor (d r_u / d r_d > 0).
    r2 = ((uv_d[:, 0] - centre[0]) ** 2 + (aspect * (uv_d[:, 1] - centre[1])) ** 2)
    if np.any(1 + r2 * (3 * kv[0] + r2 * (5 * kv[1] + 7 * r2 * kv[2])) <= 0):
        raise InputError(path, f"{where}.VICON_RADIAL2", f"lens model {kv.tolist()} folds over "
                         "inside the sensor (not a valid calibration)")
    xy_u = (vicon_undistort_pixels(uv_d, centre, kv, aspect) - c) / f
    xy_d = (uv_d - c) / f
    cols = []
    for i in range(5):
        e = np.zeros(5)
        e[i] = 1.0
        cols.append(distort(xy_u, e[:3], e[3:], "opencv") - xy_u)
    A = (np.stack(cols, axis=-1) * f[None, :, None]).reshape(-1, 5)
    b = ((xy_d - xy_u) * f).reshape(-1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    err = np.linalg.norm((distort(xy_u, sol[:3], sol[3:], "opencv") - xy_d) * f, axis=-1)
    if err.max() > max_px:
        raise InputError(path, f"{where}.VICON_RADIAL2", f"lens model {kv.tolist()} has no "
                         f"equivalent in the k1 k2 k3 p1 p2 model: fit off by up to "
                         f"{err.max():.3g} px (> {max_px} px)")
    return sol[:3], sol[3:], float(err.max())


def _camera(path: Path, el, max_fit_px: float = XCP_FIT_MAX_PX) -> Camera | None:
    ids = {a: el.get(a) for a in ("DEVICEID", "USERID", "NAME")}
    if ids["DEVICEID"] is None:
        raise InputError(path, "Camera.DEVICEID", f"missing (camera USERID={ids['USERID']!r}, "
                         f"NAME={ids['NAME']!r})")
    dev = ids["DEVICEID"].strip()
    where = f"Camera[{dev}]"
    kfs = el.findall("KeyFrames/KeyFrame")
    if not kfs:
        return None  # present in the system but not calibrated (e.g. a Vue off during the wand)
    kf = kfs[0]  # moving cameras have several; static ones one (the first holds from FRAME 0)
    kw = f"{where}.KeyFrame"
    for attr in _KEYFRAME_REQUIRED:
        if kf.get(attr) is None:
            raise InputError(path, f"{kw}.{attr}", f"missing (camera {dev})")
    w, h = _floats(path, where, "SENSOR_SIZE", el.get("SENSOR_SIZE"), 2)
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise InputError(path, f"{where}.SENSOR_SIZE", f"expected two positive integers, got {w} {h}")
    aspect = float(_floats(path, where, "PIXEL_ASPECT_RATIO", el.get("PIXEL_ASPECT_RATIO", "1"), 1)[0])
    if aspect <= 0:
        raise InputError(path, f"{where}.PIXEL_ASPECT_RATIO", f"must be positive, got {aspect}")
    skew = float(_floats(path, where, "SKEW", el.get("SKEW", "0"), 1)[0])
    if abs(skew) > 1e-9:
        raise InputError(path, f"{where}.SKEW", f"{skew}: skewed pixels are not supported")
    fl = float(_floats(path, kw, "FOCAL_LENGTH", kf.get("FOCAL_LENGTH"), 1)[0])
    if fl <= 0:
        raise InputError(path, f"{kw}.FOCAL_LENGTH", f"must be positive, got {fl}")
    f = np.array([fl, fl / aspect])
    c = _floats(path, kw, "PRINCIPAL_POINT", kf.get("PRINCIPAL_POINT"), 2)
    q = _floats(path, kw, "ORIENTATION", kf.get("ORIENTATION"), 4)
    if abs(np.linalg.norm(q) - 1) > 1e-3:
        raise InputError(path, f"{kw}.ORIENTATION", f"not a unit quaternion (norm {np.linalg.norm(q):.6g})")
    R = _quat_to_R(q / np.linalg.norm(q))
    T = _floats(path, kw, "POSITION", kf.get("POSITION"), 3) / 1000.0
    if kf.get("VICON_RADIAL2") is not None:
        parts = kf.get("VICON_RADIAL2").split()
        try:
            nums = [float(t) for t in parts[1:]] if parts else []
        except ValueError:
            nums = []
        if len(parts) != 6 or len(nums) != 5 or not np.all(np.isfinite(nums)):
            raise InputError(path, f"{kw}.VICON_RADIAL2", "expected '<model> cx cy k1 k2 k3', got "
                             f"{kf.get('VICON_RADIAL2')!r}")
        centre, kv = np.array(nums[:2]), np.array(nums[2:])
    elif kf.get("VICON_RADIAL") is not None:
        kv = np.concatenate([_floats(path, kw, "VICON_RADIAL", kf.get("VICON_RADIAL"), 2), [0.0]])
        centre = c
    else:
        raise InputError(path, f"{kw}.VICON_RADIAL2", f"missing (nor VICON_RADIAL) (camera {dev})")
    k, p, _ = _fit_lens(path, kw, f, c, centre, kv, aspect, int(w), int(h), max_fit_px)
    try:
        return Camera(dev, f, c, k, p, R, T, int(w), int(h), model="opencv")
    except ValueError as e:
        raise InputError(path, where, str(e)) from None


def _parse(path: str | Path):
    import xml.etree.ElementTree as ET

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "missing")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(path, "<xml>", f"not an .xcp (XML) file: {e}") from None
    cams = root.findall("Camera") if root.tag != "Camera" else [root]
    if not cams:
        raise InputError(path, "Cameras", "no <Camera> element")
    return path, cams


def read_xcp(path: str | Path, max_fit_px: float = XCP_FIT_MAX_PX) -> dict[str, Camera]:
    """All calibrated cameras of a Vicon .xcp, ``{DEVICEID: Camera}`` (``model="opencv"``,
    metres; the camera's name is its DEVICEID). Cameras without a KeyFrame (not calibrated)
    are left out. max_fit_px: the largest accepted error of the lens conversion, pixels.
    Raises InputError naming the file, the camera and the attribute."""
    path, els = _parse(path)
    out: dict[str, Camera] = {}
    for el in els:
        cam = _camera(path, el, max_fit_px)
        if cam is None:
            continue
        if cam.name in out:
            raise InputError(path, "Camera.DEVICEID", f"{cam.name!r} appears twice")
        out[cam.name] = cam
    if not out:
        raise InputError(path, "Camera.KeyFrames", "no calibrated camera (no KeyFrame)")
    return out


def xcp_camera(path: str | Path, camera_id: str | int | None = None,
               max_fit_px: float = XCP_FIT_MAX_PX) -> Camera:
    """One camera of a Vicon .xcp, found by its DEVICEID, else USERID, else NAME (a file with
    a single camera needs no id). The Camera is named ``camera_id`` as given (so a recipe's
    camera name survives), or the DEVICEID."""
    path, els = _parse(path)
    if camera_id is None:
        if len(els) != 1:
            raise InputError(path, "Camera", f"{len(els)} cameras: name one (DEVICEID, USERID or NAME)")
        el = els[0]
    else:
        want = str(camera_id).strip()
        el = None
        for attr in ("DEVICEID", "USERID", "NAME"):
            hits = [e for e in els if (e.get(attr) or "").strip() == want]
            if len(hits) > 1:
                raise InputError(path, f"Camera.{attr}", f"{want!r} names {len(hits)} cameras")
            if hits:
                el = hits[0]
                break
        if el is None:
            have = [e.get("DEVICEID") for e in els]
            raise InputError(path, "Camera", f"no camera with DEVICEID, USERID or NAME {want!r} "
                             f"(DEVICEIDs: {have})")
    cam = _camera(path, el, max_fit_px)
    if cam is None:
        raise InputError(path, f"Camera[{el.get('DEVICEID')}].KeyFrames", "no KeyFrame: the camera "
                         "was not calibrated")
    if camera_id is not None and str(camera_id).strip() != cam.name:
        from dataclasses import replace

        cam = replace(cam, name=str(camera_id).strip())
    return cam
