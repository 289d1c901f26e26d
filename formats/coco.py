"""COCO keypoint JSON: the dataset form and the detector-results form, COCO-17 or
COCO-WholeBody (133).

- Dataset form: ``{"images": [{"id", "file_name", ...}], "annotations": [{"image_id",
  "keypoints": [x, y, v] * 17, ...}], ...}``; ``v`` is a visibility flag (0 absent, 1
  occluded, 2 visible) and becomes confidence 1 where ``v > 0``. COCO-WholeBody annotations
  add ``foot_kpts`` (6), ``lefthand_kpts`` (21), ``righthand_kpts`` (21) (and face, unused).
- Results form (what detectors write): ``[{"image_id", "category_id", "keypoints": [x, y, s]
  * 17 or * 133, "score"}, ...]``; ``s`` is a confidence, clipped to [0, 1].

Frame index of an image: the last group of digits of its ``file_name`` when the file has an
``images`` table, else ``image_id`` itself.

KP65 is COCO-WholeBody's body (17) + feet (6) + left hand (21) + right hand (21), in that
order, so the mapping is exact: 133-point index ``i`` -> KP65 ``i`` for ``i < 23``, and
``91..132`` -> ``23..64`` (the 68 face points 23..90 are dropped).
"""
from __future__ import annotations

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

WHOLEBODY_TO_KP65 = np.r_[0:23, 91:133]  # KP65 row k comes from whole-body point WHOLEBODY_TO_KP65[k]
_PARTS = (("foot_kpts", 6, slice(17, 23)), ("lefthand_kpts", 21, slice(23, 44)),
          ("righthand_kpts", 21, slice(44, 65)))


def _annotation_to_kp65(path, ann: dict, i: int, frame: int | None, flags: bool) -> np.ndarray:
    field = f"annotations[{i}].keypoints" if flags else f"[{i}].keypoints"
    if not isinstance(ann, dict) or "keypoints" not in ann:
        raise InputError(path, field, "missing", frame)
    kp = ann["keypoints"]
    n = len(kp) // 3 if isinstance(kp, list) else -1
    out = np.zeros((N_KP65, 3))
    if n == 133:
        out[:] = flat_triplets(path, field, kp, 133, frame)[WHOLEBODY_TO_KP65]
    else:
        if n != 17:
            n = 17  # let flat_triplets report the length
        out[:17] = flat_triplets(path, field, kp, 17, frame)
        for key, m, sl in _PARTS:
            if ann.get(key):
                out[sl] = flat_triplets(path, field.replace("keypoints", key), ann[key], m, frame)
    if flags:
        out[:, 2] = (out[:, 2] > 0).astype(float)
    else:
        out[:, 2] = np.clip(out[:, 2], 0.0, 1.0)
    out[out[:, 2] <= 0] = 0.0
    return out.astype(np.float32)


def read_coco(path: str | Path, category_id: int | None = 1) -> KeypointFrames:
    """A COCO keypoint JSON file (dataset or results form) -> KeypointFrames (all people per
    frame, KP65). category_id: keep only this category (person = 1); None keeps all."""
    path = Path(path)
    d = load_json(path)
    image_frame: dict = {}
    if isinstance(d, dict):
        if "annotations" not in d:
            raise InputError(path, "annotations", "missing")
        anns, flags = d["annotations"], True
        for j, im in enumerate(d.get("images", [])):
            if not isinstance(im, dict) or "id" not in im:
                raise InputError(path, f"images[{j}].id", "missing")
            fr = frame_from_name(Path(str(im.get("file_name", ""))))
            image_frame[im["id"]] = fr if fr is not None else im["id"]
    elif isinstance(d, list):
        anns, flags = d, False
    else:
        raise InputError(path, "<json>", "expected an object or a list")
    if not isinstance(anns, list):
        raise InputError(path, "annotations", "expected a list")
    by_frame: dict[int, list[np.ndarray]] = {}
    for i, ann in enumerate(anns):
        prefix = f"annotations[{i}]" if flags else f"[{i}]"
        if not isinstance(ann, dict) or "image_id" not in ann:
            raise InputError(path, f"{prefix}.image_id", "missing")
        if category_id is not None and ann.get("category_id", category_id) != category_id:
            continue
        img = ann["image_id"]
        if image_frame and img not in image_frame:
            raise InputError(path, f"{prefix}.image_id", f"image {img!r} not in images")
        frame = image_frame.get(img, img)
        if not isinstance(frame, (int, np.integer)) or isinstance(frame, bool):
            raise InputError(path, f"{prefix}.image_id", f"cannot tell the frame of {img!r}")
        by_frame.setdefault(int(frame), []).append(_annotation_to_kp65(path, ann, i, int(frame), flags))
    for fr in image_frame.values():  # frames with no person still exist
        if isinstance(fr, (int, np.integer)):
            by_frame.setdefault(int(fr), [])
    frames = sorted(by_frame)
    per = [np.stack(by_frame[f]) if by_frame[f] else np.zeros((0, N_KP65, 3)) for f in frames]
    return stack_people(per, frames)
