"""The SMPL family (SMPL, SMPL+H, SMPL-X): loader of the files the ``smplx`` package reads.

The SMPL-X-schema test asset built from Anny (the licensed files cannot be had here) is made by
``body.smplx_from_anny``, which no pipeline stage imports.

Loader: ``load_smpl_family(path, kind=None)`` (also ``load_model("smplx", path)``); ``path`` a
``.npz`` or ``.pkl`` file, or a folder holding ``SMPLX_NEUTRAL.npz`` & co; default
``$SMPLX_MODEL_PATH``. Reads ``v_template (V,3)``, ``f (F,3)``, ``shapedirs (V,3,S)``,
``posedirs (V,3,9(J-1))``, ``J_regressor (J,V)`` (dense or scipy.sparse), ``weights (V,J)``,
``kintree_table (2,J)``; SMPL-X also ``hands_components{l,r}``/``hands_mean{l,r}``. The kind
comes from J (24 SMPL, 52 SMPL+H, 55 SMPL-X). ``.pkl`` files as distributed hold chumpy
arrays and scipy matrices: they load without chumpy (a stand-in unpickler). A bad file raises
InputError naming the file and the key.

Betas of an SMPL-X model are the shape and expression coefficients concatenated over the S
columns of ``shapedirs`` (smplx's layout: S = 20 -> 10 + 10; S >= 400 -> 300 + rest):
``smplx_betas(model, betas, expression)``. ``body_pose`` is (F, J, 3) over all joints, entry 0
(root) normally 0; ``smplx_pose(...)`` packs smplx's separate arguments.
"""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from body.model import BodyModel, check_arrays
from formats.errors import InputError

SMPL_BODY22 = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)  # fmt: skip
_HAND = tuple(f"{f}{i}" for f in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3))
SMPL_JOINTS = SMPL_BODY22 + ("left_hand", "right_hand")
SMPLH_JOINTS = SMPL_BODY22 + tuple("left_" + h for h in _HAND) + tuple("right_" + h for h in _HAND)
SMPLX_JOINTS = (SMPL_BODY22 + ("jaw", "left_eye_smplhf", "right_eye_smplhf")
                + tuple("left_" + h for h in _HAND) + tuple("right_" + h for h in _HAND))
KIND_BY_JOINTS = {24: ("smpl", SMPL_JOINTS), 52: ("smplh", SMPLH_JOINTS), 55: ("smplx", SMPLX_JOINTS)}
SMPLX_PARENTS = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)  # fmt: skip
REQUIRED = {
    "v_template": "V 3", "f": "F 3", "shapedirs": "V 3 S", "posedirs": "V 3 P",
    "J_regressor": "J V", "weights": "V J", "kintree_table": "2 J",
}  # fmt: skip
FILE_NAMES = ("SMPLX_NEUTRAL", "SMPLX_MALE", "SMPLX_FEMALE", "SMPLH_NEUTRAL", "SMPLH_MALE",
              "SMPLH_FEMALE", "SMPL_NEUTRAL", "SMPL_MALE", "SMPL_FEMALE")

# SMPL-X vertex ids of surface keypoints (public: the smplx package's vertex_ids["smplx"]).
SMPLX_SURFACE_IDS = {
    "nose": 9120, "r_eye": 9929, "l_eye": 9448, "r_ear": 616, "l_ear": 6,
    "l_big_toe": 5770, "l_small_toe": 5780, "l_heel": 8846, "r_big_toe": 8463,
    "r_small_toe": 8474, "r_heel": 8635, "l_hand_thumb4": 5361, "l_hand_index4": 4933,
    "l_hand_middle4": 5058, "l_hand_ring4": 5169, "l_hand_pinky4": 5286,
    "r_hand_thumb4": 8079, "r_hand_index4": 7669, "r_hand_middle4": 7794,
    "r_hand_ring4": 7905, "r_hand_pinky4": 8022,
}  # fmt: skip
SMPLX_NUM_VERTICES = 10475


# ----------------------------------------------------------------------------- reading


class _ChumpyStandIn:
    """Unpickled in place of chumpy objects: keeps the state, whose ``x`` is the array."""

    def __setstate__(self, state):
        self.__dict__.update(state if isinstance(state, dict) else {"x": state})

    def __array__(self, dtype=None):
        a = np.asarray(self.__dict__.get("x"))
        return a if dtype is None else a.astype(dtype)


class _Unpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.startswith("chumpy"):
            return _ChumpyStandIn
        return super().find_class(module, name)


def _to_array(v):
    if sp.issparse(v):
        return v.toarray()
    if isinstance(v, _ChumpyStandIn):
        return np.asarray(v)
    return v


