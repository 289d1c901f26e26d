"""Conversion of a fitted body (Anny by default) to a model of the SMPL family, frame by frame.

Two parts (pure numpy / scipy / libigl; no stage imports):

1. ``register(source, target)``: a surface correspondence between the two models, built once
   per model pair the way CHI3D registered SMPL-X to GHUM. The target template is fitted onto
   the source template (both at betas 0, pose 0, the source's reference posture): first its
   joints onto the source's joints of the same name (``ANNY_TO_SMPLX_ANCHOR`` for Anny), solving
   target pose, translation and shape betas; then a few rounds of ICP (each subsampled target
   vertex to its closest point of the source surface, same unknowns); then a per-vertex
   free-form offset regularised by the mesh Laplacian (non-rigid ICP with decreasing stiffness).
   The result is a :class:`Correspondence`: each target vertex on the source surface (face +
   barycentric coordinates), each source vertex on the registered target surface, and the
   nearest facet of the other mesh at every facet centroid.

2. ``convert_motion(...)``: per frame, the target points are the posed source surface at each
   target vertex's correspondence; Levenberg-Marquardt on pose (body, hands, jaw) and
   translation with the exact LBS Jacobian of ``fitting.skinned.point_jacobian`` (pose
   correctives enter the residual, not the Jacobian), on a subsample of target vertices;
   shape betas once per subject, then frozen: by default (``shape_at_rest``) one static fit
   at the subject's rest posture (pose 0, where the registration was made: betas depend on
   the subject only), else jointly with the poses of ``shape_frames`` frames of the motion. Each frame starts from the
   previous one (the first from the joint-name correspondence). The reported error is every
   target vertex's distance to the posed source SURFACE (libigl point-to-mesh), in mm.

Unknowns of a frame: ``x = [r (3) global rotation vector, T (3), theta (3 (Q-1))]`` over the
fit skeleton (every joint but the eyes), as in ``fitting/skinned.py``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import time
from pathlib import Path

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from body.lbs import forward, rest_state
from body.model import BodyModel
from body.rotations import rodrigues, rotmat_to_rotvec, skew
from fitting.skinned import (
    _fk_np,
    fit_skeleton,
    point_jacobian,
    reduced_offsets,
    subtree,
    vertex_coeffs,
)

REGISTRATION_VERSION = "1"  # part of the correspondence cache key: bump when register() changes

# SMPL-X joint -> the Anny bone whose head it sits at (from body.smplx_from_anny.ANNY_TO_SMPLX;
# copied, that module being a test-asset builder). Joints without an anchor are not matched.
ANNY_TO_SMPLX_ANCHOR: dict[str, str] = {
    "pelvis": "root", "spine1": "spine04", "spine2": "spine03", "spine3": "spine01",
    "neck": "neck01", "head": "head", "left_eye_smplhf": "eye.L", "right_eye_smplhf": "eye.R",
}  # fmt: skip
for _s, _S in (("left", "L"), ("right", "R")):
    ANNY_TO_SMPLX_ANCHOR.update({
        f"{_s}_hip": f"upperleg01.{_S}", f"{_s}_knee": f"lowerleg01.{_S}",
        f"{_s}_ankle": f"foot.{_S}", f"{_s}_collar": f"clavicle.{_S}",
        f"{_s}_shoulder": f"upperarm01.{_S}", f"{_s}_elbow": f"lowerarm01.{_S}",
        f"{_s}_wrist": f"wrist.{_S}",
    })  # fmt: skip
    for _f, _n in (("thumb", 1), ("index", 2), ("middle", 3), ("ring", 4), ("pinky", 5)):
        for _i in (1, 2, 3):
            ANNY_TO_SMPLX_ANCHOR[f"{_s}_{_f}{_i}"] = f"finger{_n}-{_i}.{_S}"

EYE_JOINTS = ("left_eye_smplhf", "right_eye_smplhf")  # not fitted (kept at pose 0)
SUBSAMPLE_RANDOM = 300  # target vertices of the per-frame fit, plus PER_JOINT per joint
PER_JOINT = 6
SUBSAMPLE_SEED = 5
BETA_PRIOR = 1e-6  # ridge of the shape least squares (per person-frame point, m^2 per beta^2)
REG_STIFFNESS = (30.0, 10.0, 3.0, 1.0)  # Laplacian weights of the free-form rounds
REG_ICP_ROUNDS = 6
REG_REJECT_M = 0.05  # ICP pairs farther than this, or with normals > 60 deg apart, are dropped


# ----------------------------------------------------------------------------- correspondence


@dataclasses.dataclass(frozen=True, eq=False)
class Correspondence:
    """The contract's ``correspondence.npz`` (see module doc); ``*_bary`` rows sum to 1."""

    tgt_vert_face: np.ndarray
    tgt_vert_bary: np.ndarray
    src_vert_face: np.ndarray
    src_vert_bary: np.ndarray
    src_face_tgt_face: np.ndarray
    tgt_face_src_face: np.ndarray
    tgt_faces: np.ndarray
    src_faces: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def target_points(self, src_vertices: np.ndarray, vertices=None) -> np.ndarray:
        """Source surface at each target vertex: (..., Vs, 3) -> (..., Vt, 3); at the target
        vertices ``vertices`` only when given: (..., len(vertices), 3)."""
        face, bary = self.tgt_vert_face, self.tgt_vert_bary
        if vertices is not None:
            face, bary = face[vertices], bary[vertices]
        tri = np.asarray(src_vertices)[..., self.src_faces[face], :]  # (..., Vt, 3, 3)
        return np.einsum("...vkx,vk->...vx", tri, bary)

    def save(self, path: Path) -> None:
        """Atomic write (a temporary file in the same folder, then renamed)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
        os.close(fd)
        try:
            with open(tmp, "wb") as fh:
                np.savez(fh, **self.arrays())
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)

    @classmethod
    def load(cls, path: Path) -> Correspondence:
        with np.load(path) as z:
            return cls(**{f.name: z[f.name] for f in dataclasses.fields(cls)})


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def correspondence_key(source_file: Path, target_file: Path) -> str:
    """sha256 of both model files' content and the registration code version."""
    h = hashlib.sha256()
    for p in (source_file, target_file):
        h.update(file_sha256(Path(p)).encode())
    h.update(REGISTRATION_VERSION.encode())
    h.update(hashlib.sha256(Path(__file__).read_bytes()).hexdigest().encode())
    return h.hexdigest()[:32]


def cached_correspondence(source: BodyModel, target: BodyModel, source_file: Path,
                          target_file: Path, cache_dir: Path, log=print):
    """(Correspondence, key, registered-now bool): from ``cache_dir/<key>.npz`` or registered
    now and written there atomically."""
    key = correspondence_key(source_file, target_file)
    path = Path(cache_dir) / f"{key}.npz"
    if path.exists():
        try:
            return Correspondence.load(path), key, False
        except Exception as e:  # a truncated/corrupt cache entry: rebuild it
            log(f"correspondence cache {path} unreadable ({e}): registering again")
    t0 = time.perf_counter()
    corr = register(source, target)
    corr.save(path)
    log(f"registered {target.name} onto {source.name} in {time.perf_counter() - t0:.1f} s "
        f"-> {path}")
    return corr, key, True


# ----------------------------------------------------------------------------- geometry


