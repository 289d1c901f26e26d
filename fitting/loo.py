"""Leave-one-out marker error: the honest accuracy figure of a marker fit on real data.

A fit's own residuals flatter it (each marker pulled the body towards itself). Here each
marker ``m`` in turn is hidden (its observations set to NaN), the sequence is refitted by the
same path as the stage (:func:`fitting.marker_fit.fit_markers`), and ``m`` is predicted from
the fitted body through the subject's placement (posed surface point + offset along the posed
face normal, ``fitting.skinned.SkinnedPoints``, the same marker definition as
``body.markers.marker_positions``). The distance to the observed ``m`` is what a marker the
fit never saw is off by: placement error + pose error + soft tissue.

The refits run with the marker fit's own options (``opts``: the recipe's
``stages.marker_fit`` section), so leave-one-out scores the fit the stage made.

``stride`` fits every k-th video frame only (default ``DEFAULT_STRIDE`` = 2).

How the refits run (:class:`_Refits`): frame after frame, the full fit (every marker) by
``fit_markers``' own path, then every held marker's refit of that frame together, each
started from its own previous frame moved by the full fit's motion and solved by the same
Levenberg-Marquardt steps as ``fitting.lm.solve``, vectorised over the held markers. Measured
on the real pyCGM capture (323 frames, 39 markers, stride 2, a shared and loaded 2-core
machine; old and new run in turn): 24-26 -> 5.9-6.3 CPU-s (12.5-13 -> 51-55 frames per
CPU-second; under heavier load 42 -> 9-11 CPU-s), median 6.855 -> 6.851 mm, p90 30.91 ->
30.98 mm; ~1 CPU-s of it was building the compiled graph. That graph is now kept per
thread (:func:`_graph`: a later call with the same subject reuses it) and its library is
found without generating its C (``fitting.compiled.function_key``): ~0.6 CPU-s on a first
call, nothing on a later one. With the graph compiled for the host CPU (``gcc -O2
-march=native``, ``fitting.compiled``) the six real captures of ``bench/cases/real.py`` went
from 36.4 to 58.5 frames per CPU-s pooled (Derrick's serve 26.5 -> 49.5, the slowest),
medians unchanged to 0.001 mm; an evaluation is then ~40 % of a refit's time, the batched
normal equations and solves most of the rest.
"""
from __future__ import annotations

import threading
import time
import warnings

import numpy as np

from artifacts import ShapeFit
from body.lbs import rest_state
from body.rotations import rotmat_to_rotvec
from fitting import mocap, skinned
from fitting.marker_fit import MarkerFitOptions, fit_markers, pack
from fitting.marker_graph import Placement, marker_coeffs, placement_of
from formats.c3d import Markers
from formats.errors import InputError

DEFAULT_STRIDE = 2
DEFAULT_FIT_OPTIONS = MarkerFitOptions()


def _stats_mm(d_m: np.ndarray) -> dict:
    d = np.asarray(d_m, float) * 1000
    if d.size == 0:
        return {"median_mm": None, "p90_mm": None, "frames": 0}
    return {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)),
            "frames": int(d.size)}


def predicted_markers(model, fit, pl: Placement, fitted_joints) -> np.ndarray:
    """(F, M) positions of the placement's markers on a :class:`artifacts.BodyFit`'s body
    (fitted joints by name, as ``fit_markers``' report lists them), metres, world."""
    skel = skinned.fit_skeleton(model, [model.joint_index(n) for n in fitted_joints])
    rest = rest_state(model, np.asarray(fit.betas, float))
    u, _ = skinned.reduced_offsets(model, rest, skel)
    H = marker_coeffs(model, rest, skel, pl)
    X = pack(skel, fit.body_pose, fit.global_orient, fit.transl)
    return np.stack([H.positions(skel, u, x) for x in X])


LAMBDA_INIT = 1e-6  # LM damping of a refit's first step (it starts close to its minimum)
REFIT_FTOL = 3e-4  # a refit frame has converged below this relative cost decrease (lm.solve: 1e-8;
# the class docstring says what 1e-6, 1e-4, 3e-4 and 1e-3 gave)


_GRAPHS = threading.local()  # per thread: {(spec, compile options): MarkerGraph}
GRAPHS_KEPT = 4


