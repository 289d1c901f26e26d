"""A whole sequence: frames split into contiguous chunks, chunks run in worker processes,
each with its own detector instance (mediapipe graphs are per process and not picklable).

Within a chunk frames run in order, so the partner's box from the previous frame seeds the
next search (:func:`detect.people.find_people`); each chunk starts fresh with a whole-image
search, which costs two extra detections per view per chunk. Chunks have a fixed length, so
results do not depend on the number of workers.
"""
from __future__ import annotations

import concurrent.futures as cf
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from detect import layout
from detect.base import DetectorFactory, call_detector, forget_stream, quiet_native_logs
from detect.hints import WearerHints
from detect.people import PeopleOptions, find_people
from pipeline.procs import process_pool


class FrameReader(Protocol):
    def read(self, cam: int, frame: int) -> np.ndarray: ...  # (H, W, 3) uint8 RGB

    def close(self) -> None: ...


class FrameSource(Protocol):
    """Picklable description of where frames come from; each worker opens its own reader."""

    def open(self) -> FrameReader: ...


@dataclass(frozen=True)
class ArraySource:
    """Frames held in memory: images (C, F, H, W, 3) uint8 RGB, indexed by ``frames`` (F,)
    video frame numbers (tests, renders)."""

    images: np.ndarray
    frames: tuple[int, ...]

    def open(self) -> "ArraySource":
        return self

    def read(self, cam: int, frame: int) -> np.ndarray:
        return self.images[cam, self.frames.index(int(frame))]

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class SequenceKeypoints:
    """Everything the stage saves. Pixels of the full image; NaN box = none.

    kp : (C, F, 2, 65, 3) float32 (x, y, confidence; 0 = missing); person 0 = marker wearer.
    boxes : (C, F, 2, 4) body crop boxes (x0, y0, x1, y1). hand_boxes : (C, F, 2, 2, 4).
    frames : (F,) video frame indices. wearer_retry : (C, F) bool. partner_mode : (C, F) int8
    (0 not found, 1 tracked, 2 whole image). cpu_s : CPU seconds spent in the workers
    (all their threads), setup included; wall_s : wall-clock seconds. meter : detector
    calls, calls that found nothing and their CPU seconds per kind (``body_calls``,
    ``body_empty``, ``body_cpu_s``, the same for ``hands``), a tracking detector's
    ``body_tracked_calls`` / ``body_static_retries``, and ``setup_cpu_s``: the part of
    ``cpu_s`` spent building detectors and opening videos (per chunk; the first chunk of a
    worker also imports mediapipe, ~1 s).
    """

    kp: np.ndarray
    boxes: np.ndarray
    hand_boxes: np.ndarray
    frames: np.ndarray
    wearer_retry: np.ndarray
    partner_mode: np.ndarray
    cpu_s: float
    wall_s: float
    meter: dict


def _run_chunk(source: FrameSource, factory: DetectorFactory, hints: WearerHints,
               frames: np.ndarray, n_cam: int, opts: PeopleOptions) -> tuple[dict, dict]:
    """Detect one chunk of frames (in a worker). hints cover exactly ``frames``. Returns
    (arrays of the chunk, meter: detector calls and CPU seconds)."""
    with quiet_native_logs():  # detector threads may log after a call has returned
        return _run_chunk_loud(source, factory, hints, frames, n_cam, opts)


class _Metered:
    """A detector wrapper counting calls and their CPU seconds per kind (for the report)."""

    def __init__(self, det):
        self.det = det
        self.name = det.name
        self.needs_pixels = det.needs_pixels
        self.streams = getattr(det, "streams", False)
        self.calls = {"body": 0, "hands": 0}
        self.empty = {"body": 0, "hands": 0}
        self.cpu_s = {"body": 0.0, "hands": 0.0}

    def detect(self, image, *, kind, box=None, cam=0, frame=0, stream=None):
        t = time.process_time()
        out = call_detector(self.det, image, kind=kind, box=box, cam=cam, frame=frame,
                            stream=stream)
        self.cpu_s[kind] += time.process_time() - t
        self.calls[kind] += 1
        self.empty[kind] += len(out) == 0
        return out

    def forget(self, stream):
        forget_stream(self.det, stream)

    def counts(self) -> dict:
        """The meter: calls, calls that found nothing, CPU seconds per kind, and the tracking
        detector's tracked calls and static retries (when it has them)."""
        out = {f"{k}_calls": v for k, v in self.calls.items()}
        out.update({f"{k}_empty": v for k, v in self.empty.items()})
        out.update({f"{k}_cpu_s": v for k, v in self.cpu_s.items()})
        for k in ("tracked_calls", "static_retries"):
            if hasattr(self.det, k):
                out[f"body_{k}"] = getattr(self.det, k)
        return out

    def close(self):
        self.det.close()


