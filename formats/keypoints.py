"""The common result of the precomputed-detection readers (OpenPose, COCO): every person found
in each frame, mapped onto the pipeline's KP65 layout (``formats.skeletons.KP65``)."""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formats.errors import InputError

N_KP65 = 65


@dataclass(frozen=True, eq=False)
class KeypointFrames:
    """Candidates per frame of one camera.

    kp: (F, N, 65, 3) float32: x, y in full-image pixels, confidence in [0, 1]; rows of
        absent keypoints and padding people are all 0 (confidence 0 = missing)
    frames: (F,) int64 video frame indices, increasing
    """

    kp: np.ndarray
    frames: np.ndarray

    def __post_init__(self):
        kp = np.asarray(self.kp, dtype=np.float32)
        fr = np.asarray(self.frames, dtype=np.int64)
        if kp.ndim != 4 or kp.shape[2:] != (N_KP65, 3) or kp.shape[0] != fr.shape[0]:
            raise ValueError(f"KeypointFrames: kp {kp.shape} / frames {fr.shape}: expected "
                             "(F, N, 65, 3) and (F,)")
        object.__setattr__(self, "kp", kp)
        object.__setattr__(self, "frames", fr)


def stack_people(per_frame: list[np.ndarray], frames, min_people: int = 0) -> KeypointFrames:
    """Pad a list of (N_f, 65, 3) arrays to (F, max N_f, 65, 3) and sort by frame index."""
    order = np.argsort(np.asarray(frames, dtype=np.int64), kind="stable")
    n = max([len(p) for p in per_frame] + [min_people])
    kp = np.zeros((len(per_frame), n, N_KP65, 3), np.float32)
    for j, i in enumerate(order):
        kp[j, : len(per_frame[i])] = per_frame[i]
    return KeypointFrames(kp, np.asarray(frames, dtype=np.int64)[order])


def frame_from_name(path: Path) -> int | None:
    """Frame index from a file name: the last group of digits (OpenPose writes
    ``<video>_000000000123_keypoints.json``; image files are usually ``000123.jpg``)."""
    m = re.findall(r"\d+", Path(path).stem)
    return int(m[-1]) if m else None


def load_json(path: Path):
    """Parsed JSON, or InputError naming the file (missing, unreadable, truncated)."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise InputError(path, "<file>", f"cannot read: {e.strerror or e}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(path, "<json>", f"invalid or truncated JSON: {e}") from None


def flat_triplets(path, field: str, value, n: int, frame: int | None) -> np.ndarray:
    """A flat [x0, y0, c0, x1, ...] list of ``n`` keypoints as (n, 3) float64, checked."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, field, "not a list of numbers", frame) from None
    if a.ndim != 1 or a.size != 3 * n:
        raise InputError(path, field, f"expected {3 * n} values ({n} keypoints x 3), got "
                         f"{a.size if a.ndim == 1 else a.shape}", frame)
    if not np.all(np.isfinite(a)):
        raise InputError(path, field, "contains NaN or inf", frame)
    return a.reshape(n, 3)
