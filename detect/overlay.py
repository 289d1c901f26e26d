"""QA overlay: both people's keypoints, bones and crop boxes drawn on a frame."""
from __future__ import annotations

import cv2
import numpy as np

from detect import constants as K
from detect import layout

#: RGB per person: marker wearer orange, partner cyan.
PERSON_RGB = ((255, 140, 0), (0, 200, 255))
#: drawn coordinates are clipped to this many pixels (a point far off the image, e.g. projected
#: from a marker metres away, overflows OpenCV's fixed-point drawing otherwise)
DRAW_LIMIT_PX = 100_000


def _pt(xy) -> tuple[int, int]:
    x, y = (float(np.clip(v, -DRAW_LIMIT_PX, DRAW_LIMIT_PX)) for v in xy[:2])
    return int(round(x)), int(round(y))


def _rect(img, box, colour, thickness):
    if np.all(np.isfinite(box)):
        cv2.rectangle(img, _pt(box[:2]), _pt(box[2:]), colour, thickness, cv2.LINE_AA)


def draw_overlay(image: np.ndarray, kp: np.ndarray, boxes: np.ndarray | None = None,
                 hand_boxes: np.ndarray | None = None, min_conf: float = K.MIN_CONF,
                 label: str = "") -> np.ndarray:
    """Copy of ``image`` (H, W, 3) uint8 RGB with the people drawn.

    kp : (P, 65, 3) pixels + confidence (person 0 = marker wearer). boxes : (P, 4) body crops
    (thin), hand_boxes : (P, 2, 4) hand crops (dashed look: thinner). label : text top-left.
    Keypoint discs grow with confidence; bones join keypoints confident at both ends.
    """
    img = np.ascontiguousarray(np.array(image, dtype=np.uint8, copy=True))
    scale = max(img.shape[:2]) / 900.0
    lw = max(1, int(round(2 * scale)))
    for p in range(len(kp)):
        col = PERSON_RGB[p % len(PERSON_RGB)]
        if boxes is not None:
            _rect(img, boxes[p], col, lw)
        if hand_boxes is not None:
            for b in hand_boxes[p]:
                _rect(img, b, col, max(1, lw // 2))
        ok = kp[p, :, 2] >= min_conf
        for a, b in layout.EDGES:
            if ok[a] and ok[b]:
                cv2.line(img, _pt(kp[p, a]), _pt(kp[p, b]), col, lw, cv2.LINE_AA)
        for k in np.nonzero(ok)[0]:
            r = max(1, int(round((1.5 + 2.5 * kp[p, k, 2]) * scale)))
            cv2.circle(img, _pt(kp[p, k]), r, col, -1, cv2.LINE_AA)
    if label:
        cv2.putText(img, label, (8, int(24 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                    (255, 255, 255), lw, cv2.LINE_AA)
    return img