def _graph(spec, copts):
    """The ``MarkerGraph`` of ``spec`` compiled with ``copts``, built once per thread and
    process (building it, ~0.6 CPU-s, is the fixed cost of a call: the engine runs the
    sequences of a subject one after the other, with the same graph). Per thread: a graph
    holds the buffers its compiled function evaluates into. The last ``GRAPHS_KEPT``."""
    from fitting.marker_graph import MarkerGraph

    memo = getattr(_GRAPHS, "memo", None)
    if memo is None:
        memo = _GRAPHS.memo = {}
    key = (spec, copts)
    g = memo.pop(key, None)
    if g is None:
        g = MarkerGraph(spec, copts)
    memo[key] = g  # most recent last
    while len(memo) > GRAPHS_KEPT:
        memo.pop(next(iter(memo)))
    return g


class _Refits:
    """The leave-one-out refits of one sequence, all held markers of a frame solved together.

    Built once: the subject's rest state, the skeleton, the placement's coefficients, the
    compiled graph, the prior and the frame solver, exactly as ``fit_markers`` builds them for
    a markers-only fit (no keypoints). Then frame after frame:

    1. the full fit (every marker) by ``fit_markers``' own path: from the first frame with
       ``MIN_MARKERS`` visible (searched from the initial pose), each later frame warm-started
       from the previous one;
    2. each held marker ``k``'s refit minimises the frame objective ``fit_markers`` would
       minimise without ``k`` (L_3d of the other markers under the same robust-scale rule,
       L_theta, and L_s toward the refit's *own* previous frame) by the steps of
       ``fitting.lm.solve``, vectorised over the held markers (:func:`_batched_lm`). It starts
       from its own previous frame moved by the full fit's motion between the two frames
       (:func:`_moved_by`), its first frame at the full fit.

    What differs from refitting the whole sequence once per held marker (``reference=True``,
    ``fit_markers``' path): the start of each frame (the reference starts from the refit's
    previous frame as it is, and its first frame from the initial pose with the graduated
    robust scale), a first damping ``LAMBDA_INIT`` of 1e-6 (lm.solve: 1e-3) and the stopping
    rule ``REFIT_FTOL`` of 3e-4 (lm.solve's frames: 1e-8). Each refit keeps its own minimum
    (it is not started at the full fit, which saw the held marker: started there, pyCGM's
    LANK refit stayed in a higher-cost minimum near the full fit in 104 of 162 frames and its
    error halved, 39 -> 19 mm, an optimistic figure), and a refit is solved to convergence
    (stopped after 1 LM iteration the demo's median fell 3.31 -> 2.49 mm, for the same
    reason). Measured against the reference: pyCGM (stride 2) median 6.855 -> 6.851, p90
    30.91 -> 30.98 mm, per marker-frame within 0.03 mm at p90, but 102 of 6,318 marker-frames
    differ by more than 1 mm (up to 33 mm: LANK 60, LTOE 29, where the two refits follow
    different minima for a stretch of ~40 frames); the demo's Push 1 median 3.33 ->
    3.31, p90 14.38 -> 12.43 mm: the reference's RWRA refit, started from the initial pose,
    stayed in a minimum of 2.6x the cost of the one found here in all its 50 frames (94 mm
    off, against 9.5). Frames before a refit's first frame with ``MIN_MARKERS`` visible are
    held (not valid), as ``fit_markers`` holds them.

    The stopping rule (``REFIT_FTOL``), measured on the real captures of ``bench/cases/
    real.py`` (stride 2, the engine's ``marker_loo``, a loaded 2-core machine), each against
    1e-6 (the rule before): ktk Serve 27.1 frames per CPU-s, median / p90 11.546 / 41.33 mm;
    1e-4: 47.3, 11.545 / 41.49, per marker-frame mean difference +0.004 mm, 528 of 21,282
    differ by > 1 mm; 3e-4: 54.2, 11.528 / 41.42, mean -0.023 mm, 866 differ by > 1 mm;
    1e-3: 59.4, 11.471 / 41.00, mean -0.342 mm, 1,366 differ by > 1 mm (up to 589 mm: a refit
    stopped near its start follows another minimum, and the figure drifts towards the full
    fit's, which saw the marker). CMU Walk: 39.5 -> 42.3 / 57.9 / 71.4 frames per CPU-s,
    mean difference -0.008 / -0.012 / -0.046 mm. 3e-4 is kept: the medians move by 0.02 mm
    at most, for twice the speed."""

    def __init__(self, model, shape: ShapeFit, template: Placement, obs, vis, opts, source):
        from fitting import compiled, priors
        from fitting.marker_fit import FrameSolver
        from fitting.marker_graph import GraphSpec, body_joints, placement_support

        pl = placement_of(shape)
        if template.names != pl.names:
            diff = sorted(set(template.names) ^ set(pl.names)) or "order"
            raise InputError(source, "markers", f"the shape_fit placement and the marker set "
                             f"differ ({diff})")
        rest = rest_state(model, np.asarray(shape.betas, float))
        self.skel = skinned.fit_skeleton(model, body_joints(model))
        self.u, _ = skinned.reduced_offsets(model, rest, self.skel)
        self.Hm = marker_coeffs(model, rest, self.skel, pl)
        spec = GraphSpec(self.skel.topology, placement_support(model, self.skel, template, self.Hm),
                         (), 0, "h36m")
        graph = _graph(spec, compiled.CompileOptions(mode=opts.compile))
        self.solver = FrameSolver(graph, self.skel, self.u, self.Hm,
                                  priors.default_prior(self.skel.names[1:]), opts)
        self.obs, self.vis, self.source = obs, np.asarray(vis, bool), source

    def run(self, held: list[int], progress=None) -> tuple[np.ndarray, np.ndarray]:
        """Refit without each marker of ``held`` (indices): each held marker's predicted
        position (F, len(held), 3) and the frames where its refit is valid (F, len(held)).
        progress : optional iterable wrapper over the frames."""
        from threadpoolctl import threadpool_limits

        from fitting.marker_fit import MIN_MARKERS

        n_full = self.vis.sum(1)
        if not np.any(n_full >= MIN_MARKERS):
            raise InputError(self.source, "markers",
                             f"no video frame has {MIN_MARKERS} or more markers")
        with threadpool_limits(limits=1):  # tiny dense algebra: BLAS threads only add overhead
            X = self._solve_frames(np.asarray(held, int), progress)
        F, K = len(self.obs), len(held)
        pred = np.zeros((F, K, 3))
        valid = np.zeros((F, K), bool)
        for j, k in enumerate(held):
            n_vis = n_full - self.vis[:, k]
            ok = n_vis >= MIN_MARKERS
            first = int(np.argmax(ok))
            if not ok[first]:
                continue  # never enough markers without k: nothing valid, nothing predicted
            Xk = X[:, j].copy()
            Xk[:first] = Xk[first]
            pred[:, j] = _positions(self.skel, self.u, self.Hm, k, Xk)
            valid[:, j] = ok
            valid[:first, j] = False
        return pred, valid

    def _solve_frames(self, held: np.ndarray, progress) -> np.ndarray:
        from fitting.marker_fit import MIN_MARKERS, initial_pose, rewrap

        S = self.solver
        F, K, n = len(self.obs), len(held), self.skel.n
        X = np.zeros((F, K, n))
        x_full = x_full_prev = None
        x_prev = np.zeros((K, n))
        started = np.zeros(K, bool)  # the refit has a previous frame (L_s applies)
        frames = range(F) if progress is None else progress(range(F), total=F,
                                                            desc="leave-one-out")
        for f in frames:
            v = self.vis[f].astype(float)
            # 1. the full fit, fit_markers' path (it starts at its first frame with enough markers)
            if x_full is None:
                if np.count_nonzero(v) < MIN_MARKERS:
                    continue
                x0 = initial_pose(self.skel, self.u, self.Hm, self.obs[f], v)
                x_full = x_full_prev = rewrap(S.solve(x0, self.obs[f], v, first=True).x)
            else:
                x_full_prev = x_full
                x_full = rewrap(S.solve(x_full, self.obs[f], v, x_prev=x_full).x)
            # 2. the held markers' refits: a started one from its own previous frame moved by
            # the full fit's motion, a new one at the full fit
            vk = np.repeat(v[None], K, axis=0)
            vk[np.arange(K), held] = 0.0
            go = started | (vk.sum(1) >= MIN_MARKERS)
            if not go.any():
                continue
            x0 = np.repeat(x_full[None], K, axis=0)
            if started.any():
                x0[started] = _moved_by(x_prev[started], x_full_prev, x_full)
            x = _batched_lm(S, x_full, x0[go], self.obs[f], v, vk[go], x_prev[go], started[go])
            x = _rewrap_rows(x)
            X[f, go] = x
            x_prev[go] = x
            started |= go
        return X


