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

Pure functions over arrays and typed artifacts (no file I/O): :func:`fit_markers` is the whole
sequence (resampling onto the video frames, graph, prior, hands, the valid mask); the stage
adapter ``stages/marker_fit.py`` reads the files and saves the result.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from artifacts import REASON_CODE, BodyFit, ShapeFit
from body.joints import regressor
from body.lbs import rest_state
from body.rotations import rodrigues, rotmat_to_rotvec
from calib import camera_vector
from fitting import compiled, lm, mocap, priors, skinned, terms
from fitting.marker_graph import (
    OBSERVED_WEIGHT,
    GraphSpec,
    MarkerGraph,
    Placement,
    body_joints,
    marker_coeffs,
    observed_joints,
    placement_of,
    placement_support,
)
from fitting.priors import PosePrior
from fitting.skinned import FitSkeleton, SkinnedPoints
from formats.errors import InputError
from formats.skeletons import LEFT_HAND, RIGHT_HAND

# the reasons (artifacts.body_fit.INVALID_REASONS) a frame of the marker fit can be not valid for
MARKER_FIT_REASONS = ("held_before_first_marker", "too_few_markers")
DEFAULT_WEIGHTS = {"L_3d": 1.0, "L_2d": 1e-6, "L_theta": 2e-7, "L_s": 1e-6}
GNC_FACTORS = (20.0, 5.0, 1.0)  # first frame: robust scale sigma times these, in turn
COMPILE_MODES = ("auto", "compiled", "interpreted")
MIN_MARKERS = 3  # a frame with fewer visible markers does not fix the pose (held, not valid)
HAND_KP65 = slice(LEFT_HAND.start, RIGHT_HAND.stop)  # KP65: left hand 21, right hand 21
OUTLIER_WEIGHT = 0.1  # a marker-frame whose robust weight is below counts as an outlier
# the report warns (``warnings``) about: a marker whose median residual exceeds this (a
# placement or labelling that is wrong: on real data a good fit is ~2-5 mm per marker) ...
WARN_MARKER_MEDIAN_MM = 15.0
# ... a marker that is an outlier (robust weight < OUTLIER_WEIGHT) in more of its frames ...
WARN_OUTLIER_SHARE = 0.05
# ... an overall p90 above this, and skin weight dropped outside the graph's supports
WARN_P90_MM = 20.0
WARN_DROPPED_WEIGHT = 0.01


