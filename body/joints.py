"""Keypoint regressors: ``regressor(model, layout) -> scipy.sparse (K, V + J)``.

A regressor acts on the posed vertices stacked with the posed joints:
``keypoints = regress(R, vertices, joints)``: vertices (F, V, 3), joints (F, J, 3) ->
(F, K, 3), same frame and units (``forward`` gives both). Layouts: ``kp65``, ``h36m17``,
``joints3d_25`` (names in ``formats.skeletons``).

Why joints and not vertices only: a joint centre as a fixed combination of skin vertices
cannot follow Anny's skeleton across shapes (measured: the knee's and spine's rest joints are
not affine in the nearby skin; the best non-negative vertex regressors missed them by 10-50 mm
on random bodies, signed ones were worse once posed), whereas the model's own posed joints
are exact. Surface points (eyes, ears, toes, heels, fingertips) stay vertex-based.

How each point is defined on a model (``points_spec``):

- ``("coco", label)``: Anny's own COCO-WholeBody body-keypoint regressor (anny's data);
- ``("head", bone)``: a joint centre = the posed joint (bone head) itself;
- ``("tip", bone)``: the mean of the bone's most distal skin vertices (fingertips, toe tips);
- ``("top", bone)``: the mean of the topmost vertices of the bone's skin (head top, z-up);
- ``("mean", names)``: the mean of other points.

CHI3D's 8 extra joints3d_25 points (``formats.skeletons``) are read as Human3.6M's toe base (the
ball of the foot: mean of the big- and little-toe joints), toe end (big-toe tip), thumb (thumb
tip) and wrist end (middle-finger knuckle).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from body.model import BodyModel
from formats.skeletons import LAYOUTS

TIP_FRACTION = 0.08  # share of a bone's vertices averaged for a tip
TOP_DEPTH_M = 0.01  # vertices within this of the top count for "top"


def _side(s: str) -> tuple[str, str]:
    return ("l", "L") if s == "l" else ("r", "R")


def anny_points() -> dict[str, tuple]:
    """Point definitions for Anny's rig (bone names of anny 0.6.2)."""
    P: dict[str, tuple] = {}
    coco = {
        "nose": "nose", "l_eye": "left_eye", "r_eye": "right_eye", "l_ear": "left_ear",
        "r_ear": "right_ear", "l_shoulder": "left_shoulder", "r_shoulder": "right_shoulder",
        "l_elbow": "left_elbow", "r_elbow": "right_elbow", "l_wrist": "left_wrist",
        "r_wrist": "right_wrist", "l_hip": "left_hip", "r_hip": "right_hip",
        "l_knee": "left_knee", "r_knee": "right_knee", "l_ankle": "left_ankle",
        "r_ankle": "right_ankle", "l_big_toe": "left_big_toe", "l_small_toe": "left_small_toe",
        "l_heel": "left_heel", "r_big_toe": "right_big_toe", "r_small_toe": "right_small_toe",
        "r_heel": "right_heel",
    }  # fmt: skip
    for k, v in coco.items():
        P["kp:" + k] = ("coco", v)
    fingers = ("thumb", "index", "middle", "ring", "pinky")
    for s in ("l", "r"):
        _, S = _side(s)
        P[f"kp:{s}_hand_wrist"] = ("head", f"wrist.{S}")
        for fi, f in enumerate(fingers, start=1):
            for i in (1, 2, 3):
                P[f"kp:{s}_hand_{f}{i}"] = ("head", f"finger{fi}-{i}.{S}")
            P[f"kp:{s}_hand_{f}4"] = ("tip", f"finger{fi}-3.{S}")
        P[f"h36:{s}_hip"] = ("head", f"upperleg01.{S}")
        P[f"h36:{s}_knee"] = ("head", f"lowerleg01.{S}")
        P[f"h36:{s}_ankle"] = ("head", f"foot.{S}")
        P[f"h36:{s}_shoulder"] = ("head", f"upperarm01.{S}")
        P[f"h36:{s}_elbow"] = ("head", f"lowerarm01.{S}")
        P[f"h36:{s}_wrist"] = ("head", f"wrist.{S}")
        P[f"h36:{s}_toe_base"] = ("mean", (f"a:toe1.{S}", f"a:toe5.{S}"))
        P[f"a:toe1.{S}"] = ("head", f"toe1-1.{S}")
        P[f"a:toe5.{S}"] = ("head", f"toe5-1.{S}")
        P[f"h36:{s}_toe_end"] = ("tip", f"toe1-2.{S}")
        P[f"h36:{s}_thumb"] = ("tip", f"finger1-3.{S}")
        P[f"h36:{s}_wrist_end"] = ("head", f"finger3-1.{S}")
    P["h36:pelvis"] = ("mean", ("h36:l_hip", "h36:r_hip"))
    P["h36:spine"] = ("head", "spine03")
    P["h36:thorax"] = ("head", "neck01")
    P["a:skull"] = ("head", "head")
    P["h36:neck_nose"] = ("mean", ("a:skull", "kp:nose"))
    P["h36:head"] = ("top", "head")
    return P


