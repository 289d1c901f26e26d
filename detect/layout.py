"""The KP65 layout as the detect package uses it: index blocks, the mediapipe pose map and
the bones drawn in masks and overlays.

TEMPORARY: body/skeletons.py (the one owner of keypoint layouts) has not landed yet; these
are derived from the names in docs/ARCHITECTURE.md and will be replaced by imports from it.
"""
from __future__ import annotations

import numpy as np

_BODY = (
    "nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder", "l_elbow",
    "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle",
    "r_ankle", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel",
)
_HAND = ("wrist",) + tuple(f"{f}{i}" for f in ("thumb", "index", "middle", "ring", "pinky")
                           for i in range(1, 5))
NAMES = _BODY + tuple("l_hand_" + n for n in _HAND) + tuple("r_hand_" + n for n in _HAND)
IDX = {n: i for i, n in enumerate(NAMES)}
N = len(NAMES)

BODY = slice(0, 23)
HANDS = (slice(23, 44), slice(44, 65))  # left, right
FEET = np.array([IDX[n] for n in ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe",
                                  "r_small_toe", "r_heel")])

_POSE33 = {0: "nose", 2: "l_eye", 5: "r_eye", 7: "l_ear", 8: "r_ear", 11: "l_shoulder",
           12: "r_shoulder", 13: "l_elbow", 14: "r_elbow", 15: "l_wrist", 16: "r_wrist",
           23: "l_hip", 24: "r_hip", 25: "l_knee", 26: "r_knee", 27: "l_ankle",
           28: "r_ankle", 29: "l_heel", 30: "r_heel", 31: "l_big_toe", 32: "r_big_toe"}
POSE33_SRC = np.array(sorted(_POSE33))
POSE33_DST = np.array([IDX[_POSE33[i]] for i in POSE33_SRC])

_BONES = [("l_shoulder", "r_shoulder"), ("l_hip", "r_hip"), ("l_shoulder", "l_hip"),
          ("r_shoulder", "r_hip"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"),
          ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"), ("l_hip", "l_knee"),
          ("l_knee", "l_ankle"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
          ("l_ankle", "l_heel"), ("l_ankle", "l_big_toe"), ("l_ankle", "l_small_toe"),
          ("r_ankle", "r_heel"), ("r_ankle", "r_big_toe"), ("r_ankle", "r_small_toe"),
          ("nose", "l_eye"), ("nose", "r_eye"), ("l_eye", "l_ear"), ("r_eye", "r_ear")]
for _s in ("l_hand_", "r_hand_"):
    for _f in ("thumb", "index", "middle", "ring", "pinky"):
        _chain = [_s + "wrist"] + [f"{_s}{_f}{i}" for i in range(1, 5)]
        _BONES += list(zip(_chain[:-1], _chain[1:], strict=True))
EDGES = np.array([(IDX[a], IDX[b]) for a, b in _BONES], dtype=np.int64)
