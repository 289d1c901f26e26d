"""Linear blend skinning of the full mesh in numpy (the peer of every skinned point).

The symbolic twin, for a fixed number of surface points whose coefficients are graph
parameters, is ``fitting/skinned.py`` (``SurfacePoints``, on the reduced fit skeleton).

Equations (one formulation for Anny and the SMPL family; ``B`` = frames or 1):

rest state of betas ``b`` (all exactly linear in b except the bind rotations):
    v_c(b)  = v_template + shapedirs b                       rest vertices  (V, 3)
    h(b)    = joint_template + joint_shapedirs b             rest joints    (J, 3)
    A_j(b)  = ref_orient_j @ polar(orient_template_j + orient_shapedirs_j b)^T   (Anny)
            = I                                                                   (SMPL family)
    o_0 = h_0,   o_j = A'_p (h_j - h_p)   (p = parent, A'_0 = I, A'_j = A_j otherwise)

posed frames (SMPL convention for global_orient R and transl T; D_j = rodrigues(body_pose_j)):
    G_0 = R D_0,             t_0 = h_0 + T
    G_j = G_p D_j,           t_j = t_p + G_p o_j           joints = t   (F, J, 3)
skinning, with pose correctives P (SMPL family only; rows of posedirs):
    v' = v_c + P vec(D_1 - I, ..., D_{J-1} - I)
    v  = sum_j w_vj (G_j A_j (v' - h_j) + t_j)

So v_world = R (v_local - h_0) + h_0 + T as in SMPL, and pose 0 is the model's reference pose
(SMPL: the rest mesh; Anny: its reference posture, each bone rotated by A_j about its head).
For Anny this equals anny's ``local-ref`` forward (tests/test_body_anny.py, 1e-6 m).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from body.model import BodyModel
from body.rotations import rodrigues, special_procrustes


@dataclasses.dataclass(frozen=True, eq=False)
class RestState:
    """The shape-dependent part of the forward, computed once per shape.

    vertices: (B, V, 3) rest mesh, metres; joints: (B, J, 3) rest joints (bone heads);
    bind_rot: (B, J, 3, 3) the A_j above, or None (identity); offsets: (B, J, 3) the o_j."""

    vertices: np.ndarray
    joints: np.ndarray
    bind_rot: np.ndarray | None
    offsets: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class BodyOutput:
    """vertices: (F, V, 3), joints: (F, J, 3) posed joints (bone heads), world, metres;
    joint_rot: (F, J, 3, 3) world rotation G_j of each joint frame (world-aligned at pose 0)."""

    vertices: np.ndarray
    joints: np.ndarray
    joint_rot: np.ndarray


def pad_betas(model: BodyModel, betas) -> np.ndarray:
    """betas: (S',) or (B, S') with S' <= model.num_betas -> (B, S) zero-padded float64."""
    b = np.atleast_2d(np.asarray(betas, dtype=float))
    S = model.num_betas
    if b.shape[-1] > S:
        raise ValueError(f"betas: {b.shape[-1]} coefficients for a model with {S}")
    if b.shape[-1] < S:
        b = np.concatenate([b, np.zeros(b.shape[:-1] + (S - b.shape[-1],))], -1)
    return b


def bind_rotations(model: BodyModel, betas: np.ndarray) -> np.ndarray | None:
    """A_j(betas) (B, J, 3, 3) for models with bind-rotation data (Anny), else None."""
    if model.orient_template is None:
        return None
    M = model.orient_template[None] + np.einsum("jxys,bs->bjxy", model.orient_shapedirs, betas)
    return model.ref_orient[None] @ np.swapaxes(special_procrustes(M), -1, -2)


def rest_state(model: BodyModel, betas) -> RestState:
    """Rest mesh, joints, bind rotations and reference offsets for betas (S',) or (B, S')."""
    b = pad_betas(model, betas)
    V, J, S = model.num_vertices, model.num_joints, model.num_betas
    n = int(np.max(np.flatnonzero(np.any(b != 0, axis=0)), initial=-1)) + 1  # skip trailing 0s
    sd = model.shapedirs.reshape(V * 3, S)
    verts = model.v_template[None] + (sd[:, :n] @ b[:, :n].T).T.reshape(-1, V, 3)
    jsd = model.joint_shapedirs.reshape(J * 3, S)
    joints = model.joint_template[None] + (jsd[:, :n] @ b[:, :n].T).T.reshape(-1, J, 3)
    A = bind_rotations(model, b)
    par = model.parents
    diff = joints - joints[:, np.maximum(par, 0)]
    if A is not None:
        Ap = A[:, np.maximum(par, 0)].copy()
        Ap[:, par == 0] = np.eye(3)  # anny: the root's bind rotation does not move its children
        diff = np.einsum("njxy,njy->njx", Ap, diff)
    diff[:, 0] = joints[:, 0]
    return RestState(vertices=verts, joints=joints, bind_rot=A, offsets=diff)


