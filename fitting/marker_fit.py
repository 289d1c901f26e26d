"""Fit the marker-wearing subject frame after frame (paper: "optimization ... performed one
frame at a time ... initialized from the result in the previous frame").

Per frame ``t`` the unknowns ``x_t = [r (3), T (3), theta ((Q-1)*3)]`` (fitting/skinned.py)
minimise

    w_3d rho(L_3d) + w_2d rho(L_2d hands) + w_theta L_theta + w_s L_s(x_t, x_{t-1})

with Geman-McClure ``rho`` per marker / keypoint (a swapped or mislabeled marker pulls with a
bounded force), gaps masked (``vis = 0``), ``L_theta`` = Gaussian + joint limits
(fitting/priors.py), ``L_s`` toward the previous frame's solution. The first frame starts from a
rigid (Kabsch) alignment of the rest-pose markers and runs a graduated robust scale. Rotation
vectors are re-wrapped to angles <= pi after every frame.

Pure functions over arrays; the stage adapter is ``stages/marker_fit.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from body.rotations import rodrigues, rotmat_to_rotvec
from fitting import lm, terms
from fitting.marker_graph import MarkerGraph
from fitting.priors import PosePrior
from fitting.skinned import FitSkeleton, slot_positions_np

DEFAULT_WEIGHTS = {"L_3d": 1.0, "L_2d": 1e-6, "L_theta": 2e-7, "L_s": 1e-6}
GNC_FACTORS = (20.0, 5.0, 1.0)  # first frame: robust scale sigma times these, in turn


@dataclass(frozen=True)
class MarkerFitOptions:
    """weights : per paper term (fitting/terms.py TERMS); sigma_marker_m : Geman-McClure scale
    of a marker's 3D error, metres; sigma_keypoint_px : the same for a 2D keypoint, pixels;
    max_iters / first_iters : LM iterations per frame / for the first frame."""

    weights: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))
    sigma_marker_m: float = 0.02
    sigma_keypoint_px: float = 15.0
    max_iters: int = 10
    first_iters: int = 60

    def __post_init__(self):
        unknown = set(self.weights) - set(terms.TERMS)
        if unknown:
            raise ValueError(f"weights: unknown terms {sorted(unknown)} (known: {terms.TERMS})")
        w = dict(DEFAULT_WEIGHTS)
        w.update(self.weights)
        object.__setattr__(self, "weights", w)


@dataclass
class SequenceFit:
    """x : (F, n) unknowns per frame; marker_residual_m : (F, M) |m - M| metres, NaN where the
    marker is not visible; robust_weight : (F, M) final IRLS weight of each marker (small =
    treated as an outlier); iterations : (F,); cost : (F,)."""

    x: np.ndarray
    marker_residual_m: np.ndarray
    robust_weight: np.ndarray
    iterations: np.ndarray
    cost: np.ndarray


def rewrap(x: np.ndarray) -> np.ndarray:
    """Re-wrap every rotation vector of ``x`` (the global one and each joint's) to angle <= pi."""
    y = np.array(x, dtype=float)
    rv = np.concatenate([y[:3], y[6:]]).reshape(-1, 3)
    ang = np.linalg.norm(rv, axis=1)
    big = ang > np.pi
    rv[big] *= (1.0 - 2.0 * np.pi / ang[big])[:, None]
    y[:3] = rv[0]
    y[6:] = rv[1:].reshape(-1)
    return y


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3), translation t (3,) minimising |R src + t - dst|; src, dst: (N, 3)."""
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


def initial_pose(skel: FitSkeleton, u: np.ndarray, Hm: np.ndarray, obs: np.ndarray,
                 vis: np.ndarray) -> np.ndarray:
    """x with pose 0 and the rigid transform aligning the rest-pose markers to ``obs`` (M, 3)."""
    x = np.zeros(skel.n)
    rest = slot_positions_np(skel, u, Hm, x)
    ok = vis > 0
    if ok.sum() < 3:
        raise ValueError("fewer than 3 visible markers: can't initialise the pose")
    R, t = kabsch(rest[ok], obs[ok])
    # world = R (p - h0) + h0 + T for rest points p, so T = t + R h0 - h0
    h0 = u[0]
    x[:3] = rotmat_to_rotvec(R)
    x[3:6] = t + R @ h0 - h0
    return x


class FrameSolver:
    """Everything fixed over a sequence: the graph, its packed parameters, prior and options."""

    def __init__(self, graph: MarkerGraph, skel: FitSkeleton, u: np.ndarray, Hm: np.ndarray,
                 prior: PosePrior, opts: MarkerFitOptions, Hk=None, cams=None):
        s = graph.spec
        self.graph, self.skel, self.u, self.Hm, self.opts = graph, skel, u, Hm, opts
        M, K, C = s.n_markers, s.n_keypoints, s.n_cameras
        self.p = graph.params(u, Hm, np.zeros((M, 3)), np.zeros(M), Hk, cams,
                              np.zeros((C, K, 2)) if K else None, np.zeros((C, K)) if K else None)
        w = opts.weights
        n = s.n_x
        pose_idx = np.arange(6, n)
        g = prior.gaussian
        self.quad_prior = terms.quadratic_L_theta(n, pose_idx, g.mean, g.sqrt_precision,
                                                  w["L_theta"])
        self.box = terms.box_L_theta(pose_idx, prior.lo, prior.hi, prior.limit_idx, w["L_theta"])
        self.row_scale = np.concatenate([np.full(3 * M, np.sqrt(w["L_3d"])),
                                         np.full(2 * C * K, np.sqrt(w["L_2d"]))])
        self.rows_m = np.arange(3 * M).reshape(M, 3)
        self.rows_k = 3 * M + np.arange(2 * C * K).reshape(C * K, 2)

    def groups(self, vis, conf, factor=1.0):
        w = self.opts.weights
        kv = max(int(np.count_nonzero(vis > 0)), 1)
        gs = [lm.RobustGroups(self.rows_m, "geman_mcclure",
                              factor * self.opts.sigma_marker_m * np.sqrt(w["L_3d"] / kv))]
        if self.graph.spec.n_keypoints and conf is not None:
            kk = max(int(np.count_nonzero(np.asarray(conf) > 0)), 1)
            gs.append(lm.RobustGroups(self.rows_k, "geman_mcclure",
                                      factor * self.opts.sigma_keypoint_px * np.sqrt(w["L_2d"] / kk)))
        return gs

    def solve(self, x0, obs, vis, uv=None, conf=None, x_prev=None, first=False) -> lm.LMResult:
        """One frame: obs (M, 3), vis (M,), optional hands uv (C, K, 2), conf (C, K)."""
        self.graph.set_observations(self.p, obs, vis, uv, conf)
        quad = self.quad_prior
        if x_prev is not None and self.opts.weights["L_s"] > 0:
            quad = quad + terms.quadratic_L_s(len(x0), np.arange(len(x0)), x_prev,
                                              self.opts.weights["L_s"])
        x = np.asarray(x0, dtype=float)
        if first:
            res = None
            for f in GNC_FACTORS:
                res = lm.solve(self.graph.fun, self.p, x, row_scale=self.row_scale,
                               groups=self.groups(vis, conf, f), quad=quad, box=self.box,
                               opts=lm.LMOptions(max_iters=self.opts.first_iters))
                x = res.x
            return res
        return lm.solve(self.graph.fun, self.p, x, row_scale=self.row_scale,
                        groups=self.groups(vis, conf), quad=quad, box=self.box,
                        opts=lm.LMOptions(max_iters=self.opts.max_iters, ftol=1e-8))


def fit_sequence(solver: FrameSolver, obs: np.ndarray, vis: np.ndarray, uv=None, conf=None,
                 progress=None) -> SequenceFit:
    """Fit every frame in order, warm-started from the previous one.

    obs : (F, M, 3) metres, world; vis : (F, M) bool/0-1; uv : (F, C, K, 2) pixels and
    conf : (F, C, K) or None (no hand keypoints). progress : optional iterable wrapper.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):  # tiny dense algebra: BLAS threads only add overhead
        return _fit_sequence(solver, obs, vis, uv, conf, progress)


