"""Keypoint layouts by name, and how each maps to the pipeline's canonical KP65. No dependencies.

``KP65``: 23 body keypoints in COCO-WholeBody order, then the left hand (21) and the right hand
(21) in the OpenPose/mediapipe hand order (wrist, thumb1-4, index1-4, middle1-4, ring1-4,
pinky1-4). ``thumb1`` is the thumb's carpometacarpal joint, ``*4`` a fingertip, ``index1`` ...
``pinky1`` the knuckles (MCP).

Each other layout has ``TO_KP65[layout]``: for each of its keypoints, the tuple of KP65 indices
whose mean approximates it (``()`` = no KP65 equivalent), and ``EXACT[layout]``: which of those
are the same anatomical point (the others are approximations, e.g. mediapipe's foot index vs
the big toe, OpenPose's neck as the shoulders' midpoint).
"""
from __future__ import annotations

BODY23 = (
    "nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder", "l_elbow",
    "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle",
    "r_ankle", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel",
)  # fmt: skip
HAND21 = ("wrist",) + tuple(
    f"{f}{i}" for f in ("thumb", "index", "middle", "ring", "pinky") for i in range(1, 5)
)
KP65 = BODY23 + tuple(f"l_hand_{n}" for n in HAND21) + tuple(f"r_hand_{n}" for n in HAND21)
LEFT_HAND = slice(23, 44)
RIGHT_HAND = slice(44, 65)


def _mirror(names: tuple[str, ...]) -> tuple[int, ...]:
    """Index of each name's left/right mirror (``l_*`` <-> ``r_*``; itself when unsided)."""
    idx = {n: i for i, n in enumerate(names)}
    sw = {"l_": "r_", "r_": "l_"}
    return tuple(idx[sw[n[:2]] + n[2:]] if n[:2] in sw else i for i, n in enumerate(names))


#: Left/right mirror of KP65 (``l_*`` <-> ``r_*``, the hand blocks swapped): a detection of a
#: person seen from behind and read as seen from the front has ``kp[KP65_FLIP]`` right.
KP65_FLIP = _mirror(KP65)

H36M17 = (
    "pelvis", "r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle", "spine", "thorax",
    "neck_nose", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
)  # fmt: skip
# CHI3D joints3d_25: 0-16 Human3.6M order; 17/18 right foot, 19/20 left foot, 21/22 left hand,
# 23/24 right hand. We read these 8 as Human3.6M's 32-joint extras: toe base (ball of the foot),
# toe end, thumb, wrist end (the hand's end: middle-finger knuckle). A choice, see body/joints.py.
JOINTS3D_25 = H36M17 + (
    "r_toe_base", "r_toe_end", "l_toe_base", "l_toe_end",
    "l_thumb", "l_wrist_end", "r_thumb", "r_wrist_end",
)  # fmt: skip

MEDIAPIPE_POSE33 = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)  # fmt: skip
OPENPOSE_BODY25 = (
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
)  # fmt: skip
MEDIAPIPE_HAND21 = HAND21  # mediapipe Hands and OpenPose hands share the order

LAYOUTS = {
    "kp65": KP65,
    "h36m17": H36M17,
    "joints3d_25": JOINTS3D_25,
    "mediapipe_pose33": MEDIAPIPE_POSE33,
    "openpose_body25": OPENPOSE_BODY25,
}


def kp65_index(name: str) -> int:
    return KP65.index(name)


def _k(*names: str) -> tuple[int, ...]:
    return tuple(KP65.index(n) for n in names)


_MP = {
    "nose": _k("nose"), "left_eye": _k("l_eye"), "right_eye": _k("r_eye"),
    "left_ear": _k("l_ear"), "right_ear": _k("r_ear"),
    "left_shoulder": _k("l_shoulder"), "right_shoulder": _k("r_shoulder"),
    "left_elbow": _k("l_elbow"), "right_elbow": _k("r_elbow"),
    "left_wrist": _k("l_wrist"), "right_wrist": _k("r_wrist"),
    "left_pinky": _k("l_hand_pinky1"), "right_pinky": _k("r_hand_pinky1"),
    "left_index": _k("l_hand_index1"), "right_index": _k("r_hand_index1"),
    "left_thumb": _k("l_hand_thumb2"), "right_thumb": _k("r_hand_thumb2"),
    "left_hip": _k("l_hip"), "right_hip": _k("r_hip"), "left_knee": _k("l_knee"),
    "right_knee": _k("r_knee"), "left_ankle": _k("l_ankle"), "right_ankle": _k("r_ankle"),
    "left_heel": _k("l_heel"), "right_heel": _k("r_heel"),
    "left_foot_index": _k("l_big_toe"), "right_foot_index": _k("r_big_toe"),
}  # fmt: skip
_MP_APPROX = {"left_pinky", "right_pinky", "left_index", "right_index", "left_thumb",
              "right_thumb", "left_foot_index", "right_foot_index"}
