"""Marker trajectories to fitting observations: resample the mocap clock onto video frames.

A Vicon capture runs at 100-240 Hz on its own clock; the fit is per video frame. A video frame
``f`` is at ``f / fps`` seconds of video time, which is ``f / fps - sync_offset_s`` on the
mocap clock (the C3D's first sample is at ``sync_offset_s`` of video time). Markers are
interpolated linearly between the two bracketing samples when both are observed; a marker
whose bracketing samples include a gap is *missing* in that frame (never bridged: a gap
filled by a guess would be fitted as if it were data).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def frame_times(n_frames: int, fps: float, sync_offset_s: float = 0.0) -> np.ndarray:
    """(F,) mocap-clock seconds of video frames ``0..n_frames-1``."""
    return np.arange(n_frames) / float(fps) - float(sync_offset_s)


def resample(times_src: np.ndarray, xyz: np.ndarray, times_dst: np.ndarray,
             tol_s: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of marker trajectories at new times.

    times_src : (Fs,) increasing sample times, seconds. xyz : (Fs, M, 3) metres, NaN = gap.
    times_dst : (F,) query times, seconds.
    Returns ``(obs (F, M, 3), visible (F, M) bool)``; ``obs`` is 0 where not visible. A query
    outside ``[times_src[0], times_src[-1]]`` (beyond ``tol_s``) is not visible.
    """
    ts = np.asarray(times_src, dtype=float)
    xyz = np.asarray(xyz, dtype=float)
    td = np.asarray(times_dst, dtype=float)
    if xyz.ndim != 3 or xyz.shape[0] != len(ts) or xyz.shape[2] != 3:
        raise ValueError(f"resample: xyz {xyz.shape} does not match {len(ts)} times")
    F, M = len(td), xyz.shape[1]
    obs = np.zeros((F, M, 3))
    vis = np.zeros((F, M), dtype=bool)
    if len(ts) == 0:
        return obs, vis
    inside = (td >= ts[0] - tol_s) & (td <= ts[-1] + tol_s)
    tq = np.clip(td, ts[0], ts[-1])
    i1 = np.clip(np.searchsorted(ts, tq, side="left"), 0, len(ts) - 1)
    i0 = np.clip(i1 - 1, 0, len(ts) - 1)
    exact = np.abs(ts[i1] - tq) <= tol_s
    i0 = np.where(exact, i1, i0)
    span = ts[i1] - ts[i0]
    a = np.where(span > 0, (tq - ts[i0]) / np.where(span > 0, span, 1.0), 0.0)
    x0, x1 = xyz[i0], xyz[i1]  # (F, M, 3)
    ok0 = np.all(np.isfinite(x0), axis=2)
    ok1 = np.all(np.isfinite(x1), axis=2)
    vis = inside[:, None] & ok0 & ok1
    interp = (1.0 - a)[:, None, None] * np.nan_to_num(x0) + a[:, None, None] * np.nan_to_num(x1)
    obs = np.where(vis[..., None], interp, 0.0)
    return obs, vis


@dataclass(frozen=True)
class VideoClock:
    """How a capture's samples map onto video frames: video frame ``f`` is at mocap time
    ``f / fps - sync_offset_s``. rate_hz : the capture's sampling rate when it overrides the
    C3D's own (recipe ``sequence.mocap.rate_hz``), else None."""

    fps: float
    sync_offset_s: float = 0.0
    rate_hz: float | None = None

    def __post_init__(self):
        if not self.fps > 0:
            raise ValueError(f"fps: must be > 0, got {self.fps}")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError(f"rate_hz: must be > 0, got {self.rate_hz}")


def video_observations(markers, frames: np.ndarray, clock: VideoClock
                       ) -> tuple[np.ndarray, np.ndarray]:
    """A capture's markers at video frames.

    markers : ``formats.c3d.Markers`` (``xyz (Fs, M, 3)`` metres, NaN gaps, ``rate_hz``,
    ``first_frame``); frames : (F,) video frame indices. Returns ``(obs (F, M, 3), visible
    (F, M) bool)`` (:func:`resample`; obs 0 where not visible)."""
    frames = np.asarray(frames, dtype=int)
    rate = clock.rate_hz or markers.rate_hz
    times_src = (markers.first_frame + np.arange(len(markers.xyz))) / rate
    times = frame_times(int(frames.max()) + 1 if len(frames) else 0, clock.fps,
                        clock.sync_offset_s)[frames]
    return resample(times_src, markers.xyz, times)
