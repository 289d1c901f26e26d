"""Crop-box math: boxes around projected points, margins, clipping, and the map from crop
coordinates back to the full image.

A box is ``(x0, y0, x1, y1)`` float pixels of the full image (OpenCV convention: the centre of
pixel column j is x = j). A missing box is all-NaN. Integer crop windows ``(x0, y0, x1, y1)``
select ``image[y0:y1, x0:x1]``.
"""
from __future__ import annotations

import numpy as np

from detect import constants as K


def box_from_points(uv: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Tight box around points.

    uv : (..., N, 2) pixels; valid : (..., N) bool (default: finite points).
    Returns (..., 4) float64 (x0, y0, x1, y1); all-NaN where no point is valid.
    """
    uv = np.asarray(uv, dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=-1)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    big = np.where(ok[..., None], uv, np.inf)
    small = np.where(ok[..., None], uv, -np.inf)
    lo = big.min(axis=-2)
    hi = small.max(axis=-2)
    box = np.concatenate([lo, hi], axis=-1)
    box[~ok.any(axis=-1)] = np.nan
    return box


def expand_box(box: np.ndarray, margin: float, min_side: float = 0.0, square: bool = False) -> np.ndarray:
    """Grow boxes about their centre.

    box : (..., 4) pixels. margin : added on every side as a fraction of the box's larger side.
    min_side : each side at least this long (pixels). square : make both sides the larger one
    (detectors letterbox to a square input anyway; a square crop keeps context on both axes).
    Returns (..., 4) float64; NaN boxes stay NaN.
    """
    box = np.asarray(box, dtype=np.float64)
    c = 0.5 * (box[..., :2] + box[..., 2:])
    size = box[..., 2:] - box[..., :2]
    big = size.max(axis=-1, keepdims=True)
    size = size + 2.0 * margin * big
    if square:
        size = np.broadcast_to(size.max(axis=-1, keepdims=True), size.shape)
    size = np.maximum(size, min_side)
    return np.concatenate([c - 0.5 * size, c + 0.5 * size], axis=-1)


def box_around(centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Square boxes: centre (..., 2) pixels, half-side (...,) pixels -> (..., 4)."""
    centre = np.asarray(centre, dtype=np.float64)
    half = np.asarray(half, dtype=np.float64)[..., None]
    return np.concatenate([centre - half, centre + half], axis=-1)


def crop_window(box: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """Integer window of one box, clipped to the image; None if the box is NaN or the window
    holds fewer than 2 x 2 pixels. Rounds outwards (floor the start, ceil the end)."""
    box = np.asarray(box, dtype=np.float64)
    if box.shape != (4,) or not np.all(np.isfinite(box)):
        return None
    x0 = max(int(np.floor(box[0])), 0)
    y0 = max(int(np.floor(box[1])), 0)
    x1 = min(int(np.ceil(box[2])), width)
    y1 = min(int(np.ceil(box[3])), height)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    return x0, y0, x1, y1


def crop_to_image(xy_norm: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """Map normalised crop coordinates (detector output: x / crop width, y / crop height) to
    full-image pixels. xy_norm : (..., 2) -> (..., 2) float64.

    Detectors of the mediapipe family normalise by the image size with the pixel-centre
    convention of the OpenCV projection (x_norm * W = column), so the map is an affine scale
    plus the window's offset; no half-pixel shift (checked against rendered truth in
    tests/test_detect_mediapipe.py)."""
    x0, y0, x1, y1 = window
    xy = np.asarray(xy_norm, dtype=np.float64)
    return xy * np.array([x1 - x0, y1 - y0], dtype=np.float64) + np.array([x0, y0], dtype=np.float64)


def hand_box_from_arm(elbow: np.ndarray, wrist: np.ndarray, person_height: np.ndarray | float) -> np.ndarray:
    """Square hand box from 2D body keypoints (a person without markers).

    elbow, wrist : (..., 2) pixels. person_height : pixels (height of the person's box).
    The hand centre lies HAND_ALONG_FOREARM x the forearm past the wrist; half-side =
    HAND_BOX_FROM_FOREARM x the forearm length, but at least HAND_BOX_FROM_HEIGHT x the
    person's height (a forearm pointing at the camera looks short) and MIN_HAND_BOX_PX / 2.
    Returns (..., 4).
    """
    elbow = np.asarray(elbow, dtype=np.float64)
    wrist = np.asarray(wrist, dtype=np.float64)
    d = wrist - elbow
    centre = wrist + K.HAND_ALONG_FOREARM * d
    half = np.maximum(K.HAND_BOX_FROM_FOREARM * np.linalg.norm(d, axis=-1),
                      K.HAND_BOX_FROM_HEIGHT * np.asarray(person_height, dtype=np.float64))
    half = np.maximum(half, 0.5 * K.MIN_HAND_BOX_PX)
    return box_around(centre, half)


def hand_centre_3d(wrist: np.ndarray, finger: np.ndarray) -> np.ndarray:
    """Centre of the hand (with fingers) from markers: wrist (..., 3) = mean of the two wrist
    markers, finger (..., 3) = the knuckle (FIN) marker; metres, world. Returns (..., 3)."""
    wrist = np.asarray(wrist, dtype=np.float64)
    finger = np.asarray(finger, dtype=np.float64)
    return wrist + K.HAND_CENTRE_ALONG * (finger - wrist)


def hand_box_from_3d(centre_uv: np.ndarray, depth: np.ndarray, focal: np.ndarray | float) -> np.ndarray:
    """Square hand box from the projected hand centre.

    centre_uv : (..., 2) pixels; depth : (...,) metres along the camera axis; focal : pixels
    (mean of fx, fy), scalar or (...,). Half-side = focal x HAND_RADIUS_M / depth (the image
    of a sphere of HAND_RADIUS_M around the hand), at least MIN_HAND_BOX_PX / 2. Boxes behind
    the camera (depth <= 0) are NaN. Returns (..., 4).
    """
    depth = np.asarray(depth, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.asarray(focal, dtype=np.float64) * K.HAND_RADIUS_M / depth
    half = np.where(depth > 0, np.maximum(half, 0.5 * K.MIN_HAND_BOX_PX), np.nan)
    return box_around(centre_uv, half)