_OP = {
    "Nose": _k("nose"), "Neck": _k("l_shoulder", "r_shoulder"),
    "RShoulder": _k("r_shoulder"), "RElbow": _k("r_elbow"), "RWrist": _k("r_wrist"),
    "LShoulder": _k("l_shoulder"), "LElbow": _k("l_elbow"), "LWrist": _k("l_wrist"),
    "MidHip": _k("l_hip", "r_hip"), "RHip": _k("r_hip"), "RKnee": _k("r_knee"),
    "RAnkle": _k("r_ankle"), "LHip": _k("l_hip"), "LKnee": _k("l_knee"), "LAnkle": _k("l_ankle"),
    "REye": _k("r_eye"), "LEye": _k("l_eye"), "REar": _k("r_ear"), "LEar": _k("l_ear"),
    "LBigToe": _k("l_big_toe"), "LSmallToe": _k("l_small_toe"), "LHeel": _k("l_heel"),
    "RBigToe": _k("r_big_toe"), "RSmallToe": _k("r_small_toe"), "RHeel": _k("r_heel"),
}  # fmt: skip
_OP_APPROX = {"Neck", "MidHip"}
_H36 = {
    "pelvis": _k("l_hip", "r_hip"), "r_hip": _k("r_hip"), "r_knee": _k("r_knee"),
    "r_ankle": _k("r_ankle"), "l_hip": _k("l_hip"), "l_knee": _k("l_knee"),
    "l_ankle": _k("l_ankle"), "spine": (), "thorax": _k("l_shoulder", "r_shoulder"),
    "neck_nose": _k("nose"), "head": (), "l_shoulder": _k("l_shoulder"),
    "l_elbow": _k("l_elbow"), "l_wrist": _k("l_wrist"), "r_shoulder": _k("r_shoulder"),
    "r_elbow": _k("r_elbow"), "r_wrist": _k("r_wrist"),
    "r_toe_base": _k("r_big_toe", "r_small_toe"), "r_toe_end": _k("r_big_toe"),
    "l_toe_base": _k("l_big_toe", "l_small_toe"), "l_toe_end": _k("l_big_toe"),
    "l_thumb": _k("l_hand_thumb4"), "l_wrist_end": _k("l_hand_middle1"),
    "r_thumb": _k("r_hand_thumb4"), "r_wrist_end": _k("r_hand_middle1"),
}  # fmt: skip
# Human3.6M joints are joint centres regressed from a body model; COCO-style hips/shoulders are
# close but not equal, so the H36M map is approximate except for the hand/foot extras.
_H36_EXACT = {"l_thumb", "r_thumb", "l_wrist_end", "r_wrist_end"}

TO_KP65: dict[str, tuple[tuple[int, ...], ...]] = {
    "kp65": tuple((i,) for i in range(len(KP65))),
    "mediapipe_pose33": tuple(_MP.get(n, ()) for n in MEDIAPIPE_POSE33),
    "openpose_body25": tuple(_OP[n] for n in OPENPOSE_BODY25),
    "h36m17": tuple(_H36[n] for n in H36M17),
    "joints3d_25": tuple(_H36[n] for n in JOINTS3D_25),
}
EXACT: dict[str, tuple[bool, ...]] = {
    "kp65": (True,) * len(KP65),
    "mediapipe_pose33": tuple(n in _MP and n not in _MP_APPROX for n in MEDIAPIPE_POSE33),
    "openpose_body25": tuple(n not in _OP_APPROX for n in OPENPOSE_BODY25),
    "h36m17": tuple(n in _H36_EXACT for n in H36M17),
    "joints3d_25": tuple(n in _H36_EXACT for n in JOINTS3D_25),
}
# Index of each layout keypoint in KP65 when it is exactly one KP65 keypoint, else -1.
INDEX_IN_KP65: dict[str, tuple[int, ...]] = {
    lay: tuple(s[0] if len(s) == 1 and ex else -1 for s, ex in zip(src, EXACT[lay], strict=True))
    for lay, src in TO_KP65.items()
}


def kp65_from(points, layout: str):
    """Map keypoints of ``layout`` to KP65 where an exact equivalent exists.

    points: (..., K_layout, D) array-like (e.g. D = 3 for x, y, confidence) -> (..., 65, D)
    numpy array, zeros where the layout has no exact KP65 equivalent."""
    import numpy as np

    p = np.asarray(points)
    out = np.zeros(p.shape[:-2] + (len(KP65), p.shape[-1]), dtype=p.dtype)
    for i, k in enumerate(INDEX_IN_KP65[layout]):
        if k >= 0:
            out[..., k, :] = p[..., i, :]
    return out


def from_kp65(points, layout: str):
    """Approximate ``layout`` keypoints from KP65 ones (means of the listed sources).

    points: (..., 65, D) -> (..., K_layout, D), NaN where there is no source."""
    import numpy as np

    p = np.asarray(points, dtype=float)
    out = np.full(p.shape[:-2] + (len(LAYOUTS[layout]), p.shape[-1]), np.nan)
    for i, src in enumerate(TO_KP65[layout]):
        if src:
            out[..., i, :] = p[..., list(src), :].mean(-2)
    return out