def _fit_sequence(solver, obs, vis, uv, conf, progress) -> SequenceFit:
    F, M, _ = obs.shape
    n = solver.graph.spec.n_x
    X = np.zeros((F, n))
    res_m = np.full((F, M), np.nan)
    rw = np.full((F, M), np.nan)
    iters = np.zeros(F, dtype=np.int64)
    cost = np.zeros(F)
    x_prev = None
    frames = range(F) if progress is None else progress(range(F), total=F, desc="marker_fit")
    for f in frames:
        v = np.asarray(vis[f], float)
        u_f = None if uv is None else uv[f]
        c_f = None if conf is None else conf[f]
        if x_prev is None:
            if np.count_nonzero(v) < 3:
                raise ValueError(f"frame {f}: fewer than 3 visible markers to start the fit")
            x0 = initial_pose(solver.skel, solver.u, solver.Hm, obs[f], v)
            r = solver.solve(x0, obs[f], v, u_f, c_f, None, first=True)
        else:
            r = solver.solve(x_prev, obs[f], v, u_f, c_f, x_prev)
        x = rewrap(r.x)
        X[f] = x
        iters[f] = r.iterations
        cost[f] = r.cost
        m = slot_positions_np(solver.skel, solver.u, solver.Hm, x)
        d = np.linalg.norm(m - np.nan_to_num(obs[f]), axis=1)
        res_m[f] = np.where(v > 0, d, np.nan)
        s = solver.opts.sigma_marker_m
        rw[f] = np.where(v > 0, (s * s / (s * s + d * d)) ** 2, np.nan)
        x_prev = x
    return SequenceFit(X, res_m, rw, iters, cost)


def unpack(skel: FitSkeleton, num_joints: int, X: np.ndarray):
    """Per-frame unknowns (F, n) -> (body_pose (F, J, 3) with zeros on non-fitted joints and the
    root, global_orient (F, 3, 3), transl (F, 3)) in the body contract's convention."""
    F = len(X)
    pose = np.zeros((F, num_joints, 3))
    pose[:, skel.joints[1:]] = X[:, 6:].reshape(F, -1, 3)
    return pose, rodrigues(X[:, :3]), X[:, 3:6].copy()
