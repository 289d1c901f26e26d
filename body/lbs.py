"""Linear blend skinning: the full mesh in numpy, a fixed number of vertex slots in CasADi.

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


# ----------------------------------------------------------------------------- CasADi slots


@dataclasses.dataclass(frozen=True)
class SlotSpec:
    """Shape of a slot-LBS graph (fixes the graph; the chosen vertices are parameters).

    num_slots: vertex slots; num_betas: 0 (shape fixed: the slots' rest positions and the rest
    joints are parameters) or S' (betas are a symbolic input, shape rows are parameters);
    fit_joints: model joints whose rotation is an input (root first); the others keep pose 0;
    posedirs: include pose-corrective rows (SMPL family) as parameters."""

    num_slots: int
    num_betas: int = 0
    fit_joints: tuple[int, ...] = ()
    posedirs: bool = False


def slot_spec(model: BodyModel, num_slots: int, num_betas: int = 0, fit_joints=None) -> SlotSpec:
    """A SlotSpec for ``model`` (default joints ``model.fit_joints``; pose correctives when the
    model has them)."""
    q = tuple(sorted(int(j) for j in (model.fit_joints if fit_joints is None else fit_joints)))
    if not q or q[0] != 0:
        raise ValueError("fit joints must include the root (joint 0)")
    return SlotSpec(num_slots, num_betas, q, model.posedirs is not None)


def slot_lbs_cs(model: BodyModel, spec: SlotSpec, name: str = "slot_lbs"):
    """The CasADi slot LBS: posed positions of ``spec.num_slots`` vertex slots and of all joints.

    The graph depends only on the model's topology (``parents``, J) and ``spec``; everything
    that depends on the subject or the chosen vertices is a parameter (``slot_params``).
    Same equations as :func:`forward` (module doc), with D_j = I for joints outside
    ``spec.fit_joints``.

    Inputs (in order; ``Q = len(fit_joints)``, ``N`` slots, ``S = num_betas``, ``P = 9 (Q-1)``):
      pose (Q, 3) local rotation vectors of the fit joints (row 0 = root, normally 0), radians;
      global_orient (3,) rotation vector about the rest root joint; transl (3,) metres;
      betas (S,)                               [only if S > 0];
      slot_rest (N, 3)    rest positions (shape fixed) or positions at betas = 0 (S > 0);
      slot_shapedirs (3N, S)  row 3i+d: d-coordinate shape row of slot i [only if S > 0];
      slot_weights (N, J) skinning weight rows (dense);
      slot_posedirs (3N, P) pose-corrective rows over the fit joints' features [if posedirs];
      joint_rest (J, 3)   rest joints (shape fixed) or at betas = 0 (S > 0);
      joint_shapedirs (3J, S) row 3j+d [only if S > 0];
      bind_rot (3J, 3)    rows 3j..3j+2 = A_j (I for the SMPL family). With symbolic betas the
                          bind rotations (polar factors, nonlinear in betas, a few degrees) are
                          held at the value given here: refresh them between LM iterations.
    Outputs: slots (N, 3) and joints (J, 3), world, metres.
    """
    import casadi as ca

    from body.rotations import rodrigues_cs

    J = model.num_joints
    par = [int(p) for p in model.parents]
    Q, N, S = len(spec.fit_joints), spec.num_slots, spec.num_betas
    qpos = {j: i for i, j in enumerate(spec.fit_joints)}
    pose = ca.SX.sym("pose", Q, 3)
    rg = ca.SX.sym("global_orient", 3)
    T = ca.SX.sym("transl", 3)
    betas = ca.SX.sym("betas", S)
    s_rest = ca.SX.sym("slot_rest", N, 3)
    s_sd = ca.SX.sym("slot_shapedirs", 3 * N, S)
    s_w = ca.SX.sym("slot_weights", N, J)
    s_pd = ca.SX.sym("slot_posedirs", 3 * N, 9 * (Q - 1))
    j_rest = ca.SX.sym("joint_rest", J, 3)
    j_sd = ca.SX.sym("joint_shapedirs", 3 * J, S)
    A = ca.SX.sym("bind_rot", 3 * J, 3)

    h = j_rest
    vc = s_rest
    if S:
        h = h + ca.reshape(ca.mtimes(j_sd, betas), 3, J).T
        vc = vc + ca.reshape(ca.mtimes(s_sd, betas), 3, N).T
    D = [rodrigues_cs(pose[i, :].T) for i in range(Q)]
    if spec.posedirs:
        feat = ca.vertcat(*[ca.vec((D[i] - ca.DM.eye(3)).T) for i in range(1, Q)])
        vc = vc + ca.reshape(ca.mtimes(s_pd, feat), 3, N).T
    Aj = [A[3 * j: 3 * j + 3, :] for j in range(J)]
    G = [None] * J
    t = [None] * J
    G[0] = ca.mtimes(rodrigues_cs(rg), D[0])
    t[0] = h[0, :].T + T
    for j in range(1, J):
        p = par[j]
        o = h[j, :].T - h[p, :].T
        if p != 0:
            o = ca.mtimes(Aj[p], o)
        t[j] = t[p] + ca.mtimes(G[p], o)
        G[j] = ca.mtimes(G[p], D[qpos[j]]) if j in qpos else G[p]
    rows = []
    for j in range(J):
        GA = ca.mtimes(G[j], Aj[j])
        tt = t[j] - ca.mtimes(GA, h[j, :].T)
        rows.append(ca.horzcat(ca.reshape(GA, 1, 9), tt.T))  # column-major GA entries, then t
    Tj = ca.vertcat(*rows)  # (J, 12)
    M = ca.mtimes(s_w, Tj)  # (N, 12) blended transforms
    out = []
    for i in range(N):
        Gi = ca.reshape(M[i, 0:9], 3, 3)
        out.append((ca.mtimes(Gi, vc[i, :].T) + M[i, 9:12].T).T)
    slots = ca.vertcat(*out) if N else ca.SX(0, 3)
    joints = ca.horzcat(*t).T
    ins = [pose, rg, T] + ([betas] if S else []) + [s_rest] + ([s_sd] if S else []) + [s_w]
    ins += ([s_pd] if spec.posedirs else []) + [j_rest] + ([j_sd] if S else []) + [A]
    in_names = ["pose", "global_orient", "transl"] + (["betas"] if S else []) + ["slot_rest"]
    in_names += (["slot_shapedirs"] if S else []) + ["slot_weights"]
    in_names += (["slot_posedirs"] if spec.posedirs else []) + ["joint_rest"]
    in_names += (["joint_shapedirs"] if S else []) + ["bind_rot"]
    return ca.Function(name, ins, [slots, joints], in_names, ["slots", "joints"])


def slot_params(model: BodyModel, spec: SlotSpec, vertex_ids, rest: RestState | None = None,
                betas=None) -> dict[str, np.ndarray]:
    """Parameters of :func:`slot_lbs_cs` for the vertices ``vertex_ids`` (<= num_slots; unused
    slots get a zero weight row and sit at the origin).

    Shape fixed (``spec.num_betas == 0``): pass ``rest`` or ``betas``. Symbolic betas: the
    template and shape rows; ``rest``/``betas`` (default betas 0) only set the frozen bind
    rotations. Returns a dict keyed by the function's input names."""
    ids = np.asarray(vertex_ids, dtype=np.int64).ravel()
    N, S, J = spec.num_slots, spec.num_betas, model.num_joints
    if len(ids) > N:
        raise ValueError(f"{len(ids)} vertices for {N} slots")
    if rest is None:
        rest = rest_state(model, np.zeros(1) if betas is None else betas)
    p: dict[str, np.ndarray] = {}
    W = np.zeros((N, J))
    W[: len(ids)] = model.weights[ids].toarray()
    p["slot_weights"] = W
    s_rest = np.zeros((N, 3))
    if S:
        s_rest[: len(ids)] = model.v_template[ids]
        sd = np.zeros((N, 3, S))
        sd[: len(ids)] = model.shapedirs[ids, :, :S]
        p["slot_shapedirs"] = sd.reshape(3 * N, S)
        p["joint_rest"] = np.array(model.joint_template)
        p["joint_shapedirs"] = np.asarray(model.joint_shapedirs[:, :, :S]).reshape(3 * J, S)
    else:
        s_rest[: len(ids)] = rest.vertices[0, ids]
        p["joint_rest"] = np.array(rest.joints[0])
    p["slot_rest"] = s_rest
    if spec.posedirs:
        Q = len(spec.fit_joints)
        P = np.asarray(model.posedirs).reshape(J - 1, 9, -1, 3)  # (joint-1, 9, V, 3)
        sel = P[np.asarray(spec.fit_joints[1:]) - 1][:, :, ids, :]  # (Q-1, 9, n, 3)
        pd = np.zeros((N, 3, Q - 1, 9))
        pd[: len(ids)] = sel.transpose(2, 3, 0, 1)
        p["slot_posedirs"] = pd.reshape(3 * N, 9 * (Q - 1))
    A = np.tile(np.eye(3), (J, 1, 1)) if rest.bind_rot is None else rest.bind_rot[0]
    p["bind_rot"] = A.reshape(3 * J, 3)
    return p


