"""Subject shape: fit to a body scan, then place the markers on that body (MoSh++ stage I idea).

1. ``fit_scan``: shape ``betas`` (the first S of the model's basis), a neutral pose of the body
   joints, and the rigid transform from the model to the scan's frame, minimising robust
   (Geman-McClure) point-to-plane distances in both directions: scan points to the model
   surface (closest points with ``igl.point_mesh_squared_distance``) and model vertices to the
   scan (nearest scan point, its normal). Holes in the scan leave model vertices far from any
   scan point: the robust loss gives them ~0 weight. A Gaussian prior on betas (whitened, unit
   variance) and on the pose keeps unobserved directions put. Damped Gauss-Newton with a
   forward-difference Jacobian of ``body.lbs.forward`` (the full mesh in numpy: ~100 params).
2. ``refine_placement``: with the shape fixed, alternate (a) the poses of a handful of frames
   (the compiled marker graph, as in marker_fit) and (b) each marker's rest position, a linear
   least-squares problem once the poses are fixed, regularised toward the template placement,
   then re-projected on the surface as (face, barycentric, offset along the normal).
3. no scan (``fit_betas``): betas are fitted to the markers of those frames too (a third
   alternation step, forward-difference Gauss-Newton on betas with poses and placement fixed).

:func:`fit_shape` is the whole subject (scan fit, else marker-based shape, else the mean;
then the placement on the captures), returning an ``artifacts.ShapeFit`` and a report;
:func:`shape_from_scan` and :func:`fit_placement` are its two steps. No file I/O: the stage
adapter ``stages/shape_fit.py`` reads the scan and the captures.

Placement: ``face (M,)`` model face index, ``bary (M, 3)`` barycentric coordinates,
``offset (M,)`` metres along the rest-pose face normal (outwards). A marker skins like the
blend of its face's vertices (weights interpolated with ``bary``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from body.lbs import forward, rest_state
from body.model import BodyModel
from body.rotations import rodrigues
from fitting import compiled, marker_fit, priors, robust, skinned
from fitting.marker_graph import (
    GraphSpec,
    MarkerGraph,
    Placement,
    body_joints,
    marker_coeffs,
    marker_rest_points,
    marker_support,
    marker_weights,
    placement_of,
    to_shape_fit,
)
from geometry import face_areas, face_normals

# constants
FD_STEP = 1e-6
COARSE_BETAS = 10  # scan fit: betas fitted in the first third of the iterations
SIZE_GRID = (-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0)  # marker-based shape: start grid (betas 0, 1)


# ---------------------------------------------------------------------------- surface helpers


def project_to_surface(rest_vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest surface points of ``points (M, 3)``: (face (M,), bary (M, 3), signed offset (M,)
    along the face normal)."""
    import igl

    _, fidx, closest = igl.point_mesh_squared_distance(points, rest_vertices, faces)
    fidx = np.asarray(fidx, dtype=np.int64)
    tri = rest_vertices[faces[fidx]]
    bary = igl.barycentric_coordinates(closest, tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy())
    bary = np.clip(np.asarray(bary), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    n = face_normals(rest_vertices, faces[fidx])
    surf = np.einsum("mk,mkd->md", bary, tri)
    off = np.einsum("md,md->m", points - surf, n)
    return fidx, bary, off


# ---------------------------------------------------------------------------- scan fit


@dataclass(frozen=True)
class ScanFitOptions:
    """num_betas: shape coefficients fitted; n_points: scan points sampled per iteration;
    n_vertices: model vertices sampled for the model-to-scan direction; iters: Gauss-Newton
    iterations; sigma_m: Geman-McClure scale (metres); beta_weight, pose_weight: prior
    weights (residual units: metres^2 per point, averaged); headings: initial rotations about
    the vertical tried for the rigid start; max_pair_m, min_normal_dot: a model vertex's pair
    with its nearest scan point is used only if closer than this and their normals' dot
    product exceeds this (holes); final_pair_m: the distance cut of the last third of the
    iterations (a cut from the start loses the scan when the start is far from it)."""

    num_betas: int = 404  # all of anny's: 150 left 6.3 mm v2v on the bench, 404 gives 4.4
    n_points: int = 4000
    n_vertices: int = 2000
    iters: int = 40
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


def bind_jacobian(model: BodyModel, betas: np.ndarray, S: int, eps: float = 1e-5):
    """d bind_rotations / d betas[:S]: (J, 3, 3, S) by central differences, or None for models
    without bind rotations (the SMPL family)."""
    from body.lbs import bind_rotations, pad_betas

    if model.orient_template is None:
        return None
    b = pad_betas(model, betas)
    E = np.zeros((2 * S, b.shape[1]))
    E[np.arange(S), np.arange(S)] = eps
    E[S + np.arange(S), np.arange(S)] = -eps
    A = bind_rotations(model, b + E)  # (2S, J, 3, 3)
    return np.moveaxis((A[:S] - A[S:]) / (2 * eps), 0, -1)


def vertex_jacobian(model: BodyModel, rest, skel: skinned.FitSkeleton, x: np.ndarray,
                    vids: np.ndarray, S: int, dA: np.ndarray | None = None) -> np.ndarray:
    """d vertices[vids] / d [betas[:S], x]: (len(vids), 3, S + n).

    Betas: analytic through the rest vertices, rest joints and offsets, plus the bind
    rotations through ``dA = bind_jacobian(...)`` (J, 3, 3, S) when given (Anny's reference
    posture changes with the shape: ignoring it lets the pose absorb shape); x: forward
    differences with the rest state fixed (``FD_STEP``)."""
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
    c = dt - np.einsum("jab,jbs->jas", GA, dh)  # (J, 3, S)
    W = model.weights[vids]  # (n_v, J) sparse
    Mv = (W @ GA.reshape(J, 9)).reshape(-1, 3, 3)
    sd = np.asarray(model.shapedirs[vids, :, :S], dtype=float)
    jb = np.einsum("vab,vbs->vas", Mv, sd) + (W @ c.reshape(J, -1)).reshape(-1, 3, S)
    if dA is not None:  # skinning: sum_j w_vj G_j dA_j (v_c - h_j)
        GdA = np.einsum("jab,jbcs->jacs", G, dA)  # (J, 3, 3, S)
        Mv_d = (W @ GdA.reshape(J, -1)).reshape(-1, 3, 3, S)
        jb += np.einsum("vacs,vc->vas", Mv_d, rest.vertices[0, vids])
        jb -= (W @ np.einsum("jacs,jc->jas", GdA, h).reshape(J, -1)).reshape(-1, 3, S)
    v0 = _posed_vertices(model, skel, None, x, rest=rest)[vids]
    jx = np.zeros((len(vids), 3, len(x)))
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = FD_STEP
        jx[:, :, k] = (_posed_vertices(model, skel, None, x + e, rest=rest)[vids] - v0) / FD_STEP
    return np.concatenate([jb, jx], axis=2)


def _scan_residuals(model, skel, b, x, rest, corr):
    """Point-to-plane residuals (metres): scan points to their model surface points, then
    sampled model vertices to their nearest scan points."""
    cb, cf, pts, cn, vsel, q_pts, q_n = corr
    faces = np.asarray(model.faces)
    vv = _posed_vertices(model, skel, b, x, rest=rest)
    m = np.einsum("ik,ikd->id", cb, vv[faces[cf]])
    return np.concatenate([np.einsum("id,id->i", m - pts, cn),
                           np.einsum("id,id->i", vv[vsel] - q_pts, q_n)])


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
    for it in range(opts.iters):
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
        vids = np.unique(np.concatenate([faces[cf].reshape(-1), vsel]))
        pos = np.full(len(v), -1)
        pos[vids] = np.arange(len(vids))
        Jv = vertex_jacobian(model, rest, skel, x, vids, S, bind_jacobian(model, betas, S))
        J1 = np.einsum("ik,id,ikdz->iz", cb, cn, Jv[pos[faces[cf]]])
        J2 = np.einsum("id,idz->iz", q_n, Jv[pos[vsel]])
        Jr = np.concatenate([J1, J2])
        z = np.concatenate([betas, x])
        H = (Jr * w[:, None]).T @ Jr + np.diag(prior_w)
        g = (Jr * w[:, None]).T @ r + prior_w * z
        c0 = cost(betas, x, rest)
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


# ---------------------------------------------------------------------------- placement


@dataclass(frozen=True)
class PlacementOptions:
    """rounds: alternations; slide_sd_m / offset_sd_m: prior spread of the placement around
    the template (tangential / along the normal), metres; data_sd_m: expected marker error
    (noise plus model error) that weighs the data against that prior; pose_iters: LM iterations per pose;
    num_betas, beta_weight, beta_steps: for the marker-based shape (no scan): coefficients,
    prior weight, Gauss-Newton steps per round."""

    rounds: int = 4
    slide_sd_m: float = 0.02
    offset_sd_m: float = 0.005
    data_sd_m: float = 0.002
    pose_iters: int = 30
    num_betas: int = 20
    beta_weight: float = 1e-4
    beta_steps: int = 3
    beta_sigma_m: float = 0.03


def _solve_poses(solver, obs, vis, X=None):
    out = []
    for f in range(len(obs)):
        if X is None:
            x0 = marker_fit.initial_pose(solver.skel, solver.u, solver.Hm, obs[f], vis[f])
            r = solver.solve(x0, obs[f], vis[f], first=True)
        else:
            r = solver.solve(X[f], obs[f], vis[f])
        out.append(marker_fit.rewrap(r.x))
    return np.array(out)


def _update_placement(model, rest, skel, u, pl: Placement, X, obs, vis, opts: PlacementOptions
                      ) -> Placement:
    """Per marker: the rest point minimising |posed - observed|^2 over frames plus the prior,
    linear in the rest point once poses and skinning weights are fixed."""
    faces = np.asarray(model.faces)
    Wm = marker_weights(model, pl).toarray()  # (M, J)
    h = rest.joints[0]
    A = rest.bind_rot[0] if rest.bind_rot is not None else np.broadcast_to(np.eye(3), (len(h), 3, 3))
    _, s = skinned.reduced_offsets(model, rest, skel)
    frames = [skinned._fk_np(skel, u, x) for x in X]
    p0 = marker_rest_points(rest.vertices[0], faces, pl)
    n0 = face_normals(rest.vertices[0], faces[pl.face])
    new = np.zeros_like(p0)
    for m in range(len(p0)):
        js = np.flatnonzero(Wm[m] > 0)
        rows_A, rows_b = [], []
        for f, (G, t) in enumerate(frames):
            if vis[f, m] <= 0:
                continue
            # world = sum_j w_j (G_o A_j (p - h_j) + G_o s_j + t_o), o = owner(j)
            L = np.zeros((3, 3))
            c = np.zeros(3)
            for j in js:
                o = skel.owner[j]
                L += Wm[m, j] * G[o] @ A[j]
                c += Wm[m, j] * (G[o] @ (s[j] - A[j] @ h[j]) + t[o])
            rows_A.append(L / opts.data_sd_m)
            rows_b.append((obs[f, m] - c) / opts.data_sd_m)
        # prior: tangential slide ~ slide_sd, normal offset ~ offset_sd around the template
        P = np.eye(3) - np.outer(n0[m], n0[m])
        prior = P / opts.slide_sd_m + np.outer(n0[m], n0[m]) / opts.offset_sd_m
        rows_A.append(prior)
        rows_b.append(prior @ p0[m])
        AA = np.concatenate(rows_A)
        bb = np.concatenate(rows_b)
        new[m] = np.linalg.lstsq(AA, bb, rcond=None)[0]
    face, bary, off = project_to_surface(rest.vertices[0], faces, new)
    return replace(pl, face=face, bary=bary, offset=off)


def _beta_step(model, skel, betas, pl, X, obs, vis, opts):
    """One damped Gauss-Newton step on betas with poses and placement fixed."""
    S = len(betas)

    def markers(b):
        rest = rest_state(model, b)
        u, _ = skinned.reduced_offsets(model, rest, skel)
        Hm = marker_coeffs(model, rest, skel, pl)
        return np.concatenate([Hm.positions(skel, u, x) for x in X])

    ok = (vis > 0).reshape(-1)
    target = obs.reshape(-1, 3)
    m0 = markers(betas)
    e0 = (m0 - target)[ok]
    r = e0.reshape(-1)
    # Geman-McClure IRLS weights per marker: poses solved with a wrong shape leave outliers
    sw = np.repeat(np.sqrt(robust.weight(np.sum(e0 * e0, axis=1), "geman_mcclure",
                                         opts.beta_sigma_m)), 3)
    J = np.zeros((len(r), S))
    for k in range(S):
        e = np.zeros(S)
        e[k] = 1e-4
        J[:, k] = ((markers(betas + e) - target)[ok].reshape(-1) - r) / 1e-4
    J *= sw[:, None]
    r = r * sw
    w = opts.beta_weight * len(r)
    H = J.T @ J + w * np.eye(S)
    return betas - np.linalg.solve(H + 1e-3 * np.diag(np.diag(H)), J.T @ r + w * betas)


def _size_start(model, skel, betas, pl, obs, vis, make_solver) -> np.ndarray:
    """Marker-based shape start: the mean body can be far from the subject (anny's mean
    spans children to adults), and poses fitted with a wrong size fold limbs. Try a grid over
    the first two betas (the largest size/build modes of the whitened basis) and keep the
    body whose per-frame pose fits leave the smallest robust marker residual."""
    best = (np.inf, betas)
    for b0 in SIZE_GRID:
        for b1 in SIZE_GRID[::2]:
            cand = betas.copy()
            cand[0] = b0
            if len(cand) > 1:
                cand[1] = b1
            rest = rest_state(model, cand)
            u, _ = skinned.reduced_offsets(model, rest, skel)
            Hm = marker_coeffs(model, rest, skel, pl)
            solver = make_solver(rest, skel, u, Hm)
            cost = sum(solver.solve(marker_fit.initial_pose(skel, u, Hm, o, v), o, v,
                                    first=True).cost for o, v in zip(obs, vis, strict=True))
            if cost < best[0]:
                best = (cost, cand)
    return best[1]


@dataclass
class PlacementFit:
    """placement, betas (S,), poses X (K, n) of the frames used, residual_mm (K, M) NaN where
    not visible, rounds."""

    placement: Placement
    betas: np.ndarray
    X: np.ndarray
    residual_mm: np.ndarray


def refine_placement(model: BodyModel, betas: np.ndarray, pl: Placement, obs: np.ndarray,
                     vis: np.ndarray, make_solver, opts: PlacementOptions = PlacementOptions(),
                     fit_betas: bool = False, log=None) -> PlacementFit:
    """MoSh++ stage I: marker placement (and, with ``fit_betas``, shape) from a few frames.

    obs : (K, M, 3) metres, world, of well-spread frames; vis : (K, M).
    make_solver(rest, skel, u, Hm) -> marker_fit.FrameSolver over the body joints.
    """
    betas = np.array(betas, dtype=float)
    skel = skinned.fit_skeleton(model, body_joints(model))
    if fit_betas:
        betas = _size_start(model, skel, betas, pl, obs, vis, make_solver)
    X = None
    rounds = 2 * opts.rounds if fit_betas else opts.rounds  # shape, placement, poses: slower
    for k in range(rounds):
        rest = rest_state(model, betas)
        u, _ = skinned.reduced_offsets(model, rest, skel)
        Hm = marker_coeffs(model, rest, skel, pl)
        solver = make_solver(rest, skel, u, Hm)
        X = _solve_poses(solver, obs, vis, X)
        pl = _update_placement(model, rest, skel, u, pl, X, obs, vis, opts)
        if fit_betas:
            for _ in range(opts.beta_steps):
                betas = _beta_step(model, skel, betas, pl, X, obs, vis, opts)
        if log:
            log(f"placement round {k + 1}/{rounds}")
    rest = rest_state(model, betas)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    Hm = marker_coeffs(model, rest, skel, pl)
    solver = make_solver(rest, skel, u, Hm)
    X = _solve_poses(solver, obs, vis, X)
    res = np.stack([np.linalg.norm(Hm.positions(skel, u, x) - np.nan_to_num(o),
                                   axis=1) for x, o in zip(X, obs, strict=True)])
    res = np.where(vis > 0, 1000 * res, np.nan)
    return PlacementFit(pl, betas, X, res)


def spread_frames(vis: np.ndarray, obs: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` well-spread frames: mostly-visible frames chosen by farthest-point
    sampling on the marker configuration (centred), so poses differ."""
    F = len(obs)
    frac = (vis > 0).mean(axis=1)
    cand = np.flatnonzero(frac >= min(0.9, frac.max()))
    if len(cand) <= k:
        return cand
    feat = np.nan_to_num(obs[cand] - np.nanmean(obs[cand], axis=1, keepdims=True)).reshape(len(cand), -1)
    chosen = [int(np.argmax(frac[cand]))]
    d = np.linalg.norm(feat - feat[chosen[0]], axis=1)
    while len(chosen) < k:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(feat - feat[i], axis=1))
    del F
    return np.sort(cand[chosen])


# ---------------------------------------------------------------------------- one subject


@dataclass(frozen=True)
class ShapeFitOptions:
    """The shape fit's options (also the recipe's ``stages.shape_fit`` section).

    num_betas : shape coefficients fitted to a scan; marker_num_betas : without a scan;
    scan_iters, scan_points : scan fit iterations and scan points per iteration; frames :
    well-spread capture frames used to place the markers; rounds : placement alternations;
    slide_sd_mm / offset_sd_mm : how far a marker may move from the template (prior spread,
    millimetres); compile : how the residual function runs; seed : sampling of scan points."""

    # defaults stated once, in the options of the functions they feed (metres there)
    num_betas: int = ScanFitOptions.num_betas  # all of anny's
    marker_num_betas: int = PlacementOptions.num_betas
    scan_iters: int = ScanFitOptions.iters
    scan_points: int = ScanFitOptions.n_points
    frames: int = 8
    rounds: int = PlacementOptions.rounds
    slide_sd_mm: float = PlacementOptions.slide_sd_m * 1000
    offset_sd_mm: float = PlacementOptions.offset_sd_m * 1000
    compile: Literal["auto", "compiled", "interpreted"] = "auto"
    seed: int = 0

    def __post_init__(self):
        problems = []  # every bad field, in one message
        for name in ("num_betas", "marker_num_betas", "scan_iters", "scan_points", "frames",
                     "rounds"):
            if getattr(self, name) < 1:
                problems.append(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("slide_sd_mm", "offset_sd_mm"):
            if not getattr(self, name) > 0:
                problems.append(f"{name}: must be > 0, got {getattr(self, name)}")
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
                                num_betas=self.marker_num_betas)


def _mm_stats(d: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(d)), "p90": float(np.percentile(d, 90)),
            "mean": float(np.mean(d))}


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


def fit_placement(model: BodyModel, shape, captures, opts: ShapeFitOptions, log=None):
    """MoSh++ stage I on a subject's captures: ``shape``'s placement (the template) refined,
    and, when ``shape.shape_source == "markers"``, its betas fitted too.

    shape : :class:`artifacts.ShapeFit` to start from; captures : sequence of (F_i, M, 3)
    marker arrays (metres, NaN gaps, the placement's marker order). Returns
    ``(ShapeFit with placement_source "refined", report)`` (residuals and moves in mm)."""
    template = placement_of(shape)
    obs_all = np.concatenate([np.asarray(c, float) for c in captures])
    vis = np.all(np.isfinite(obs_all), axis=2)
    idx = spread_frames(vis, obs_all, opts.frames)
    obs = obs_all[idx]
    skel = skinned.fit_skeleton(model, body_joints(model))
    graph = MarkerGraph(GraphSpec(skel.topology, marker_support(model, skel, template)),
                        compiled.CompileOptions(mode=opts.compile), log=log)
    prior = priors.default_prior(skel.names[1:])

    def make_solver(_rest, skel_, u, Hm):
        return marker_fit.FrameSolver(graph, skel_, u, Hm, prior, marker_fit.MarkerFitOptions())

    pf = refine_placement(model, shape.betas, template, obs, vis[idx].astype(float),
                          make_solver, opts.placement(),
                          fit_betas=str(shape.shape_source) == "markers", log=log)
    per = np.nanmedian(pf.residual_mm, axis=0)
    rest0 = rest_state(model, pf.betas)
    faces = np.asarray(model.faces)
    moved = np.linalg.norm(marker_rest_points(rest0.vertices[0], faces, pf.placement)
                           - marker_rest_points(rest0.vertices[0], faces, template), axis=1) * 1000
    report = {
        "placement_frames": [int(i) for i in idx],
        "placement_residual_mm": {"median": float(np.nanmedian(pf.residual_mm)),
                                  "p90": float(np.nanpercentile(pf.residual_mm, 90)),
                                  "per_marker_median": {n: float(v) for n, v in
                                                        zip(template.names, per, strict=True)}},
        "placement_moved_mm": {"median": float(np.median(moved)), "max": float(np.max(moved))},
    }
    return to_shape_fit(pf.betas, pf.placement, str(shape.shape_source), "refined"), report


def fit_shape(model: BodyModel, template: Placement, scan, captures, opts: ShapeFitOptions,
              rng: np.random.Generator, log=None):
    """A subject's shape and marker placement.

    template : the marker set's template placement; scan : ``(points (N, 3), normals (N, 3) or
    None)`` metres, or None; captures : sequence of (F_i, M, 3) marker arrays of the
    sequences the subject wears markers in (template order, NaN gaps), possibly empty.
    The shape comes from the scan, else from the markers (MoSh++ stage I, less accurate),
    else it is the mean shape; the placement is refined on the captures when there are any.
    Returns ``(artifacts.ShapeFit, report)``.
    """
    report: dict = {"body_model": model.name, "num_markers": len(template.names)}
    captures = [c for c in captures if len(c)]
    if scan is not None:
        betas, rep = shape_from_scan(model, scan[0], scan[1], opts, rng, log)
        report.update(rep)
    elif captures:
        report["shape_source"] = "markers"
        report["note"] = ("no scan: the shape is fitted to the markers of a few well-spread "
                          "frames (MoSh++ stage I), less accurate than a scan fit")
        betas = np.zeros(opts.marker_num_betas)
    else:
        report["shape_source"] = "mean"
        report["note"] = "no scan and no marker capture: mean shape"
        betas = np.zeros(opts.num_betas)
    out = to_shape_fit(betas, template, report["shape_source"], "template")
    if captures:
        out, rep = fit_placement(model, out, captures, opts, log)
        report.update(rep)
    else:
        report["placement"] = "template (no capture to refine it)"
    report["num_betas"] = int(len(out.betas))
    return out, report
