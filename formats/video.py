"""Videos (OpenCV) and mocap-to-video time alignment.

- :class:`VideoReader`: frame-accurate reading by index; frames are ``(H, W, 3) uint8 RGB``.
  Forward reads decode sequentially; a backward or far jump seeks, then the reader checks the
  decoder's reported position and falls back to decoding from the start if the seek was not
  exact.
- :func:`write_mp4`: MP4 (``mp4v``, or the first available of the fourccs asked for, e.g.
  H.264 ``avc1``) from RGB frames.
- Real files (:func:`video_info` reads the MP4/MOV container itself, no decoding): the
  rotation metadata (``VideoInfo.rotation``: degrees the display matrix turns the coded frames;
  the reader applies it on decode (``CAP_PROP_ORIENTATION_AUTO``), so ``width``/``height`` are
  the decoded, upright size: taken from the first frame), the frame durations (``fps_min``/``fps_max``, a variable frame rate is
  flagged by :func:`video_warnings`), :func:`common_length` (cameras of different lengths: the
  shortest wins, with a warning naming each video) and :func:`size_fit` (a decoded size against
  the calibration's: equal, or a few pixels smaller (``SIZE_TOL_PX``), padded at the right /
  bottom so pixel coordinates are unchanged; else an InputError saying both sizes and the
  rotation). ``VideoReader(path, size=(w, h))`` returns frames padded/cropped that way.
- :func:`resample_to_video`: markers sampled at the mocap rate (Vicon 100/200/240 Hz) to the
  video frames (e.g. 50 fps) by time. Convention: video frame ``j`` is at video time
  ``j / fps``; the recipe's sync offset is the video time of mocap time 0, so frame ``j``
  maps to mocap time ``j / fps - offset_s``, and mocap sample ``i`` is at
  ``(first_frame + i) / rate_hz`` (see :class:`formats.c3d.Markers`).
"""
from __future__ import annotations

import threading
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
#: Largest number of pixels a decoded frame may lack against its calibration, per side: one
#: codec macroblock (a 1088-pixel sensor side is often encoded 1080 wide: the Pose2Sim demo).
SIZE_TOL_PX = 16
#: Relative spread of the container's frame durations, (max - min) / median, above which the
#: frame rate counts as variable (a timebase rounding of 1/90000 s at 60 fps is 0.15 %).
VFR_TOL = 0.01
#: Cap on the MP4 boxes read into memory while looking for the track headers (bytes).
MP4_MAX_BOX = 256 * 1024 * 1024


@dataclass(frozen=True)
class VideoInfo:
    """n_frames: frames the container reports; fps: frames per second; width, height: pixels of
    the decoded (upright) frames; rotation: degrees of the container's display rotation (0, 90,
    180, 270; OpenCV applies it); fps_min, fps_max: the rates of the longest and the shortest
    frame duration in the container's timestamps (None: not an MP4/MOV, not measured)."""

    n_frames: int
    fps: float
    width: int
    height: int
    rotation: int = 0
    fps_min: float | None = None
    fps_max: float | None = None

    @property
    def variable_rate(self) -> bool:
        """The container's frame durations spread more than ``VFR_TOL``."""
        if self.fps_min is None or self.fps_max is None:
            return False
        return (1 / self.fps_min - 1 / self.fps_max) * self.fps > VFR_TOL


