"""Subject shape: fit to a body scan, then place the markers on that body (MoSh++ stage I idea).

1. ``fit_scan``: shape ``betas`` (the first S of the model's basis), a neutral pose of the body
   joints, and the rigid transform from the model to the scan's frame, minimising robust
   (Geman-McClure) point-to-plane distances in both directions: scan points to the model
   surface (closest points with ``igl.point_mesh_squared_distance``) and model vertices to the
   scan (nearest scan point, its normal). Holes in the scan leave model vertices far from any
   scan point: the robust loss gives them ~0 weight. A Gaussian prior on betas (whitened, unit
   variance) and on the pose keeps unobserved directions put. Damped Gauss-Newton with a
   forward-difference Jacobian of ``body.lbs.forward`` (the full mesh in numpy: ~100 params).
2. ``refine_placement`` (``fitting/placement.py``, MoSh stage I): the captures tracked frame
   after frame with the template placement, well-spread well-tracked frames chosen (ghosts,
   glitches and swapped labels excluded), then poses / placement (robust, slide capped at
   5 cm, offset prior 9.5 mm bounded in [0, 35] mm) / betas alternated from the tracked
   poses; a marker that leaves its segment is reported and put back on the template.
3. no scan (``fit_betas``): betas and the frames' poses are fitted jointly in that
   alternation (robust Levenberg-Marquardt, weak prior, rest posture kept at the mean's).

:func:`fit_shape` is the whole subject (scan fit, else marker-based shape, else the mean;
then the placement on the captures), returning an ``artifacts.ShapeFit`` and a report;
:func:`shape_from_scan` and :func:`fit_placement` are its two steps. No file I/O: the stage
adapter ``stages/shape_fit.py`` reads the scan and the captures.

Placement: ``face (M,)`` model face index, ``bary (M, 3)`` barycentric coordinates,
``offset (M,)`` metres along the rest-pose face normal (outwards). A marker skins like the
blend of its face's vertices (weights interpolated with ``bary``).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from body.lbs import forward, rest_state
from body.model import BodyModel
from body.rotations import rodrigues
from fitting import compiled, marker_fit, priors, robust, skinned
from fitting.marker_graph import (  # noqa: F401 - re-exported (bench/fitting_synth.py)
    GraphSpec,
    MarkerGraph,
    Placement,
    body_joints,
    marker_rest_points,
    marker_support,
    placement_of,
    to_shape_fit,
)
from fitting.placement import (  # noqa: F401 - re-exported
    PLACEMENT_FROM,
    PlacementFit,
    PlacementOptions,
    project_to_surface,
    refine_placement,
)
from geometry import face_areas, face_normals

# constants
FD_STEP = 1e-6
COARSE_BETAS = 10  # scan fit: betas fitted in the first third of the iterations


# ---------------------------------------------------------------------------- scan fit


@dataclass(frozen=True)
class ScanFitOptions:
    """num_betas: shape coefficients fitted; n_points: scan points sampled per iteration;
    n_vertices: model vertices sampled for the model-to-scan direction; iters: Gauss-Newton
    iterations of the schedule (coarse betas, all betas, neutral pose pulled); max_iters: the
    last phase goes on past ``iters`` while the cost still falls by more than falling_frac
    over three iterations, up to this many in all (with a fixed count, the head of
    tests/test_shape_fit.py's body stayed 63 mm off on one machine's rounding, still moving
    at iteration 30); sigma_m: Geman-McClure scale (metres); beta_weight, pose_weight: prior
    weights (residual units: metres^2 per point, averaged); headings: initial rotations about
    the vertical tried for the rigid start; max_pair_m, min_normal_dot: a model vertex's pair
    with its nearest scan point is used only if closer than this and their normals' dot
    product exceeds this (holes); final_pair_m: the distance cut of the last third of the
    iterations (a cut from the start loses the scan when the start is far from it)."""

    # all of anny's: 150 left 6.3 mm v2v on the bench, 404 gives 4.4 (template-space v2v, the
    # bench's measure before session 28)
    num_betas: int = 404
    n_points: int = 4000
    n_vertices: int = 2000
    iters: int = 40
    max_iters: int | None = None  # None: twice iters
    falling_frac: float = 0.05
    sigma_m: float = 0.015
    beta_weight: float = 1e-8
    pose_weight: float = 1e-4
    final_pose_weight: float = 1e-4
    headings: int = 8
    max_pair_m: float = np.inf  # 0.02 cut the fit off the scan from a far start
    final_pair_m: float = 0.02  # the same cut in the last third only, once the fit is on the scan
    min_normal_dot: float = 0.5


@dataclass
class ScanFit:
    """betas (S,), x: fit-skeleton unknowns of the neutral pose (model to scan frame),
    joints: the fitted body joints; scan_to_model_mm: (N,) final distances of all scan points;
    iterations."""

    betas: np.ndarray
    x: np.ndarray
    joints: np.ndarray
    scan_to_model_mm: np.ndarray
    iterations: int


def _posed_vertices(model, skel, betas, x, rest=None):
    """(V, 3) world vertices of the fit-skeleton unknowns x (non-fitted joints at pose 0)."""
    pose = np.zeros((1, model.num_joints, 3))
    pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
    out = forward(model, betas, pose, rodrigues(x[:3])[None], x[3:6][None], rest=rest)
    return out.vertices[0]


def _rigid_start(model, skel, points, rng, opts, S) -> tuple[np.ndarray, np.ndarray]:
    """(betas (S,), x): a start for the scan fit: the mean body aligned to the scan
    (centroids, then the best of ``opts.headings`` rotations about z refined by rigid ICP).
    (A start from the best of a size grid over the first betas, as the marker-based shape
    does, was tried: it fitted the surface as well and the neutral-pose vertices worse.)"""
    from scipy.spatial import cKDTree

    from body.rotations import rotmat_to_rotvec

    sub = points[rng.choice(len(points), min(2000, len(points)), replace=False)]
    tree = cKDTree(sub)

    def icp(v0, R, t, n_iter):
        for _ in range(n_iter):
            d, i = tree.query(v0 @ R.T + t)
            keep = d < np.percentile(d, 80)
            R, t = marker_fit.kabsch(v0[keep], sub[i[keep]])
        d1, _ = tree.query(v0 @ R.T + t)
        d2, _ = cKDTree(v0 @ R.T + t).query(sub)
        return R, t, np.mean(np.minimum(d1, 0.05) ** 2) + np.mean(np.minimum(d2, 0.05) ** 2)

    v0 = _posed_vertices(model, skel, np.zeros(1), np.zeros(skel.n))
    best = None
    for k in range(opts.headings):
        a = 2 * np.pi * k / opts.headings
        R = rodrigues(np.array([0.0, 0.0, a]))
        R, t, score = icp(v0, R, sub.mean(0) - R @ v0.mean(0), 8)
        if best is None or score < best[0]:
            best = (score, R, t, np.zeros(S))
    _, R, t, b = best
    x = np.zeros(skel.n)
    h0 = rest_state(model, b).joints[0, 0]
    x[:3] = rotmat_to_rotvec(R)
    x[3:6] = t + R @ h0 - h0
    return b, x


def bind_jacobian(model: BodyModel, betas: np.ndarray, S: int):
    """d bind_rotations / d betas[:S]: (J, 3, 3, S), or None for models without bind rotations
    (the SMPL family).

    Closed form: A_j = ref_j R_j^T with R_j the polar factor of M_j = template_j + sum_s b_s
    D_js (:func:`body.lbs.bind_rotations`). With M = R P, dR = R [w]x where
    (tr(P) I - P) w = k and [k]x = R^T dM - dM^T R (the derivative of the polar factor; for a
    skew [w]x and a symmetric P, P [w]x + [w]x P = [(tr(P) I - P) w]x). One 3 x 3 solve per
    joint instead of 2 S polar decompositions of the whole skeleton (central differences, kept
    as the test's peer)."""
    from body.lbs import pad_betas
    from body.rotations import skew, special_procrustes

    if model.orient_template is None:
        return None
    b = pad_betas(model, betas)[0]
    D = np.asarray(model.orient_shapedirs, dtype=float)
    M = model.orient_template + np.einsum("jxys,s->jxy", D, b)
    R = special_procrustes(M)  # (J, 3, 3)
    P = np.swapaxes(R, -1, -2) @ M
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    RtD = np.einsum("jyx,jyzs->jxzs", R, D[..., :S])  # R^T dM per beta
    K = RtD - np.swapaxes(RtD, 1, 2)
    k = np.stack([K[:, 2, 1], K[:, 0, 2], K[:, 1, 0]], axis=1)  # (J, 3, S)
    L = np.trace(P, axis1=-2, axis2=-1)[:, None, None] * np.eye(3) - P
    w = np.linalg.solve(L, k)  # (J, 3, S)
    W = skew(np.moveaxis(w, -1, 1))  # (J, S, 3, 3)
    dR = np.einsum("jab,jsbc->jsac", R, W)  # R [w]x
    # d(ref R^T) = ref dR^T
    return np.einsum("jab,jscb->jacs", np.asarray(model.ref_orient, float), dR)


def _joint_terms(model: BodyModel, rest, skel: skinned.FitSkeleton, x: np.ndarray, S: int,
                 dA: np.ndarray | None):
    """The posed frames at x and the joints' part of d vertex / d betas[:S]: (G (J, 3, 3),
    GA = G A (J, 3, 3), the rest joints h (J, 3), c (J, 3, S)) with a vertex's betas
    derivative sum_j w_vj (G_j A_j shapedirs_v + c_j) (+ the bind rotations' part)."""
    from body.lbs import forward_kinematics

    pose = np.zeros((1, model.num_joints, 3))
    pose[0, skel.joints[1:]] = x[6:].reshape(-1, 3)
    G, _, _ = forward_kinematics(model, rest, pose, rodrigues(x[:3])[None], x[3:6][None])
    G = G[0]  # (J, 3, 3)
    J = model.num_joints
    A = rest.bind_rot[0] if rest.bind_rot is not None else np.broadcast_to(np.eye(3), (J, 3, 3))
    par = np.asarray(model.parents)
    pp = np.maximum(par, 0)
    h = rest.joints[0]
    dh = np.asarray(model.joint_shapedirs[:, :, :S], dtype=float)  # (J, 3, S)
    Ap = A[pp].copy()
    Ap[par == 0] = np.eye(3)
    do = np.einsum("jab,jbs->jas", Ap, dh - dh[pp])
    if dA is not None:  # offsets o_j = A'_p (h_j - h_p) move with the bind rotations too
        dAp = dA[pp].copy()
        dAp[par == 0] = 0.0
        do += np.einsum("jabs,jb->jas", dAp, h - h[pp])
    do[0] = dh[0]
    dt = np.zeros_like(do)
    dt[0] = do[0]
    for j in range(1, J):
        dt[j] = dt[par[j]] + G[par[j]] @ do[j]
    GA = G @ A
    return G, GA, h, dt - np.einsum("jab,jbs->jas", GA, dh)


def vertex_jacobian(model: BodyModel, rest, skel: skinned.FitSkeleton, x: np.ndarray,
                    vids: np.ndarray, S: int, dA: np.ndarray | None = None) -> np.ndarray:
    """d vertices[vids] / d [betas[:S], x]: (len(vids), 3, S + n).

    Betas: analytic through the rest vertices, rest joints and offsets, plus the bind
    rotations through ``dA = bind_jacobian(...)`` (J, 3, 3, S) when given (Anny's reference
    posture changes with the shape: ignoring it lets the pose absorb shape); x: forward
    differences with the rest state fixed (``FD_STEP``). The scan fit projects it onto its
    rows without forming it (:func:`residual_jacobian`); this per-vertex form is that one's
    peer in the tests."""
    from scipy import sparse

    G, GA, h, c = _joint_terms(model, rest, skel, x, S, dA)
    J = model.num_joints
    W = model.weights[vids]  # (n_v, J) sparse
    Mv = (W @ GA.reshape(J, 9)).reshape(-1, 3, 3)
    sd = np.asarray(model.shapedirs[vids, :, :S], dtype=float)
    jb = np.einsum("vab,vbs->vas", Mv, sd) + (W @ c.reshape(J, -1)).reshape(-1, 3, S)
    if dA is not None:  # skinning: sum_j w_vj G_j dA_j (v_c - h_j)
        GdA = np.einsum("jab,jbcs->jcas", G, dA).reshape(3 * J, 3 * S)  # rows (j, c)
        Wc = W.tocoo()  # w_vj (v_c - h_j) at column (j, c): one sparse product, (V, 3 S) out
        d = Wc.data[:, None] * (rest.vertices[0, vids][Wc.row] - h[Wc.col])
        Wc = sparse.csr_matrix((d.reshape(-1), (np.repeat(Wc.row, 3),
                                                (3 * Wc.col[:, None] + np.arange(3)).reshape(-1))),
                               shape=(len(vids), 3 * J))
        jb += (Wc @ GdA).reshape(-1, 3, S)
    v0 = _posed_vertices(model, skel, None, x, rest=rest)[vids]
    jx = np.zeros((len(vids), 3, len(x)))
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = FD_STEP
        jx[:, :, k] = (_posed_vertices(model, skel, None, x + e, rest=rest)[vids] - v0) / FD_STEP
    return np.concatenate([jb, jx], axis=2)


def residual_jacobian(model: BodyModel, rest, skel: skinned.FitSkeleton, x: np.ndarray,
                      rows: np.ndarray, verts: np.ndarray, vecs: np.ndarray, n_rows: int, S: int,
                      dA: np.ndarray | None = None) -> np.ndarray:
    """d r / d [betas[:S], x]: (n_rows, S + n) for residuals linear in the posed vertices,
    r_i = sum over m with rows[m] = i of vecs[m] . vertex[verts[m]] (+ constants): the scan
    fit's point-to-plane rows (barycentric weight x normal per face corner).

    The same derivative as ``B @`` :func:`vertex_jacobian` (B the sparse row operator), without
    the (vertices, 3, S + n) array: each of its terms is projected onto the rows first, so the
    shape directions, the joint terms and the bind rotations enter as sparse-by-dense products
    and the pose's forward differences as differences of r."""
    from scipy import sparse

    G, GA, h, c = _joint_terms(model, rest, skel, x, S, dA)
    J, V = model.num_joints, model.num_vertices
    rows, verts, vecs = np.asarray(rows), np.asarray(verts), np.asarray(vecs, float)
    # the rest vertices through the shape directions: vecs^T (W GA)_v shapedirs_v
    W = model.weights
    Mv = (W[verts] @ GA.reshape(J, 9)).reshape(-1, 3, 3)
    vb = np.einsum("ma,mab->mb", vecs, Mv)
    B1 = sparse.csr_matrix((vb.reshape(-1), (np.repeat(rows, 3),
                                             (3 * verts[:, None] + np.arange(3)).reshape(-1))),
                           shape=(n_rows, 3 * V))
    jb = B1 @ np.asarray(model.shapedirs, float).reshape(3 * V, -1)[:, :S]
    # the joints (and bind rotations) through the skinning weights: each row's nonzero w_vj
    Wm = W[verts].tocoo()  # row k of Wm = block m
    mr, mj, mw = rows[Wm.row], Wm.col, Wm.data
    B2 = sparse.csr_matrix(((mw[:, None] * vecs[Wm.row]).reshape(-1),
                            (np.repeat(mr, 3), (3 * mj[:, None] + np.arange(3)).reshape(-1))),
                           shape=(n_rows, 3 * J))
    jb += B2 @ c.reshape(3 * J, S)
    if dA is not None:  # sum_j w_vj vecs . G_j dA_j (v_c - h_j)
        GdA = np.einsum("jab,jbcs->jcas", G, dA).reshape(9 * J, S)  # rows (j, c, a)
        lever = rest.vertices[0, verts[Wm.row]] - h[mj]  # (k, 3)
        val = mw[:, None, None] * lever[:, :, None] * vecs[Wm.row][:, None, :]  # (k, c, a)
        B3 = sparse.csr_matrix((val.reshape(-1), (np.repeat(mr, 9), (9 * mj[:, None]
                                                                      + np.arange(9)).reshape(-1))),
                               shape=(n_rows, 9 * J))
        jb += B3 @ GdA
    B = sparse.csr_matrix((vecs.reshape(-1), (np.repeat(rows, 3),
                                               (3 * verts[:, None] + np.arange(3)).reshape(-1))),
                          shape=(n_rows, 3 * V))
    r0 = B @ _posed_vertices(model, skel, None, x, rest=rest).reshape(-1)
    jx = np.empty((n_rows, len(x)))
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = FD_STEP
        jx[:, k] = (B @ _posed_vertices(model, skel, None, x + e, rest=rest).reshape(-1) - r0) / FD_STEP
    return np.concatenate([jb, jx], axis=1)


def _scan_residuals(model, skel, b, x, rest, corr):
    """Point-to-plane residuals (metres): scan points to their model surface points, then
    sampled model vertices to their nearest scan points."""
    cb, cf, pts, cn, vsel, q_pts, q_n = corr
    faces = np.asarray(model.faces)
    vv = _posed_vertices(model, skel, b, x, rest=rest)
    m = np.einsum("ik,ikd->id", cb, vv[faces[cf]])
    return np.concatenate([np.einsum("id,id->i", m - pts, cn),
                           np.einsum("id,id->i", vv[vsel] - q_pts, q_n)])


def _still_falling(costs: list[float], frac: float, k: int = 3) -> bool:
    """Whether the scan fit's cost still falls: the mean of the last ``k`` iterations' start
    costs is more than ``frac`` below the mean of the ``k`` before them (each iteration samples
    new points, so one iteration's cost moves by a few per cent at the plateau)."""
    if len(costs) < 2 * k:
        return True
    last, before = np.mean(costs[-k:]), np.mean(costs[-2 * k:-k])
    return bool(last < (1 - frac) * before)


def fit_scan(model: BodyModel, points: np.ndarray, normals: np.ndarray | None,
             rng: np.random.Generator, opts: ScanFitOptions = ScanFitOptions(), log=None,
             init: tuple[np.ndarray, np.ndarray] | None = None) -> ScanFit:
    """Fit shape and neutral pose to a scan.

    points : (N, 3) metres, the scan's frame; normals : (N, 3) unit or None (then the model's
    vertex normals stand in for the scan's). Returns :class:`ScanFit`.
    """
    import igl
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float)
    S = min(opts.num_betas, model.num_betas)
    skel = skinned.fit_skeleton(model, body_joints(model))
    n = skel.n
    if init is None:
        betas, x = _rigid_start(model, skel, points, rng, opts, S)
    else:
        betas = np.zeros(S)
        b0 = np.asarray(init[0], float)[:S]
        betas[:len(b0)] = b0
        x = np.array(init[1], dtype=float)
    tree = cKDTree(points)
    faces = np.asarray(model.faces)
    lam = 1e-3
    iters = 0
    stalls = 0
    costs: list[float] = []  # the robust cost at each iteration's start (fresh samples)
    for it in range(max(opts.iters, opts.max_iters or 2 * opts.iters)):
        if it >= opts.iters and not _still_falling(costs, opts.falling_frac):
            break
        iters = it + 1
        # coarse to fine: the first third of the iterations fits only the first betas
        s_on = min(S, COARSE_BETAS) if it < opts.iters // 3 else S
        # last third: the neutral pose pulled to pose 0 (a scan is taken in the neutral
        # pose; a free pose absorbs shape, which the neutral-pose mesh then lacks)
        last_third = it >= opts.iters - opts.iters // 3
        pw = opts.final_pose_weight if last_third else opts.pose_weight
        cut = min(opts.max_pair_m, opts.final_pair_m) if last_third else opts.max_pair_m
        prior_w = np.concatenate([np.full(s_on, opts.beta_weight), np.full(S - s_on, 1e3),
                                  np.zeros(6), np.full(n - 6, pw)])
        rest = rest_state(model, betas)
        v = _posed_vertices(model, skel, betas, x, rest=rest)
        sel = rng.choice(len(points), min(opts.n_points, len(points)), replace=False)
        sp_ = points[sel]
        _, cf, cp = igl.point_mesh_squared_distance(sp_, v, faces)
        cf = np.asarray(cf, dtype=np.int64)
        tri = v[faces[cf]]
        cb = np.clip(np.asarray(igl.barycentric_coordinates(
            cp, tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy())), 0, 1)
        cb /= np.maximum(cb.sum(1, keepdims=True), 1e-12)
        cn = face_normals(v, faces[cf])
        # model vertices sampled by surface area (fingers and face are densely meshed)
        area = np.zeros(len(v))
        np.add.at(area, faces.reshape(-1), np.repeat(face_areas(v, faces) / 3, 3))
        vsel = rng.choice(len(v), min(opts.n_vertices, len(v)), replace=False, p=area / area.sum())
        qd, qi = tree.query(v[vsel])
        vn = igl.per_vertex_normals(v, faces)[vsel]
        q_pts = points[qi]
        q_n = np.asarray(normals, float)[qi] if normals is not None else vn
        # model vertices over the scan's holes (soles, armpits) have their nearest scan point
        # on the hole's rim, often with a normal across theirs: their point-to-plane residual
        # can be small and would pull the unseen surface onto the rim's tangent plane (it
        # flattened the feet). Keep pairs that face the same way (a distance cut too lost the
        # scan where the start is far from it: v2v 6.1 -> 7.4 mm in tests/test_shape_fit.py;
        # the normal test alone gave 4.8).
        ok = (qd < cut) & (np.einsum("id,id->i", vn, q_n) > opts.min_normal_dot)
        vsel, q_pts, q_n = vsel[ok], q_pts[ok], q_n[ok]

        corr = (cb, cf, sp_, cn, vsel, q_pts, q_n)

        def cost(b, xx, rest_b=None, corr=corr, prior_w=prior_w):
            rr = _scan_residuals(model, skel, b, xx, rest_b, corr)
            zz = np.concatenate([b, xx])
            return float(np.mean(robust.rho(rr * rr, "geman_mcclure", opts.sigma_m))
                         + np.sum(prior_w * zz * zz))

        r = _scan_residuals(model, skel, betas, x, rest, corr)
        N = len(r)
        w = robust.weight(r * r, "geman_mcclure", opts.sigma_m) / N
        # Jacobian of the residuals through the vertices they touch
        n1 = len(cf)
        rows = np.concatenate([np.repeat(np.arange(n1), 3), n1 + np.arange(len(vsel))])
        verts = np.concatenate([faces[cf].reshape(-1), vsel])
        vecs = np.concatenate([(cb[:, :, None] * cn[:, None, :]).reshape(-1, 3), q_n])
        Jr = residual_jacobian(model, rest, skel, x, rows, verts, vecs, len(r), S,
                               bind_jacobian(model, betas, S))
        z = np.concatenate([betas, x])
        H = (Jr * w[:, None]).T @ Jr + np.diag(prior_w)
        g = (Jr * w[:, None]).T @ r + prior_w * z
        c0 = cost(betas, x, rest)
        costs.append(c0)
        step = np.zeros_like(z)
        c1 = c0
        for _ in range(10):
            step = -np.linalg.solve(H + lam * np.diag(np.maximum(np.diag(H), 1e-12)), g)
            c1 = cost(z[:S] + step[:S], z[S:] + step[S:])
            if c1 < c0:
                lam = max(lam * 0.3, 1e-7)
                break
            lam *= 10
        else:
            step = np.zeros_like(z)
        z = z + step
        betas, x = z[:S], marker_fit.rewrap(z[S:])
        if log and (iters % 10 == 0 or iters == 1):
            log(f"scan fit iteration {iters}: robust cost {min(c0, c1):.4e}")
        stalls = stalls + 1 if np.abs(step).max() < 1e-7 else 0
        if stalls >= 3:  # no descent on three different point samples: converged
            break
    v = _posed_vertices(model, skel, betas, x)
    d2, _, _ = igl.point_mesh_squared_distance(points, v, faces)
    return ScanFit(betas, x, skel.joints, 1000 * np.sqrt(np.asarray(d2)), iters)


