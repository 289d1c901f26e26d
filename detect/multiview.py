"""Cross-view consistency of 2D keypoints: a keypoint that disagrees with what the other
calibrated views agree on is dropped.

The per-view rules (:mod:`detect.people`) can be fooled where the two people overlap in the
image: a single-person detector then sometimes returns a skeleton mixing both people, or the
partner's body with the left/right swapped. The four calibrated views catch most of it: each
keypoint of each person is triangulated with RANSAC over the views (pycolmap, through
:func:`calib.geometry.triangulate`); when at least ``min_agree`` views agree on a 3D point
(reprojection error <= ``max_error_px``), a view whose observation misses it by more is an
outlier and its confidence is set to 0. With fewer agreeing views nothing is judged.

``min_agree=2`` although two views can agree by chance (rays passing within the threshold):
on the studio bench sequences Grab / Handshake / Hit (every 10th frame) it removed 258 / 227 /
109 observations whose median error was 67 / 52 / 40 px (27 / 12 / 5 of them were within
15 px of the truth), cut the p90 error from 27 / 22 / 17 to 17 / 16 / 15 px and removed the one
identity swap; ``min_agree=3`` removed about half as many and left the swap (in that frame
only two views saw the partner correctly).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detect import constants as K


@dataclass(frozen=True)
class CrossViewOptions:
    """max_error_px : RANSAC inlier threshold (pixels, undistorted image).
    min_agree : views that must agree before the others can be called outliers.
    min_conf : observations below are ignored."""

    max_error_px: float = K.CROSS_VIEW_PX
    min_agree: int = 2
    min_conf: float = K.MIN_CONF


@dataclass(frozen=True)
class CrossView:
    """outlier : (C, ...) bool, observed but missing the point >= min_agree views agree on.
    confirmed : (C, ...) bool, observed and one of those agreeing views.
    xyz : (..., 3) that point (world metres; NaN where fewer views agree), or None."""

    outlier: np.ndarray
    confirmed: np.ndarray
    xyz: np.ndarray | None = None


def cross_view_check(cams, kp: np.ndarray, opts: CrossViewOptions = CrossViewOptions()) -> CrossView:
    """Judge keypoints seen in several views.

    cams : C calib.Camera. kp : (C, ...) + (3,) keypoints (x, y pixels, confidence), e.g.
    (C, F, 2, 65, 3) from the keypoints stage. An observation counts when its confidence
    >= min_conf. See :class:`CrossView`.
    """
    from calib.geometry import TriangulateOptions, triangulate

    kp = np.asarray(kp, dtype=np.float64)
    obs = (kp[..., 2] >= opts.min_conf) & np.all(np.isfinite(kp[..., :2]), axis=-1)
    t = triangulate(cams, kp, TriangulateOptions(ransac=True, max_error_px=opts.max_error_px,
                                                 min_views=opts.min_agree, min_conf=opts.min_conf))
    inl = np.moveaxis(t.inliers, -1, 0)  # (C, ...)
    judged = inl.sum(axis=0) >= opts.min_agree
    xyz = np.where(judged[..., None], t.xyz, np.nan)
    return CrossView(obs & judged[None] & ~inl, obs & judged[None] & inl, xyz)


def cross_view_outliers(cams, kp: np.ndarray, opts: CrossViewOptions = CrossViewOptions()) -> np.ndarray:
    """(C, ...) bool: :attr:`CrossView.outlier` of :func:`cross_view_check`."""
    return cross_view_check(cams, kp, opts).outlier
