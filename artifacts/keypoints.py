"""``Keypoints2D``: the keypoints stage's ``keypoints.npz`` (2D keypoints of both people in every
view; layout in docs/ARCHITECTURE.md, "Keypoints artifact").

Axes: ``C`` cameras (recipe order, ids in ``cameras``), ``F`` detected frames (video frame
indices in ``frames``: with a stride they are not ``arange(F)``), persons ``2`` (0 = the
subject wearing markers, 1 = the partner), ``65`` KP65 keypoints (``formats.skeletons``).
Pixels of the full image; confidence in [0, 1], 0 = missing; a NaN box = none.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import ArtifactError, FieldSpec, TypedArtifact
from formats import skeletons as S

#: Persons along the person axis.
WEARER, PARTNER = 0, 1
#: KP65 blocks.
BODY = slice(0, len(S.BODY23))
HANDS = slice(S.LEFT_HAND.start, S.RIGHT_HAND.stop)
HAND = {"left": S.LEFT_HAND, "right": S.RIGHT_HAND}
#: ``partner_mode`` codes, in code order.
PARTNER_MODES = ("missing", "tracked", "whole_image")

# dtypes the fields are stored as (a value of the same dtype kind is cast on construction).
_DTYPES = {"kp": np.float32, "boxes": np.float32, "hand_boxes": np.float32, "frames": np.int64,
           "partner_mode": np.int8, "conf_raw": np.float32}


@dataclass(frozen=True, eq=False)
class Keypoints2D(TypedArtifact):
    """Both people's 2D keypoints per camera and detected frame.

    kp : (C, F, 2, 65, 3) float32 x, y pixels and confidence (cross-view outliers at 0).
    boxes : (C, F, 2, 4) float32 body crop boxes (x0, y0, x1, y1). hand_boxes : (C, F, 2, 2, 4)
    float32 (person, left/right). frames : (F,) int64 video frame indices, increasing.
    wearer_retry : (C, F) bool, the wearer came from its isolated crop. partner_mode : (C, F)
    int8 (:data:`PARTNER_MODES`). cross_view_outlier : (C, F, 2, 65) bool, dropped by the
    cross-view check (their ``kp`` confidence is 0). conf_raw : (C, F, 2, 65) float32, the
    detector's confidences before that check. cameras : (C,) str camera ids.
    """

    KIND: ClassVar[str] = "keypoints2d"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "keypoints"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("kp", "f", "C F 2 65 3", doc="x, y pixels, confidence"),
        FieldSpec("boxes", "f", "C F 2 4", doc="body crop boxes, NaN = none"),
        FieldSpec("hand_boxes", "f", "C F 2 2 4", doc="hand crop boxes, NaN = none"),
        FieldSpec("frames", "i", "F", doc="video frame indices"),
        FieldSpec("wearer_retry", "b", "C F"),
        FieldSpec("partner_mode", "i", "C F"),
        FieldSpec("cross_view_outlier", "b", "C F 2 65"),
        FieldSpec("conf_raw", "f", "C F 2 65", finite=True),
        FieldSpec("cameras", "U", "C"),
    )

    kp: np.ndarray
    boxes: np.ndarray
    hand_boxes: np.ndarray
    frames: np.ndarray
    wearer_retry: np.ndarray
    partner_mode: np.ndarray
    cross_view_outlier: np.ndarray
    conf_raw: np.ndarray
    cameras: np.ndarray

    def __post_init__(self):
        super().__post_init__()
        for name, dt in _DTYPES.items():
            a = getattr(self, name)
            if a.dtype.kind == np.dtype(dt).kind and a.dtype != dt:
                object.__setattr__(self, name, a.astype(dt))

    # ---------------------------------------------------------------- named slices

    @property
    def n_frames(self) -> int:
        return int(len(self.frames))

    @property
    def camera_ids(self) -> list[str]:
        return [str(c) for c in self.cameras]

    def camera(self, name: str) -> int:
        """Index of camera ``name`` on the C axis (KeyError naming the known ones)."""
        ids = self.camera_ids
        if name not in ids:
            raise KeyError(f"camera {name!r} not in the keypoints (cameras: {ids})")
        return ids.index(name)

    def person(self, person: int) -> np.ndarray:
        """(C, F, 65, 3) keypoints of ``person`` (:data:`WEARER` or :data:`PARTNER`)."""
        return self.kp[:, :, _person(person)]

    def body(self, person: int) -> np.ndarray:
        """(C, F, 23, 3) body keypoints (COCO-WholeBody body + feet order) of ``person``."""
        return self.kp[:, :, _person(person), BODY]

    def hands(self, person: int) -> np.ndarray:
        """(C, F, 42, 3) hand keypoints of ``person``: left hand 21, then right hand 21."""
        return self.kp[:, :, _person(person), HANDS]

    def hand(self, person: int, side: str) -> np.ndarray:
        """(C, F, 21, 3) one hand (``"left"`` / ``"right"``) of ``person``."""
        if side not in HAND:
            raise ValueError(f"hand side: expected 'left' or 'right', got {side!r}")
        return self.kp[:, :, _person(person), HAND[side]]

    # ---------------------------------------------------------------- checks

    def _frame(self, bad: np.ndarray) -> int | None:
        """The video frame of the first True of ``bad`` (C, F, ...)."""
        b = np.asarray(bad).reshape(bad.shape[0], bad.shape[1], -1).any(axis=(0, 2))
        if not b.any():
            return None
        i = int(np.argmax(b))
        return int(self.frames[i])

    def _check(self, file: Path) -> None:
        fr = np.asarray(self.frames)
        if np.any(fr < 0):
            raise ArtifactError(file, "frames", f"negative video frame index {int(fr.min())}")
        if np.any(np.diff(fr) <= 0):
            i = int(np.argmax(np.diff(fr) <= 0))
            raise ArtifactError(file, "frames", f"not increasing: {int(fr[i])} then "
                                f"{int(fr[i + 1])}", int(fr[i + 1]))
        ids = self.camera_ids
        if len(set(ids)) != len(ids) or any(not c for c in ids):
            raise ArtifactError(file, "cameras", f"camera ids must be unique and non-empty: {ids}")
        for name, conf in (("kp", self.kp[..., 2]), ("conf_raw", self.conf_raw)):
            bad = ~(np.isfinite(conf) & (conf >= 0) & (conf <= 1))
            if bad.any():
                raise ArtifactError(file, name, f"confidence outside [0, 1]: e.g. "
                                    f"{float(conf[bad].reshape(-1)[0]):.4g}", self._frame(bad))
        bad = (self.kp[..., 2] > 0) & ~np.all(np.isfinite(self.kp[..., :2]), axis=-1)
        if bad.any():
            raise ArtifactError(file, "kp", "non-finite x, y of a keypoint with confidence > 0",
                                self._frame(bad))
        for name in ("boxes", "hand_boxes"):
            b = np.asarray(getattr(self, name), dtype=np.float64)
            fin = np.isfinite(b)
            bad = fin.any(axis=-1) & ~fin.all(axis=-1)
            if bad.any():
                raise ArtifactError(file, name, "a box partly NaN (a box is 4 numbers or all "
                                    "NaN)", self._frame(bad))
            with np.errstate(invalid="ignore"):
                bad = fin.all(axis=-1) & ((b[..., 2] < b[..., 0]) | (b[..., 3] < b[..., 1]))
            if bad.any():
                raise ArtifactError(file, name, "a box with x1 < x0 or y1 < y0 (expected "
                                    "x0, y0, x1, y1)", self._frame(bad))
        pm = np.asarray(self.partner_mode)
        bad = (pm < 0) | (pm >= len(PARTNER_MODES))
        if bad.any():
            raise ArtifactError(file, "partner_mode", f"code {int(pm[bad][0])} not in 0.."
                                f"{len(PARTNER_MODES) - 1} {PARTNER_MODES}", self._frame(bad))
        want = np.where(self.cross_view_outlier, 0.0, self.conf_raw)
        bad = self.kp[..., 2] != want
        if bad.any():
            raise ArtifactError(file, "kp", "confidence differs from conf_raw with the "
                                "cross_view_outlier observations at 0", self._frame(bad))


def _person(person: int) -> int:
    if person not in (WEARER, PARTNER):
        raise ValueError(f"person: expected {WEARER} (wearer) or {PARTNER} (partner), got {person!r}")
    return person
