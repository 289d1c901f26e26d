"""OpenPose JSON (``--write_json``): one file per frame, BODY_25 body + 21-point hands.

File: ``{"version": 1.3, "people": [{"pose_keypoints_2d": [x, y, c] * 25,
"hand_left_keypoints_2d": [x, y, c] * 21, "hand_right_keypoints_2d": [...], ...}, ...]}``;
coordinates in full-image pixels (OpenPose's default ``--keypoint_scale 0``), confidence 0 for
a keypoint not found. Named ``<video>_<12-digit frame>_keypoints.json``: the frame index is the
last group of digits in the name.

Mapping to KP65 (``formats.skeletons``): the BODY_25 keypoints with an exact KP65 equivalent
(all but ``Neck`` and ``MidHip``, which are not KP65 points); the hands in the same 21-point
order. Hands or face absent from a person -> confidence 0.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from formats.errors import InputError
from formats.keypoints import (
    N_KP65,
    KeypointFrames,
    flat_triplets,
    frame_from_name,
    load_json,
    stack_people,
)
from formats.skeletons import INDEX_IN_KP65, LEFT_HAND, OPENPOSE_BODY25, RIGHT_HAND

_BODY_SRC = [i for i, k in enumerate(INDEX_IN_KP65["openpose_body25"]) if k >= 0]
_BODY_DST = [INDEX_IN_KP65["openpose_body25"][i] for i in _BODY_SRC]


def person_to_kp65(path, person: dict, i: int, frame: int | None) -> np.ndarray:
    """One OpenPose person dict -> (65, 3) float32 KP65 (x, y pixels; confidence in [0, 1])."""
    if not isinstance(person, dict):
        raise InputError(path, f"people[{i}]", "expected an object", frame)
    field = f"people[{i}].pose_keypoints_2d"
    if "pose_keypoints_2d" not in person:
        raise InputError(path, field, "missing", frame)
    out = np.zeros((N_KP65, 3))
    body = flat_triplets(path, field, person["pose_keypoints_2d"], len(OPENPOSE_BODY25), frame)
    out[_BODY_DST] = body[_BODY_SRC]
    for key, sl in (("hand_left_keypoints_2d", LEFT_HAND), ("hand_right_keypoints_2d", RIGHT_HAND)):
        v = person.get(key)
        if v:  # OpenPose writes [] when hands were not requested
            out[sl] = flat_triplets(path, f"people[{i}].{key}", v, 21, frame)
    out[:, 2] = np.clip(out[:, 2], 0.0, 1.0)
    out[out[:, 2] <= 0] = 0.0
    return out.astype(np.float32)


def read_openpose_frame(path: str | Path, frame: int | None = None) -> np.ndarray:
    """One OpenPose JSON file -> (N, 65, 3) float32, one row per person found."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict) or "people" not in d:
        raise InputError(path, "people", "missing", frame)
    people = d["people"]
    if not isinstance(people, list):
        raise InputError(path, "people", "expected a list", frame)
    if not people:
        return np.zeros((0, N_KP65, 3), np.float32)
    return np.stack([person_to_kp65(path, p, i, frame) for i, p in enumerate(people)])


def read_openpose(source: str | Path | Sequence[str | Path]) -> KeypointFrames:
    """A folder of OpenPose JSON files (or a list of them, or one file) -> KeypointFrames
    sorted by the frame index in each file name."""
    if isinstance(source, (str, Path)):
        src = Path(source)
        if src.is_dir():
            files = sorted(src.glob("*.json"))
            if not files:
                raise InputError(src, "*.json", "no OpenPose JSON files in the folder")
        else:
            files = [src]
    else:
        files = [Path(p) for p in source]
    frames, per = [], []
    seen: dict[int, Path] = {}
    for f in files:
        fr = frame_from_name(f)
        if fr is None:
            raise InputError(f, "<file name>", "no frame number in the name")
        if fr in seen:
            raise InputError(f, "<file name>", f"frame {fr} also given by {seen[fr].name}", fr)
        seen[fr] = f
        frames.append(fr)
        per.append(read_openpose_frame(f, fr))
    return stack_people(per, frames)


def write_openpose_frame(path: str | Path, people: np.ndarray) -> Path:
    """Write (N, 65, 3) KP65 people as an OpenPose BODY_25 + hands JSON file (Neck and MidHip
    from the shoulders' and hips' midpoints when both are present). For tests and the studio."""
    import json

    path = Path(path)
    people = np.asarray(people, dtype=np.float64)
    out = []
    for p in people:
        body = np.zeros((len(OPENPOSE_BODY25), 3))
        body[_BODY_SRC] = p[_BODY_DST]
        for name, (a, b) in (("Neck", (5, 6)), ("MidHip", (11, 12))):
            if p[a, 2] > 0 and p[b, 2] > 0:
                body[OPENPOSE_BODY25.index(name)] = (p[a] + p[b]) / 2
        out.append({"person_id": [-1], "pose_keypoints_2d": body.ravel().tolist(),
                    "face_keypoints_2d": [],
                    "hand_left_keypoints_2d": p[LEFT_HAND].ravel().tolist(),
                    "hand_right_keypoints_2d": p[RIGHT_HAND].ravel().tolist(),
                    "pose_keypoints_3d": [], "face_keypoints_3d": [],
                    "hand_left_keypoints_3d": [], "hand_right_keypoints_3d": []})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"version": 1.3, "people": out}))
    return path