# ---------------------------------------------------------------------------- one subject


@dataclass(frozen=True)
class ShapeFitOptions:
    """The shape fit's options (also the recipe's ``stages.shape_fit`` section).

    num_betas : shape coefficients fitted to a scan; marker_num_betas : without a scan;
    scan_iters, scan_points : scan fit iterations and scan points per iteration; frames :
    well-spread, well-tracked capture frames used to place the markers; rounds : placement
    alternations; slide_sd_mm / offset_sd_mm : prior spread of a marker's slide from the
    template and of its skin offset around the nominal 9.5 mm (millimetres); max_slide_mm /
    max_offset_mm : their hard bounds; track_step : every k-th capture frame is tracked;
    placement_from : with static trials, ``"all"`` (placed and shaped on the static trials
    first, then refined with the movement frames), ``"static"`` (the static trials alone) or
    ``"movement"`` (the static trials unused; ``fitting.placement.PlacementOptions``);
    static_frames : static frames kept beside ``frames`` movement frames in the refinement;
    static_compare : also place from the movement alone and report both placements' movement
    residuals (the static trial's contribution; twice the work);
    compile : how the residual function runs; seed : sampling of scan points."""

    # defaults stated once, in the options of the functions they feed (metres there)
    num_betas: int = ScanFitOptions.num_betas  # all of anny's
    marker_num_betas: int = PlacementOptions.num_betas
    scan_iters: int = ScanFitOptions.iters
    scan_points: int = ScanFitOptions.n_points
    frames: int = PlacementOptions.frames
    rounds: int = PlacementOptions.rounds
    slide_sd_mm: float = PlacementOptions.slide_sd_m * 1000
    offset_sd_mm: float = PlacementOptions.offset_sd_m * 1000
    max_slide_mm: float = PlacementOptions.max_slide_m * 1000
    max_offset_mm: float = PlacementOptions.max_offset_m * 1000
    track_step: int = PlacementOptions.track_step
    placement_from: Literal["all", "static", "movement"] = "all"
    static_frames: int = PlacementOptions.static_frames
    static_compare: bool = False
    compile: Literal["auto", "compiled", "interpreted"] = "auto"
    seed: int = 0

    def __post_init__(self):
        problems = []  # every bad field, in one message
        for name in ("num_betas", "marker_num_betas", "scan_iters", "scan_points", "frames",
                     "rounds", "track_step"):
            if getattr(self, name) < 1:
                problems.append(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("slide_sd_mm", "offset_sd_mm", "max_slide_mm", "max_offset_mm"):
            if not getattr(self, name) > 0:
                problems.append(f"{name}: must be > 0, got {getattr(self, name)}")
        if self.static_frames < 0:
            problems.append(f"static_frames: must be >= 0, got {self.static_frames}")
        if self.placement_from not in PLACEMENT_FROM:
            problems.append(f"placement_from: must be one of {', '.join(PLACEMENT_FROM)}, "
                            f"got {self.placement_from!r}")
        if self.compile not in marker_fit.COMPILE_MODES:
            problems.append(f"compile: must be one of {', '.join(marker_fit.COMPILE_MODES)}, "
                            f"got {self.compile!r}")
        if problems:
            raise ValueError("; ".join(problems))

    def scan(self) -> ScanFitOptions:
        return ScanFitOptions(num_betas=self.num_betas, iters=self.scan_iters,
                              n_points=self.scan_points)

    def placement(self) -> PlacementOptions:
        return PlacementOptions(rounds=self.rounds, slide_sd_m=self.slide_sd_mm / 1000,
                                offset_sd_m=self.offset_sd_mm / 1000,
                                max_slide_m=self.max_slide_mm / 1000,
                                max_offset_m=self.max_offset_mm / 1000,
                                num_betas=self.marker_num_betas, frames=self.frames,
                                track_step=self.track_step, placement_from=self.placement_from,
                                static_frames=self.static_frames)


def _mm_stats(d: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(d)), "p90": float(np.percentile(d, 90)),
            "p99": float(np.percentile(d, 99)), "mean": float(np.mean(d))}


