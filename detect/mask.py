"""Hiding a person from a single-person detector.

mediapipe's pose solution finds one person per image. To find the partner in an image where
the marker wearer is also visible we paint the wearer out: a silhouette made of thick capsules
along the wearer's detected bones plus discs at its keypoints and at its projected markers,
filled with the background colour (the median of the image border: plain studio walls, and
close enough on real lab backgrounds for a detector to see "no person" there).

Why a silhouette and not the wearer's whole crop box: in the close-contact actions (hug, grab,
handshake) the partner overlaps the wearer's box; blanking the box would blank the partner.
"""
from __future__ import annotations

import cv2
import numpy as np

from detect import constants as K


def silhouette_mask(
    shape: tuple[int, int],
    kp: np.ndarray,
    edges: np.ndarray,
    radius: float,
    points: np.ndarray | None = None,
    polygons: tuple = (),
    blobs: tuple = (),
    min_conf: float = K.MIN_CONF,
) -> np.ndarray:
    """(H, W) bool mask of a person.

    shape : (H, W). kp : (K, 3) keypoints (x, y px, confidence). edges : (E, 2) int keypoint
    index pairs (bones), drawn as capsules of ``radius`` pixels; every confident keypoint and
    every row of ``points`` (M, 2) (projected markers; NaN rows ignored) gets a disc of
    ``radius``. polygons : index sequences filled when all their keypoints are confident
    (the torso). blobs : ``(indices, radius_px)`` discs at the mean of the confident ones (the
    head around the face keypoints).
    """
    h, w = shape
    m = np.zeros((h, w), np.uint8)
    r = max(int(round(radius)), 1)
    kp = np.asarray(kp, dtype=np.float64)
    ok = kp[:, 2] >= min_conf

    def pt(xy):
        return int(round(xy[0])), int(round(xy[1]))

    for a, b in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        if ok[a] and ok[b]:
            cv2.line(m, pt(kp[a]), pt(kp[b]), 1, thickness=2 * r + 1, lineType=cv2.LINE_8)
    for idx in polygons:
        idx = np.asarray(idx)
        if ok[idx].all():
            cv2.fillPoly(m, [np.round(kp[idx, :2]).astype(np.int32)], 1)
    for idx, rad in blobs:
        idx = np.asarray(idx)
        if ok[idx].any():
            cv2.circle(m, pt(kp[idx][ok[idx], :2].mean(axis=0)), max(int(round(rad)), 1), 1, -1)
    pts = [kp[ok, :2]]
    if points is not None:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        pts.append(p[np.all(np.isfinite(p), axis=1)])
    for x, y in np.concatenate(pts, axis=0):
        if -r <= x < w + r and -r <= y < h + r:
            cv2.circle(m, (int(round(x)), int(round(y))), r, 1, thickness=-1)
    return m.astype(bool)


def border_colour(image: np.ndarray, width: int = 4) -> np.ndarray:
    """(3,) uint8 median colour of the image's outer ``width`` pixels (the background)."""
    img = np.asarray(image)
    border = np.concatenate(
        [img[:width].reshape(-1, 3), img[-width:].reshape(-1, 3),
         img[:, :width].reshape(-1, 3), img[:, -width:].reshape(-1, 3)], axis=0)
    return np.median(border, axis=0).astype(np.uint8)


def paint_out(image: np.ndarray, mask: np.ndarray, colour: np.ndarray | None = None) -> np.ndarray:
    """Copy of ``image`` (H, W, 3) uint8 with ``mask`` (H, W) bool pixels set to ``colour``
    (default: :func:`border_colour`)."""
    col = border_colour(image) if colour is None else np.asarray(colour, np.uint8)
    out = np.array(image, copy=True)
    # cv2.copyTo is ~10x faster than boolean indexing on a 900 x 900 frame.
    h, w = out.shape[:2]
    fill = cv2.merge([np.full((h, w), int(c), np.uint8) for c in col])  # numpy's 3-channel fill is slow
    cv2.copyTo(fill, np.asarray(mask, dtype=np.uint8), out)
    return out
