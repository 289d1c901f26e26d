"""Scores of detected keypoints against projected ground truth (bench and reports).

Groups of the KP65 layout: ``body`` = the 17 COCO body keypoints (face, arms, legs),
``feet`` = the 6 foot keypoints, ``hands`` = the 42 hand keypoints.
"""
from __future__ import annotations

import warnings

import numpy as np

from detect import constants as K
from detect import layout

GROUPS = {
    "body": np.arange(0, 17),
    "feet": np.arange(17, 23),
    "hands": np.arange(23, 65),
}


def keypoint_errors(kp: np.ndarray, truth_uv: np.ndarray, in_image: np.ndarray | None = None,
                    min_conf: float = K.MIN_CONF) -> np.ndarray:
    """Pixel distance of each detected keypoint to its truth.

    kp : (..., K, 3) detections; truth_uv : (..., K, 2) projected truth; in_image : (..., K)
    bool, truth inside the image (default: finite truth). Returns (..., K) float64, NaN where
    not detected (confidence < min_conf) or the truth is not in the image.
    """
    kp = np.asarray(kp, dtype=np.float64)
    truth_uv = np.asarray(truth_uv, dtype=np.float64)
    ok = (kp[..., 2] >= min_conf) & np.all(np.isfinite(truth_uv), axis=-1)
    if in_image is not None:
        ok &= np.asarray(in_image, dtype=bool)
    d = np.linalg.norm(kp[..., :2] - truth_uv, axis=-1)
    return np.where(ok, d, np.nan)


def group_summary(err: np.ndarray, detected_of: np.ndarray | None = None) -> dict[str, float]:
    """Median error per group and overall (keys ``median_px``, ``median_px_body``, ...).

    err : (..., K) from :func:`keypoint_errors`. detected_of : (..., K) bool, the keypoints
    that could be detected (truth in image); adds ``detected_<group>`` fractions.
    """
    out: dict[str, float] = {}
    e = np.asarray(err, dtype=np.float64)
    allv = e[np.isfinite(e)]
    out["median_px"] = float(np.median(allv)) if allv.size else float("nan")
    out["p90_px"] = float(np.percentile(allv, 90)) if allv.size else float("nan")
    for g, idx in GROUPS.items():
        v = e[..., idx]
        v = v[np.isfinite(v)]
        out[f"median_px_{g}"] = float(np.median(v)) if v.size else float("nan")
        if detected_of is not None:
            can = np.asarray(detected_of, dtype=bool)[..., idx]
            out[f"detected_{g}"] = float(np.isfinite(e[..., idx])[can].mean()) if can.any() else float("nan")
    return out


def _median_dist(kp, tr, ok):
    d = np.linalg.norm(kp[..., :2] - tr, axis=-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.where(ok, d, np.nan), axis=-1)


def _judged(kp, tr, p, min_conf):
    q = 1 - p
    return (kp[:, :, p, :, 2] >= min_conf) & np.all(np.isfinite(tr[:, :, p]), -1) \
        & np.all(np.isfinite(tr[:, :, q]), -1)


def _body_only(kp: np.ndarray, truth_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body keypoints of detections and truth (float64) and the left/right mirror index
    among them."""
    return (np.asarray(kp, dtype=np.float64)[..., layout.BODY, :],
            np.asarray(truth_uv, dtype=np.float64)[..., layout.BODY, :], layout.FLIP[layout.BODY])


#: a person's detection farther than this (median px) from both people's truth is somebody
#: else's (a bystander, an operator), not a swap of the two
OTHER_PX = 100.0


def _distances(kp, tr, flip, p, ok):
    """(own, other): median px of person p's detection to its own and the other person's truth,
    each the better of as labelled and mirrored."""
    own = np.fmin(_median_dist(kp[:, :, p], tr[:, :, p], ok),
                  _median_dist(kp[:, :, p], tr[:, :, p][..., flip, :], ok))
    other = np.fmin(_median_dist(kp[:, :, p], tr[:, :, 1 - p], ok),
                    _median_dist(kp[:, :, p], tr[:, :, 1 - p][..., flip, :], ok))
    return own, other


def _whose(kp, truth_uv, min_conf, min_kp):
    """(judged, own, other), each (C, F, 2): whether each person's detection is judged (at
    least ``min_kp`` confident body keypoints with finite truth for both people) and its
    :func:`_distances` to its own and the other person's truth."""
    kp, tr, flip = _body_only(kp, truth_uv)
    judged, own, other = (np.zeros(kp.shape[:3], bool), np.zeros(kp.shape[:3]),
                          np.zeros(kp.shape[:3]))
    for p in (0, 1):
        ok = _judged(kp, tr, p, min_conf)
        judged[:, :, p] = ok.sum(-1) >= min_kp
        own[:, :, p], other[:, :, p] = _distances(kp, tr, flip, p, ok)
    return judged, own, other


def identity_swaps(kp: np.ndarray, truth_uv: np.ndarray, min_conf: float = K.MIN_CONF,
                   min_kp: int = 4, other_px: float = OTHER_PX) -> np.ndarray:
    """(C, F) bool: in that view and frame a person's body keypoints lie nearer (median) the
    other person's truth than its own truth, read either way round (left/right as labelled,
    or mirrored: a left/right flip of the right person is :func:`lr_flips`, not a swap), and
    within ``other_px`` of it (farther from both, it is somebody else: :func:`somebody_else`).

    kp : (C, F, 2, K, 3); truth_uv : (C, F, 2, K, 2). A person with fewer than ``min_kp``
    confident body keypoints (with finite truth for both people) is not judged.
    """
    judged, own, other = _whose(kp, truth_uv, min_conf, min_kp)
    return np.any(judged & (other < own) & (other <= other_px), axis=-1)


def somebody_else(kp: np.ndarray, truth_uv: np.ndarray, min_conf: float = K.MIN_CONF,
                  min_kp: int = 4, other_px: float = OTHER_PX) -> np.ndarray:
    """(C, F, 2) bool: the person's body keypoints lie farther than ``other_px`` (median) from
    both people's truth, either way round: the detector found somebody else (a bystander in
    the background) in that person's place. Arguments as :func:`identity_swaps`."""
    judged, own, other = _whose(kp, truth_uv, min_conf, min_kp)
    return judged & (np.fmin(own, other) > other_px)


def lr_flips(kp: np.ndarray, truth_uv: np.ndarray, min_conf: float = K.MIN_CONF,
             min_kp: int = 4) -> np.ndarray:
    """(C, F, 2) bool: the person's body keypoints match its own truth clearly better mirrored
    (left and right labels swapped: median error under half that as labelled; in profile views
    both readings fit about as well and nothing is counted), and are neither an identity swap
    nor somebody else."""
    swapped = identity_swaps(kp, truth_uv, min_conf=min_conf, min_kp=min_kp)
    others = somebody_else(kp, truth_uv, min_conf=min_conf, min_kp=min_kp)
    kp, tr, flip = _body_only(kp, truth_uv)
    out = np.zeros(kp.shape[:3], bool)
    for p in (0, 1):
        ok = _judged(kp, tr, p, min_conf)
        d = _median_dist(kp[:, :, p], tr[:, :, p], ok)
        df = _median_dist(kp[:, :, p], tr[:, :, p][..., flip, :], ok)
        out[:, :, p] = (ok.sum(-1) >= min_kp) & (df < 0.5 * d) & ~swapped & ~others[:, :, p]
    return out