def closest_on_mesh(points: np.ndarray, V: np.ndarray, F: np.ndarray):
    """(distance (N,), face (N,), barycentric (N, 3), closest point (N, 3)) on mesh V, F."""
    d2, fi, c = igl.point_mesh_squared_distance(np.ascontiguousarray(points, float),
                                                 np.ascontiguousarray(V, float),
                                                 np.ascontiguousarray(F, np.int64))
    fi = np.asarray(fi, np.int64).ravel()
    return np.sqrt(np.maximum(d2, 0)), fi, barycentric(c, V[F[fi]]), c


def barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of points p (N, 3) in triangles tri (N, 3, 3), clipped
    to the triangle and renormalised (p is assumed on or next to its triangle)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bc = np.clip(np.stack([1 - v - w, v, w], 1), 0, 1)
    return bc / np.maximum(bc.sum(1, keepdims=True), 1e-12)


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def uniform_laplacian(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Graph Laplacian I - D^-1 A of a triangle mesh (n vertices)."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n)).tocsr()
    A.data[:] = 1.0
    deg = np.asarray(A.sum(1)).ravel()
    return (sp.eye(n) - sp.diags(1.0 / np.maximum(deg, 1)) @ A).tocsr()


# ----------------------------------------------------------------------------- the target rig


def lm_solve(fun, x, iters: int, lam: float = 1e-3, tol: float = 1e-4):
    """Levenberg-Marquardt: ``fun(x) -> (r (m,), J (m, n))``; returns (x, cost)."""
    r, J = fun(x)
    cost = float(r @ r)
    for _ in range(iters):
        JtJ = J.T @ J
        g = J.T @ r
        diag = np.diag(JtJ).copy() + 1e-9
        while True:
            dx = np.linalg.solve(JtJ + lam * np.diag(diag), -g)
            r2, J2 = fun(x + dx)
            c2 = float(r2 @ r2)
            if c2 < cost:
                lam = max(lam / 3, 1e-7)
                break
            lam *= 4
            if lam > 1e8:
                return x, cost
        done = cost - c2 < tol * cost
        x, r, J, cost = x + dx, r2, J2, c2
        if done:
            break
    return x, cost


class TargetRig:
    """The target model's points as functions of the frame unknowns ``x`` and shape ``betas``.

    ``slots``: rest points given by (weights rows (N, J), rest points linear in betas); the
    positions are exact LBS of the reduced tree plus the pose correctives of the current pose
    (their derivative is left out of the Jacobian)."""

    def __init__(self, model: BodyModel, vertices: np.ndarray, num_betas: int = 10):
        self.model = model
        J = model.num_joints
        fit = [j for j in range(J) if model.joint_names[j] not in EYE_JOINTS]
        self.skel = fit_skeleton(model, fit)
        self.sub_tree = subtree(self.skel)
        self.K = min(num_betas, model.num_shape or model.num_betas)
        self.vertices = np.asarray(vertices, np.int64)
        W = model.weights[self.vertices]
        self._base = self._coeffs(np.zeros(model.num_betas), W)
        self._dirs = []
        for k in range(self.K):
            e = np.zeros(model.num_betas)
            e[k] = 1.0
            u, H = self._coeffs(e, W)
            self._dirs.append((u - self._base[0], H - self._base[1]))
        pd = model.posedirs
        self.posedirs = (None if pd is None else np.ascontiguousarray(
            pd.reshape(pd.shape[0], -1, 3)[:, self.vertices].reshape(pd.shape[0], -1)))
        self.Wq = self._base[1][..., 3]  # (N, Q) skinning weight of each fitted joint
        self.set_betas(np.zeros(self.K))

    def _coeffs(self, betas, W):
        rest = rest_state(self.model, betas)
        u, _ = reduced_offsets(self.model, rest, self.skel)
        H = vertex_coeffs(self.model, rest, self.skel, W, rest.vertices[0][self.vertices])
        return u, H

    def set_betas(self, betas):
        self.betas = np.asarray(betas, float)[: self.K].copy()
        u, H = self._base[0].copy(), self._base[1].copy()
        for b, (du, dH) in zip(self.betas, self._dirs, strict=False):
            u += b * du
            H += b * dH
        self.u, self.H = u, H

    @property
    def n(self) -> int:
        return self.skel.n

    def full_pose(self, x) -> np.ndarray:
        """(J, 3) axis-angle of every model joint (entry 0 zero; non-fitted joints zero)."""
        p = np.zeros((self.model.num_joints, 3))
        p[self.skel.joints[1:]] = np.asarray(x[6:]).reshape(-1, 3)
        return p

    def params(self, x):
        """(global_orient (3, 3), transl (3,), body_pose (J, 3)) in body.forward's convention."""
        return rodrigues(np.asarray(x[:3])), np.asarray(x[3:6]).copy(), self.full_pose(x)

    def x_from(self, R, T, pose) -> np.ndarray:
        return np.concatenate([rotmat_to_rotvec(R), T, pose[self.skel.joints[1:]].ravel()])

    def _slots(self, x):
        H = self.H
        if self.posedirs is not None:
            D = rodrigues(self.full_pose(x)[1:])
            feat = (D - np.eye(3)).reshape(-1)
            dv = (feat @ self.posedirs).reshape(-1, 3)  # rest-frame correctives (N, 3)
            H = H.copy()
            H[..., :3] += self.Wq[..., None] * dv[:, None, :]
        return H

    def positions(self, x) -> np.ndarray:
        pos, _ = point_jacobian(self.skel, self.u, self._slots(x), x, self.sub_tree)
        return pos

    def fit(self, x, targets, weights=None, iters: int = 8, prior=None):
        """LM on x: ``sum w |pos - target|^2`` (+ ``prior (x0, sigma (n,))`` Tikhonov)."""
        w = np.ones(len(targets)) if weights is None else np.asarray(weights, float)
        sw = np.sqrt(w)[:, None, None]

        def fun(xx):
            pos, Jac = point_jacobian(self.skel, self.u, self._slots(xx), xx, self.sub_tree)
            r = ((pos - targets) * sw[..., 0]).ravel()
            Jm = (Jac * sw).reshape(-1, len(xx))
            if prior is not None:
                x0, s = prior
                r = np.concatenate([r, (xx - x0) / s])
                Jm = np.vstack([Jm, np.diag(1.0 / s)])
            return r, Jm

        return lm_solve(fun, np.asarray(x, float), iters)

    def beta_directions(self, x) -> np.ndarray:
        """(K, N, 3) d positions / d betas at x (positions are exactly linear in betas)."""
        G, _ = _fk_np(self.skel, self.u, x)
        x0 = np.array(x, float)
        x0[3:6] = 0.0
        out = np.empty((self.K, len(self.vertices), 3))
        for k, (du, dH) in enumerate(self._dirs):
            _, tk = _fk_np(self.skel, du, x0)  # the translation part is linear in u
            out[k] = np.einsum("qab,nqb->na", G, dH[..., :3]) + np.einsum("qa,nq->na", tk,
                                                                           self.Wq)
        return out

    def fit_betas(self, xs, targets, weights=None, prior: float = BETA_PRIOR) -> np.ndarray:
        """Betas minimising ``sum_f sum_n w |pos_f(betas) - target_f|^2 + prior |betas|^2``."""
        A = np.zeros((self.K, self.K))
        b = np.zeros(self.K)
        for i, (x, tgt) in enumerate(zip(xs, targets, strict=True)):
            w = np.ones(len(tgt)) if weights is None else np.asarray(weights[i])
            D = self.beta_directions(x).reshape(self.K, -1)  # (K, 3N)
            r = (self.positions(x) - tgt).ravel()  # at the current betas
            ww = np.repeat(w, 3)
            A += (D * ww) @ D.T
            b += (D * ww) @ r
        n_pts = sum(len(t) for t in targets)
        A += prior * n_pts * np.eye(self.K)
        b += prior * n_pts * self.betas  # pull toward 0: d(prior |beta|^2)/d step
        step = -np.linalg.solve(A, b)
        return self.betas + step


    def fit_shape(self, xs, targets, iters: int = 10, prior: float = BETA_PRIOR):
        """Joint LM on the frames' unknowns ``xs`` and the shared betas (set on the rig):
        normal equations assembled per frame block (the betas couple them)."""
        xs = [np.asarray(x, float).copy() for x in xs]
        K, n, S = self.K, self.n, len(xs)
        n_pts = sum(len(t) for t in targets)
        mu = prior * n_pts

        def evaluate(xs_, b):
            self.set_betas(b)
            out, cost = [], mu * float(b @ b)
            for x, tgt in zip(xs_, targets, strict=True):
                pos, Jx = point_jacobian(self.skel, self.u, self._slots(x), x, self.sub_tree)
                r = (pos - tgt).ravel()
                Jb = self.beta_directions(x).reshape(K, -1).T
                out.append((r, Jx.reshape(-1, n), Jb))
                cost += float(r @ r)
            return out, cost

        b = self.betas.copy()
        blocks, cost = evaluate(xs, b)
        lam = 1e-3
        for _ in range(iters):
            N = S * n + K
            A = np.zeros((N, N))
            g = np.zeros(N)
            for i, (r, Jx, Jb) in enumerate(blocks):
                sl = slice(i * n, (i + 1) * n)
                A[sl, sl] = Jx.T @ Jx
                A[sl, S * n:] = Jx.T @ Jb
                A[S * n:, sl] = A[sl, S * n:].T
                A[S * n:, S * n:] += Jb.T @ Jb
                g[sl] = Jx.T @ r
                g[S * n:] += Jb.T @ r
            A[S * n:, S * n:] += mu * np.eye(K)
            g[S * n:] += mu * b
            d = np.diag(A).copy() + 1e-9
            while True:
                step = np.linalg.solve(A + lam * np.diag(d), -g)
                xs2 = [x + step[i * n:(i + 1) * n] for i, x in enumerate(xs)]
                b2 = b + step[S * n:]
                blocks2, c2 = evaluate(xs2, b2)
                if c2 < cost:
                    lam = max(lam / 3, 1e-7)
                    break
                lam *= 4
                if lam > 1e8:
                    self.set_betas(b)
                    return xs
            done = cost - c2 < 1e-6 * cost
            xs, b, blocks, cost = xs2, b2, blocks2, c2
            if done:
                break
        self.set_betas(b)
        return xs


def subsample_vertices(model: BodyModel, n_random: int = SUBSAMPLE_RANDOM,
                       per_joint: int = PER_JOINT, seed: int = SUBSAMPLE_SEED) -> np.ndarray:
    """Target vertices of the per-frame fit: the ``per_joint`` vertices most bound to each joint
    (so every finger segment is seen) plus ``n_random`` at random."""
    W = model.weights.tocsc()
    pick = set()
    for j in range(model.num_joints):
        col = W[:, j]
        rows, vals = col.indices, col.data
        if len(rows):
            pick.update(rows[np.argsort(-vals)[:per_joint]].tolist())
    rng = np.random.default_rng(seed)
    pick.update(rng.choice(model.num_vertices, size=min(n_random, model.num_vertices),
                           replace=False).tolist())
    return np.array(sorted(pick), np.int64)


def joint_pairs(source: BodyModel, target: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """(source joint indices, target joint indices) matched by name: identical names first
    (a target converted onto itself), else the Anny anchors of ``ANNY_TO_SMPLX_ANCHOR``."""
    s_names = {n: i for i, n in enumerate(source.joint_names)}
    si, ti = [], []
    for j, n in enumerate(target.joint_names):
        m = n if n in s_names else ANNY_TO_SMPLX_ANCHOR.get(n)
        if m is not None and m in s_names:
            si.append(s_names[m])
            ti.append(j)
    if len(ti) < 4:
        raise ValueError(f"only {len(ti)} joints of {target.name} match {source.name}'s by name")
    return np.array(si), np.array(ti)


class JointRig(TargetRig):
    """The target's joints (``joints``) as slots: same machinery, points = the joints."""

    def __init__(self, model: BodyModel, joints: np.ndarray, num_betas: int = 10):
        self._joints = np.asarray(joints, np.int64)
        self.model = model
        fit = [j for j in range(model.num_joints) if model.joint_names[j] not in EYE_JOINTS]
        self.skel = fit_skeleton(model, fit)
        self.sub_tree = subtree(self.skel)
        self.K = min(num_betas, model.num_shape or model.num_betas)
        self.vertices = self._joints  # only their count matters below
        Wj = sp.csr_matrix((np.ones(len(self._joints)), (np.arange(len(self._joints)),
                                                         self._joints)),
                           shape=(len(self._joints), model.num_joints))
        self._base = self._jcoeffs(np.zeros(model.num_betas), Wj)
        self._dirs = []
        for k in range(self.K):
            e = np.zeros(model.num_betas)
            e[k] = 1.0
            u, H = self._jcoeffs(e, Wj)
            self._dirs.append((u - self._base[0], H - self._base[1]))
        self.posedirs = None
        self.Wq = self._base[1][..., 3]
        self.set_betas(np.zeros(self.K))

    def _jcoeffs(self, betas, W):
        rest = rest_state(self.model, betas)
        u, _ = reduced_offsets(self.model, rest, self.skel)
        return u, vertex_coeffs(self.model, rest, self.skel, W, rest.joints[0][self._joints])


def init_from_joints(rig: TargetRig, jrig: JointRig, src_joints: np.ndarray, x0=None,
                     shape: bool = False, rounds: int = 3) -> np.ndarray:
    """Frame unknowns putting the target's joints on ``src_joints`` (jrig's order): a rigid
    Procrustes start, then LM on the joints (and, ``shape``, betas by least squares)."""
    if x0 is None:
        p0 = jrig.positions(np.zeros(jrig.n))
        mu_a, mu_b = p0.mean(0), src_joints.mean(0)
        U, _, Vt = np.linalg.svd((src_joints - mu_b).T @ (p0 - mu_a))
        R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        x0 = np.zeros(jrig.n)
        x0[:3] = rotmat_to_rotvec(R)
        root = jrig.u[0]
        x0[3:6] = mu_b - R @ (mu_a - root) - root
    x = x0
    sig = np.full(jrig.n, 3.0)  # weak pose prior: joints alone leave twists free
    sig[:6] = 1e3
    for _ in range(rounds if shape else 1):
        x, _ = jrig.fit(x, src_joints, iters=15, prior=(np.zeros(jrig.n), sig))
        if shape:
            b = jrig.fit_betas([x], [src_joints], prior=1e-3)
            jrig.set_betas(b)
            rig.set_betas(b)
    return x


# ----------------------------------------------------------------------------- registration


def register(source: BodyModel, target: BodyModel) -> Correspondence:
    """Register the target template onto the source template (module doc, part 1)."""
    src = forward(source, np.zeros(source.num_betas), np.zeros((1, source.num_joints, 3)),
                  np.eye(3)[None], np.zeros((1, 3)))
    Vs, Fs = src.vertices[0], np.asarray(source.faces, np.int64)
    Ft = np.asarray(target.faces, np.int64)
    ns = vertex_normals(Vs, Fs)
    si, ti = joint_pairs(source, target)
    rig = TargetRig(target, subsample_vertices(target))
    jrig = JointRig(target, ti)
    x = init_from_joints(rig, jrig, src.joints[0][si], shape=True)
    # ICP on pose, translation and betas (subsample)
    for _ in range(REG_ICP_ROUNDS):
        pos = rig.positions(x)
        d, fi, bc, c = closest_on_mesh(pos, Vs, Fs)
        nt = vertex_normals(*_posed_target(target, rig, x))[rig.vertices]
        nsrc = np.einsum("nk,nkx->nx", bc, ns[Fs[fi]])
        w = ((d < REG_REJECT_M) & ((nt * nsrc).sum(1) > 0.5)).astype(float)
        x, _ = rig.fit(x, c, w, iters=6)
        rig.set_betas(rig.fit_betas([x], [c], [w], prior=1e-5))
    Vt, _ = _posed_target(target, rig, x)
    # free-form offsets, Laplacian-regularised, decreasing stiffness
    L = uniform_laplacian(Ft, len(Vt))
    LtL = (L.T @ L).tocsc()
    off = np.zeros_like(Vt)
    for alpha in REG_STIFFNESS:
        for _ in range(2):
            cur = Vt + off
            d, fi, bc, c = closest_on_mesh(cur, Vs, Fs)
            nsrc = np.einsum("nk,nkx->nx", bc, ns[Fs[fi]])
            w = ((d < REG_REJECT_M) & ((vertex_normals(cur, Ft) * nsrc).sum(1) > 0.5))
            Wd = sp.diags(w.astype(float) + 1e-6)
            A = (Wd + alpha * LtL).tocsc()
            rhs = Wd @ (c - Vt)
            solve = spla.factorized(A)
            off = np.stack([solve(rhs[:, k]) for k in range(3)], 1)
    reg = Vt + off
    _, tvf, tvb, _ = closest_on_mesh(reg, Vs, Fs)
    _, svf, svb, _ = closest_on_mesh(Vs, reg, Ft)
    _, sft, _, _ = closest_on_mesh(Vs[Fs].mean(1), reg, Ft)
    _, tfs, _, _ = closest_on_mesh(reg[Ft].mean(1), Vs, Fs)
    return Correspondence(tgt_vert_face=tvf, tgt_vert_bary=tvb, src_vert_face=svf,
                          src_vert_bary=svb, src_face_tgt_face=sft, tgt_face_src_face=tfs,
                          tgt_faces=Ft, src_faces=Fs)


def _posed_target(target: BodyModel, rig: TargetRig, x):
    R, T, pose = rig.params(x)
    b = np.zeros(target.num_betas)
    b[: rig.K] = rig.betas
    out = forward(target, b, pose[None], R[None], T[None])
    return out.vertices[0], np.asarray(target.faces, np.int64)


# ----------------------------------------------------------------------------- per-frame fit


@dataclasses.dataclass
class PersonConversion:
    """One person's converted motion (F frames) in body.forward's convention of the target."""

    global_orient: np.ndarray  # (F, 3, 3)
    transl: np.ndarray  # (F, 3)
    body_pose: np.ndarray  # (F, J, 3) axis-angle over all target joints
    betas: np.ndarray  # (K,)
    v2s_mean_mm: np.ndarray  # (F,)
    v2s_median_mm: np.ndarray
    v2s_p95_mm: np.ndarray
    v2s_max_mm: np.ndarray
    cpu_s: float
    restarts: int = 0  # kept for the report's layout: frames are fitted independently now


ITERS = 2
SHAPE_ITERS = 6
#: target vertices whose distance to the source surface is measured each frame (a fixed random
#: sample: the per-frame mean / median / p95 of 2,000 of the 10,604 stand-in vertices are within
#: a few percent of the whole mesh's; the max is the sample's)
V2S_POINTS = 2000
V2S_SEED = 11
FRAME_BLOCK = 32  # frames fitted together (memory: the Gram matrices are (block, 162, 162))


@dataclasses.dataclass(frozen=True)
class RestSolution:
    """The target fitted at the source template's rest posture (source betas 0): the start of
    every subject's rest fit. ``G (Q, 3, 3)`` global rotations of the fitted joints, ``t0 (3,)``
    root position, ``betas (K,)``."""

    G: np.ndarray
    t0: np.ndarray
    betas: np.ndarray


def template_rest(source: BodyModel, target: BodyModel, corr: Correspondence) -> RestSolution:
    """The target on the source template at rest: joint-name start, then the joint LM on pose
    and betas of :class:`TargetRig` (slow, once per model pair: see :func:`cached_rest`)."""
    rig = TargetRig(target, subsample_vertices(target))
    out = forward(source, np.zeros(source.num_betas), np.zeros((1, source.num_joints, 3)),
                  np.eye(3)[None], np.zeros((1, 3)))
    si, ti = joint_pairs(source, target)
    jrig = JointRig(target, ti)
    x = init_from_joints(rig, jrig, out.joints[0][si], shape=True)
    xs = rig.fit_shape([x], [corr.target_points(out.vertices[0])[rig.vertices]],
                       iters=SHAPE_ITERS + 2)
    G, t = _fk_np(rig.skel, rig.u, xs[0])
    return RestSolution(G=G, t0=t[0].copy(), betas=rig.betas.copy())


def cached_rest(source, target, corr, key: str, cache_dir: Path) -> RestSolution:
    """:func:`template_rest` from ``cache_dir/<key>.rest.npz`` (the correspondence's key), else
    computed now and written there atomically."""
    path = Path(cache_dir) / f"{key}.rest.npz"
    if path.exists():
        try:
            with np.load(path) as z:
                return RestSolution(G=z["G"], t0=z["t0"], betas=z["betas"])
        except Exception:  # a truncated cache entry: compute it again
            pass
    rs = template_rest(source, target, corr)
    _save_rest(rs, path)
    return rs


def subject_rest(source: BodyModel, corr: Correspondence, rig: GlobalRig, betas,
                 rest: RestSolution) -> RestSolution:
    """The target fitted at the subject's rest posture (source ``betas``, pose 0): LM on the
    global rotations, the root and the betas jointly, from the template's ``rest``."""
    out = forward(source, betas, np.zeros((1, source.num_joints, 3)), np.eye(3)[None],
                  np.zeros((1, 3)))
    tg = corr.target_points(out.vertices)[:, rig.vertices]
    rig.set_betas(rest.betas)
    G = rest.G[None].copy()
    t0 = best_t0(rig, G, tg, rig.correctives(G))
    G, t0, _ = rig.fit_pose(G, t0, tg, iters=SHAPE_ITERS, shape_prior=BETA_PRIOR)
    return RestSolution(G=G[0], t0=t0[0], betas=rig.betas.copy())


def cached_subject_rest(source, corr, rig, betas, rest: RestSolution, key: str, cache_dir: Path) -> tuple[RestSolution, bool]:
    """(:func:`subject_rest`, computed-now bool) from ``cache_dir/<key>.subject-<h>.npz``
    (``h``: the hash of the subject's betas and of the template's rest), else computed now and
    written there atomically. Betas depend on the subject only: once per subject."""
    h = hashlib.sha256(np.ascontiguousarray(betas, float).tobytes())
    for a in (rest.G, rest.t0, rest.betas):
        h.update(np.ascontiguousarray(a, float).tobytes())
    path = Path(cache_dir) / f"{key}.subject-{h.hexdigest()[:16]}.npz"
    if path.exists():
        try:
            with np.load(path) as z:
                return RestSolution(G=z["G"], t0=z["t0"], betas=z["betas"]), False
        except Exception:  # a truncated cache entry: compute it again
            pass
    rs = subject_rest(source, corr, rig, betas, rest)
    _save_rest(rs, path)
    return rs, True


def _save_rest(rs: RestSolution, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
    os.close(fd)
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, G=rs.G, t0=rs.t0, betas=rs.betas)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def anchor_joints(source: BodyModel, target: BodyModel, rig) -> np.ndarray:
    """(Q,) the source joint each fitted target joint turns with (``joint_pairs``), -1: none."""
    si, ti = joint_pairs(source, target)
    anchors = -np.ones(rig.Q, np.int64)
    pos = {int(j): i for i, j in enumerate(rig.skel.joints)}
    for s_, t_ in zip(si, ti, strict=True):
        if int(t_) in pos:
            anchors[pos[int(t_)]] = s_
    return anchors


def v2s_vertices(model: BodyModel, n: int = V2S_POINTS, seed: int = V2S_SEED) -> np.ndarray:
    """The target vertices the v2s figures are measured on (all when ``n`` is 0 or >= V)."""
    V = model.num_vertices
    if not n or n >= V:
        return np.arange(V)
    return np.sort(np.random.default_rng(seed).choice(V, size=n, replace=False))


_REST_MEMO: list = []  # [(source model, betas bytes, rest_state, forward at rest)], newest last
_REST_MEMO_SIZE = 4


def _source_rest(source: BodyModel, betas):
    """(``rest_state(source, betas)``, ``forward`` of it at pose 0): a subject's shape part,
    computed once per (model object, betas) in a process (a subject is in many sequences).
    The memo holds the model itself, so an entry can't match another model at a reused id."""
    b = np.ascontiguousarray(betas, float).tobytes()
    for m in _REST_MEMO:
        if m[0] is source and m[1] == b:
            return m[2], m[3]
    rest = rest_state(source, betas)
    at0 = forward(source, None, np.zeros((1, source.num_joints, 3)), np.eye(3)[None],
                  np.zeros((1, 3)), rest=rest)
    _REST_MEMO.append((source, b, rest, at0))
    del _REST_MEMO[:-_REST_MEMO_SIZE]
    return rest, at0


def convert_motion(source: BodyModel, target: BodyModel, corr: Correspondence, betas,
                   body_pose, global_orient, transl, iters: int = ITERS, progress=None,
                   rig=None, fit_shape: bool = True, rest: RestSolution | None = None,
                   adjacency: np.ndarray | None = None, eval_rig=None,
                   subject: RestSolution | None = None) -> PersonConversion:
    """Convert one person's source motion (body.forward arguments of ``source``: betas (S,),
    body_pose (F, Js, 3), global_orient (F, 3, 3), transl (F, 3)) to ``target``.

    Betas once per subject, at its rest posture (pose 0, where the registration was made):
    ``subject`` (:func:`subject_rest`, computed here when not given; ``fit_shape=False``: the
    template's ``rest`` as it is).
    Then every frame on its own, all frames batched: each target joint starts turned as its
    source anchor joint turned from rest (:func:`initial_rotations`), then ``iters`` LM
    iterations on the global rotations and the root. ``v2s``: every target vertex's distance to
    the posed source surface near its correspondence (:func:`surface_distance`), mm, over the
    vertices of ``eval_rig`` (default :func:`v2s_vertices`)."""
    t_cpu = time.process_time()
    body_pose = np.asarray(body_pose, float)
    F = len(body_pose)
    rig = rig if rig is not None else GlobalRig(target, subsample_vertices(target))
    rest = rest if rest is not None else template_rest(source, target, corr)
    Fs = np.asarray(source.faces, np.int64)
    TT = adjacency if adjacency is not None else igl.triangle_triangle_adjacency(Fs)[0]
    rest_src, src0 = _source_rest(source, betas)
    if subject is None:
        subject = (subject_rest(source, corr, rig, betas, rest) if fit_shape
                   else rest)
    rig.set_betas(subject.betas)
    G_rest = subject.G[None]
    anchors = anchor_joints(source, target, rig)
    ev = (eval_rig if eval_rig is not None
          else GlobalRig(target, v2s_vertices(target), rig.K, shape=False))
    ev.set_betas(rig.betas)
    ev_face = corr.tgt_vert_face[ev.vertices]
    Jt = target.num_joints
    R_all = np.zeros((F, 3, 3))
    T_all = np.zeros((F, 3))
    P_all = np.zeros((F, Jt, 3))
    stats = np.full((4, F), np.nan)
    blocks = [np.arange(i, min(i + FRAME_BLOCK, F)) for i in range(0, F, FRAME_BLOCK)]
    loop = blocks if progress is None else progress(blocks, total=len(blocks), desc="convert")
    for fb in loop:
        out = forward(source, None, body_pose[fb], global_orient[fb], transl[fb], rest=rest_src)
        Vs = out.vertices
        tg = corr.target_points(Vs, rig.vertices)  # the fitted points only
        G = initial_rotations(rig, out.joint_rot, src0.joint_rot[0], anchors, G_rest[0])
        ps = rig.parts_sparse(G, rig.correctives(G))  # the start's parts, used twice
        t0 = best_t0(rig, G, tg, parts=ps)
        G, t0, _ = rig.fit_pose(G, t0, tg, iters=iters, parts=ps)
        D = rig.local_rotations(G)
        R_all[fb] = G[:, 0]
        T_all[fb] = t0 - rig.u[0]
        P_all[np.ix_(fb, rig.skel.joints[1:])] = rotmat_to_rotvec(D[:, 1:])
        d = surface_distance(ev.positions(G, t0, ev.correctives(G)), ev_face, Vs, Fs, TT) * 1e3
        stats[:, fb] = (d.mean(1), np.median(d, 1), np.percentile(d, 95, axis=1), d.max(1))
    return PersonConversion(global_orient=R_all, transl=T_all, body_pose=P_all,
                            betas=rig.betas.copy(), v2s_mean_mm=stats[0], v2s_median_mm=stats[1],
                            v2s_p95_mm=stats[2], v2s_max_mm=stats[3],
                            cpu_s=time.process_time() - t_cpu, restarts=0)


# ----------------------------------------------------------------------------- batched fit (global rotations)
#
# The target's LBS in *global* joint rotations: with G_q the world rotation of fitted joint q and
# t_0 the world position of the root joint, a skinned point is exactly
#     v = (sum_q W_q) t_0 + sum_q G_q c_q,
#     c_q = l_q + W_q d + sum_{k child of q} S_k u_k       (S_k = sum of W over k's subtree)
# with (l, W) the slot coefficients of fitting/skinned.py, u the reduced-tree offsets and d the
# pose correctives (rest frame). It is linear in each G_q and in t_0, and turning G_q by a world
# rotation vector w moves v by w x (G_q c_q) alone: Gauss-Newton on independent global
# rotations has normal equations built from one Gram matrix P^T P of the points' per-joint parts
# p_q = G_q c_q, for all frames at once.

class GlobalRig:
    """Points of the target (rest vertices ``vertices``) as functions of the global rotations
    ``G (F, Q, 3, 3)`` of the fitted joints, the root position ``t0 (F, 3)`` and ``betas``."""

    def __init__(self, model: BodyModel, vertices: np.ndarray, num_betas: int = 10,
                 shape: bool = True):
        """``shape=False``: no beta directions (the betas cannot be fitted; set_betas
        recomputes the coefficients), a cheaper rig for points that are only posed."""
        self.model = model
        J = model.num_joints
        fit = [j for j in range(J) if model.joint_names[j] not in EYE_JOINTS]
        self.skel = fit_skeleton(model, fit)
        Q = len(self.skel.joints)
        self.Q = Q
        self.K = min(num_betas, model.num_shape or model.num_betas)
        self.vertices = np.asarray(vertices, np.int64)
        W = model.weights[self.vertices]
        A = subtree(self.skel).astype(float)
        self._children = sp.csr_matrix((np.ones(Q - 1), (self.skel.parents[1:], np.arange(1, Q))),
                                       shape=(Q, Q))

        Wc = W.tocoo()
        rows, cols, vals = Wc.row, Wc.col, Wc.data
        own = self.skel.owner[cols]
        gather = sp.csr_matrix((np.ones(len(rows)), (rows * Q + own, np.arange(len(rows)))),
                               shape=(len(self.vertices) * Q, len(rows)))  # sums into H

        def coeffs(betas):  # fitting.skinned.vertex_coeffs, vectorised (no bind rotations)
            rest = rest_state(model, betas)
            u, s = reduced_offsets(model, rest, self.skel)
            d = rest.vertices[0][self.vertices][rows] - rest.joints[0][cols]
            if rest.bind_rot is not None:
                d = np.einsum("nab,nb->na", rest.bind_rot[0][cols], d)
            vals4 = np.concatenate([vals[:, None] * (d + s[cols]), vals[:, None]], 1)
            return u, (gather @ vals4).reshape(len(self.vertices), Q, 4)

        u0, H0 = coeffs(np.zeros(model.num_betas))
        self.Wq = H0[..., 3]  # (N, Q)
        self.SW = self.Wq @ A.T  # (N, Q): weight of q's subtree
        self.Wsum = self.Wq.sum(1)  # (N,)
        self._c0, self._u0 = self._c(H0[..., :3], u0), u0
        self._coeffs = coeffs
        dc, du = [], []
        for k in range(self.K if shape else 0):
            e = np.zeros(model.num_betas)
            e[k] = 1.0
            u, H = coeffs(e)
            du.append(u - u0)
            dc.append(self._c(H[..., :3] - H0[..., :3], u - u0))
        self._dc = np.stack(dc) if shape else None  # (K, N, Q, 3)
        self._du = np.stack(du) if du else np.zeros((0, Q, 3))
        pd = model.posedirs
        self.posedirs = (None if pd is None else np.ascontiguousarray(
            pd.reshape(pd.shape[0], -1, 3)[:, self.vertices].reshape(pd.shape[0], -1)))
        nz = (self.SW > 0) | (self.Wq > 0)
        for k in range(self.K if shape else 0):
            nz |= np.abs(self._dc[k]).sum(-1) > 0
        pn, pq = np.nonzero(nz)  # the (point, joint) pairs with a part, grouped by joint
        order = np.lexsort((pn, pq))
        self.pn, self.pq = pn[order], pq[order]
        self._seg = np.searchsorted(self.pq, np.arange(Q + 1))
        self.pw = self.Wq[self.pn, self.pq]
        N = len(self.vertices)
        self.S = sp.csr_matrix((np.ones(len(self.pn)), (self.pn, np.arange(len(self.pn)))),
                               shape=(N, len(self.pn)))
        self.Sq = sp.csr_matrix((np.ones(len(self.pn)), (self.pq, np.arange(len(self.pn)))),
                                shape=(Q, len(self.pn)))  # sums the pairs of each joint
        self._cols = 3 * self.pq[:, None] + np.arange(3)  # columns of a pair in (N, 3Q)
        self.set_betas(np.zeros(self.K))

    def _c(self, l, u):
        X = (self.SW * u[:, 0][None], self.SW * u[:, 1][None], self.SW * u[:, 2][None])
        # child q's offset, carried by its parent: (Q, Q) sparse parent-of matrix times (N, Q)
        return l + np.stack([(self._children @ x.T).T for x in X], -1)

    def set_betas(self, betas):
        self.betas = np.asarray(betas, float)[: self.K].copy()
        if self._dc is None:  # recomputed from the model: memo of the last few betas
            key = self.betas.tobytes()
            memo = self.__dict__.setdefault("_memo", {})
            if key not in memo:
                b = np.zeros(self.model.num_betas)
                b[: self.K] = self.betas
                u, H = self._coeffs(b)
                memo[key] = (u, self._c(H[..., :3], u))
                while len(memo) > 4:
                    memo.pop(next(iter(memo)))
            self.u, self.c = memo[key]
        else:
            self.c = self._c0 + np.einsum("k,knqx->nqx", self.betas, self._dc)
            self.u = self._u0 + np.einsum("k,kqx->qx", self.betas, self._du)
        if hasattr(self, "pn"):
            self.cp = self.c[self.pn, self.pq]  # (nnz, 3)

    # --- kinematics
    def local_rotations(self, G):
        """(F, Q, 3, 3) D_q = G_p^T G_q (D_0 = G_0)."""
        D = G.copy()
        par = self.skel.parents
        D[:, 1:] = np.swapaxes(G[:, par[1:]], -1, -2) @ G[:, 1:]
        return D

    def correctives(self, G):
        """(F, N, 3) rest-frame pose correctives of the points, or None."""
        if self.posedirs is None:
            return None
        D = self.local_rotations(G)
        J = self.model.num_joints
        full = np.broadcast_to(np.eye(3), (len(G), J, 3, 3)).copy()
        full[:, self.skel.joints] = D
        feat = (full[:, 1:] - np.eye(3)).reshape(len(G), -1)
        return (feat @ self.posedirs).reshape(len(G), -1, 3)

    def parts_sparse(self, G, d=None):
        """(F, nnz, 3) the nonzero parts p_q = G_q (c_q + W_q d) of the (point, joint) pairs."""
        out = np.empty((len(G), len(self.pn), 3))
        Gt = np.swapaxes(G, -1, -2)
        for q in range(self.Q):  # one small GEMM per joint
            a, b = self._seg[q], self._seg[q + 1]
            if b > a:
                c = self.cp[a:b]
                if d is not None:
                    c = c + self.pw[a:b, None] * d[:, self.pn[a:b]]
                out[:, a:b] = c @ Gt[:, q]
        return out

    def parts(self, G, d=None):
        """(F, N, Q, 3) p_q = G_q c_q (+ W_q G_q d), zero where the pair has no part."""
        ps = self.parts_sparse(G, d)
        p = np.zeros((len(G), len(self.vertices), self.Q, 3))
        p[:, self.pn, self.pq] = ps
        return p

    def sum_parts(self, ps):
        F = ps.shape[0]
        return (self.S @ ps.transpose(1, 0, 2).reshape(ps.shape[1], F * 3)).reshape(-1, F, 3).transpose(1, 0, 2)

    def positions(self, G, t0, d=None):
        return self.Wsum[None, :, None] * t0[:, None] + self.sum_parts(self.parts_sparse(G, d))

    # --- fits
    def _seg_sum(self, S, x):
        """(F, rows, 3) sparse S (rows, nnz) applied to pair values x (F, nnz, 3)."""
        F = x.shape[0]
        y = S @ x.transpose(1, 0, 2).reshape(x.shape[1], F * 3)
        return y.reshape(-1, F, 3).transpose(1, 0, 2)

    def fit_pose(self, G, t0, targets, iters: int = 3, lam: float = 1e-3, shape_prior=None,
                 parts=None):
        """Batched LM on (G, t0) of every frame: ``sum_n |v_n - target_n|^2``; with
        ``shape_prior`` (one frame only) the betas too, with ridge ``shape_prior * N``.
        One trial step per iteration: a frame whose cost does not drop keeps its unknowns and
        raises its damping. ``parts``: the start's ``parts_sparse(G, correctives(G))`` when
        the caller has them (not for a betas fit; updated in place). Returns (G, t0, cost (F,))."""
        F, Q = G.shape[:2]
        G, t0 = G.copy(), t0.copy()
        N = targets.shape[1]
        K = self.K if shape_prior is not None else 0
        if K and F != 1:
            raise ValueError("fit_pose: betas are fitted on one frame")
        if K and self._dc is None:
            raise ValueError("fit_pose: a rig built with shape=False cannot fit betas")
        n3 = 3 * Q
        n = n3 + 3 + K
        ws = self.Wsum
        lamf = np.full(F, lam)
        mu = 0.0 if not K else shape_prior * N
        Sw = self.Sq @ sp.diags(ws[self.pn])  # sum over a joint's pairs, weighted by W_n
        flat = (self.pn[:, None] * n3 + self._cols).ravel()  # the pairs' slots in P (N * 3Q)

        def evaluate(G, t0, b):
            if K:
                self.set_betas(b)
            ps = self.parts_sparse(G, self.correctives(G))
            r = ws[None, :, None] * t0[:, None] + self.sum_parts(ps) - targets
            return ps, r, (r * r).sum((1, 2)) + mu * float(b @ b)

        b = self.betas.copy()
        if parts is not None and not K:  # the caller's parts_sparse(G, correctives(G))
            ps = parts
            r = ws[None, :, None] * t0[:, None] + self.sum_parts(ps) - targets
            cost = (r * r).sum((1, 2))
        else:
            ps, r, cost = evaluate(G, t0, b)
        for _ in range(iters):
            P = np.zeros((F, N * n3), np.float32)
            P[:, flat] = ps.reshape(F, -1)
            P = P.reshape(F, N, n3)
            # M[f, a, x, b, y] = sum_n p_na[x] p_nb[y]; the rotation block of the normal
            # equations is A[(a, x), (b, y)] = tr(M_ab) delta_xy - M[a, y, b, x]
            M = np.matmul(np.swapaxes(P, 1, 2), P).astype(float).reshape(F, Q, 3, Q, 3)
            A = np.zeros((F, n, n))
            A[:, :n3, :n3] = -M.transpose(0, 1, 4, 3, 2).reshape(F, n3, n3)
            tr = M[:, :, 0, :, 0] + M[:, :, 1, :, 1] + M[:, :, 2, :, 2]  # (F, Q, Q)
            for x in range(3):
                A[:, x:n3:3, x:n3:3] += tr
            s = self._seg_sum(Sw, ps)  # (F, Q, 3) sum_n W_n p_na
            A[:, n3:n3 + 3, :n3] = (-skew(s)).transpose(0, 2, 1, 3).reshape(F, 3, n3)
            A[:, :n3, n3:n3 + 3] = np.swapaxes(A[:, n3:n3 + 3, :n3], 1, 2)
            A[:, n3:n3 + 3, n3:n3 + 3] = np.eye(3) * float((ws ** 2).sum())
            g = np.empty((F, n))
            g[:, :n3] = self._seg_sum(self.Sq, np.cross(ps, r[:, self.pn])).reshape(F, n3)
            g[:, n3:n3 + 3] = np.einsum("fnx,n->fx", r, ws)
            if K:
                p = np.zeros((N, Q, 3))
                p[self.pn, self.pq] = ps[0]
                BB, Aab, wB, gB = shape_blocks(G[0], self._dc, p, ws, r[0])
                A[0, n3 + 3:, n3 + 3:] = BB + mu * np.eye(K)
                A[0, :n3, n3 + 3:] = Aab.reshape(n3, K)
                A[0, n3:n3 + 3, n3 + 3:] = wB
                A[0, n3 + 3:, :n3 + 3] = A[0, :n3 + 3, n3 + 3:].T
                g[0, n3 + 3:] = gB + mu * b
            diag = np.einsum("fii->fi", A)
            A[:, np.arange(n), np.arange(n)] += lamf[:, None] * diag + 1e-12
            step = -np.linalg.solve(A, g[..., None])[..., 0]
            Gn = rodrigues(step[:, :n3].reshape(F, Q, 3)) @ G
            tn = t0 + step[:, n3:n3 + 3]
            bn = b + step[0, n3 + 3:] if K else b
            psn, rn, cn = evaluate(Gn, tn, bn)
            ok = cn < cost
            G[ok], t0[ok], ps[ok], r[ok], cost[ok] = Gn[ok], tn[ok], psn[ok], rn[ok], cn[ok]
            if K and ok[0]:
                b = bn
            lamf = np.where(ok, np.maximum(lamf / 3, 1e-7), lamf * 10)
        if K:
            self.set_betas(b)
        return G, t0, cost


def shape_blocks(G0, dc, p, ws, r0):
    """The betas' blocks of :meth:`GlobalRig.fit_pose`'s normal equations on one frame: with
    ``B[n, a, k] = sum_qb G0[q, a, b] dc[k, n, q, b]`` (d v_n / d beta_k; ``G0 (Q, 3, 3)``,
    ``dc (K, N, Q, 3)``), returns ``(B^T B (K, K), sum_n p_nq x B_nk (Q, 3, K),
    sum_n ws_n B_n (3, K), sum_n B_n^T r_n (K,))`` for the per-joint parts ``p (N, Q, 3)``,
    the points' weight sums ``ws (N,)`` and residuals ``r0 (N, 3)``. Matrix products
    throughout (the einsum / ``np.cross`` form, kept in the tests as the peer, was most of
    a subject's rest fit: 220 -> 70 ms)."""
    K, N, Q, _ = dc.shape
    n3 = 3 * Q
    B = (dc.reshape(K * N, n3) @ np.swapaxes(G0, 1, 2).reshape(n3, 3)
         ).reshape(K, N, 3).transpose(1, 2, 0)
    Bm = B.reshape(N * 3, K)
    # T[q, b, c, k] = sum_n p[n, q, b] B[n, c, k]; the cross product's components from it
    T = (p.reshape(N, n3).T @ B.reshape(N, 3 * K)).reshape(Q, 3, 3, K)
    cross = np.stack([T[:, 1, 2] - T[:, 2, 1], T[:, 2, 0] - T[:, 0, 2],
                      T[:, 0, 1] - T[:, 1, 0]], axis=1)
    return Bm.T @ Bm, cross, (ws @ B.reshape(N, 3 * K)).reshape(3, K), r0.reshape(N * 3) @ Bm


def _grad_rot(pf, r, Q):
    """(F, 3Q) sum_n p_nq x r_n of parts pf (F, N, 3Q) and residuals r (F, N, 3)."""
    F = len(pf)
    pr = (np.swapaxes(pf, 1, 2) @ r).reshape(F, Q, 3, 3)  # sum_n p_a r_b
    g = np.stack([pr[..., 1, 2] - pr[..., 2, 1], pr[..., 2, 0] - pr[..., 0, 2],
                  pr[..., 0, 1] - pr[..., 1, 0]], -1)
    return g.reshape(F, 3 * Q)


def initial_rotations(rig: GlobalRig, G_src, src_rest, anchors, G_rest):
    """(F, Q, 3, 3): each fitted target joint turned as its source anchor joint turned from the
    rest posture (``G_src (F, Js, 3, 3)`` source joint rotations, ``src_rest (Js, 3, 3)`` at
    rest, ``anchors (Q,)`` source joint or -1, ``G_rest (Q, 3, 3)`` the target at rest);
    joints without an anchor keep their rest rotation relative to their parent."""
    F, Q = len(G_src), rig.Q
    G = np.empty((F, Q, 3, 3))
    par = rig.skel.parents
    for q in range(Q):
        a = anchors[q]
        if a >= 0:
            G[:, q] = G_src[:, a] @ (src_rest[a].T @ G_rest[q])
        else:
            p = par[q]
            G[:, q] = G[:, p] @ (G_rest[p].T @ G_rest[q]) if p >= 0 else G_rest[q]
    return G


def best_t0(rig, G, targets, d=None, parts=None):
    """(F, 3) the root position that best places the points posed by ``G`` (``parts``: their
    ``rig.parts_sparse(G, d)`` when already computed)."""
    p = rig.sum_parts(rig.parts_sparse(G, d) if parts is None else parts)  # (F, N, 3)
    ws = rig.Wsum
    return np.einsum("fnx,n->fx", targets - p, ws) / float((ws ** 2).sum())


def joint_positions(rig: GlobalRig, G, t0):
    """(F, Q, 3) world positions of the fitted joints: t_q = t_p + G_p u_q."""
    t = np.empty(G.shape[:2] + (3,))
    t[:, 0] = t0
    par = rig.skel.parents
    for q in range(1, rig.Q):
        t[:, q] = t[:, par[q]] + G[:, par[q]] @ rig.u[q]
    return t


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _point_triangle(p, a, b, c):
    """Exact distances (M,) of points to triangles, all as coordinate rows (3, M); whether each
    point's projection falls inside its triangle (M,), and its unclamped barycentric
    coordinates (3, M)."""
    e0, e1, v2 = b - a, c - a, p - a
    d00, d01, d11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
    d20, d21 = _dot(v2, e0), _dot(v2, e1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w])
    inside = (bary[0] >= 0) & (v >= 0) & (w >= 0)
    n = np.stack([e0[1] * e1[2] - e0[2] * e1[1], e0[2] * e1[0] - e0[0] * e1[2],
                  e0[0] * e1[1] - e0[1] * e1[0]])
    dist = np.abs(_dot(v2, n)) / np.sqrt(np.maximum(_dot(n, n), 1e-60))
    out = np.flatnonzero(~inside)
    if len(out):
        po = p[:, out]
        best = None
        for s0, s1 in ((a, b), (b, c), (c, a)):
            s0, e = s0[:, out], (s1 - s0)[:, out]
            q = po - s0
            t = np.clip(_dot(q, e) / np.maximum(_dot(e, e), 1e-30), 0, 1)
            r = q - t * e
            dd = _dot(r, r)
            best = dd if best is None else np.minimum(best, dd)
        dist[out] = np.sqrt(best)
    return dist, inside, bary


def surface_distance(points, faces0, V, F, TT, steps: int = 6):
    """Distance (..., N) of each point (..., N, 3) to the surface (..., Vn, 3), F near its start
    facet ``faces0 (N,)``: from it walk to the neighbouring facet (``TT``,
    igl.triangle_triangle_adjacency) across the edge the point's projection lies beyond, until
    it falls inside a facet; then the facet across the last one's edge nearest to the
    projection (a ridge between two facets); the smallest exact
    point-to-facet distance seen. An upper bound of the distance to the whole surface, equal to
    it unless another part of the body is closer (contact, a fold) or the walk is cut short
    (``steps``). Leading axes (frames) are batched."""
    points = np.asarray(points, float)
    lead = points.shape[:-2]
    Vn = V.shape[-2]
    B = int(np.prod(lead)) if lead else 1
    P = points.reshape(-1, 3).T.copy()  # (3, B N)
    VR = np.ascontiguousarray(V, float).reshape(-1, 3)  # (B Vn, 3): a corner is one row
    N = points.shape[-2]
    off = np.repeat(np.arange(B) * Vn, N)
    f = np.tile(np.asarray(faces0, np.int64), B)

    def tri(idx, faces):
        g = F[faces] + off[idx, None]  # (M, 3) rows of VR
        X = np.ascontiguousarray(VR[g].transpose(1, 2, 0))  # (corner, coordinate, M)
        return X[0], X[1], X[2]

    best = np.full(B * N, np.inf)
    last = np.zeros((3, B * N))  # barycentric coordinates in the last facet
    active = np.arange(B * N)
    for _ in range(steps):
        d, inside, bary = _point_triangle(P[:, active], *tri(active, f[active]))
        best[active] = np.minimum(best[active], d)
        last[:, active] = bary
        go = ~inside
        if not go.any():
            break
        a = active[go]
        k = np.argmin(bary[:, go], 0)  # the vertex the projection is farthest beyond
        nxt = TT[f[a], (k + 1) % 3]  # facet across the opposite edge
        ok = nxt >= 0
        f[a[ok]] = nxt[ok]
        active = a[ok]
    nb = TT[f, (np.argmin(last, 0) + 1) % 3]
    nb = np.where(nb >= 0, nb, f)
    best = np.minimum(best, _point_triangle(P, *tri(np.arange(B * N), nb))[0])
    return best.reshape(lead + (N,))


def smplx_arrays(target: BodyModel, pose: np.ndarray) -> dict[str, np.ndarray]:
    """Split (F, J, 3) axis-angle over all target joints into smplx's arguments as rotation
    matrices: ``body_pose (F, 21, 3, 3)``, and for SMPL-X ``jaw_pose``, ``leye_pose``,
    ``reye_pose (F, 3, 3)``, ``left_hand_pose``/``right_hand_pose (F, 15, 3, 3)`` (SMPL+H:
    hands only; SMPL: ``body_pose (F, 23, 3, 3)``)."""
    Rm = rodrigues(np.asarray(pose, float))
    J = target.num_joints
    if J == 55:
        return {"body_pose": Rm[:, 1:22], "jaw_pose": Rm[:, 22], "leye_pose": Rm[:, 23],
                "reye_pose": Rm[:, 24], "left_hand_pose": Rm[:, 25:40],
                "right_hand_pose": Rm[:, 40:55]}
    if J == 52:
        return {"body_pose": Rm[:, 1:22], "left_hand_pose": Rm[:, 22:37],
                "right_hand_pose": Rm[:, 37:52]}
    return {"body_pose": Rm[:, 1:]}