def _finite(v) -> float | None:
    """A report float: None for NaN / inf ("not seen")."""
    v = float(v)
    return v if np.isfinite(v) else None


def _stats(a: np.ndarray) -> dict[str, float | None]:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    if not len(a):
        return {"median": None, "p90": None}
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90))}


def shape_from_scan(model: BodyModel, points: np.ndarray, normals: np.ndarray | None,
                    opts: ShapeFitOptions, rng: np.random.Generator, log=None
                    ) -> tuple[np.ndarray, dict]:
    """Betas (S,) fitted to a scan (:func:`fit_scan`) and a report (scan distances in mm)."""
    if log:
        log(f"fitting {opts.num_betas} shape coefficients to {len(points)} scan points")
    sf = fit_scan(model, points, normals, rng, opts.scan(), log=log)
    return sf.betas, {"shape_source": "scan", "scan_points": int(len(points)),
                      "scan_to_model_mm": _mm_stats(sf.scan_to_model_mm),
                      "scan_iterations": sf.iterations}


def fit_placement(model: BodyModel, shape, captures, opts: ShapeFitOptions, log=None,
                  names=None, static=(), static_names=None):
    """MoSh stage I on a subject's captures (``fitting.placement.refine_placement``):
    ``shape``'s placement (the template) refined, and, when ``shape.shape_source ==
    "markers"``, its betas fitted too.

    shape : :class:`artifacts.ShapeFit` to start from; captures : sequence of (F_i, M, 3)
    marker arrays (metres, NaN gaps, the placement's marker order) of movement; static : the
    same for static trials (placed from first, ``opts.placement_from``); names /
    static_names : the captures' names in the report (default their index as a string,
    ``static<i>``). Returns ``(ShapeFit with placement_source "refined", report)``
    (residuals, slides and offsets in mm; every float finite, None where a marker was not
    seen; with static trials ``static_trial``: what they contributed)."""
    template = placement_of(shape)
    captures = [np.asarray(c, float) for c in captures]
    static = [np.asarray(c, float) for c in static]
    names = [str(i) for i in range(len(captures))] if names is None else [str(n) for n in names]
    snames = ([f"static{i}" for i in range(len(static))] if static_names is None
              else [str(n) for n in static_names])
    skel = skinned.fit_skeleton(model, body_joints(model))
    graph = MarkerGraph(GraphSpec(skel.topology, marker_support(model, skel, template)),
                        compiled.CompileOptions(mode=opts.compile), log=log)
    prior = priors.default_prior(skel.names[1:])

    def make_solver(_rest, skel_, u, Hm):
        return marker_fit.FrameSolver(graph, skel_, u, Hm, prior, marker_fit.MarkerFitOptions())

    fit_betas = str(shape.shape_source) == "markers"
    pf = refine_placement(model, shape.betas, template, captures, make_solver,
                          opts.placement(), fit_betas=fit_betas, log=log, static=static)
    names = snames + names  # PlacementFit.frames index the static trials first
    M = len(template.names)
    rest0 = rest_state(model, pf.betas)
    faces = np.asarray(model.faces)
    moved = np.linalg.norm(marker_rest_points(rest0.vertices[0], faces, pf.placement)
                           - marker_rest_points(rest0.vertices[0], faces, template), axis=1) * 1000
    with warnings.catch_warnings():  # a marker never seen: None, no warning
        warnings.simplefilter("ignore", RuntimeWarning)
        per = np.nanmedian(pf.residual_mm, axis=0) if len(pf.residual_mm) else np.full(M, np.nan)
    tr = (np.concatenate([t.residual_m for t in pf.tracks]) * 1000 if pf.tracks
          else np.zeros((0, M)))
    report = {
        "placement_frames": [{"capture": names[c], "frame": int(f)} for c, f in pf.frames],
        "placement_frames_note": "frame: index into that capture's marker samples",
        "placement_residual_mm": {**_stats(pf.residual_mm),
                                  "per_marker_median": {n: _finite(v) for n, v in
                                                        zip(template.names, per, strict=True)}},
        "placement_moved_mm": {"median": float(np.median(moved)), "max": float(np.max(moved))},
        "placement_slide_mm": {n: float(v * 1000) for n, v in
                               zip(template.names, pf.slide_m, strict=True)},
        "placement_offset_mm": {n: float(v * 1000) for n, v in
                                zip(template.names, pf.offset_m, strict=True)},
        "placement_slide_max_mm": float(np.max(pf.slide_m) * 1000),
        "placement_offset_max_mm": float(np.max(pf.offset_m) * 1000),
        "markers_off_segment": list(pf.off_segment),
        "markers_on_wand": list(pf.on_wand),
        "tracking_residual_mm": {**_stats(tr), "frames": int(len(tr)),
                                 "step": int(opts.track_step),
                                 "per_marker": {n: _stats(tr[:, i]) for i, n in
                                                enumerate(template.names)}},
        "tracking_outlier_marker_frames": int(pf.outliers),
        "betas_norm": float(np.linalg.norm(pf.betas)),
    }
    if static:
        report["static_trial"] = static_contribution(model, pf, template, names, len(static),
                                                     opts.placement_from)
    return to_shape_fit(pf.betas, pf.placement, str(shape.shape_source), "refined"), report


