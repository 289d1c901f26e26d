"""Stage ``marker_fit`` (per sequence): the subject wearing markers, frame after frame.

Reads the sequence's C3D (any Vicon export: ``Subject:`` prefixes, extra non-marker points,
gaps, 100-240 Hz; only the markers of the subject's marker set are used), the subject's
``shape_fit`` (betas and marker placement), the cameras, and, when available, the
``keypoints`` artifact (person 0's hand keypoints only; the stage runs without them).
Markers are resampled onto the video frames (fitting/mocap.py), then fitted with
``fitting.marker_fit``. Writes

- ``fit.npz``: ``body_pose (F, J, 3)`` local axis-angle (the body contract; zeros on joints
  not fitted), ``global_orient (F, 3, 3)``, ``transl (F, 3)`` metres, ``betas (S,)``,
  ``frames (F,)`` video frame indices, ``marker_names (M,)``, ``marker_residual_m (F, M)``
  (NaN where not observed), ``marker_weight (F, M)`` (robust weight: small = outlier),
  ``visible (F, M)``;
- ``report.json``: residual statistics in mm per marker and overall, speed, prior source,
  whether hands were used; ``residuals.png``: residual per frame (median, p90, max).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from formats.errors import InputError
from pipeline.spec import Stage, StageContext

HAND_KP = slice(23, 65)  # KP65: left hand 21, right hand 21


def _default_weights() -> dict[str, float]:
    from fitting.marker_fit import DEFAULT_WEIGHTS

    return dict(DEFAULT_WEIGHTS)


@dataclass(frozen=True)
class Options:
    """weights: per paper term (L_3d, L_2d, L_theta, L_s); sigma_marker_mm: robust scale of a
    marker's error; sigma_keypoint_px: of a hand keypoint; max_iters / first_iters: LM
    iterations per frame / first frame; use_hands: use person 0's hand keypoints when the
    keypoints artifact has them; min_hand_conf: keypoints below are ignored; max_frames: fit
    only the first N frames (quick runs); compile: how the residual function runs."""

    weights: dict[str, float] = field(default_factory=_default_weights)
    sigma_marker_mm: float = 20.0
    sigma_keypoint_px: float = 15.0
    max_iters: int = 10
    first_iters: int = 60
    use_hands: bool = True
    min_hand_conf: float = 0.3
    max_frames: int | None = None
    compile: Literal["auto", "compiled", "interpreted"] = "auto"


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"c3d": Path(seq.c3d)}
    for cam in recipe.cameras:
        out[f"calibration:{cam}"] = Path(seq.calibration[cam])
    out["video"] = Path(seq.videos[recipe.cameras[0]])  # frame count when no keypoints
    return out


# ------------------------------------------------------------------------- shared helpers


def load_body(recipe, load_model):
    """The recipe's body model (``body_model.kind`` / ``path``)."""
    bm = recipe.body_model
    return load_model(bm.kind, bm.path) if bm.path is not None else load_model(bm.kind)


def template_placement(model, markerset: str):
    """The marker set's template placement on ``model`` as a fitting.shape.Placement."""
    from body import markers as bm
    from fitting.shape import Placement

    if markerset == "plug-in-gait":
        ms = bm.plug_in_gait(model)
    elif markerset.endswith(".json"):
        ms = bm.load_json(markerset, num_faces=len(model.faces))
    else:
        raise InputError(markerset, "markerset", "expected 'plug-in-gait' or a marker-set .json")
    return Placement(tuple(ms.names), np.asarray(ms.faces, np.int64), np.asarray(ms.bary, float),
                     np.asarray(ms.offsets, float))


def placement_from_artifact(art):
    from fitting.shape import Placement

    a = art.arrays("shape")
    return a["betas"], Placement(tuple(str(n) for n in a["marker_names"]),
                                 np.asarray(a["marker_face"]), np.asarray(a["marker_bary"]),
                                 np.asarray(a["marker_offset"]))


def video_frame_count(path: Path) -> int:
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    if n <= 0:
        raise InputError(path, "frames", "can't read the frame count of the video")
    return n


