"""Detections a lab computed with its own detector (OpenPose JSON, COCO JSON), behind the same
:class:`detect.base.Detector` interface.

The files hold every person the detector found in each full frame, already in full-image
pixels and converted to KP65 by the readers (``formats/openpose.py``, ``formats/coco.py``).
"Detecting in a box" here means keeping the candidates that have at least
``MIN_IN_BOX`` confident keypoints inside the box; the stage's rules (the marker wearer is the
candidate that matches its markers, the partner by the paper's rule) do the rest. No pixels are
needed, so the stage skips decoding video.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detect import constants as K
from detect import layout
from detect.base import Detections, Kind

#: A candidate counts as "in the box" with at least this many confident keypoints inside it.
MIN_IN_BOX = 3


@dataclass(frozen=True, eq=False)
class PrecomputedDetector:
    """Candidates per camera and frame.

    kp : (C, F, N, 65, 3) float32, every person found (padding rows have confidence 0);
        C in the recipe's camera order, F matching ``frames``.
    frames : (F,) video frame indices the files cover.
    Also its own factory (``build`` returns itself): it is plain data, so it pickles.
    """

    kp: np.ndarray
    frames: tuple[int, ...]
    name: str = "precomputed"
    needs_pixels: bool = False

    def __post_init__(self):
        kp = np.asarray(self.kp, dtype=np.float32)
        if kp.ndim != 5 or kp.shape[3:] != (layout.N, 3) or kp.shape[1] != len(self.frames):
            raise ValueError(f"PrecomputedDetector.kp: expected (C, {len(self.frames)}, N, "
                             f"{layout.N}, 3), got {kp.shape}")
        object.__setattr__(self, "kp", kp)
        object.__setattr__(self, "frames", tuple(int(f) for f in self.frames))
        object.__setattr__(self, "_row", {f: i for i, f in enumerate(self.frames)})

    @classmethod
    def from_frames(cls, per_camera: list) -> "PrecomputedDetector":
        """The detector of one sequence from each camera's detections (C
        :class:`formats.keypoints.KeypointFrames`, recipe camera order, as read by
        ``formats.openpose.read_openpose`` / ``formats.coco.read_coco``): every camera's
        candidates on the union of the frames the files cover (a frame missing from one camera
        has no candidates there; cameras with fewer people are padded with confidence 0)."""
        if not per_camera:
            raise ValueError("PrecomputedDetector.from_frames: no camera")
        frames = np.unique(np.concatenate([np.asarray(k.frames, dtype=np.int64)
                                           for k in per_camera]))
        n = max([k.kp.shape[1] for k in per_camera] + [1])
        kp = np.zeros((len(per_camera), len(frames), n, layout.N, 3), np.float32)
        for c, k in enumerate(per_camera):
            rows = np.searchsorted(frames, np.asarray(k.frames, dtype=np.int64))
            kp[c, rows, :k.kp.shape[1]] = k.kp
        return cls(kp, tuple(int(f) for f in frames))

    def build(self) -> "PrecomputedDetector":
        return self

    def close(self) -> None:
        pass

    def detect(self, image: np.ndarray | None, *, kind: Kind,  # noqa: ARG002 (interface)
               box: np.ndarray | None = None, cam: int = 0, frame: int = 0) -> Detections:
        """Candidates of (cam, frame) with >= MIN_IN_BOX confident keypoints in ``box`` (all
        when None); a frame the files don't cover has none. kind="hands": each candidate's
        hands as separate candidates (one hand block filled each)."""
        i = self._row.get(int(frame))
        if i is None:
            return Detections.empty()
        cands = self.kp[cam, i]
        if kind == "hands":
            parts = []
            for sl in layout.HANDS:
                h = np.zeros_like(cands)
                h[:, sl] = cands[:, sl]
                parts.append(h)
            cands = np.concatenate(parts, axis=0)
        conf = cands[..., 2] >= K.MIN_CONF
        if box is not None:
            b = np.asarray(box, dtype=np.float64)
            if not np.all(np.isfinite(b)):
                return Detections.empty()
            x, y = cands[..., 0], cands[..., 1]
            conf &= (x >= b[0]) & (x <= b[2]) & (y >= b[1]) & (y <= b[3])
        need = MIN_IN_BOX if kind == "body" else 1
        return Detections(cands[conf.sum(axis=1) >= need])