def _pooled_mm(tracks_m) -> dict[str, float | None]:
    """Median / p90 / frames of tracked residuals (list of (T, M) metres, NaN unseen)."""
    a = (np.concatenate([np.asarray(t, float).reshape(-1) for t in tracks_m]) * 1000
         if tracks_m else np.zeros(0))
    return {**_stats(a), "marker_frames": int(np.isfinite(a).sum())}


def static_contribution(model: BodyModel, pf: PlacementFit, template: Placement, names,
                        n_static: int, placement_from: str) -> dict:
    """What the static trials contributed to a placement (``refine_placement(static=...)``):
    the placement frames taken from each capture and the static trials' share of them; the
    placement from the static trials alone (its residual on its static frames, the movement
    tracked with it) against the final one (the movement tracked with it, how far the
    movement frames moved each marker from it, the change of betas)."""
    used = {n: 0 for n in names}
    for c, _ in pf.frames:
        used[names[c]] += 1
    n_st = sum(1 for c, _ in pf.frames if c < n_static)
    out = {"placement_from": pf.static["placement_from"] if pf.static else "movement",
           "option": placement_from, "frames_used": used,
           "static_share_of_placement_frames": n_st / max(len(pf.frames), 1),
           "final": {"movement_tracking_mm": _pooled_mm(
               [t.residual_m for t in pf.tracks[n_static:]]),
               "static_tracking_mm": _pooled_mm([t.residual_m for t in pf.tracks[:n_static]])}}
    if pf.static is None:
        out["note"] = "placement_from movement: the static trials were not used"
        return out
    faces = np.asarray(model.faces)
    rv = rest_state(model, pf.betas).vertices[0]
    moved = np.linalg.norm(marker_rest_points(rv, faces, pf.placement)
                           - marker_rest_points(rv, faces, pf.static["static_placement"]),
                           axis=1) * 1000
    sb, fb = pf.static["static_betas"], np.asarray(pf.betas, float)
    out["static_only"] = {
        "placement_residual_mm": _stats(pf.static["static_residual_mm"]),
        "movement_tracking_mm": _pooled_mm(pf.static["movement_tracking_static_m"]),
        "betas_norm": float(np.linalg.norm(sb))}
    out["moved_by_movement_mm"] = {"median": float(np.median(moved)),
                                   "max": float(np.max(moved)),
                                   "per_marker": {n: float(v) for n, v in
                                                  zip(template.names, moved, strict=True)}}
    out["betas_change_norm"] = float(np.linalg.norm(fb - sb[:len(fb)]))
    return out