def read_model_file(path: str | Path) -> dict:
    """The raw arrays of a .npz/.pkl model file (chumpy-free; sparse made dense)."""
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=True) as z:
                raw = {k: z[k] for k in z.files}
        elif path.suffix == ".pkl":
            with open(path, "rb") as fh:
                raw = _Unpickler(fh, encoding="latin1").load()
        else:
            raise InputError(path, "-", "expected a .npz or .pkl model file")
    except InputError:
        raise
    except Exception as e:  # corrupt file, wrong format
        raise InputError(path, "-", f"cannot read model file: {e}") from e
    if not isinstance(raw, dict):
        raise InputError(path, "-", f"expected a mapping of arrays, got {type(raw).__name__}")
    out = {}
    for k, v in raw.items():
        v = _to_array(v)
        if isinstance(v, np.ndarray) and v.dtype == object and v.shape == ():
            v = _to_array(v.item())
        out[k] = v
    return out


def resolve_path(path: str | Path | None) -> Path:
    if path is None:
        env = os.environ.get("SMPLX_MODEL_PATH")
        if not env:
            raise InputError("$SMPLX_MODEL_PATH", "-", "no SMPL-family model path given (recipe or env)")
        path = env
    p = Path(path)
    if p.is_dir():
        for n in FILE_NAMES:
            for ext in (".npz", ".pkl"):
                if (p / (n + ext)).exists():
                    return p / (n + ext)
        raise InputError(p, "-", f"no model file ({', '.join(FILE_NAMES)} .npz/.pkl) in this folder")
    if not p.exists():
        raise InputError(p, "-", "model file not found")
    return p


def load_smpl_family(path: str | Path | None = None, kind: str | None = None) -> BodyModel:
    """Load an SMPL / SMPL+H / SMPL-X model file (smplx package schema). See module doc."""
    path = resolve_path(path)
    z = read_model_file(path)
    for k in REQUIRED:
        if k in z:
            try:
                z[k] = np.asarray(z[k], dtype=np.int64 if k in ("f", "kintree_table") else np.float64)
            except (TypeError, ValueError) as e:
                raise InputError(path, k, f"not a numeric array: {e}") from e
    check_arrays(z, REQUIRED, path)
    V = z["v_template"].shape[0]
    J = z["kintree_table"].shape[1]
    if J not in KIND_BY_JOINTS:
        raise InputError(path, "kintree_table", f"{J} joints: expected 24 (SMPL), 52 (SMPL+H) or 55 (SMPL-X)")
    found, names = KIND_BY_JOINTS[J]
    if kind is not None and kind != found:
        raise InputError(path, "kintree_table", f"{J} joints is a {found} model, not {kind}")
    if z["posedirs"].shape[2] != 9 * (J - 1):
        raise InputError(path, "posedirs", f"expected (V, 3, {9 * (J - 1)}), got {z['posedirs'].shape}")
    parents = z["kintree_table"][0].astype(np.int64).copy()
    parents[0] = -1
    if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, J)):
        raise InputError(path, "kintree_table", "each parent must come before its child")
    f = z["f"]
    if f.min() < 0 or f.max() >= V:
        raise InputError(path, "f", f"vertex ids outside [0, {V})")
    S = z["shapedirs"].shape[2]
    if found == "smplx":
        if S == 20:
            ns, ne = 10, 10
        elif S >= 400:
            ns, ne = 300, S - 300
        else:
            raise InputError(path, "shapedirs", f"SMPL-X needs 20 or >= 400 columns (smplx's layout), got {S}")
    else:
        ns, ne = S, 0
    Jr = z["J_regressor"]
    W = z["weights"]
    if np.any(np.abs(W.sum(1) - 1) > 1e-3):
        raise InputError(path, "weights", "rows must sum to 1")
    extras = {"J_regressor": Jr, "kind": found}
    for k in ("hands_componentsl", "hands_componentsr", "hands_meanl", "hands_meanr"):
        if k in z:
            extras[k] = np.asarray(z[k], dtype=float)
    if found == "smplx":
        fit = tuple(i for i, n in enumerate(names) if n not in ("jaw", "left_eye_smplhf", "right_eye_smplhf"))
    else:
        fit = tuple(range(J))
    Wsp = sp.csr_matrix(W)
    Wsp.eliminate_zeros()
    return BodyModel(
        name=found,
        v_template=z["v_template"],
        faces=f,
        shapedirs=z["shapedirs"],
        joint_template=Jr @ z["v_template"],
        joint_shapedirs=np.einsum("jv,vds->jds", Jr, z["shapedirs"]),
        parents=parents,
        joint_names=names,
        weights=Wsp,
        posedirs=z["posedirs"].reshape(-1, 9 * (J - 1)).T.copy(),
        num_shape=ns,
        num_expression=ne,
        fit_joints=fit,
        extras=extras,
        source=str(path),
    )