def residual_plot(path: Path, res_mm: np.ndarray, fps: float, title: str) -> None:
    """PNG of per-frame marker residuals (median, p90, max over visible markers), mm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(len(res_mm)) / fps
    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=100)
    with np.errstate(all="ignore"):
        for q, lab in ((50, "median"), (90, "p90"), (100, "max")):
            ax.plot(t, np.nanpercentile(res_mm, q, axis=1), label=lab, lw=1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("marker residual (mm)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _hands(ctx: StageContext, o: Options, model, rest, skel, F):
    """(Hk (K, Q, 4), uv (F, C, K, 2), conf (F, C, K), frames) or None when no hand data."""
    kp_art = ctx.inputs.get("keypoints")
    if not o.use_hands or kp_art is None:
        return None
    if isinstance(kp_art, dict):
        kp_art = next(iter(kp_art.values()))
    try:
        from body.joints import regressor
    except ImportError:
        return None
    arr = kp_art.arrays("keypoints")
    kp = np.asarray(arr["kp"], float)  # (C, F, 2, 65, 3)
    hand = kp[:, :, 0, HAND_KP]  # person 0 (the marker wearer)
    conf = hand[..., 2]
    conf = np.where(conf >= o.min_hand_conf, conf, 0.0)
    if not np.any(conf > 0):
        return None
    from fitting.skinned import regressed_coeffs

    R = regressor(model, "kp65")[HAND_KP]
    Hk = regressed_coeffs(model, rest, skel, R)
    n = min(F, hand.shape[1])
    uv = np.transpose(hand[:, :n, :, :2], (1, 0, 2, 3))
    return Hk, uv, np.transpose(conf[:, :n], (1, 0, 2)), np.asarray(arr.get("frames", np.arange(n)))


def run(ctx: StageContext) -> None:
    from body import load_model
    from body.lbs import rest_state
    from calib import camera_vector
    from calib.io import read_chi3d_camera
    from fitting import compiled, marker_fit, mocap, priors, shape, skinned
    from fitting.marker_graph import GraphSpec, MarkerGraph
    from formats.c3d import read_c3d

    o: Options = ctx.params or Options()
    seq = ctx.recipe.sequence(ctx.unit)
    model = load_body(ctx.recipe, load_model)
    shape_art = ctx.inputs["shape_fit"]
    if isinstance(shape_art, dict):
        shape_art = shape_art[seq.markers_on]
    betas, pl = placement_from_artifact(shape_art)

    mk = read_c3d(ctx.raw["c3d"], markers=list(pl.names), allow_missing=True)
    rate = seq.mocap.rate_hz or mk.rate_hz
    times_src = (mk.first_frame + np.arange(len(mk.xyz))) / rate
    kp_art = ctx.inputs.get("keypoints")
    if kp_art is not None and not isinstance(kp_art, dict):
        # the keypoints stage may run with a frame stride: fit exactly its video frames
        frames = np.asarray(kp_art.arrays("keypoints")["frames"], dtype=int)
    else:
        frames = np.arange(video_frame_count(ctx.raw["video"]))
    if o.max_frames:
        frames = frames[: o.max_frames]
    F = len(frames)
    times = mocap.frame_times(int(frames.max()) + 1 if F else 0, seq.fps,
                              seq.mocap.sync_offset_s)[frames]
    obs, vis = mocap.resample(times_src, mk.xyz, times)
    first = int(np.argmax(vis.sum(1) >= 3)) if np.any(vis.sum(1) >= 3) else None
    if first is None:
        raise InputError(ctx.raw["c3d"], "markers", "no video frame has 3 or more markers")
    if np.any(vis.sum(1)[first:] < 3):
        bad = first + int(np.argmax(vis.sum(1)[first:] < 3))
        ctx.log(f"{ctx.unit}: frames with < 3 markers from frame {bad}: pose held from prior")

    rest = rest_state(model, betas)
    cams = [read_chi3d_camera(ctx.raw[f"calibration:{c}"], name=c) for c in ctx.recipe.cameras]
    hands = None
    joints = model.fit_joints
    skel_full = skinned.fit_skeleton(model, joints)
    hands = _hands(ctx, o, model, rest, skel_full, F)
    skel = skel_full if hands is not None else skinned.fit_skeleton(model, shape.body_joints(model))
    u, _ = skinned.reduced_offsets(model, rest, skel)
    Hm = shape.marker_coeffs(model, rest, skel, pl)
    template = template_placement(model, ctx.recipe.subjects[seq.markers_on].markerset)
    if template.names != pl.names:
        raise InputError(ctx.raw["c3d"], "markers", "shape_fit placement and marker set differ")
    spec = GraphSpec(skel.topology, shape.marker_support(model, skel, template),
                     skinned.support_of(hands[0]) if hands else (), len(cams) if hands else 0,
                     cams[0].model if hands else "h36m")
    t0 = time.perf_counter()
    graph = MarkerGraph(spec, compiled.CompileOptions(mode=o.compile), log=ctx.log)
    t_build = time.perf_counter() - t0
    prior = priors.default_prior(skel.names[1:])
    fopts = marker_fit.MarkerFitOptions(weights=dict(o.weights),
                                        sigma_marker_m=o.sigma_marker_mm / 1000,
                                        sigma_keypoint_px=o.sigma_keypoint_px,
                                        max_iters=o.max_iters, first_iters=o.first_iters)
    solver = marker_fit.FrameSolver(
        graph, skel, u, Hm, prior, fopts,
        Hk=hands[0] if hands else None,
        cams=np.stack([camera_vector(c) for c in cams]) if hands else None)
    uv = conf = None
    if hands:
        n = hands[1].shape[0]
        uv = np.zeros((F,) + hands[1].shape[1:])
        conf = np.zeros((F,) + hands[2].shape[1:])
        uv[:n], conf[:n] = hands[1][:F], hands[2][:F]
    t0 = time.perf_counter()
    sl = slice(first, F)
    fit = marker_fit.fit_sequence(solver, obs[sl], vis[sl].astype(float),
                                  None if uv is None else uv[sl], None if conf is None else conf[sl],
                                  progress=ctx.progress)
    t_fit = time.perf_counter() - t0
    X = np.zeros((F, skel.n))
    X[sl] = fit.x
    X[:first] = fit.x[0]  # frames before the markers appear: held at the first solution
    res = np.full((F, len(pl.names)), np.nan)
    wgt = np.full_like(res, np.nan)
    res[sl], wgt[sl] = fit.marker_residual_m, fit.robust_weight
    body_pose, R, T = marker_fit.unpack(skel, model.num_joints, X)
    ctx.out.save_arrays("fit", body_pose=body_pose, global_orient=R, transl=T,
                        betas=np.asarray(betas, float), frames=frames,
                        marker_names=np.array(pl.names), marker_residual_m=res,
                        marker_weight=wgt, visible=vis)
    mm = res * 1000
    with np.errstate(all="ignore"):
        per = {n: {"median": float(np.nanmedian(mm[:, i])), "p90": float(np.nanpercentile(mm[:, i], 90)),
                   "visible": float(vis[:, i].mean())} for i, n in enumerate(pl.names)}
    report = {
        "sequence": ctx.unit, "subject": seq.markers_on, "frames": F, "first_fitted_frame": first,
        "markers": len(pl.names),
        "markers_missing_from_c3d": [n for i, n in enumerate(pl.names) if not vis[:, i].any()],
        "residual_mm": {"median": float(np.nanmedian(mm)), "p90": float(np.nanpercentile(mm, 90)),
                        "max": float(np.nanmax(mm))},
        "outlier_marker_frames": int(np.nansum(wgt < 0.1)),
        "per_marker": per,
        "hands": bool(hands), "fitted_joints": list(skel.names),
        "prior": prior.source, "weights": dict(fopts.weights),
        "compiled": graph.fun.compiled, "build_s": round(t_build, 3),
        "fit_s": round(t_fit, 3), "fps": round((F - first) / max(t_fit, 1e-9), 1),
        "mean_iterations": float(np.mean(fit.iterations)),
        "skin_weight_outside_support": float(graph.dropped_weight),
    }
    ctx.out.save_json("report", report)
    residual_plot(ctx.out.path("residuals.png"), mm, seq.fps,
                  f"{ctx.unit}: marker residuals ({'with' if hands else 'no'} hand keypoints)")


STAGE = Stage(name="marker_fit", func=run, per="sequence", upstream=("shape_fit", "keypoints"),
              params=Options, raw_inputs=raw_inputs, version="1",
              doc="pose of the subject wearing markers, frame after frame")
