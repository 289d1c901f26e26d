"""``BodyFit``: a fitted body motion (stage marker_fit's ``fit.npz``; the partner fit writes the
same kind, without the marker fields), with a per-frame ``valid`` mask.

Only valid frames are ground truth. A frame that is not valid carries the code of why in
``invalid_reason`` (names in :data:`INVALID_REASONS`, code = index):

- ``0 fitted``: fitted to its own observations (the only valid code);
- ``1 held_before_first_marker``: before the first frame with enough markers (3) to start the
  fit; the pose is held at the first solution;
- ``2 too_few_markers``: fewer than 3 markers visible; the pose is what the prior and the
  previous frame give (held), not measured.
- ``3 too_few_keypoints``, ``4 held_before_first_keypoints``, ``5 poor_reprojection``,
  ``6 too_few_views``: the partner fit's (``fitting.partner_fit``): too few detections to fit
  (held), before its first fitted frame (held), fitted but its median reprojection too large,
  fitted but seen by fewer views than ``min_valid_views`` (no view left to check the others).

Every later stage honours the mask, and reports say how many frames are not valid and why.

Within a valid frame, a body part that no marker (and no keypoint) observed is not ground truth
either: the optional ``observed (F, J)`` says per frame which joints of ``body_pose`` the
frame's evidence observes (``fitting.marker_graph.observed_joints``; e.g. the arms and head of a
lower-body marker set are never observed). Absent (older fits): every joint of a valid frame
counts as observed. A fit from keypoints also says which keypoints the fitted body agrees with
in two views (``keypoints_observed (F, 65)``): a point of the body at a keypoint is ground truth
only there.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import (
    ArtifactError,
    FieldSpec,
    TypedArtifact,
    check_metres,
    check_range,
    check_rotations,
    first_frame,
)

INVALID_REASONS: tuple[str, ...] = ("fitted", "held_before_first_marker", "too_few_markers",
                                    "too_few_keypoints", "held_before_first_keypoints",
                                    "poor_reprojection", "too_few_views")
REASON_CODE: dict[str, int] = {n: i for i, n in enumerate(INVALID_REASONS)}
MARKER_FIELDS = ("marker_names", "marker_residual_m", "marker_weight", "visible")


@dataclass(frozen=True, eq=False)
class BodyFit(TypedArtifact):
    """One person's fitted motion over F video frames (body contract of ``body.forward``).

    body_pose : (F, J, 3) local axis-angle per joint (zeros on joints not fitted and the root);
    global_orient : (F, 3, 3) rotation about the rest root joint; transl : (F, 3) metres;
    betas : (S,); frames : (F,) video frame indices (increasing);
    valid : (F,) bool, ground truth frames; invalid_reason : (F,) int8 code into
    ``INVALID_REASONS`` (0 exactly where valid).
    Markers (all or none): marker_names (M,); marker_residual_m (F, M) |model - observed|
    metres, NaN where not observed (and in frames held before the first marker);
    marker_weight (F, M) robust weight in [0, 1] (small = treated as an outlier), NaN likewise;
    visible (F, M) bool.
    observed : optional (F, J) bool, the joints the frame's markers / keypoints observe (see
    the module docstring); None = all.
    keypoints_observed : optional (F, 65) bool, a fit from keypoints: the KP65 keypoints the
    fitted body agrees with in at least two views (``fitting.partner_fit.OBSERVED_PX``): a
    point of the body at such a keypoint (an elbow, a knee) is ground truth only where it is
    True, even when ``observed`` holds the joints it hangs on through other keypoints (two
    views that agree on the wrist can leave the elbow free); None = no such restriction.
    """

    KIND: ClassVar[str] = "body_fit"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "fit"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("body_pose", "f", "F J 3", finite=True, doc="radians, axis-angle"),
        FieldSpec("global_orient", "f", "F 3 3", finite=True),
        FieldSpec("transl", "f", "F 3", finite=True, doc="metres"),
        FieldSpec("betas", "f", "S", finite=True),
        FieldSpec("frames", "iu", "F"),
        FieldSpec("valid", "b", "F"),
        FieldSpec("invalid_reason", "iu", "F"),
        FieldSpec("marker_names", "U", "M", optional=True),
        FieldSpec("marker_residual_m", "f", "F M", optional=True, doc="metres, NaN = not seen"),
        FieldSpec("marker_weight", "f", "F M", optional=True),
        FieldSpec("visible", "b", "F M", optional=True),
        FieldSpec("observed", "b", "F J", optional=True, doc="joints observed per frame"),
        FieldSpec("keypoints_observed", "b", "F 65", optional=True,
                  doc="KP65 keypoints the fit agrees with in two views, per frame"),
    )

    body_pose: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    frames: np.ndarray
    valid: np.ndarray
    invalid_reason: np.ndarray
    marker_names: np.ndarray | None = None
    marker_residual_m: np.ndarray | None = None
    marker_weight: np.ndarray | None = None
    visible: np.ndarray | None = None
    observed: np.ndarray | None = None
    keypoints_observed: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def has_markers(self) -> bool:
        return self.marker_names is not None

    def joints_observed(self) -> np.ndarray:
        """(F, J) bool: ``observed`` and the frame valid (all joints where ``observed`` is
        absent)."""
        v = np.asarray(self.valid, bool)[:, None]
        if self.observed is None:
            return np.repeat(v, np.asarray(self.body_pose).shape[1], axis=1)
        return np.asarray(self.observed, bool) & v

    def reasons(self) -> dict[str, int]:
        """Frames per reason code name (every name, ``fitted`` = the valid frames)."""
        codes = np.asarray(self.invalid_reason)
        return {n: int(np.count_nonzero(codes == i)) for i, n in enumerate(INVALID_REASONS)}

    def _check(self, file: Path) -> None:
        check_rotations(self.global_orient, file, "global_orient")
        check_metres(self.transl, file, "transl")
        fr = np.asarray(self.frames)
        if np.any(fr < 0):
            raise ArtifactError(file, "frames", "negative video frame index", first_frame(fr < 0))
        if len(fr) > 1 and np.any(np.diff(fr) <= 0):
            raise ArtifactError(file, "frames", "not increasing",
                                int(np.argmax(np.diff(fr) <= 0)) + 1)
        code = np.asarray(self.invalid_reason)
        unknown = (code < 0) | (code >= len(INVALID_REASONS))
        if unknown.any():
            f = first_frame(unknown)
            raise ArtifactError(file, "invalid_reason", f"unknown code {int(code[f])} (known: "
                                + ", ".join(f"{i} {n}" for i, n in enumerate(INVALID_REASONS))
                                + ")", f)
        bad = np.asarray(self.valid) != (code == 0)
        if bad.any():
            f = first_frame(bad)
            raise ArtifactError(file, "valid", f"is {bool(self.valid[f])} but invalid_reason is "
                                f"{int(code[f])} ({INVALID_REASONS[int(code[f])]}): valid must "
                                "be exactly the frames with reason 0", f)
        present = [n for n in MARKER_FIELDS if getattr(self, n) is not None]
        if present and len(present) != len(MARKER_FIELDS):
            missing = [n for n in MARKER_FIELDS if n not in present]
            raise ArtifactError(file, missing[0], f"missing while {', '.join(present)} "
                                "are present (the marker fields come together)")
        if not present:
            return
        names = [str(n) for n in self.marker_names]
        if len(set(names)) != len(names):
            raise ArtifactError(file, "marker_names", "duplicate names")
        res = np.asarray(self.marker_residual_m, float)
        if np.any(res[np.isfinite(res)] < 0):
            raise ArtifactError(file, "marker_residual_m", "negative distance",
                                first_frame(np.isfinite(res) & (res < 0)))
        check_metres(res[..., None] if res.ndim == 1 else np.nan_to_num(res), file,
                     "marker_residual_m")
        seen_nan = ~np.asarray(self.visible) & np.isfinite(res)
        if seen_nan.any():
            raise ArtifactError(file, "marker_residual_m", "a residual where the marker is not "
                                "visible", first_frame(seen_nan))
        check_range(self.marker_weight, file, "marker_weight", 0.0, 1.0, " (robust weight)")
