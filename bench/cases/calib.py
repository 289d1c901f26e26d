"""Cameras and formats: accuracy and speed on a synthetic CHI3D-like 4-camera rig.

- ``calib.h36m_as_opencv5_rms_px`` / ``_max_px``: fitting a Human3.6M lens (|p| <= 3e-3, the
  CHI3D kind) with OpenCV's 5 coefficients (``convert_distortion``), worst of 20 cameras; the
  12-coefficient OpenCV form is exact and not measured here (tests check it to 1e-6 px).
- ``calib.project_ns_per_point``: numpy ``project`` on 100k points.
- ``calib.triangulate_median_mm`` / ``_ms_per_point``: pycolmap RANSAC triangulation of 500
  points seen by 4 cameras with 1 px Gaussian noise per axis.
- ``calib.refine_centre_mm`` / ``_rotation_deg`` / ``_rms_after_px`` / ``_ms``: one camera
  bumped by 3 cm and 1 degree, recovered by ``refine_rig`` from 39 markers x 100 frames at
  1 px noise with 20 % occlusion (worst camera).
- ``formats.c3d_read_ms``: reading a 39-marker, 24,000-frame (100 s at 240 Hz) C3D (almost
  all of it inside ezc3d's own reader).
- ``formats.video_random_read_ms``: random-access frame reads of a 900x900 mp4v video.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

GOALS = {
    "calib.h36m_as_opencv5_max_px": ("<=", 1.0),
    "calib.triangulate_median_mm": ("<=", 5.0),
    "calib.refine_centre_mm": ("<=", 3.0),
    "calib.refine_rotation_deg": ("<=", 0.05),
    "calib.triangulate_ms_per_point": ("<=", 1.0),
}


def _camera(rng, name, model="h36m"):
    from calib import look_at

    a = rng.uniform(0, 2 * np.pi)
    return look_at(name, [4 * np.cos(a), 4 * np.sin(a), rng.uniform(1.0, 2.5)],
                   rng.normal([0, 0, 1.0], 0.2), f=rng.uniform(900, 1200, 2),
                   c=rng.uniform(400, 500, 2), width=900, height=900,
                   k=[rng.uniform(-0.3, 0.1), rng.uniform(-0.1, 0.3), rng.uniform(-0.05, 0.05)],
                   p=rng.uniform(-3e-3, 3e-3, 2), model=model)


def run(work: Path) -> dict[str, float]:
    from scipy.spatial.transform import Rotation

    from calib import project
    from calib.convert import convert_distortion
    from calib.geometry import TriangulateOptions, refine_rig, triangulate
    from formats.c3d import Markers, read_c3d, write_c3d
    from formats.video import VideoReader, write_mp4

    rng = np.random.default_rng(0)
    out: dict[str, float] = {}
    conv = [convert_distortion(_camera(rng, "c"), "opencv") for _ in range(20)]
    out["calib.h36m_as_opencv5_rms_px"] = max(c.rms_px for c in conv)
    out["calib.h36m_as_opencv5_max_px"] = max(c.max_px for c in conv)

    cams = [_camera(rng, f"c{i}") for i in range(4)]
    X = rng.uniform([-0.6, -0.6, 0.1], [0.6, 0.6, 1.9], (100_000, 3))
    t0 = time.perf_counter()
    project(cams[0], X)
    out["calib.project_ns_per_point"] = (time.perf_counter() - t0) / len(X) * 1e9

    Xt = X[:500]
    uv = np.stack([project(c, Xt) for c in cams]) + rng.normal(0, 1.0, (4, 500, 2))
    kp = np.concatenate([uv, np.ones((4, 500, 1))], axis=-1)
    t0 = time.perf_counter()
    tri = triangulate(cams, kp, TriangulateOptions())
    out["calib.triangulate_ms_per_point"] = (time.perf_counter() - t0) / 500 * 1e3
    out["calib.triangulate_median_mm"] = float(np.nanmedian(np.linalg.norm(tri.xyz - Xt, axis=1)) * 1e3)

    Xm = X[: 39 * 100]
    uvm = np.stack([project(c, Xm) for c in cams]) + rng.normal(0, 1.0, (4, len(Xm), 2))
    uvm[:, rng.random(len(Xm)) < 0.2] = np.nan
    dR = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(1.0)).as_matrix()
    start = list(cams)
    start[1] = replace(cams[1], R=dR @ cams[1].R, T=cams[1].T + rng.normal(size=3) / np.sqrt(3) * 0.03)
    t0 = time.perf_counter()
    r = refine_rig(start, Xm, uvm)
    out["calib.refine_ms"] = (time.perf_counter() - t0) * 1e3
    out["calib.refine_centre_mm"] = max(np.linalg.norm(a.T - b.T) for a, b in zip(r.cameras, cams, strict=True)) * 1e3
    out["calib.refine_rotation_deg"] = max(
        np.rad2deg(np.linalg.norm(Rotation.from_matrix(a.R @ b.R.T).as_rotvec()))
        for a, b in zip(r.cameras, cams, strict=True))
    out["calib.refine_rms_before_px"] = float(np.max(r.rms_before_px))
    out["calib.refine_rms_after_px"] = float(np.max(r.rms_after_px))

    work.mkdir(parents=True, exist_ok=True)
    xyz = rng.normal(0, 0.5, (24_000, 39, 3))
    path = write_c3d(work / "bench.c3d", Markers([f"M{i}" for i in range(39)], xyz, 240.0, 0, "S"))
    t0 = time.perf_counter()
    read_c3d(path)
    out["formats.c3d_read_ms"] = (time.perf_counter() - t0) * 1e3

    frames = (np.full((900, 900, 3), j % 256, np.uint8) for j in range(100))
    vpath = write_mp4(work / "bench.mp4", frames, 50)
    idx = rng.integers(0, 100, 30)
    with VideoReader(vpath) as v:
        t0 = time.perf_counter()
        for i in idx:
            v[int(i)]
        out["formats.video_random_read_ms"] = (time.perf_counter() - t0) / len(idx) * 1e3
    return out