def smplx_betas(model: BodyModel, betas=None, expression=None) -> np.ndarray:
    """Full betas (B, S) of an SMPL-family model from smplx-style ``betas (B, <=num_shape)`` and
    ``expression (B, <=num_expression)`` (SMPL-X); missing ones are 0."""
    b = np.zeros((1, model.num_betas))
    if betas is not None:
        x = np.atleast_2d(np.asarray(betas, float))
        b = np.repeat(b, x.shape[0], 0) if b.shape[0] != x.shape[0] else b
        b[:, : x.shape[1]] = x
    if expression is not None:
        e = np.atleast_2d(np.asarray(expression, float))
        if b.shape[0] != e.shape[0]:
            b = np.repeat(b, e.shape[0], 0)
        b[:, model.num_shape: model.num_shape + e.shape[1]] = e
    return b


def smplx_pose(body_pose, jaw=None, leye=None, reye=None, left_hand=None, right_hand=None) -> np.ndarray:
    """Our (F, 55, 3) body_pose from smplx's arguments: body_pose (F, 21, 3), jaw/eyes (F, 3),
    hands (F, 15, 3) axis-angle (flat-hand-mean convention). Entry 0 (root) is 0."""
    bp = np.asarray(body_pose, float).reshape(-1, 21, 3)
    F = bp.shape[0]

    def g(x, n):
        return np.zeros((F, n, 3)) if x is None else np.asarray(x, float).reshape(F, n, 3)

    return np.concatenate([np.zeros((F, 1, 3)), bp, g(jaw, 1), g(leye, 1), g(reye, 1),
                           g(left_hand, 15), g(right_hand, 15)], 1)


def smplfamily_points(model: BodyModel) -> dict[str, tuple]:
    """Keypoint definitions (``body.joints``) for SMPL-family models: joint centres from the
    model's joints, surface points from SMPL-X vertex ids (SMPL-X topology only)."""
    if model.name != "smplx":
        raise ValueError(f"keypoint regressors are defined for anny and smplx, not {model.name}")
    P: dict[str, tuple] = {}
    surface = model.num_vertices == SMPLX_NUM_VERTICES
    for k, vid in SMPLX_SURFACE_IDS.items():
        if surface:
            P["kp:" + k] = ("vertices", ([vid], [1.0]))
    fingers = {"thumb": "thumb", "index": "index", "middle": "middle", "ring": "ring", "pinky": "pinky"}
    for s, side in (("l", "left"), ("r", "right")):
        P[f"kp:{s}_shoulder"] = ("head", f"{side}_shoulder")
        P[f"kp:{s}_elbow"] = ("head", f"{side}_elbow")
        P[f"kp:{s}_wrist"] = ("head", f"{side}_wrist")
        P[f"kp:{s}_hip"] = ("head", f"{side}_hip")
        P[f"kp:{s}_knee"] = ("head", f"{side}_knee")
        P[f"kp:{s}_ankle"] = ("head", f"{side}_ankle")
        P[f"kp:{s}_hand_wrist"] = ("head", f"{side}_wrist")
        for f, n in fingers.items():
            for i in (1, 2, 3):
                P[f"kp:{s}_hand_{f}{i}"] = ("head", f"{side}_{n}{i}")
            if not surface:
                P[f"kp:{s}_hand_{f}4"] = ("tip", f"{side}_{n}3")
        for n in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist"):
            P[f"h36:{s}_{n}"] = P[f"kp:{s}_{n}"]
        P[f"h36:{s}_thumb"] = P.get(f"kp:{s}_hand_thumb4", ("tip", f"{side}_thumb3"))
        P[f"h36:{s}_wrist_end"] = ("head", f"{side}_middle1")
        if surface:
            P[f"h36:{s}_toe_base"] = ("mean", (f"kp:{s}_big_toe", f"kp:{s}_small_toe"))
            P[f"h36:{s}_toe_end"] = ("head", f"{side}_foot")
        else:
            P[f"h36:{s}_toe_base"] = ("head", f"{side}_foot")
            P[f"h36:{s}_toe_end"] = ("tip", f"{side}_foot")
    P["h36:pelvis"] = ("head", "pelvis")
    P["h36:spine"] = ("head", "spine2")
    P["h36:thorax"] = ("head", "neck")
    P["h36:neck_nose"] = ("mean", ("a:head", "kp:nose")) if surface else ("head", "head")
    P["a:head"] = ("head", "head")
    P["h36:head"] = ("top", "head")
    return P
