"""The one detector interface: an image (or a box in it) in, candidate people out.

Every detector returns :class:`Detections`: ``kp (N, 65, 3)`` candidates in the canonical
KP65 layout, in full-image pixels, whatever it looked at (a crop, the whole image, or a
precomputed file). Confidence 0 means "this keypoint was not found".

``kind="body"`` asks for whole people (body keypoints, and hand keypoints if the detector
gives them together); ``kind="hands"`` asks for hands: each candidate then has one of its two
hand blocks filled (left or right as the detector labelled it, in the person's anatomical
sense) and everything else 0.
"""
from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from detect.constants import N_KP

Kind = Literal["body", "hands"]


@dataclass(frozen=True)
class Detections:
    """Candidate people found in one image.

    kp : (N, 65, 3) float32: x, y in pixels of the full image (OpenCV convention: the centre
        of pixel (i, j) is at (j, i)), confidence in [0, 1]; 0 = not found.
    """

    kp: np.ndarray

    def __post_init__(self):
        kp = np.asarray(self.kp, dtype=np.float32)
        if kp.ndim != 3 or kp.shape[1:] != (N_KP, 3):
            raise ValueError(f"Detections.kp: expected (N, {N_KP}, 3), got {kp.shape}")
        object.__setattr__(self, "kp", kp)

    def __len__(self) -> int:
        return len(self.kp)

    @staticmethod
    def empty() -> "Detections":
        return Detections(np.zeros((0, N_KP, 3), np.float32))

    @staticmethod
    def concat(parts: "list[Detections]") -> "Detections":
        if not parts:
            return Detections.empty()
        return Detections(np.concatenate([p.kp for p in parts], axis=0))


class Detector(Protocol):
    """What the keypoints stage needs from a detector.

    needs_pixels : False for precomputed files (the stage then skips decoding video).
    """

    name: str
    needs_pixels: bool

    def detect(
        self,
        image: np.ndarray | None,
        *,
        kind: Kind,
        box: np.ndarray | None = None,
        cam: int = 0,
        frame: int = 0,
    ) -> Detections:
        """Candidates in ``image`` (H, W, 3) uint8 RGB, restricted to ``box`` (x0, y0, x1, y1)
        pixels when given (None: the whole image). ``cam`` (index into the recipe's camera
        list) and ``frame`` (video frame index) identify the image for precomputed detectors.
        Returned keypoints are in full-image pixels."""
        ...

    def close(self) -> None: ...


class DetectorFactory(Protocol):
    """A picklable recipe for a detector: each worker process builds its own instance."""

    def build(self) -> Detector: ...


def call_detector(det, image, *, kind: Kind, box=None, cam: int = 0, frame: int = 0,
                  stream=None) -> Detections:
    """``det.detect(...)``, naming the ``stream`` (the person followed from frame to frame in
    one view, e.g. ``("wearer",)``: :mod:`detect.run` resets the streams when it moves on to
    another view) to detectors that track (``det.streams`` true: mediapipe's video mode);
    other detectors are called without it."""
    if stream is not None and getattr(det, "streams", False):
        return det.detect(image, kind=kind, box=box, cam=cam, frame=frame, stream=stream)
    return det.detect(image, kind=kind, box=box, cam=cam, frame=frame)


def forget_stream(det, stream) -> None:
    """Tell a tracking detector that its last result on ``stream`` was rejected (it must not
    track that person on); a no-op for other detectors."""
    if stream is not None and getattr(det, "streams", False):
        det.forget(stream)


def reset_streams(det) -> None:
    """Make a tracking detector forget every stream (its next call on each detects afresh,
    as a new detector's would: a tracking detector has ``reset()`` as well as
    ``forget(stream)``); a no-op for other detectors. :mod:`detect.run` calls it at the start
    of each chunk and view, so no state crosses a chunk whatever ran before it."""
    if getattr(det, "streams", False):
        det.reset()


@contextlib.contextmanager
def quiet_native_logs():
    """Send file descriptor 2 (native stderr) to /dev/null inside the block. Python-level
    exceptions still propagate; only C++ logging is lost."""
    try:
        sys.stderr.flush()
    except (AttributeError, ValueError):
        pass
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        try:
            sys.stderr.flush()
        except (AttributeError, ValueError):
            pass
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
