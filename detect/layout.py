"""The KP65 layout as the detect package uses it: index blocks, the mediapipe pose map and the
bones drawn in masks and overlays. Names and maps come from ``formats.skeletons`` (their owner).
"""
from __future__ import annotations

import numpy as np

from formats import skeletons as S

NAMES = S.KP65
IDX = {n: i for i, n in enumerate(NAMES)}
N = len(NAMES)

BODY = slice(0, 23)
HANDS = (S.LEFT_HAND, S.RIGHT_HAND)  # left, right

# mediapipe pose -> KP65: the exact correspondences, plus foot_index -> big_toe (the tip of the
# foot between the first two toes, ~1-2 cm from the big toe's tip: close enough for L_2d, and
# otherwise the feet would only have heels). Pose's pinky/index/thumb points are not used as
# hand keypoints: hands come from the hand detector.
_src = [i for i, k in enumerate(S.INDEX_IN_KP65["mediapipe_pose33"]) if k >= 0]
_dst = [S.INDEX_IN_KP65["mediapipe_pose33"][i] for i in _src]
for _n, _k in (("left_foot_index", "l_big_toe"), ("right_foot_index", "r_big_toe")):
    _src.append(S.MEDIAPIPE_POSE33.index(_n))
    _dst.append(IDX[_k])
POSE33_SRC = np.array(_src)
POSE33_DST = np.array(_dst)

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

#: Filled when painting a person out: the torso quadrilateral; the head as a disc around the
#: face keypoints.
TORSO = np.array([IDX[n] for n in ("l_shoulder", "r_shoulder", "r_hip", "l_hip")])
FACE = np.array([IDX[n] for n in ("nose", "l_eye", "r_eye", "l_ear", "r_ear")])

#: Left/right mirror of KP65 (l_* <-> r_*, the hand blocks swapped): formats.skeletons owns it.
FLIP = np.array(S.KP65_FLIP)