def _rewrap_rows(X: np.ndarray) -> np.ndarray:
    """``fitting.marker_fit.rewrap`` of each row of X (B, n)."""
    Y = np.array(X, dtype=float)
    rv = np.concatenate([Y[:, :3], Y[:, 6:]], axis=1).reshape(len(Y), -1, 3)
    ang = np.linalg.norm(rv, axis=2)
    big = ang > np.pi
    rv[big] *= (1.0 - 2.0 * np.pi / ang[big])[:, None]
    Y[:, :3] = rv[:, 0]
    Y[:, 6:] = rv[:, 1:].reshape(len(Y), -1)
    return Y


def _moved_by(X: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Poses X (B, n) moved as the pose ``a`` (n,) moved to ``b``: the root turned by
    ``R_b R_a^T`` (world) and shifted by ``T_b - T_a``, each joint turned by ``D_a^T D_b``
    (its own frame). Rotations are composed, not rotation vectors added (a vector re-wrapped
    near pi between a and b would make the sum a wrong start)."""
    from body.rotations import rodrigues

    B, Q = len(X), (X.shape[1] - 3) // 3

    def turns(x):  # (..., n) -> (..., Q, 3, 3): the root's and each joint's rotation
        r = np.concatenate([x[..., :3], x[..., 6:]], axis=-1)
        return rodrigues(r.reshape(*x.shape[:-1], Q, 3))

    Dx, Da, Db = turns(X), turns(a), turns(b)
    out = np.empty_like(X)
    root = Db[0] @ Da[0].T @ Dx[:, 0]
    joints = Dx[:, 1:] @ (Da[1:].transpose(0, 2, 1) @ Db[1:])[None]
    turned = rotmat_to_rotvec(np.concatenate([root[:, None], joints], axis=1).reshape(-1, 3, 3))
    turned = turned.reshape(B, Q, 3)
    out[:, :3] = turned[:, 0]
    out[:, 3:6] = X[:, 3:6] + (b[3:6] - a[3:6])
    out[:, 6:] = turned[:, 1:].reshape(B, -1)
    return out


def _positions(skel, u, Hm, k: int, X: np.ndarray) -> np.ndarray:
    """(F, 3) world position of marker ``k`` of ``Hm`` at unknowns ``X (F, n)``: the numpy FK
    of ``fitting.skinned`` (``SkinnedPoints.positions``) vectorised over frames."""
    from body.rotations import rodrigues

    F, Q = len(X), len(skel.joints)
    rv = np.concatenate([X[:, :3], X[:, 6:]], axis=1).reshape(F, Q, 3)
    D = rodrigues(rv)  # (F, Q, 3, 3)
    G = np.zeros((F, Q, 3, 3))
    t = np.zeros((F, Q, 3))
    G[:, 0] = D[:, 0]
    t[:, 0] = u[0] + X[:, 3:6]
    for i in range(1, Q):
        p = skel.parents[i]
        G[:, i] = G[:, p] @ D[:, i]
        t[:, i] = t[:, p] + G[:, p] @ u[i]
    H = Hm.corners[k]  # (3, Q, 4)
    corners = (np.einsum("fqab,cqb->fca", G, H[..., :3])
               + np.einsum("fqa,cq->fca", t, H[..., 3]))  # (F, 3 corners, 3)
    return skinned.points_on_corners(corners[:, None], Hm.bary[[k]], Hm.offset[[k]])[:, 0]


def _batched_lm(S, x_full: np.ndarray, x0: np.ndarray, obs: np.ndarray, vis_all: np.ndarray,
                vis: np.ndarray, x_prev: np.ndarray, has_prev: np.ndarray) -> np.ndarray:
    """``FrameSolver.solve`` (a later frame: no graduated scale) for B problems of one frame
    at once. obs (M, 3), vis_all (M,): the frame's markers; problem b sees the markers
    ``vis[b]`` (a subset of ``vis_all``), starts at ``x0[b]`` and, where ``has_prev[b]``, has
    L_s toward ``x_prev[b]``; x_full (n,): the full fit of the frame (problems starting there
    share one evaluation). The steps of ``fitting.lm.solve`` per problem (Marquardt damping
    from ``LAMBDA_INIT``, its up/down schedule, gtol / xtol, ``REFIT_FTOL``, ``opts.max_iters``
    iterations, ``first_iters`` for a problem without a previous frame), with the normal
    equations and the linear solves vectorised. Returns x (B, n)."""
    from fitting.lm import DIAG_FLOOR, LAMBDA_MAX, LMOptions

    o = S.opts
    lmo = LMOptions(ftol=REFIT_FTOL, lambda_init=LAMBDA_INIT)
    graph, fun = S.graph, S.graph.fun
    B, n = x0.shape
    m = fun.n_r
    w = o.weights
    # per problem: parameters (its visibility), robust scale, quadratic terms
    P = np.repeat(S.p[None], B, axis=0)  # MarkerGraph.set_observations, for all B at once
    P[:, graph.slices["obs"]] = np.where(vis[:, :, None] > 0, np.nan_to_num(obs)[None],
                                         0.0).reshape(B, -1)
    P[:, graph.slices["vis"]] = vis
    kv = np.maximum(np.count_nonzero(vis > 0, axis=1), 1)
    sigma = o.sigma_marker_m * np.sqrt(w["L_3d"] / kv)  # FrameSolver.groups, factor 1
    rows = S.rows_m  # (M, 3): one group per marker, every row of r (no keypoints)
    # the quadratic terms of problem b: the prior q (shared) + L_s toward x_prev[b], i.e.
    # H_b = q.H + sprev_b I, g_b = q.g + sprev_b x_prev[b] (never formed per problem)
    q = S.quad_prior
    qH = np.ascontiguousarray(q.H)
    sprev = has_prev * max(w["L_s"], 0.0)  # (B,) L_s weight per problem
    gq = q.g[None] + sprev[:, None] * x_prev
    cq = q.c + sprev * np.sum(x_prev * x_prev, axis=1)
    diag = np.arange(n)
    box = S.box
    scale = S.row_scale
    flat = fun._flat
    jrows = fun.rows  # the Jacobian is kept as its nonzeros (B, nnz), row-scaled
    scale_nz = scale[jrows]

    def evaluate(idx, xs):
        r = np.empty((len(idx), m))
        jnz = np.empty((len(idx), len(flat)))
        for i, b in enumerate(idx):
            r[i], jnz[i] = fun(xs[i], P[b])
        return finish(idx, xs, r * scale, jnz * scale_nz)

    def finish(idx, xs, r, J):
        s = np.sum(r[:, rows] ** 2, axis=2)  # (b, M) squared norms
        sg = sigma[idx][:, None]
        s2 = sg * sg
        c = np.sum(s2 * s / (s2 + s), axis=1)  # fitting.robust.rho, geman_mcclure
        wm = (s2 / (s2 + s)) ** 2  # fitting.robust.weight
        wr = np.ones((len(idx), m))
        wr[:, rows] = wm[:, :, None]
        c += (np.sum((xs @ qH) * xs, axis=1) + sprev[idx] * np.sum(xs * xs, axis=1)
              - 2.0 * np.sum(gq[idx] * xs, axis=1) + cq[idx])  # lm.Quadratic.cost
        if box is not None:
            rb = _box_residual(box, xs)
            c += np.sum(rb * rb, axis=1)
        return r, J, c, wr

    x = np.array(x0, float)
    r = np.zeros((B, m))
    J = np.zeros((B, len(flat)))
    cost = np.zeros(B)
    wr = np.ones((B, m))
    shared = np.all(x == x_full[None], axis=1)
    if shared.any():
        # problems starting at the full fit: one evaluation with every marker of the frame,
        # then per problem its held marker's rows zeroed and L_3d's 1/K rescaled
        # (terms.L_3d: sqrt(vis_i / K_vis))
        sh = np.flatnonzero(shared)
        p_all = S.p.copy()
        graph.set_observations(p_all, obs, vis_all)
        r0, jnz0 = fun(x_full, p_all)
        k_all = max(int(np.count_nonzero(vis_all > 0)), 1)
        fac = np.sqrt(k_all / kv[sh])[:, None] * np.repeat(vis[sh] > 0, 3, axis=1)  # (b, 3M)
        r[sh], J[sh], cost[sh], wr[sh] = finish(sh, x[sh], (r0 * scale)[None] * fac,
                                                (jnz0 * scale_nz)[None] * fac[:, jrows])
    own = np.flatnonzero(~shared)
    if len(own):
        r[own], J[own], cost[own], wr[own] = evaluate(own, x[own])
    lam = np.full(B, lmo.lambda_init)
    it = np.zeros(B, int)
    max_it = np.where(has_prev, o.max_iters, o.first_iters)
    active = np.ones(B, bool)
    need = np.ones(B, bool)  # normal equations to (re)build at x
    H = np.zeros((B, n, n))
    g = np.zeros((B, n))
    d = np.zeros((B, n))
    while active.any():
        # a new iteration for each problem whose last step was accepted
        nb = np.flatnonzero(active & need)
        if len(nb):
            out = it[nb] >= max_it[nb]
            active[nb[out]] = False
            nb = nb[~out]
            it[nb] += 1
            sw = np.sqrt(wr[nb])
            Jw = np.zeros((len(nb), m * n))
            Jw[:, flat] = J[nb] * sw[:, jrows]
            Jw = Jw.reshape(len(nb), m, n)
            JwT = Jw.transpose(0, 2, 1)
            Hn = JwT @ Jw
            Hn += qH
            Hn[:, diag, diag] += sprev[nb, None]
            gn = (JwT @ (r[nb] * sw)[:, :, None])[:, :, 0]
            gn += x[nb] @ qH + sprev[nb, None] * x[nb] - gq[nb]  # qH is symmetric
            if box is not None:  # lm's hinge: active coordinates only (rb is 0 elsewhere)
                rb = _box_residual(box, x[nb])
                Hn[:, box.idx, box.idx] += box.weight * (rb != 0)
                gn[:, box.idx] += np.sqrt(box.weight) * rb
            H[nb], g[nb] = Hn, gn
            active[nb[np.max(np.abs(gn), axis=1) < lmo.gtol]] = False
            d[nb] = np.maximum(np.diagonal(Hn, axis1=1, axis2=2), DIAG_FLOOR)
            need[nb] = False
        tb = np.flatnonzero(active)
        if not len(tb):
            break
        Hd = H[tb].copy()
        Hd[:, np.arange(n), np.arange(n)] += lam[tb, None] * d[tb]
        ok = np.ones(len(tb), bool)
        try:
            step = -np.linalg.solve(Hd, g[tb][..., None])[..., 0]
        except np.linalg.LinAlgError:  # one by one, as lm.solve (a singular one damps more)
            step = np.zeros((len(tb), n))
            for j in range(len(tb)):
                try:
                    step[j] = -np.linalg.solve(Hd[j], g[tb[j]])
                except np.linalg.LinAlgError:
                    ok[j] = False
        better = np.zeros(len(tb), bool)
        ev = tb[ok]
        if len(ev):
            x_new = x[ev] + step[ok]
            r_new, J_new, c_new, w_new = evaluate(ev, x_new)
            imp = np.isfinite(c_new) & (c_new < cost[ev])
            acc = ev[imp]
            rel = (cost[acc] - c_new[imp]) / np.maximum(cost[acc], 1e-300)
            small = (np.linalg.norm(step[ok][imp], axis=1)
                     < lmo.xtol * (np.linalg.norm(x[acc], axis=1) + lmo.xtol))
            x[acc], r[acc], J[acc], cost[acc], wr[acc] = (x_new[imp], r_new[imp], J_new[imp],
                                                           c_new[imp], w_new[imp])
            lam[acc] = np.maximum(lam[acc] * lmo.lambda_down, 1e-12)
            need[acc] = True
            active[acc[(rel < lmo.ftol) | small]] = False
            better[np.flatnonzero(ok)[imp]] = True
        rej = tb[~better]  # no descent at this damping (or a singular system): damp more
        lam[rej] *= lmo.lambda_up
        active[rej[lam[rej] >= LAMBDA_MAX]] = False  # no descent at any damping: a minimum
    return x


def _box_residual(box, X: np.ndarray) -> np.ndarray:
    """``fitting.lm.Box.residual`` of each row of X (B, n): (B, k)."""
    v = X[:, box.idx]
    return np.sqrt(box.weight) * (np.maximum(0.0, v - box.hi) + np.minimum(0.0, v - box.lo))


def leave_one_out(model, shape: ShapeFit, template: Placement, markers: Markers,
                  clock: mocap.VideoClock, frames, held=None,
                  opts: MarkerFitOptions = DEFAULT_FIT_OPTIONS, stride: int = DEFAULT_STRIDE,
                  progress=None, source: str = "markers", reference: bool = False) -> dict:
    """Leave-one-out error of each held-out marker.

    model, shape, template, markers, clock, frames : as :func:`fit_markers` (``frames`` the
    video frames to score); opts : the :class:`MarkerFitOptions` every refit runs with: pass
    the ones the recipe gives ``stages.marker_fit`` (weights, robust scale, iterations,
    compile mode), so the figure scores the fit the stage made (no keypoints are passed:
    ``use_hands`` has no effect here); ``opts.max_frames`` applies after the stride; held : marker
    names to hold out (default every marker of the shape's placement); stride : fit every
    k-th frame (>= 1); progress : optional iterable wrapper (over the frames; over the held
    markers with ``reference``); source : the capture's file, named in input errors;
    reference : refit by calling ``fit_markers`` once per held marker (~4x slower; the graph
    is still built once), the path the default (:class:`_Refits`: the same numbers once the
    reference's start-up transient has passed, except where the two reach different minima)
    is tested against.

    Returns ``{"per_marker": {name: {"median_mm", "p90_mm", "frames"}}, "median_mm",
    "p90_mm"`` (over every held-out marker-frame), ``"cpu_s"`` (process CPU seconds),
    ``"fps_per_cpu_s"`` (the sequence's frames, ``frames`` before the stride, per CPU second),
    ``"stride"``, ``"fitted_frames"``, ``"frames"`` (F',) the frames fitted and ``"error_mm"``
    (F', len(held)) each held marker's prediction error, NaN where not scored}. Only frames
    where the fit is valid and the held marker observed are scored.
    """
    if int(stride) < 1:
        raise ValueError(f"stride: must be >= 1, got {stride}")
    pl = placement_of(shape)
    held = list(pl.names if held is None else held)
    unknown = [n for n in held if n not in pl.names]
    if unknown:
        raise InputError(source, "held", f"markers not in the placement: {unknown}")
    try:
        markers = markers.select(pl.names)
    except KeyError as e:
        raise InputError(source, "markers", str(e)) from None
    n_sequence = len(frames)
    frames = np.asarray(frames, dtype=np.int64)[::int(stride)]
    if opts.max_frames:
        frames = frames[:opts.max_frames]
    obs, vis = mocap.video_observations(markers, frames, clock)
    c0 = time.process_time()
    per, pooled = {}, []
    err = np.full((len(frames), len(held)), np.nan)
    it = held if progress is None or not reference else progress(held, total=len(held),
                                                                 desc="leave-one-out")
    refit = None if reference else _Refits(model, shape, template, obs, vis, opts, source)
    graphs: dict = {}  # one graph for every refit: hiding a marker does not change its spec
    if refit is not None:
        preds, valids = refit.run([pl.names.index(name) for name in held], progress)
    for name in it:
        k = pl.names.index(name)
        if refit is not None:
            pred, valid = preds[:, held.index(name)], valids[:, held.index(name)]
        else:
            xyz = markers.xyz.copy()
            xyz[:, k] = np.nan
            hidden = Markers(markers.names, xyz, markers.rate_hz, markers.first_frame,
                             markers.subject)
            fit, rep = fit_markers(model, shape, template, hidden, clock, frames, opts=opts,
                                   source=source, graphs=graphs)
            one = Placement((name,), pl.face[[k]], pl.bary[[k]], pl.offset[[k]])
            pred = predicted_markers(model, fit, one, rep["fitted_joints"])[:, 0]
            valid = np.asarray(fit.valid, bool)
        ok = vis[:, k] & valid
        d = np.linalg.norm(pred[ok] - obs[ok, k], axis=1)
        err[ok, held.index(name)] = d * 1000
        per[name] = _stats_mm(d)
        pooled.append(d)
    allm = np.concatenate(pooled) if pooled else np.zeros(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        overall = _stats_mm(allm)
    cpu = float(time.process_time() - c0)
    return {"per_marker": per, "median_mm": overall["median_mm"], "p90_mm": overall["p90_mm"],
            "cpu_s": cpu, "fps_per_cpu_s": n_sequence / max(cpu, 1e-9), "stride": int(stride),
            "fitted_frames": int(len(frames)), "frames": frames, "error_mm": err}
