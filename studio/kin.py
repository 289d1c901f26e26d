"""Kinematics for motion synthesis: a posed person, joint frames, posing helpers and a small
damped least-squares inverse kinematics on ``body.lbs.forward_kinematics`` (joints only: the
mesh is skinned once the motion is decided).

Body frame: the Anny model at ``global_orient = I`` faces ``-y`` with its left on ``+x`` and
z up; :data:`LEFT`, :data:`FWD`, :data:`UP` name those axes. The local rotation ``D_j`` of a
joint acts in its parent's frame, and joint frames are world-aligned at pose 0
(``body.lbs``), so a rotation ``W`` of joint j's subtree about its head, given in the world,
is ``D_j <- G_p^T W G_p D_j`` (G_p: the parent's world rotation).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from body import BodyModel, RestState, rest_state
from body.lbs import forward_kinematics
from body.rotations import rodrigues, rotmat_to_rotvec

LEFT = np.array([1.0, 0.0, 0.0])
FWD = np.array([0.0, -1.0, 0.0])
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Person:
    """A body model with a fixed shape. betas: (S,); rest: its RestState; floor_z: the
    translation z that puts the lowest vertex of pose 0 (standing) on the floor z = 0."""

    model: BodyModel
    betas: np.ndarray
    rest: RestState
    floor_z: float

    @staticmethod
    def make(model: BodyModel, betas: np.ndarray) -> Person:
        rest = rest_state(model, betas)
        return Person(model, np.asarray(betas, float), rest, float(-rest.vertices[0, :, 2].min()))

    def j(self, name: str) -> int:
        return self.model.joint_index(name)

    def fk(self, pose: np.ndarray, R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """pose (B, J, 3), R (B, 3, 3), T (B, 3) -> joints (B, J, 3), world rotations (B, J, 3, 3)."""
        G, t, _ = forward_kinematics(self.model, self.rest, pose, R, T)
        return t, G

    def chain(self, joints) -> np.ndarray:
        """Sorted indices of ``joints`` and all their ancestors (what FK of them needs)."""
        need = set()
        par = self.model.parents
        for j in joints:
            while j >= 0 and j not in need:
                need.add(int(j))
                j = par[j]
        return np.array(sorted(need))

    def fk_chain(self, pose: np.ndarray, R: np.ndarray, T: np.ndarray, chain: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of the joints of ``chain`` only (from :meth:`chain`; parents come
        before children since ``parents[j] < j``): the same equations as
        ``body.lbs.forward_kinematics`` (G_0 = R D_0, t_0 = o_0 + T, G_j = G_p D_j,
        t_j = t_p + G_p o_j). pose (B, J, 3), R (B, 3, 3), T (B, 3). Returns joints (B, J, 3)
        and rotations (B, J, 3, 3), valid on ``chain`` only (zeros elsewhere)."""
        B, J = pose.shape[0], pose.shape[1]
        D = rodrigues(pose[:, chain])
        off = self.rest.offsets[0]
        G = np.zeros((B, J, 3, 3))
        t = np.zeros((B, J, 3))
        par = self.model.parents
        for k, j in enumerate(chain):
            if j == 0:
                G[:, 0] = R @ D[:, k]
                t[:, 0] = off[0] + T
            else:
                p = par[j]
                G[:, j] = G[:, p] @ D[:, k]
                t[:, j] = t[:, p] + G[:, p] @ off[j]
        return t, G

    def rest_joints(self) -> np.ndarray:
        """(J, 3) joints at pose 0, body frame (global orient I, transl 0)."""
        return self.fk(np.zeros((1, self.model.num_joints, 3)), np.eye(3)[None], np.zeros((1, 3)))[0][0]


def yaw(theta: float) -> np.ndarray:
    """(3, 3) rotation about world z by theta radians."""
    return rodrigues(np.array([0.0, 0.0, theta]))


def heading_rotation(direction_xy: np.ndarray) -> np.ndarray:
    """(3, 3) global orientation that turns the body's forward (FWD) to ``direction_xy`` (2,)."""
    d = np.asarray(direction_xy, float)
    return yaw(np.arctan2(d[1], d[0]) - np.arctan2(FWD[1], FWD[0]))


def rotate_about_joint(person: Person, pose: np.ndarray, joint: int, rotvec_world: np.ndarray,
                       R: np.ndarray | None = None) -> np.ndarray:
    """Rotate the subtree of ``joint`` about its head by ``rotvec_world`` (3,) (axis-angle in the
    frame of ``R``, default the body frame). pose: (J, 3) -> new (J, 3)."""
    R = np.eye(3) if R is None else R
    _, G = person.fk(pose[None], R[None], np.zeros((1, 3)))
    p = person.model.parents[joint]
    Gp = G[0, p] if p >= 0 else np.eye(3)
    W = R @ rodrigues(np.asarray(rotvec_world, float)) @ R.T
    D = rodrigues(pose[joint])
    out = pose.copy()
    out[joint] = rotmat_to_rotvec(Gp.T @ W @ Gp @ D)
    return out