def marker_lbs_cs(model: BodyModel, spec: SlotSpec, name: str = "marker_lbs"):
    """Markers on a slot graph: ``spec.num_slots`` must be 3 M (three vertex slots per marker).

    Inputs: those of :func:`slot_lbs_cs`, then ``bary (M, 3)`` and ``offsets (M,)`` metres.
    Outputs: markers (M, 3) = sum_k bary_k v_k + offset * unit normal of the posed triangle
    (the numpy twin is ``body.markers.marker_positions``), joints (J, 3)."""
    import casadi as ca

    f = slot_lbs_cs(model, spec, name + "_slots")
    M = spec.num_slots // 3
    if 3 * M != spec.num_slots:
        raise ValueError("marker graphs need 3 slots per marker")
    ins = [ca.SX.sym(f.name_in(i), f.size_in(i)) for i in range(f.n_in())]
    slots, joints = f(*ins)
    bary = ca.SX.sym("bary", M, 3)
    offs = ca.SX.sym("offsets", M)
    out = []
    for m in range(M):
        a, b, c = slots[3 * m, :].T, slots[3 * m + 1, :].T, slots[3 * m + 2, :].T
        n = ca.cross(b - a, c - a)
        n = n / ca.norm_2(n)
        out.append((bary[m, 0] * a + bary[m, 1] * b + bary[m, 2] * c + offs[m] * n).T)
    names = [f.name_in(i) for i in range(f.n_in())] + ["bary", "offsets"]
    return ca.Function(name, ins + [bary, offs], [ca.vertcat(*out), joints], names, ["markers", "joints"])


def marker_params(model: BodyModel, spec: SlotSpec, markerset, rest: RestState | None = None,
                  betas=None) -> dict[str, np.ndarray]:
    """Parameters of :func:`marker_lbs_cs` for a ``body.markers.MarkerSet`` (<= num_slots/3
    markers; unused markers are degenerate and should be masked by the caller)."""
    M = spec.num_slots // 3
    n = len(markerset.names)
    if n > M:
        raise ValueError(f"{n} markers for {M} marker slots")
    ids = np.asarray(model.faces)[markerset.faces].ravel()
    p = slot_params(model, spec, ids, rest=rest, betas=betas)
    bary = np.zeros((M, 3))
    bary[:n] = markerset.bary
    offs = np.zeros(M)
    offs[:n] = markerset.offsets
    # unused markers: a non-degenerate dummy triangle so the normal stays finite
    if n < M:
        p["slot_rest"][3 * n:] = np.tile(np.eye(3), (M - n, 1))
        p["slot_weights"][3 * n:, 0] = 1.0
    p["bary"] = bary
    p["offsets"] = offs
    return p
