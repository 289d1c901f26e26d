"""Videos (OpenCV) and mocap-to-video time alignment.

- :class:`VideoReader`: frame-accurate reading by index; frames are ``(H, W, 3) uint8 RGB``.
  Forward reads decode sequentially; a backward or far jump seeks, then the reader checks the
  decoder's reported position and falls back to decoding from the start if the seek was not
  exact.
- :func:`write_mp4`: MP4 (``mp4v``) from RGB frames.
- :func:`resample_to_video`: markers sampled at the mocap rate (Vicon 100/200/240 Hz) to the
  video frames (e.g. 50 fps) by time. Convention: video frame ``j`` is at video time
  ``j / fps``; the recipe's sync offset is the video time of mocap time 0, so frame ``j``
  maps to mocap time ``j / fps - offset_s``, and mocap sample ``i`` is at
  ``(first_frame + i) / rate_hz`` (see :class:`formats.c3d.Markers`).
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formats.c3d import Markers
from formats.errors import InputError

#: A forward jump of at most this many frames is decoded instead of seeking.
MAX_FORWARD_DECODE = 64
#: Sample-index tolerance under which a video time counts as hitting a mocap sample exactly.
SAMPLE_HIT_TOL = 1e-6


@dataclass(frozen=True)
class VideoInfo:
    """n_frames: frames the container reports; fps: frames per second; width, height: pixels."""

    n_frames: int
    fps: float
    width: int
    height: int


class VideoReader:
    """Random access to the frames of one video file by index.

    ``with VideoReader(path) as v: img = v[17]`` -> (H, W, 3) uint8 RGB. Reading past the
    end raises InputError naming the file and the frame.
    """

    def __init__(self, path: str | Path):
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "<file>", "missing")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise InputError(self.path, "<video>", "cannot open (corrupt or unsupported codec)")
        n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(self._cap.get(cv2.CAP_PROP_FPS))
        w = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if n <= 0 or w <= 0 or h <= 0 or not fps > 0:
            self._cap.release()
            raise InputError(self.path, "<video>", f"no frames or bad header ({n} frames, "
                             f"{w}x{h}, {fps} fps)")
        self.info = VideoInfo(n, fps, w, h)
        self._pos = 0  # index of the frame the next read() returns

    def __len__(self) -> int:
        return self.info.n_frames

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        self._cap.release()

    def _read_next(self, index: int) -> np.ndarray:
        import cv2

        ok, img = self._cap.read()
        if not ok:
            raise InputError(self.path, "<video>", f"cannot decode frame (the file reports "
                             f"{self.info.n_frames} frames)", frame=index)
        self._pos += 1
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def _seek(self, index: int) -> None:
        import cv2

        if index > 0 and self._cap.set(cv2.CAP_PROP_POS_FRAMES, index) and \
                int(round(self._cap.get(cv2.CAP_PROP_POS_FRAMES))) == index:
            self._pos = index
            return
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._pos = 0
        while self._pos < index:
            if not self._cap.grab():
                raise InputError(self.path, "<video>", "cannot decode frame", frame=self._pos)
            self._pos += 1

    def __getitem__(self, index: int) -> np.ndarray:
        """Frame ``index`` (0-based) as (H, W, 3) uint8 RGB."""
        index = int(index)
        if not 0 <= index < self.info.n_frames:
            raise InputError(self.path, "frame", f"index out of range 0..{self.info.n_frames - 1}",
                             frame=index)
        if not self._pos <= index <= self._pos + MAX_FORWARD_DECODE:
            self._seek(index)
        while self._pos < index:
            if not self._cap.grab():
                raise InputError(self.path, "<video>", "cannot decode frame", frame=self._pos)
            self._pos += 1
        return self._read_next(index)

    def frames(self, indices: Iterable[int] | None = None):
        """Yield frames (all, or ``indices`` in the given order)."""
        for i in range(len(self)) if indices is None else indices:
            yield self[i]


def video_info(path: str | Path) -> VideoInfo:
    """Frame count, fps and size of a video file."""
    with VideoReader(path) as v:
        return v.info


def write_mp4(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Write RGB frames ``(H, W, 3) uint8`` (all the same size) to an MP4 (``mp4v``) at ``fps``."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    try:
        for j, img in enumerate(frames):
            img = np.asarray(img)
            if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                raise InputError(path, "frames", f"expected (H, W, 3) uint8, got {img.shape} "
                                 f"{img.dtype}", frame=j)
            if writer is None:
                size = (img.shape[1], img.shape[0])
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size)
                if not writer.isOpened():
                    raise InputError(path, "<video>", "cannot open an mp4v writer")
            elif (img.shape[1], img.shape[0]) != size:
                raise InputError(path, "frames", f"size {img.shape[1]}x{img.shape[0]} != first "
                                 f"frame's {size[0]}x{size[1]}", frame=j)
            writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    finally:
        if writer is not None:
            writer.release()
    if writer is None:
        raise InputError(path, "frames", "no frames to write")
    return path


def resample_to_video(markers: Markers, n_frames: int, fps: float, offset_s: float = 0.0,
                      source: str | Path = "<markers>") -> np.ndarray:
    """Marker positions at the times of video frames ``0..n_frames-1``.

    markers: sampled at ``markers.rate_hz``; n_frames, fps: the video; offset_s: the recipe's
    ``mocap.sync_offset_s``, the video time of mocap time 0, so video frame ``f`` is at mocap
    time ``f / fps - offset_s`` (the convention of ``recipes.schema.MocapSpec`` and
    ``fitting.mocap.frame_times``); source: the C3D path, for error messages.
    Returns (n_frames, M, 3) float64 metres: linear interpolation between the two neighbouring
    samples, the sample itself when a frame time hits one, NaN when either neighbour is a gap.
    Raises InputError naming ``source`` and the first video frame the capture does not cover.
    """
    if not fps > 0:
        raise InputError(source, "fps", f"must be positive, got {fps}")
    xyz = markers.xyz
    F = len(xyz)
    # Fractional sample index of each video frame.
    s = (np.arange(n_frames) / fps - offset_s) * markers.rate_hz - markers.first_frame
    outside = (s < -SAMPLE_HIT_TOL) | (s > F - 1 + SAMPLE_HIT_TOL)
    if outside.any():
        j = int(np.flatnonzero(outside)[0])
        t0, t1 = (markers.times_s[0], markers.times_s[-1]) if F else (np.nan, np.nan)
        raise InputError(source, "markers", f"the capture covers {t0:.4f}..{t1:.4f} s but video "
                         f"frame {j} is at mocap time {j / fps - offset_s:.4f} s (offset "
                         f"{offset_s} s, {fps} fps, {markers.rate_hz} Hz)", frame=j)
    near = np.rint(s)
    hit = np.abs(s - near) < SAMPLE_HIT_TOL
    i0 = np.clip(np.floor(s).astype(int), 0, max(F - 2, 0))
    w = np.clip(s - i0, 0.0, 1.0)[:, None, None]
    i1 = np.minimum(i0 + 1, F - 1)
    out = (1.0 - w) * xyz[i0] + w * xyz[i1]  # NaN if either neighbour is NaN
    out[hit] = xyz[near[hit].astype(int)]
    return out