class VideoReader:
    """Random access to the frames of one video file by index.

    ``with VideoReader(path) as v: img = v[17]`` -> (H, W, 3) uint8 RGB. Reading past the
    end raises InputError naming the file and the frame.
    """

    def __init__(self, path: str | Path, size: tuple[int, int] | None = None):
        """size: (width, height) of the calibration; frames are padded (black, right/bottom) or
        cropped to it (:func:`size_fit`; InputError beyond ``SIZE_TOL_PX``)."""
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
        # frames upright as a player shows them (the display rotation of phones' portrait videos)
        self._cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        ok, first = self._cap.read()  # the decoded size (after the rotation) is the truth
        if not ok:
            self._cap.release()
            raise InputError(self.path, "<video>", "cannot decode frame 0", frame=0)
        h, w = first.shape[:2]
        rot, fps_min, fps_max = _container_timing(self.path)
        rot = rot or int(round(self._cap.get(cv2.CAP_PROP_ORIENTATION_META))) % 360
        self.info = VideoInfo(n, fps, w, h, rot, fps_min, fps_max)
        self._first = cv2.cvtColor(first, cv2.COLOR_BGR2RGB)
        self._pos = 1  # index of the frame the next read() returns
        self._pad = None if size is None else size_fit(self.path, self.info, *size)

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
        if index == 0:
            return self._fit(self._first.copy())
        if not self._pos <= index <= self._pos + MAX_FORWARD_DECODE:
            self._seek(index)
        while self._pos < index:
            if not self._cap.grab():
                raise InputError(self.path, "<video>", "cannot decode frame", frame=self._pos)
            self._pos += 1
        return self._fit(self._read_next(index))

    def _fit(self, img: np.ndarray) -> np.ndarray:
        if self._pad is None or self._pad == (0, 0):
            return img
        w, h = img.shape[1] + self._pad[0], img.shape[0] + self._pad[1]
        out = np.zeros((h, w, 3), np.uint8)
        hh, ww = min(h, img.shape[0]), min(w, img.shape[1])
        out[:hh, :ww] = img[:hh, :ww]
        return out

    def frames(self, indices: Iterable[int] | None = None):
        """Yield frames (all, or ``indices`` in the given order)."""
        for i in range(len(self)) if indices is None else indices:
            yield self[i]


def video_info(path: str | Path) -> VideoInfo:
    """Frame count, fps and size of a video file."""
    with VideoReader(path) as v:
        return v.info


# ------------------------------------------------------------------------ what real files need
def size_fit(path, info: VideoInfo, width: int, height: int,
             tol: int = SIZE_TOL_PX) -> tuple[int, int]:
    """How the decoded frames of ``path`` meet the calibration's ``width x height``: the
    ``(dx, dy)`` pixels to pad at the right / bottom (negative: to crop), so that a pixel's
    coordinates are the same in the video and in the calibration. Accepted when each side is
    within ``tol`` pixels; else InputError saying both sizes (and the rotation metadata, or
    that width and height are swapped: a portrait calibration for a landscape video)."""
    dx, dy = int(width) - info.width, int(height) - info.height
    if abs(dx) <= tol and abs(dy) <= tol:
        return dx, dy
    what = (f"decoded frames are {info.width}x{info.height} (container rotation "
            f"{info.rotation} deg, applied), the calibration says {width}x{height}")
    if (info.width, info.height) == (int(height), int(width)) or (
            abs(info.width - int(height)) <= tol and abs(info.height - int(width)) <= tol):
        what += ("; width and height are swapped: the video is "
                 f"{'portrait' if info.height > info.width else 'landscape'} and the "
                 "calibration is not (rotation metadata missing, or the calibration is of the "
                 "unrotated sensor)")
    raise InputError(path, "size", what + f" (at most {tol} px apart per side are accepted)")


def common_length(infos: dict) -> tuple[int, list[str]]:
    """The frames every camera has: ``infos`` ``{path: VideoInfo}`` (recipe order). Returns the
    shortest length and one warning per video of another length, naming it and both counts."""
    if not infos:
        return 0, []
    n = min(i.n_frames for i in infos.values())
    short = next(p for p, i in infos.items() if i.n_frames == n)
    return n, [f"{p}: frames: {i.n_frames} frames, but {short} of the same sequence has {n}: "
               f"the sequence is cut to the shortest, {n} frames"
               for p, i in infos.items() if i.n_frames != n]


def video_warnings(path, info: VideoInfo) -> list[str]:
    """What is odd but usable in one video: a variable frame rate (the spread of the
    container's frame durations, as rates), a display rotation."""
    out = []
    if info.variable_rate:
        out.append(f"{path}: fps: variable frame rate: the container's frame durations give "
                   f"{info.fps_min:.3f}..{info.fps_max:.3f} fps (nominal {info.fps:g}); frames "
                   f"are taken as evenly spaced at the nominal rate")
    if info.rotation:
        out.append(f"{path}: rotation: the container turns the frames by {info.rotation} deg "
                   f"(applied on decode: {info.width}x{info.height})")
    return out


def _boxes(f, end: int):
    """Yield ``(type, payload start, payload end)`` of the MP4 boxes in ``[f.tell(), end)``."""
    import struct

    pos = f.tell()
    while pos + 8 <= end:
        f.seek(pos)
        size, kind = struct.unpack(">I4s", f.read(8))
        head = 8
        if size == 1:
            size = struct.unpack(">Q", f.read(8))[0]
            head = 16
        elif size == 0:
            size = end - pos
        if size < head or pos + size > end:
            return
        yield kind.decode("latin-1"), pos + head, pos + size
        pos += size


