"""A whole sequence: frames split into contiguous chunks, chunks run in worker processes,
each with its own detector instance (mediapipe graphs are per process and not picklable).

Within a chunk each view's frames run in order, so the partner's box from the previous frame
seeds the next search (:func:`detect.people.find_people`) and a tracking detector follows
the people; each chunk and each view starts fresh (the detector's streams are reset, then a
whole-image search, which costs two extra detections per view per chunk). Chunks have a
fixed length, so results do not depend on the number of workers. A detector is built once
per pool task (a few consecutive chunks, :func:`task_groups`), or once for the whole
sequence in this process: building mediapipe's graphs is cheap but each graph's first
detection costs ~0.2 s (its model's weights are prepared), which per chunk of 32 frames was
more than the tracking it enables saved.
"""
from __future__ import annotations

import concurrent.futures as cf
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from detect import layout
from detect.base import (
    DetectorFactory,
    call_detector,
    forget_stream,
    quiet_native_logs,
    reset_streams,
)
from detect.hints import WearerHints
from detect.people import PeopleOptions, find_people
from pipeline.procs import process_pool

#: Pool tasks per worker process (see :func:`task_groups`).
TASKS_PER_WORKER = 3


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

    def reset(self):
        reset_streams(self.det)

    def counts(self) -> dict:
        """The meter: calls, calls that found nothing, CPU seconds per kind, and the tracking
        detector's tracked calls and static retries (when it has them)."""
        out = {f"{k}_calls": v for k, v in self.calls.items()}
        out.update({f"{k}_empty": v for k, v in self.empty.items()})
        out.update({f"{k}_cpu_s": v for k, v in self.cpu_s.items()})
        for k in ("tracked_calls", "static_retries"):
            if hasattr(self.det, k):
                out[f"body_{k}"] = getattr(self.det, k)
        for k in ("tracked_hand_calls", "hand_static_retries"):
            if hasattr(self.det, k):
                out[f"hands_{k.replace('hand_', '')}"] = getattr(self.det, k)
        return out

    def close(self):
        self.det.close()


def _run_chunks(source: FrameSource, factory: DetectorFactory,
                parts: list[tuple[WearerHints, np.ndarray]], n_cam: int, opts: PeopleOptions,
                step: Callable[[int], None] | None = None) -> tuple[list[dict], dict]:
    """Detect a few chunks of frames (in a worker, or for the whole sequence in this process)
    with one detector and one set of video readers; ``parts`` = (hints covering exactly the
    chunk's frames, frames) per chunk; ``step(1)`` after each (progress, in this process).
    Returns (the arrays of each chunk, meter: detector calls and CPU seconds of all)."""
    with quiet_native_logs():  # detector threads may log after a call has returned
        t0 = time.process_time()
        det = _Metered(factory.build())
        reader = source.open() if det.needs_pixels else None
        setup = time.process_time() - t0  # the detector's import and graphs, the video readers
        out = []
        try:
            for hints, frames in parts:
                out.append(_run_chunk(reader, det, hints, frames, n_cam, opts))
                if step is not None:
                    step(1)
        finally:
            if reader is not None:
                reader.close()
            det.close()
        meter = det.counts()
        meter["cpu_s"] = time.process_time() - t0
        meter["setup_cpu_s"] = setup
    return out, meter


