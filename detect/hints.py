"""What the marker wearer's 3D markers tell the detector in each view: where to crop the
body and the hands, and where some keypoints must be (to check that the person found in the
crop is the wearer and not the partner standing in it).

Marker names follow Vicon Plug-in Gait (LSHO, LWRA, ...); a C3D label's subject prefix
("Alice:LSHO") is ignored and matching is case-insensitive. Other marker sets work with
fewer hints: without wrist/finger markers the hand crops come from the detected arm instead.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib import Camera, project, world_to_cam
from detect import constants as K
from detect import layout
from detect.crops import box_from_points, expand_box, hand_box_from_3d, hand_centre_3d

#: (wrist markers, knuckle marker) per side (0 left, 1 right).
PIG_HAND = (
    (("LWRA", "LWRB"), "LFIN"),
    (("RWRA", "RWRB"), "RFIN"),
)

#: Head markers: their mean is the head's centre (~10 cm behind the nose, between the ears).
PIG_HEAD = ("LFHD", "RFHD", "LBHD", "RBHD")

#: KP65 keypoint -> markers whose mean lies near it (a few cm off the joint centre: markers
#: sit on the skin). Used only as a coarse identity check, never as keypoints.
PIG_ANCHORS = {
    "l_shoulder": ("LSHO",), "r_shoulder": ("RSHO",),
    "l_elbow": ("LELB",), "r_elbow": ("RELB",),
    "l_wrist": ("LWRA", "LWRB"), "r_wrist": ("RWRA", "RWRB"),
    "l_hip": ("LASI", "LPSI"), "r_hip": ("RASI", "RPSI"),
    "l_knee": ("LKNE",), "r_knee": ("RKNE",),
    "l_ankle": ("LANK",), "r_ankle": ("RANK",),
    "l_heel": ("LHEE",), "r_heel": ("RHEE",),
    "l_big_toe": ("LTOE",), "r_big_toe": ("RTOE",),
}


def _key(label: str) -> str:
    return label.rsplit(":", 1)[-1].strip().upper()


def _mean_of(markers: np.ndarray, index: dict[str, int], names) -> np.ndarray:
    """(F, 3) mean of the named markers (NaN if any is missing or unknown)."""
    idx = [index.get(n) for n in names]
    if any(i is None for i in idx):
        return np.full((markers.shape[0], 3), np.nan)
    return markers[:, idx].mean(axis=1)


@dataclass(frozen=True)
class WearerHints:
    """Per view and frame, from the markers. Pixels of the full image; NaN = unknown.

    box : (C, F, 4) body crop box (projected-marker box + margin, square).
    hand_boxes : (C, F, 2, 4) hand crop boxes (left, right).
    wrists : (C, F, 2, 2) projected wrist (mean of the wrist markers), left and right.
    anchors : (C, F, 65, 2) where markers place some KP65 keypoints (PIG_ANCHORS).
    markers : (C, F, M, 2) projected markers (for the silhouette mask).
    """

    box: np.ndarray
    hand_boxes: np.ndarray
    wrists: np.ndarray
    anchors: np.ndarray
    markers: np.ndarray

    def view(self, c: int, f: int) -> "WearerHints":
        """The hints of one view and frame (leading axes dropped)."""
        return WearerHints(self.box[c, f], self.hand_boxes[c, f], self.wrists[c, f],
                           self.anchors[c, f], self.markers[c, f])

    def frames(self, sel) -> "WearerHints":
        """The hints of a subset of frames (index or slice on the F axis)."""
        return WearerHints(self.box[:, sel], self.hand_boxes[:, sel], self.wrists[:, sel],
                           self.anchors[:, sel], self.markers[:, sel])


def _project_visible(cam: Camera, X: np.ndarray) -> np.ndarray:
    """project() with points behind the camera or missing set to NaN. X (..., 3) -> (..., 2)."""
    X = np.asarray(X, dtype=np.float64)
    ok = np.all(np.isfinite(X), axis=-1)
    Xs = np.where(ok[..., None], X, 0.0)
    z = world_to_cam(cam, Xs)[..., 2]
    uv = project(cam, Xs)
    uv[~ok | (z <= 0)] = np.nan
    return uv


def head_centre(markers: np.ndarray, labels: list[str]) -> np.ndarray:
    """(F, 3) the wearer's head centre: the mean of the PIG_HEAD markers, or, where some are
    unseen, the mean of the seen ones if there are at least MIN_HEAD_MARKERS of them (within
    ~8 cm of the centre: the markers sit ~10 cm from it; NaN otherwise, and when the marker
    set has none). markers : (F, M, 3) metres, world."""
    markers = np.asarray(markers, dtype=np.float64)
    index = {}
    for i, lab in enumerate(labels):
        index.setdefault(_key(lab), i)
    idx = [index.get(n) for n in PIG_HEAD]
    if any(i is None for i in idx):
        return np.full((markers.shape[0], 3), np.nan)
    H = markers[:, idx]  # (F, 4, 3)
    seen = np.all(np.isfinite(H), axis=-1)
    n = seen.sum(axis=1)
    out = np.where(seen[..., None], H, 0.0).sum(axis=1) / np.maximum(n, 1)[:, None]
    out[n < K.MIN_HEAD_MARKERS] = np.nan
    return out


def wearer_hints(cams: list[Camera], markers: np.ndarray, labels: list[str],
                 body_margin: float = K.BODY_MARGIN) -> WearerHints:
    """Crop boxes and identity anchors of the marker wearer in every view.

    cams : C cameras. markers : (F, M, 3) float, metres, world, NaN = not seen (already
    resampled to the video frames). labels : M marker labels.
    """
    markers = np.asarray(markers, dtype=np.float64)
    f_count, m_count = markers.shape[:2]
    if len(labels) != m_count:
        raise ValueError(f"wearer_hints: {len(labels)} labels for {m_count} markers")
    index = {}
    for i, lab in enumerate(labels):
        index.setdefault(_key(lab), i)
    n_cam = len(cams)
    box = np.full((n_cam, f_count, 4), np.nan)
    hand_boxes = np.full((n_cam, f_count, 2, 4), np.nan)
    wrists = np.full((n_cam, f_count, 2, 2), np.nan)
    anchors = np.full((n_cam, f_count, layout.N, 2), np.nan)
    uv_m = np.full((n_cam, f_count, m_count, 2), np.nan)

    anchor_3d = {layout.IDX[k]: _mean_of(markers, index, names) for k, names in PIG_ANCHORS.items()}
    hand_3d = []
    for wrist_names, fin in PIG_HAND:
        w3 = _mean_of(markers, index, wrist_names)
        f3 = _mean_of(markers, index, (fin,))
        hand_3d.append((w3, hand_centre_3d(w3, f3)))

    for c, cam in enumerate(cams):
        uv = _project_visible(cam, markers)
        uv_m[c] = uv
        tight = box_from_points(uv)
        box[c] = expand_box(tight, body_margin, min_side=K.MIN_BODY_BOX_PX, square=True)
        for k, X in anchor_3d.items():
            anchors[c, :, k] = _project_visible(cam, X)
        focal = float(np.mean(cam.f))
        for s, (w3, h3) in enumerate(hand_3d):
            wrists[c, :, s] = _project_visible(cam, w3)
            ok = np.all(np.isfinite(h3), axis=-1)
            h3s = np.where(ok[:, None], h3, 0.0)
            depth = np.where(ok, world_to_cam(cam, h3s)[:, 2], np.nan)
            hand_boxes[c, :, s] = hand_box_from_3d(_project_visible(cam, h3), depth, focal)
    return WearerHints(box, hand_boxes, wrists, anchors, uv_m)