def layout_keys(layout: str) -> list[str]:
    if layout == "kp65":
        return ["kp:" + n for n in LAYOUTS["kp65"]]
    if layout in ("h36m17", "joints3d_25"):
        return ["h36:" + n for n in LAYOUTS[layout]]
    raise ValueError(f"no regressor for layout {layout!r} (kp65, h36m17, joints3d_25)")


def _tip(model: BodyModel, bone: int) -> tuple[np.ndarray, np.ndarray]:
    W = model.weights.tocsc()
    col = W[:, bone]
    ids = col.indices[col.data >= 0.5]
    p = max(int(model.parents[bone]), 0)
    axis = model.joint_template[bone] - model.joint_template[p]
    axis /= np.linalg.norm(axis)
    proj = (model.v_template[ids] - model.joint_template[bone]) @ axis
    n = max(4, int(round(TIP_FRACTION * len(ids))))
    sel = ids[np.argsort(-proj)[:n]]
    return sel, np.full(len(sel), 1.0 / len(sel))


def _top(model: BodyModel, bone: int) -> tuple[np.ndarray, np.ndarray]:
    W = model.weights.tocsc()
    col = W[:, bone]
    ids = col.indices[col.data >= 0.5]
    z = model.v_template[ids, 2]
    sel = ids[z > z.max() - TOP_DEPTH_M]
    return sel, np.full(len(sel), 1.0 / len(sel))


def points_spec(model: BodyModel) -> dict[str, tuple]:
    if model.name == "anny":
        return anny_points()
    from body.smplfamily import smplfamily_points

    return smplfamily_points(model)


def regressor(model: BodyModel, layout: str) -> sp.csr_matrix:
    """Sparse (K, V + J) keypoint regressor of ``layout`` for ``model`` over the stacked posed
    vertices and joints; rows are non-negative and sum to 1."""
    spec = points_spec(model)
    cache: dict[str, np.ndarray] = {}
    V, J = model.num_vertices, model.num_joints

    def row(key: str) -> np.ndarray:
        if key in cache:
            return cache[key]
        if key not in spec:
            raise ValueError(f"{model.name}: keypoint {key.split(':')[1]!r} is not defined on this "
                             f"mesh ({model.num_vertices} vertices)")
        kind, arg = spec[key]
        r = np.zeros(V + J)
        if kind == "coco":
            labels = [str(s) for s in model.extras["coco_labels"]]
            r[:V] = model.extras["coco_regressor"][labels.index(arg)]
        elif kind == "vertices":
            ids, w = arg
            r[np.asarray(ids)] = w
        elif kind == "mean":
            r = np.mean([row(k) for k in arg], axis=0)
        elif kind == "head":
            r[V + model.joint_index(arg)] = 1.0
        else:
            ids, w = {"tip": _tip, "top": _top}[kind](model, model.joint_index(arg))
            r[ids] = w
        r = r / r.sum()
        cache[key] = r
        return r

    m = sp.csr_matrix(np.stack([row(k) for k in layout_keys(layout)]))
    m.eliminate_zeros()
    return m


def regress(reg: sp.spmatrix, vertices: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Keypoints. reg: (K, V + J); vertices (F, V, 3) and joints (F, J, 3) (or unbatched
    (V, 3), (J, 3)) -> (F, K, 3) (or (K, 3))."""
    x = np.concatenate([np.asarray(vertices, float), np.asarray(joints, float)], -2)
    if x.ndim == 2:
        return np.asarray(reg @ x)
    F, N, _ = x.shape
    out = reg @ x.transpose(1, 0, 2).reshape(N, F * 3)
    return np.asarray(out).reshape(-1, F, 3).transpose(1, 0, 2)


def keypoints(model: BodyModel, out, layout: str) -> np.ndarray:
    """Keypoints of ``layout`` from a ``forward`` output: (F, K, 3), world, metres."""
    return regress(regressor(model, layout), out.vertices, out.joints)