def _run_chunk_loud(source, factory, hints, frames, n_cam, opts):
    t0 = time.process_time()
    det = _Metered(factory.build())
    reader = source.open() if det.needs_pixels else None
    setup = time.process_time() - t0  # the detector's import and graphs, the video readers
    n = len(frames)
    kp = np.zeros((n_cam, n, 2, layout.N, 3), np.float32)
    boxes = np.full((n_cam, n, 2, 4), np.nan)
    hand_boxes = np.full((n_cam, n, 2, 2, 4), np.nan)
    retry = np.zeros((n_cam, n), bool)
    mode = np.zeros((n_cam, n), np.int8)
    try:
        prev = [None] * n_cam
        isolated = [False] * n_cam
        masked = [True] * n_cam
        for i, fr in enumerate(frames):
            for c in range(n_cam):
                img = reader.read(c, int(fr)) if reader is not None else None
                r = find_people(img, hints.view(c, i), prev[c], det, opts, cam=c, frame=int(fr),
                                wearer_isolated_first=isolated[c], partner_masked_first=masked[c])
                isolated[c] = r.wearer_retry
                if r.partner_mode:
                    masked[c] = r.partner_masked
                kp[c, i], boxes[c, i], hand_boxes[c, i] = r.kp, r.boxes, r.hand_boxes
                retry[c, i], mode[c, i] = r.wearer_retry, r.partner_mode
                prev[c] = r.partner_box if r.partner_mode else None
    finally:
        if reader is not None:
            reader.close()
        det.close()
    out = dict(kp=kp, boxes=boxes, hand_boxes=hand_boxes, wearer_retry=retry, partner_mode=mode)
    meter = det.counts()
    meter["cpu_s"] = time.process_time() - t0
    meter["setup_cpu_s"] = setup
    return out, meter


def _silence_native_stderr() -> None:
    """Worker initializer: native stderr (fd 2) to /dev/null for the worker's lifetime (the
    detector's graph threads log at any time). Errors still reach the parent: exceptions are
    pickled back with their tracebacks."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)


def chunks(n: int, chunk: int) -> list[slice]:
    """Split range(n) into contiguous slices of at most ``chunk`` frames, as even as possible
    (the count depends only on n and chunk, never on the number of workers)."""
    if n == 0:
        return []
    k = -(-n // max(chunk, 1))
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def detect_sequence(source: FrameSource, factory: DetectorFactory, hints: WearerHints,
                    frames: np.ndarray, opts: PeopleOptions | None = None, workers: int = 1,
                    chunk: int = 32,
                    progress: Callable[..., Any] = lambda it, **_: it) -> SequenceKeypoints:
    """Keypoints of both people in every view and frame.

    hints : (C, F, ...) for exactly ``frames`` (F,) video frame indices. workers : processes
    (<= 1: run in this process; > 1: a "spawn" pool, each worker building its own detector
    from ``factory``). chunk : frames per task; each task starts the partner search afresh.
    progress : ``progress(iterable, total=, desc=)`` wrapper.
    """
    opts = PeopleOptions() if opts is None else opts
    frames = np.asarray(frames, dtype=np.int64)
    n_cam, n = hints.box.shape[:2]
    if n != len(frames):
        raise ValueError(f"detect_sequence: hints cover {n} frames, got {len(frames)} frame indices")
    parts = chunks(n, chunk)
    t0 = time.perf_counter()
    results: dict[int, tuple[dict, dict]] = {}
    if workers <= 1:
        for j, sl in enumerate(progress(parts, total=len(parts), desc="keypoints")):
            results[j] = _run_chunk(source, factory, hints.frames(sl), frames[sl], n_cam, opts)
    else:
        # workers die with this process (kill -9 included) and are killed, not awaited, when
        # the block is left by an exception (a failed chunk, SIGTERM during the stage)
        with process_pool(workers, initializer=_silence_native_stderr) as pool:
            futs = {pool.submit(_run_chunk, source, factory, hints.frames(sl), frames[sl], n_cam,
                                opts): j for j, sl in enumerate(parts)}
            for fut in progress(cf.as_completed(futs), total=len(futs), desc="keypoints"):
                results[futs[fut]] = fut.result()
    wall = time.perf_counter() - t0

    def cat(key, axis=1):
        if not parts:
            return None
        return np.concatenate([results[j][0][key] for j in range(len(parts))], axis=axis)

    if not parts:
        z = np.zeros((n_cam, 0), bool)
        return SequenceKeypoints(np.zeros((n_cam, 0, 2, layout.N, 3), np.float32),
                                 np.zeros((n_cam, 0, 2, 4)), np.zeros((n_cam, 0, 2, 2, 4)),
                                 frames, z, z.astype(np.int8), 0.0, wall, {})
    meter: dict = {}
    for _, m in results.values():
        for k, v in m.items():
            meter[k] = meter.get(k, 0) + v
    return SequenceKeypoints(cat("kp"), cat("boxes"), cat("hand_boxes"), frames,
                             cat("wearer_retry"), cat("partner_mode"),
                             float(meter.pop("cpu_s")), wall, meter)


@dataclass(frozen=True)
class VideoSource:
    """Frames decoded from one video file per camera (``paths`` in camera order) with
    :class:`formats.video.VideoReader` (frame-accurate; forward reads within a chunk decode
    sequentially). Each worker opens its own readers."""

    paths: tuple[str, ...]

    def open(self) -> "_VideoReaders":
        return _VideoReaders(self.paths)


class _VideoReaders:
    def __init__(self, paths):
        from formats.video import VideoReader

        self.readers = []
        try:
            for p in paths:
                self.readers.append(VideoReader(p))
        except Exception:
            self.close()
            raise

    def read(self, cam: int, frame: int) -> np.ndarray:
        return self.readers[cam][frame]

    def close(self) -> None:
        for r in self.readers:
            r.close()