@dataclass(frozen=True)
class MarkerFitOptions:
    """The marker fit's options (also the recipe's ``stages.marker_fit`` section).

    weights : per paper term (L_3d, L_2d, L_theta, L_s), missing ones at their default;
    sigma_marker_mm : Geman-McClure scale of a marker's 3D error, millimetres;
    sigma_keypoint_px : the same for a 2D hand keypoint, pixels; max_iters / first_iters : LM
    iterations per frame / for the first frame; use_hands : fit person 0's hand keypoints when
    given; min_hand_conf : hand keypoints below this confidence are ignored; max_frames : fit
    only the first N frames (quick runs); compile : how the residual function runs
    (``fitting.compiled.CompileOptions.mode``)."""

    weights: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))
    sigma_marker_mm: float = 20.0
    sigma_keypoint_px: float = 15.0
    max_iters: int = 10
    first_iters: int = 60
    use_hands: bool = True
    min_hand_conf: float = 0.3
    max_frames: int | None = None
    compile: Literal["auto", "compiled", "interpreted"] = "auto"

    def __post_init__(self):
        problems = []  # every bad field, in one message
        for name, v in self.weights.items():
            if name not in DEFAULT_WEIGHTS:
                problems.append(f"weights.{name}: unknown term (known: "
                                f"{', '.join(DEFAULT_WEIGHTS)})")
            elif not float(v) >= 0:
                problems.append(f"weights.{name}: must be >= 0, got {v}")
        for name in ("sigma_marker_mm", "sigma_keypoint_px"):
            if not getattr(self, name) > 0:
                problems.append(f"{name}: must be > 0, got {getattr(self, name)}")
        for name in ("max_iters", "first_iters"):
            if getattr(self, name) < 1:
                problems.append(f"{name}: must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.min_hand_conf <= 1:
            problems.append(f"min_hand_conf: must be in [0, 1], got {self.min_hand_conf}")
        if self.max_frames is not None and self.max_frames < 1:
            problems.append(f"max_frames: must be >= 1, got {self.max_frames}")
        if self.compile not in COMPILE_MODES:
            problems.append(f"compile: must be one of {', '.join(COMPILE_MODES)}, "
                            f"got {self.compile!r}")
        if problems:
            raise ValueError("; ".join(problems))
        w = dict(DEFAULT_WEIGHTS)
        w.update({k: float(v) for k, v in self.weights.items()})
        object.__setattr__(self, "weights", w)

    @property
    def sigma_marker_m(self) -> float:
        return self.sigma_marker_mm / 1000

    # the options a fit used travel with its artifact (``options.json``), so that a stage
    # refitting the same capture (marker_loo) uses the recipe's options, not the defaults
    OPTIONS_FILE = "options"

    def save(self, writer) -> None:
        """Write ``options.json`` (every field) through the engine's writer."""
        import dataclasses

        writer.save_json(self.OPTIONS_FILE, {"kind": "marker_fit_options",
                                             **dataclasses.asdict(self)})

    @classmethod
    def load(cls, artifact) -> MarkerFitOptions:
        """The options saved by :meth:`save` in a marker_fit artifact; an ``InputError``
        naming the file and field when missing or not these options."""
        import dataclasses
        import json
        from pathlib import Path

        from formats.errors import InputError

        file = Path(getattr(artifact, "dir", artifact)) / f"{cls.OPTIONS_FILE}.json"
        try:  # an engine artifact, or its folder
            doc = (artifact.json(cls.OPTIONS_FILE) if hasattr(artifact, "json")
                   else json.loads(file.read_text()))
        except FileNotFoundError:
            raise InputError(file, "<file>", "missing (a marker_fit artifact of older code: "
                             "recompute marker_fit)") from None
        if not isinstance(doc, dict) or doc.get("kind") != "marker_fit_options":
            raise InputError(file, "kind", "not marker_fit options")
        known = {f.name for f in dataclasses.fields(cls)}
        try:
            return cls(**{k: v for k, v in doc.items() if k in known})
        except (TypeError, ValueError) as e:
            raise InputError(file, "options", str(e)) from None


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


def initial_pose(skel: FitSkeleton, u: np.ndarray, Hm: SkinnedPoints, obs: np.ndarray,
                 vis: np.ndarray) -> np.ndarray:
    """x with pose 0 and the rigid transform aligning the pose-0 markers ``Hm`` to ``obs``
    (M, 3)."""
    x = np.zeros(skel.n)
    rest = Hm.positions(skel, u, x)
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

    def __init__(self, graph: MarkerGraph, skel: FitSkeleton, u: np.ndarray, Hm: SkinnedPoints,
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
        m = solver.Hm.positions(solver.skel, solver.u, x)  # = body.markers.marker_positions
        d = np.linalg.norm(m - np.nan_to_num(obs[f]), axis=1)
        res_m[f] = np.where(v > 0, d, np.nan)
        s = solver.opts.sigma_marker_m
        rw[f] = np.where(v > 0, (s * s / (s * s + d * d)) ** 2, np.nan)
        x_prev = x
    return SequenceFit(X, res_m, rw, iters, cost)


def pack(skel: FitSkeleton, body_pose, global_orient, transl) -> np.ndarray:
    """The inverse of :func:`unpack`: a fit's body_pose (F, J, 3), global_orient (F, 3, 3)
    and transl (F, 3) -> per-frame unknowns (F, n) (the fitted joints' rotation vectors;
    the global rotation as a rotation vector of angle <= pi)."""
    F = len(transl)
    return np.concatenate([rotmat_to_rotvec(np.asarray(global_orient)), np.asarray(transl),
                           np.asarray(body_pose)[:, skel.joints[1:]].reshape(F, -1)], axis=1)


def unpack(skel: FitSkeleton, num_joints: int, X: np.ndarray):
    """Per-frame unknowns (F, n) -> (body_pose (F, J, 3) with zeros on non-fitted joints and the
    root, global_orient (F, 3, 3), transl (F, 3)) in the body contract's convention."""
    F = len(X)
    pose = np.zeros((F, num_joints, 3))
    pose[:, skel.joints[1:]] = X[:, 6:].reshape(F, -1, 3)
    return pose, rodrigues(X[:, :3]), X[:, 3:6].copy()


# ---------------------------------------------------------------------------- one sequence


def _hand_observations(model, rest, skel, keypoints, frames, cams, opts: MarkerFitOptions):
    """Person 0's hand keypoints at the fit's frames: (Hk (K, Q, 4), uv (F, C, K, 2),
    conf (F, C, K)), or None when there are none (or ``use_hands`` is off). Keypoints are
    matched to the fit's video frames by index and to the cameras by id."""
    if keypoints is None or not opts.use_hands:
        return None
    hand = np.asarray(keypoints.hands(0), float)  # (C, Fk, K, 3), person 0 = the marker wearer
    hand = hand[[keypoints.camera(c.name) for c in cams]]
    conf = hand[..., 2]
    conf = np.where(conf >= opts.min_hand_conf, conf, 0.0)
    kf = np.asarray(keypoints.frames, dtype=int)
    pos = np.clip(np.searchsorted(kf, frames), 0, max(len(kf) - 1, 0))
    hit = (kf[pos] == frames) if len(kf) else np.zeros(len(frames), bool)
    F, C, K = len(frames), hand.shape[0], hand.shape[2]
    uv = np.zeros((F, C, K, 2))
    cf = np.zeros((F, C, K))
    uv[hit] = np.transpose(hand[:, pos[hit], :, :2], (1, 0, 2, 3))
    cf[hit] = np.transpose(conf[:, pos[hit]], (1, 0, 2))
    if not np.any(cf > 0):
        return None
    Hk = skinned.regressed_coeffs(model, rest, skel, regressor(model, "kp65")[HAND_KP65])
    return Hk, uv, cf


def fit_markers(model, shape: ShapeFit, template: Placement, markers, clock: mocap.VideoClock,
                frames: np.ndarray, cams=(), keypoints=None,
                opts: MarkerFitOptions = MarkerFitOptions(), progress=None, log=None,
                source: str = "markers", graphs: dict | None = None) -> tuple[BodyFit, dict]:
    """The marker-wearing subject's motion over a sequence's video frames.

    model : BodyModel; shape : the subject's :class:`artifacts.ShapeFit` (betas and marker
    placement); template : the marker set's template placement (the compiled graph's supports
    are its supports joined with the joints skinning the subject's placement,
    ``marker_graph.placement_support``: one compile per subject, cached on disk); markers : ``formats.c3d.Markers`` of the
    subject (names of ``shape``; gaps NaN); clock : how mocap samples map to video frames;
    frames : (F,) video frame indices to fit (``opts.max_frames`` keeps the first N);
    cams : ``calib.Camera`` per view, in the order of the keypoints' cameras they name (only
    needed with keypoints); keypoints : ``artifacts.Keypoints2D`` or None (person 0's hand
    keypoints drive the fingers when ``opts.use_hands``); progress : iterable wrapper for the
    per-frame loop; log : ``log(str)``; source : the capture's file, named in input errors;
    graphs : a dict the caller keeps across calls (leave-one-out's refits of one sequence):
    graphs built here are stored in it by their spec and reused (building one costs ~1 s).

    Frames before the first one with ``MIN_MARKERS`` visible markers are held at the first
    solution (``held_before_first_marker``), later frames with fewer are held by the prior and
    the previous frame (``too_few_markers``); neither is valid. Returns the
    :class:`artifacts.BodyFit` and a report dict (residuals in mm, speed, what was used).
    """
    pl = placement_of(shape)
    if template.names != pl.names:
        diff = sorted(set(template.names) ^ set(pl.names)) or "order"
        raise InputError(source, "markers", f"the shape_fit placement and the marker set "
                         f"differ ({diff})")
    if tuple(markers.names) != pl.names:
        try:
            markers = markers.select(pl.names)
        except KeyError as e:
            raise InputError(source, "markers", str(e)) from None
    frames = np.asarray(frames, dtype=np.int64)
    if opts.max_frames:
        frames = frames[: opts.max_frames]
    F = len(frames)
    obs, vis = mocap.video_observations(markers, frames, clock)
    n_vis = vis.sum(1)
    if not np.any(n_vis >= MIN_MARKERS):
        raise InputError(source, "markers", f"no video frame has {MIN_MARKERS} or more markers")
    first = int(np.argmax(n_vis >= MIN_MARKERS))
    few = np.flatnonzero(n_vis[first:] < MIN_MARKERS) + first
    if len(few) and log:
        log(f"frames with < {MIN_MARKERS} markers from frame {int(frames[few[0]])}: pose held "
            "from the prior and the previous frame (not valid)")

    betas = np.asarray(shape.betas, float)
    rest = rest_state(model, betas)
    skel_full = skinned.fit_skeleton(model, model.fit_joints)
    hands = _hand_observations(model, rest, skel_full, keypoints, frames, list(cams), opts)
    skel = skel_full if hands is not None else skinned.fit_skeleton(model, body_joints(model))
    u, _ = skinned.reduced_offsets(model, rest, skel)
    Hm = marker_coeffs(model, rest, skel, pl)
    spec = GraphSpec(skel.topology, placement_support(model, skel, template, Hm),
                     skinned.support_of(hands[0]) if hands else (), len(cams) if hands else 0,
                     cams[0].model if hands else "h36m")
    t0 = time.perf_counter()
    graph = None if graphs is None else graphs.get((spec, opts.compile))
    if graph is None:
        graph = MarkerGraph(spec, compiled.CompileOptions(mode=opts.compile), log=log)
        if graphs is not None:
            graphs[(spec, opts.compile)] = graph
    t_build = time.perf_counter() - t0
    prior = priors.default_prior(skel.names[1:])
    solver = FrameSolver(graph, skel, u, Hm, prior, opts, Hk=hands[0] if hands else None,
                         cams=np.stack([camera_vector(c) for c in cams]) if hands else None)
    uv = conf = None
    if hands:
        _, uv, conf = hands
    sl = slice(first, F)
    t0, c0 = time.perf_counter(), time.thread_time()
    fit = fit_sequence(solver, obs[sl], vis[sl].astype(float),
                       None if uv is None else uv[sl], None if conf is None else conf[sl],
                       progress=progress)
    t_fit, c_fit = time.perf_counter() - t0, time.thread_time() - c0
    X = np.zeros((F, skel.n))
    X[sl] = fit.x
    X[:first] = fit.x[0]  # frames before the markers appear: held at the first solution
    res = np.full((F, len(pl.names)), np.nan)
    wgt = np.full_like(res, np.nan)
    res[sl], wgt[sl] = fit.marker_residual_m, fit.robust_weight
    reason = np.zeros(F, np.int8)
    reason[:first] = REASON_CODE["held_before_first_marker"]
    reason[few] = REASON_CODE["too_few_markers"]
    body_pose, R, T = unpack(skel, model.num_joints, X)
    # joints that no visible marker (no seen hand keypoint) moves are not ground truth
    observed = observed_joints(
        model, skel, skinned.points_support(Hm, OBSERVED_WEIGHT), vis,
        skinned.support_of(hands[0], OBSERVED_WEIGHT) if hands else (),
        (conf > 0).any(axis=1) if hands else None)
    out = BodyFit(body_pose=body_pose, global_orient=R, transl=T, betas=betas, frames=frames,
                  valid=reason == 0, invalid_reason=reason, marker_names=np.array(pl.names),
                  marker_residual_m=res, marker_weight=wgt, visible=vis, observed=observed)
    mm = res * 1000
    with warnings.catch_warnings():  # a marker never seen: NaN statistics, no warning
        warnings.simplefilter("ignore", RuntimeWarning)
        per = {n: {"median": float(np.nanmedian(mm[:, i])),
                   "p90": float(np.nanpercentile(mm[:, i], 90)),
                   "max": float(np.nanmax(mm[:, i])) if vis[:, i].any() else float("nan"),
                   "worst_frame": int(frames[np.nanargmax(mm[:, i])]) if vis[:, i].any()
                   else None,
                   "outlier_share": float(np.mean(wgt[vis[:, i], i] < OUTLIER_WEIGHT))
                   if vis[:, i].any() else 0.0,
                   "visible": float(vis[:, i].mean())} for i, n in enumerate(pl.names)}
    reasons = out.reasons()
    jobs = out.joints_observed()[:, model.fit_joints]
    never = [model.joint_names[j] for j, o in zip(model.fit_joints, jobs.any(axis=0),
                                                    strict=True) if not o]
    report = {
        "frames": F, "first_fitted_frame": first,
        "frames_valid": reasons["fitted"],
        "frames_not_valid": {n: reasons[n] for n in MARKER_FIT_REASONS},
        "markers": len(pl.names),
        "markers_missing_from_c3d": [n for i, n in enumerate(pl.names) if not vis[:, i].any()],
        "residual_mm": {"median": float(np.nanmedian(mm)), "p90": float(np.nanpercentile(mm, 90)),
                        "max": float(np.nanmax(mm))},
        "outlier_marker_frames": int(np.nansum(wgt < OUTLIER_WEIGHT)),
        # fit joints x valid frames that no marker / keypoint observed (not ground truth)
        "joint_frames_not_observed": int((~jobs[reason == 0]).sum()),
        "joints_never_observed": never,
        "per_marker": per,
        "hands": bool(hands), "fitted_joints": list(skel.names),
        "prior": prior.source, "weights": dict(opts.weights),
        "compiled": graph.fun.compiled, "build_s": round(t_build, 3),
        "fit_s": round(t_fit, 3), "fit_cpu_s": c_fit,
        "fps_per_cpu_s": round((F - first) / max(c_fit, 1e-9), 1),
        "fps_wall": round((F - first) / max(t_fit, 1e-9), 1),
        "mean_iterations": float(np.mean(fit.iterations)),
        "skin_weight_outside_support": float(graph.dropped_weight),
    }
    report["warnings"] = report_warnings(report)
    return out, report


def report_warnings(report: dict, swapped=()) -> list[str]:
    """Plain sentences for what a person must look at in a marker-fit report: markers with a
    large median residual or many outlier frames (naming the marker, its figures and its worst
    frame), an overall p90 above ``WARN_P90_MM``, skin weight dropped outside the graph's
    supports, markers never seen, frames not valid. Empty when nothing is off. swapped : the
    markers the capture's cleaning found in a label swap (``fitting.marker_clean``); only
    their outlier warning blames labels (elsewhere outliers on smooth data are soft tissue or
    placement the model does not follow)."""
    out = []
    for n, m in report["per_marker"].items():
        if m["visible"] == 0:
            continue
        if m["median"] > WARN_MARKER_MEDIAN_MM:
            out.append(f"marker {n}: median residual {m['median']:.0f} mm (p90 {m['p90']:.0f}, "
                       f"max {m['max']:.0f} at frame {m['worst_frame']}): its placement or its "
                       "labels are wrong")
        elif m["outlier_share"] > WARN_OUTLIER_SHARE:
            out.append(f"marker {n}: an outlier in {100 * m['outlier_share']:.0f} % of its frames "
                       f"(max {m['max']:.0f} mm at frame {m['worst_frame']}): "
                       + ("the capture's cleaning found label swaps in it" if n in swapped else
                          "the model does not follow it (soft tissue or placement; the "
                          "capture's cleaning found no label swap in it)"))
    r = report["residual_mm"]
    if r["p90"] > WARN_P90_MM:
        out.append(f"residual p90 {r['p90']:.0f} mm over all markers (median {r['median']:.1f}): "
                   "the median hides it")
    if report["skin_weight_outside_support"] > WARN_DROPPED_WEIGHT:
        out.append(f"{100 * report['skin_weight_outside_support']:.1f} % of the markers' skin "
                   "weight lies outside the fitted joints' supports and was dropped")
    if report["markers_missing_from_c3d"]:
        out.append(f"markers never seen in the capture: {', '.join(report['markers_missing_from_c3d'])}")
    bad = {k: v for k, v in report["frames_not_valid"].items() if v}
    if bad:
        out.append("frames not valid: " + ", ".join(f"{v} {k}" for k, v in bad.items()))
    return out