def forward_kinematics(model: BodyModel, rest: RestState, body_pose, global_orient, transl):
    """Posed joint frames. body_pose: (F, J, 3) axis-angle; global_orient: (F, 3, 3);
    transl: (F, 3). Returns (G (F, J, 3, 3) world rotations, t (F, J, 3) joints, D local rots)."""
    pose = np.asarray(body_pose, dtype=float)
    F, J = pose.shape[0], model.num_joints
    if pose.shape[1:] != (J, 3):
        raise ValueError(f"body_pose: expected (F, {J}, 3), got {pose.shape}")
    Rg = np.broadcast_to(np.asarray(global_orient, dtype=float), (F, 3, 3))
    T = np.broadcast_to(np.asarray(transl, dtype=float), (F, 3))
    D = rodrigues(pose)
    off = np.broadcast_to(rest.offsets, (F, J, 3))
    G = np.empty((F, J, 3, 3))
    t = np.empty((F, J, 3))
    G[:, 0] = Rg @ D[:, 0]
    t[:, 0] = off[:, 0] + T
    par = model.parents
    for idx in model.levels:
        p = par[idx]
        G[:, idx] = G[:, p] @ D[:, idx]
        t[:, idx] = t[:, p] + np.einsum("fjab,fjb->fja", G[:, p], off[:, idx])
    return G, t, D


def skin(model: BodyModel, rest: RestState, G, t, D) -> np.ndarray:
    """Skin the full mesh: (F, V, 3) world vertices from the posed frames (see module doc)."""
    F, J = G.shape[:2]
    GA = G if rest.bind_rot is None else G @ rest.bind_rot
    h = np.broadcast_to(rest.joints, (F, J, 3))
    tt = t - np.einsum("fjab,fjb->fja", GA, h)
    T12 = np.concatenate([GA.reshape(F, J, 9), tt], -1)  # (F, J, 12)
    M = (model.weights @ T12.transpose(1, 0, 2).reshape(J, F * 12)).reshape(-1, F, 12)
    M = M.transpose(1, 0, 2)  # (F, V, 12)
    v = np.broadcast_to(rest.vertices, (F,) + rest.vertices.shape[1:])
    if model.posedirs is not None:
        feat = (D[:, 1:] - np.eye(3)).reshape(F, -1)
        v = v + (feat @ model.posedirs).reshape(F, -1, 3)
    return np.einsum("fvab,fvb->fva", M[..., :9].reshape(F, -1, 3, 3), v) + M[..., 9:]


def forward(model: BodyModel, betas, body_pose, global_orient, transl, rest: RestState | None = None) -> BodyOutput:
    """Posed mesh and joints (the Body contract, ARCHITECTURE.md).

    betas: (S',) or (F, S'), S' <= model.num_betas (zero-padded);
    body_pose: (F, J, 3) local axis-angle per joint, radians (entry 0 = root, normally 0);
    global_orient: (F, 3, 3) rotation about the rest root joint; transl: (F, 3) metres.
    rest: a precomputed ``rest_state(model, betas)`` (skips the shape part).
    Returns BodyOutput(vertices (F, V, 3), joints (F, J, 3), joint_rot (F, J, 3, 3)), world, metres."""
    if rest is None:
        if betas is None:
            raise ValueError("forward: give betas or a precomputed rest state")
        rest = rest_state(model, betas)
    G, t, D = forward_kinematics(model, rest, body_pose, global_orient, transl)
    return BodyOutput(vertices=skin(model, rest, G, t, D), joints=t, joint_rot=G)


lbs_np = forward


def posed_at(model: BodyModel, fit, frames, chunk: int = 64) -> tuple[list, list]:
    """A fitted body (``fit``: ``frames``, ``betas``, ``body_pose``, ``global_orient``,
    ``transl``, e.g. an ``artifacts.BodyFit``) posed at video ``frames``: ``(vertices,
    joints)``, two lists with per frame (V, 3) / (J, 3) or None where the fit has no such frame;
    ``chunk`` frames posed at a time (a batch's skinning holds V x 12 floats per frame)."""
    frames = np.asarray(frames)
    wf = np.asarray(fit.frames)
    V: list = [None] * len(frames)
    J: list = [None] * len(frames)
    if not len(wf):
        return V, J
    pos = np.searchsorted(wf, frames).clip(0, len(wf) - 1)
    at = np.flatnonzero(wf[pos] == frames)
    betas = np.asarray(fit.betas, float)
    for s0 in range(0, len(at), chunk):
        sel = at[s0:s0 + chunk]
        i = pos[sel]
        o = forward(model, betas, np.asarray(fit.body_pose)[i], np.asarray(fit.global_orient)[i],
                    np.asarray(fit.transl)[i])
        for k, f in enumerate(sel):
            V[f], J[f] = o.vertices[k], o.joints[k]
    return V, J