def _run_chunk(reader, det, hints: WearerHints, frames: np.ndarray, n_cam: int,
               opts: PeopleOptions) -> dict:
    """One chunk, view after view: each view's frames in order (the partner's box, the
    wearer's crop variant and the partner's search image carry from frame to frame), the
    detector's streams reset at the start of every view (a tracking detector then follows
    one view at a time: its streams name the person, not the view; a chunk's results do not
    depend on what the detector saw before)."""
    n = len(frames)
    kp = np.zeros((n_cam, n, 2, layout.N, 3), np.float32)
    boxes = np.full((n_cam, n, 2, 4), np.nan)
    hand_boxes = np.full((n_cam, n, 2, 2, 4), np.nan)
    retry = np.zeros((n_cam, n), bool)
    mode = np.zeros((n_cam, n), np.int8)
    for c in range(n_cam):
        reset_streams(det)
        prev, isolated, masked = None, False, True
        for i, fr in enumerate(frames):
            img = reader.read(c, int(fr)) if reader is not None else None
            r = find_people(img, hints.view(c, i), prev, det, opts, cam=c, frame=int(fr),
                            wearer_isolated_first=isolated, partner_masked_first=masked)
            isolated = r.wearer_retry
            if r.partner_mode:
                masked = r.partner_masked
            kp[c, i], boxes[c, i], hand_boxes[c, i] = r.kp, r.boxes, r.hand_boxes
            retry[c, i], mode[c, i] = r.wearer_retry, r.partner_mode
            prev = r.partner_box if r.partner_mode else None
    return dict(kp=kp, boxes=boxes, hand_boxes=hand_boxes, wearer_retry=retry, partner_mode=mode)


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
    (<= 1: run in this process, one detector; > 1: a "spawn" pool, each task (a few
    consecutive chunks, :func:`task_groups`) building its own detector from ``factory``).
    chunk : frames per chunk; each chunk starts the partner search and the detector's
    tracking afresh in every view. progress : ``progress(iterable, total=, desc=)`` wrapper
    (advanced per chunk, or per task's chunks).
    """
    opts = PeopleOptions() if opts is None else opts
    frames = np.asarray(frames, dtype=np.int64)
    n_cam, n = hints.box.shape[:2]
    if n != len(frames):
        raise ValueError(f"detect_sequence: hints cover {n} frames, got {len(frames)} frame indices")
    parts = chunks(n, chunk)
    t0 = time.perf_counter()
    results: dict[int, dict] = {}
    meters: list[dict] = []
    todo = [(hints.frames(sl), frames[sl]) for sl in parts]
    if workers <= 1:
        # one detector for the whole sequence (its warm-up is paid once), chunk after chunk
        done = _Progress(progress, len(parts))
        out, meter = _run_chunks(source, factory, todo, n_cam, opts, step=done.step)
        results.update(enumerate(out))
        meters.append(meter)
        done.close()
    else:
        # a task is a few consecutive chunks run with one detector (each worker pays the
        # detector's warm-up once per task, not per chunk); workers die with this process
        # (kill -9 included) and are killed, not awaited, when the block is left by an
        # exception (a failed chunk, SIGTERM during the stage)
        groups = task_groups(len(parts), workers)
        with process_pool(workers, initializer=_silence_native_stderr) as pool:
            futs = {pool.submit(_run_chunks, source, factory, [todo[j] for j in g], n_cam,
                                opts): g for g in groups}
            done = _Progress(progress, len(parts))
            for fut in cf.as_completed(futs):
                out, meter = fut.result()
                for j, arrays in zip(futs[fut], out, strict=True):
                    results[j] = arrays
                meters.append(meter)
                done.step(len(futs[fut]))
            done.close()
    wall = time.perf_counter() - t0

    def cat(key, axis=1):
        if not parts:
            return None
        return np.concatenate([results[j][key] for j in range(len(parts))], axis=axis)

    if not parts:
        z = np.zeros((n_cam, 0), bool)
        return SequenceKeypoints(np.zeros((n_cam, 0, 2, layout.N, 3), np.float32),
                                 np.zeros((n_cam, 0, 2, 4)), np.zeros((n_cam, 0, 2, 2, 4)),
                                 frames, z, z.astype(np.int8), 0.0, wall, {})
    meter: dict = {}
    for m in meters:
        for k, v in m.items():
            meter[k] = meter.get(k, 0) + v
    return SequenceKeypoints(cat("kp"), cat("boxes"), cat("hand_boxes"), frames,
                             cat("wearer_retry"), cat("partner_mode"),
                             float(meter.pop("cpu_s")), wall, meter)


def task_groups(n_parts: int, workers: int) -> list[list[int]]:
    """Consecutive chunk indices per pool task: about TASKS_PER_WORKER tasks per worker (a
    task pays the detector's warm-up once; more tasks balance the load and move the
    progress bar). Which chunks share a task changes no result: each chunk starts afresh."""
    if n_parts == 0:
        return []
    k = min(n_parts, max(1, workers) * TASKS_PER_WORKER)
    edges = np.linspace(0, n_parts, k + 1).round().astype(int)
    return [list(range(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


class _Progress:
    """``progress(iterable, total=, desc=)`` driven by hand: ``step(n)`` advances n chunks."""

    def __init__(self, progress, total: int):
        self._it = iter(progress(range(total), total=total, desc="keypoints"))
        self._left = total

    def step(self, n: int) -> None:
        for _ in range(min(n, self._left)):
            next(self._it, None)
        self._left -= n

    def close(self) -> None:
        for _ in self._it:
            pass


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