# --------------------------------------------------------------------------------------- IK
@dataclass(frozen=True)
class Dof:
    """One joint solved by IK. kind ``"ball"`` (3 unknowns, the rotation vector) or ``"hinge"``
    (1 unknown: angle about ``axis``, (3,) in the joint's local frame, radians within
    ``limits``). weight: how strongly the solution is pulled back to the nominal pose."""

    joint: int
    kind: str = "ball"
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    limits: tuple[float, float] = (-np.pi, np.pi)
    weight: float = 0.05


@dataclass(frozen=True)
class Goal:
    """Put the point ``offset`` (3,) (metres, in the frame of ``joint``; world-aligned at pose 0)
    at ``target`` (3,) world metres. weight: residual weight."""

    joint: int
    offset: tuple[float, float, float]
    target: tuple[float, float, float]
    weight: float = 1.0


def effector(person: Person, pose, R, T, joint: int, offset) -> np.ndarray:
    """World position (B, 3) of a point rigidly attached to a joint frame. pose (B, J, 3)."""
    t, G = person.fk(pose, R, T)
    return t[:, joint] + G[:, joint] @ np.asarray(offset, float)


def _pack(pose: np.ndarray, dofs: list[Dof]) -> np.ndarray:
    x = []
    for d in dofs:
        if d.kind == "hinge":
            x.append([float(pose[d.joint] @ np.asarray(d.axis))])
        else:
            x.append(pose[d.joint])
    return np.concatenate(x)


def _unpack(x: np.ndarray, base: np.ndarray, dofs: list[Dof]) -> np.ndarray:
    """x: (B, n) -> poses (B, J, 3) from base (J, 3)."""
    out = np.repeat(base[None], len(x), 0)
    i = 0
    for d in dofs:
        if d.kind == "hinge":
            out[:, d.joint] = x[:, i:i + 1] * np.asarray(d.axis)[None]
            i += 1
        else:
            out[:, d.joint] = x[:, i:i + 3]
            i += 3
    return out


def _clip(x: np.ndarray, dofs: list[Dof]) -> np.ndarray:
    x = x.copy()
    i = 0
    for d in dofs:
        if d.kind == "hinge":
            x[i] = np.clip(x[i], *d.limits)
            i += 1
        else:
            n = np.linalg.norm(x[i:i + 3])
            if n > d.limits[1]:
                x[i:i + 3] *= d.limits[1] / n
            i += 3
    return x


def solve_ik(person: Person, pose: np.ndarray, R: np.ndarray, T: np.ndarray, goals: list[Goal],
             dofs: list[Dof], nominal: np.ndarray | None = None, iters: int = 12,
             damping: float = 1e-3, tol: float = 1e-4) -> np.ndarray:
    """Damped least squares (Levenberg-Marquardt) on the joints of ``dofs``.

    Minimises ``sum_g w_g^2 |effector_g - target_g|^2 + sum_d w_d^2 |x_d - x_d^nominal|^2``
    with a finite-difference Jacobian (one batched forward-kinematics call per iteration).
    pose: (J, 3) start (also the values of joints not in ``dofs``); R (3, 3), T (3,) the
    global orientation and translation; nominal: (J, 3) pose the regulariser pulls to
    (default: ``pose``). Returns the solved (J, 3) pose. tol: metres of goal residual.
    """
    nominal = pose if nominal is None else nominal
    x = _pack(pose, dofs)
    xn = _pack(nominal, dofs)
    wreg = np.concatenate([[d.weight] * (1 if d.kind == "hinge" else 3) for d in dofs])
    chain = person.chain([g.joint for g in goals] + [d.joint for d in dofs])
    tg = np.array([g.target for g in goals], float)
    wg = np.array([g.weight for g in goals], float)
    n = len(x)
    eps = 1e-5
    lam = damping

    def residual_batch(X):
        P = _unpack(X, pose, dofs)
        B = len(X)
        t, G = person.fk_chain(P, np.broadcast_to(R, (B, 3, 3)), np.broadcast_to(T, (B, 3)), chain)
        e = [(t[:, g.joint] + G[:, g.joint] @ np.asarray(g.offset, float) - tg[i]) * wg[i]
             for i, g in enumerate(goals)]
        rg = np.concatenate(e, axis=1) if e else np.zeros((B, 0))
        return np.concatenate([rg, (X - xn) * wreg], axis=1)

    r = residual_batch(x[None])[0]
    cost = r @ r
    for _ in range(iters):
        X = np.concatenate([x[None], x[None] + eps * np.eye(n)])
        Rb = residual_batch(X)
        J = (Rb[1:] - Rb[0]).T / eps  # (m, n)
        H = J.T @ J
        g = J.T @ Rb[0]
        improved = False
        for _ in range(6):
            dx = -np.linalg.solve(H + lam * (np.diag(np.diag(H)) + 1e-9 * np.eye(n)), g)
            xt = _clip(x + dx, dofs)
            rt = residual_batch(xt[None])[0]
            if rt @ rt < cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        gain = cost - rt @ rt
        x, r, cost = xt, rt, rt @ rt
        lam = max(lam / 10, 1e-7)
        gres = r[: 3 * len(goals)].reshape(-1, 3) / np.maximum(wg[:, None], 1e-12)
        if not len(goals) or np.linalg.norm(gres[:1], axis=1).max() < tol or gain < 1e-3 * cost + 1e-12:
            break
    return _unpack(x[None], pose, dofs)[0]