def fit_shape(model: BodyModel, template: Placement, scan, captures, opts: ShapeFitOptions,
              rng: np.random.Generator, log=None, static=(), names=None, static_names=None):
    """A subject's shape and marker placement.

    template : the marker set's template placement; scan : ``(points (N, 3), normals (N, 3) or
    None)`` metres, or None; captures : sequence of (F_i, M, 3) marker arrays of the
    sequences the subject wears markers in (template order, NaN gaps), possibly empty;
    static : the same for static trials (``opts.placement_from``: placed from first, then
    refined with the captures, by default); names / static_names : their names in the report
    (default ``"0"``, ``"1"``, ... and ``"static0"``, ...). With ``opts.static_compare`` the
    placement is also fitted from the captures alone and the report's ``static_trial.
    without_static`` gives its movement residual beside the final one's.
    The shape comes from the scan, else from the markers (MoSh stage I, less accurate),
    else it is the mean shape; the placement is refined on the captures when there are any.
    Returns ``(artifacts.ShapeFit, report)``.
    """
    report: dict = {"body_model": model.name, "num_markers": len(template.names)}
    static = list(static)
    captures = list(captures)
    names = [str(i) for i in range(len(captures))] if names is None else list(names)
    snames = ([f"static{i}" for i in range(len(static))] if static_names is None
              else list(static_names))
    st_pairs = [(c, n) for c, n in zip(static, snames, strict=True) if len(c)]
    mv_pairs = [(c, n) for c, n in zip(captures, names, strict=True) if len(c)]
    static, snames = [c for c, _ in st_pairs], [n for _, n in st_pairs]
    captures, names = [c for c, _ in mv_pairs], [n for _, n in mv_pairs]
    anything = static + captures
    if scan is not None:
        betas, rep = shape_from_scan(model, scan[0], scan[1], opts, rng, log)
        report.update(rep)
    elif anything:
        report["shape_source"] = "markers"
        report["note"] = ("no scan: the shape is fitted to the markers of well-spread, "
                          "well-tracked frames (MoSh stage I), less accurate than a scan fit")
        betas = np.zeros(opts.marker_num_betas)
    else:
        report["shape_source"] = "mean"
        report["note"] = "no scan and no marker capture: mean shape"
        betas = np.zeros(opts.num_betas)
    out = to_shape_fit(betas, template, report["shape_source"], "template")
    if anything:
        start = out
        out, rep = fit_placement(model, start, captures, opts, log, names=names, static=static,
                                 static_names=snames)
        report.update(rep)
        if opts.static_compare and static and captures and opts.placement_from != "movement":
            from dataclasses import replace as _replace

            _, alone = fit_placement(model, start, captures,
                                     _replace(opts, placement_from="movement"), log,
                                     names=names, static=static, static_names=snames)
            report["static_trial"]["without_static"] = {
                "movement_tracking_mm": alone["static_trial"]["final"]["movement_tracking_mm"],
                "placement_residual_mm": {k: alone["placement_residual_mm"][k]
                                          for k in ("median", "p90")},
                "betas_norm": alone["betas_norm"]}
    else:
        report["placement"] = "template (no capture to refine it)"
    report["num_betas"] = int(len(out.betas))
    return out, report