def _container_timing(path: Path) -> tuple[int, float | None, float | None]:
    """``(rotation deg, fps_min, fps_max)`` of the first video track of an MP4/MOV from its
    ``tkhd`` display matrix and ``stts`` sample durations (``mdhd`` timescale); ``(0, None,
    None)`` for another container or a file the parser does not follow."""
    import math
    import struct

    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(0)
            moov = next(((a, b) for k, a, b in _boxes(f, size) if k == "moov"), None)
            if moov is None or moov[1] - moov[0] > MP4_MAX_BOX:
                return 0, None, None
            f.seek(moov[0])
            for kind, a, b in list(_boxes(f, moov[1])):
                if kind != "trak":
                    continue
                f.seek(a)
                found = {}

                def walk(lo, hi, found=found):
                    f.seek(lo)
                    for k, x, y in list(_boxes(f, hi)):
                        if k in ("mdia", "minf", "stbl"):
                            walk(x, y)
                        elif k in ("tkhd", "mdhd", "hdlr", "stts"):
                            f.seek(x)
                            found[k] = f.read(y - x)

                walk(a, b)
                if "hdlr" not in found or found["hdlr"][8:12] != b"vide":
                    continue
                tk = found.get("tkhd", b"")
                off = 4 + (32 if tk[:1] == b"" else 20) + 8 + 8
                rot = 0
                if len(tk) >= off + 36:
                    m = struct.unpack(">9i", tk[off:off + 36])
                    rot = int(round(math.degrees(math.atan2(m[1], m[0])))) % 360
                md, st = found.get("mdhd", b""), found.get("stts", b"")
                scale = struct.unpack(">I", md[20:24] if md[:1] == b"" else md[12:16])[0] \
                    if len(md) >= 24 else 0
                if not scale or len(st) < 8:
                    return rot, None, None
                n = struct.unpack(">I", st[4:8])[0]
                ent = np.frombuffer(st[8:8 + 8 * n], dtype=">u4").reshape(-1, 2)
                d = ent[ent[:, 0] > 0, 1]
                # the last sample's duration is often a muxer's guess: judge the others
                if len(ent) and ent[-1, 0] == 1 and len(d) > 1:
                    d = d[:-1]
                d = d[d > 0]
                if not len(d):
                    return rot, None, None
                return rot, scale / float(d.max()), scale / float(d.min())
    except (OSError, struct.error, ValueError):
        pass
    return 0, None, None


_FOURCC_OK: dict[str, bool] = {}
_FOURCC_LOCK = threading.Lock()


def fourcc_available(fourcc: str) -> bool:
    """Whether this OpenCV build can write MP4s with ``fourcc`` (probed once per process with a
    tiny file: ``avc1`` (H.264) needs an FFmpeg with an H.264 encoder)."""
    with _FOURCC_LOCK:
        return _probe(fourcc)


def _probe(fourcc: str) -> bool:
    if fourcc not in _FOURCC_OK:
        import os
        import tempfile

        import cv2

        fd, tmp = tempfile.mkstemp(suffix=".mp4")
        os.close(fd)
        saved = os.dup(2)  # a failed probe is not an error: FFmpeg's complaint goes nowhere
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
            w = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*fourcc), 25.0, (64, 64))
            _FOURCC_OK[fourcc] = bool(w.isOpened())
            w.release()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            os.close(null)
            os.unlink(tmp)
    return _FOURCC_OK[fourcc]


def write_mp4(path: str | Path, frames: Iterable[np.ndarray], fps: float,
              codecs: tuple[str, ...] = ("mp4v",)) -> Path:
    """Write RGB frames ``(H, W, 3) uint8`` (all the same size) to an MP4 at ``fps``, with the
    first of ``codecs`` (fourccs, e.g. ``("avc1", "mp4v")``: H.264 where the OpenCV build has
    an encoder for it) that :func:`fourcc_available` finds; default ``mp4v``."""
    import cv2

    usable = [c for c in codecs if fourcc_available(c)]
    if not usable:
        raise InputError(path, "<video>", f"no MP4 writer for {', '.join(codecs)}")
    fourcc = usable[0]

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
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps), size)
                if not writer.isOpened():
                    raise InputError(path, "<video>", f"cannot open an {fourcc} writer")
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
