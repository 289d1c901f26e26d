"""Choosing people among candidates: the paper's rule for the partner, and the candidate that
is the marker wearer inside its crop.

The paper (section "3D Reconstruction in a Controlled Setup", L_2d): "For the subject not
wearing markers, we run a keypoint predictor on the whole image. For each keypoint type, out of
the several detections, we first drop the ones in close proximity to the keypoint of the
subject wearing markers. From the remaining ones, we select the detection with the highest
confidence." :func:`select_partner` is that rule; it also drops whole candidates that are the
marker wearer found again (most of their keypoints coincide with the wearer's), which the
per-keypoint rule alone would let through for keypoints where the two detections differ.

All arrays are KP65 (K = 65): ``(N, K, 3)`` candidates (x, y pixels, confidence), ``(K, 3)`` one
person; confidence 0 = missing.
"""
from __future__ import annotations

import numpy as np

from detect import constants as K


def near_same_type(cands: np.ndarray, ref: np.ndarray, radius: float, min_conf: float = K.MIN_CONF) -> np.ndarray:
    """(N, K) bool: candidate keypoint k is within ``radius`` pixels of ``ref``'s keypoint k
    (both confident). cands (N, K, 3), ref (K, 3)."""
    cands = np.asarray(cands, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    d = np.linalg.norm(cands[..., :2] - ref[None, :, :2], axis=-1)
    both = (cands[..., 2] >= min_conf) & (ref[None, :, 2] >= min_conf)
    return both & (d < radius)


def is_same_person(
    cands: np.ndarray, ref: np.ndarray, radius: float, frac: float = K.SAME_PERSON_FRAC,
    min_conf: float = K.MIN_CONF,
) -> np.ndarray:
    """(N,) bool: at least ``frac`` of the keypoints confident in both the candidate and ``ref``
    are within ``radius`` of ``ref``'s keypoint of the same type (and at least 3 such)."""
    cands = np.asarray(cands, dtype=np.float64)
    both = (cands[..., 2] >= min_conf) & (np.asarray(ref)[None, :, 2] >= min_conf)
    near = near_same_type(cands, ref, radius, min_conf)
    n_both = both.sum(axis=1)
    return (n_both >= 3) & (near.sum(axis=1) >= frac * np.maximum(n_both, 1))


def select_partner(
    cands: np.ndarray, wearer: np.ndarray, radius: float, min_conf: float = K.MIN_CONF,
    drop_same_person: bool = True, coherent: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's rule, per keypoint type.

    cands : (N, K, 3) candidates (x, y px, confidence), e.g. every person a detector found in
        the whole image. wearer : (K, 3) the marker wearer's keypoints (from its crop).
    radius : pixels; "close proximity" to the wearer's keypoint of the same type.
    drop_same_person : also drop whole candidates that are the wearer found again.
    coherent : a keypoint may come from another candidate than the "primary" one (the most
        confident in total after dropping) only if it lies in the primary's keypoint box grown
        by COHERENT_MARGIN. The per-keypoint rule is there to merge partial detections of the
        partner (a detector splitting one person in two); without this guard it also takes, say,
        a bystander's knee when the partner's knee was dropped for being near the wearer's.
    Returns (partner (K, 3) float32, source (K,) int: index of the candidate each keypoint came
    from, -1 where none survived; those keypoints have confidence 0).
    """
    cands = np.asarray(cands, dtype=np.float64)
    n, nk = cands.shape[:2]
    out = np.zeros((nk, 3), np.float32)
    src = np.full(nk, -1, np.int64)
    if n == 0:
        return out, src
    keep = cands[..., 2] >= min_conf
    keep &= ~near_same_type(cands, wearer, radius, min_conf)
    if drop_same_person:
        keep &= ~is_same_person(cands, wearer, radius, min_conf=min_conf)[:, None]
    if coherent and keep.any():
        primary = int(np.argmax(np.where(keep, cands[..., 2], 0.0).sum(axis=1)))
        pts = cands[primary, keep[primary], :2]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        grow = K.COHERENT_MARGIN * max(float((hi - lo).max()), 1.0)
        inside = np.all((cands[..., :2] >= lo - grow) & (cands[..., :2] <= hi + grow), axis=-1)
        keep &= inside
    conf = np.where(keep, cands[..., 2], -1.0)
    best = conf.argmax(axis=0)
    has = conf[best, np.arange(nk)] >= 0
    src[has] = best[has]
    out[has] = cands[best[has], np.nonzero(has)[0]]
    return out, src


def box_support(cands: np.ndarray, box: np.ndarray, min_conf: float = K.MIN_CONF) -> np.ndarray:
    """(N,) summed confidence of each candidate's keypoints that fall inside ``box`` (4,)."""
    cands = np.asarray(cands, dtype=np.float64)
    x, y, c = cands[..., 0], cands[..., 1], cands[..., 2]
    inside = (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3]) & (c >= min_conf)
    return np.where(inside, c, 0.0).sum(axis=1)


def anchor_error(cands: np.ndarray, anchors: np.ndarray, min_conf: float = K.MIN_CONF) -> np.ndarray:
    """(N,) median pixel distance between each candidate's keypoints and ``anchors`` (K, 2):
    where the markers say those keypoints are (NaN = no anchor). NaN when a candidate shares
    fewer than 3 keypoints with the anchors."""
    cands = np.asarray(cands, dtype=np.float64)
    anchors = np.asarray(anchors, dtype=np.float64)
    ok = (cands[..., 2] >= min_conf) & np.all(np.isfinite(anchors), axis=-1)[None]
    d = np.linalg.norm(cands[..., :2] - anchors[None], axis=-1)
    d = np.where(ok, d, np.nan)
    out = np.full(len(cands), np.nan)
    for i in range(len(cands)):
        if ok[i].sum() >= 3:
            out[i] = np.nanmedian(d[i])
    return out


def pick_hand(
    cands: np.ndarray, side: int, anchor: np.ndarray, max_dist: float, hand_slices: tuple[slice, slice],
    min_conf: float = K.MIN_CONF, mislabel_penalty: float = 0.25,
) -> np.ndarray | None:
    """The hand (21, 3) among hand candidates whose wrist is nearest ``anchor`` (2,) pixels.

    cands : (N, K, 3) hand detections (one hand block filled each). side : 0 left, 1 right
    (the hand being looked for). hand_slices : (left block, right block) of the layout.
    A detection labelled with the other side still counts (handedness classifiers err on
    crops) but its distance is increased by ``mislabel_penalty`` x max_dist. None when no hand
    wrist lies within ``max_dist``.
    """
    cands = np.asarray(cands, dtype=np.float64)
    anchor = np.asarray(anchor, dtype=np.float64)
    best, best_cost = None, np.inf
    if not np.all(np.isfinite(anchor)):
        return None
    for cand in cands:
        for s, sl in enumerate(hand_slices):
            block = cand[sl]
            if block[0, 2] < min_conf:
                continue
            d = float(np.linalg.norm(block[0, :2] - anchor))
            if d > max_dist:
                continue
            cost = d + (mislabel_penalty * max_dist if s != side else 0.0)
            if cost < best_cost:
                best, best_cost = block.copy(), cost
    return None if best is None else best.astype(np.float32)
