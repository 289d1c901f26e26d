"""The camera rig of the studio: four calibrated 900x900 cameras around the capture volume.

Like CHI3D's: one camera near each corner of the room, a few metres from the centre, a little
above head height, all looking at the middle of the volume, with mild Human3.6M-model lens
distortion. Cameras are ``calib.Camera`` (CHI3D convention ``X_cam = (X_world - T) @ R.T``,
OpenCV axes: x right, y down, z forward).
"""
from __future__ import annotations

import numpy as np

from calib import Camera, look_at
from studio import constants as C


def make_rig(rng: np.random.Generator) -> list[Camera]:
    """Four cameras (names ``constants.CAMERA_NAMES``) with jittered placement and intrinsics."""
    cams = []
    w, h = C.IMAGE_SIZE
    for name, az in zip(C.CAMERA_NAMES, C.CAMERA_AZIMUTHS_DEG, strict=True):
        a = np.deg2rad(az + rng.uniform(-1, 1) * C.CAMERA_AZIMUTH_JITTER_DEG)
        d = rng.uniform(*C.CAMERA_DISTANCE_M)
        centre = np.array([d * np.cos(a), d * np.sin(a), rng.uniform(*C.CAMERA_HEIGHT_M)])
        target = np.asarray(C.CAMERA_LOOKAT_M) + rng.uniform(-1, 1, 3) * C.CAMERA_LOOKAT_JITTER_M
        f0 = rng.uniform(*C.CAMERA_FOCAL_PX)
        f = (f0 * (1 + rng.uniform(-0.003, 0.003)), f0 * (1 + rng.uniform(-0.003, 0.003)))
        c = (w / 2 + rng.uniform(-1, 1) * C.CAMERA_PRINCIPAL_JITTER_PX,
             h / 2 + rng.uniform(-1, 1) * C.CAMERA_PRINCIPAL_JITTER_PX)
        k = tuple(rng.uniform(lo, hi) for lo, hi in C.CAMERA_K_RANGE)
        p = tuple(rng.uniform(-1, 1, 2) * C.CAMERA_P_ABS)
        cams.append(look_at(name, centre, target, f, c, w, h, k=k, p=p, model="h36m"))
    return cams
