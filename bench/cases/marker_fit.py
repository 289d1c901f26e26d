"""marker_fit accuracy and speed on a synthetic marker capture with exact ground truth.

Data (bench/fitting_synth.py): an Anny subject drawn like the studio's, Plug-in Gait
markers slid from their template, 150 frames at 50 fps of a smooth motion of the 22 fitted
body joints, markers with 1 mm noise and occlusion gaps on 30 % of them. The fit is given the
subject's true shape and marker placement (what shape_fit estimates is scored by the
shape_fit case), so these figures isolate the per-frame fit.

Keys:
- ``marker_fit.mpjpe_mm``: mean joint position error over frames and the fitted body joints;
- ``marker_fit.mpvpe_mm``: mean vertex error over frames and all vertices;
- ``marker_fit.fps_per_core``: frames per CPU-second of the compiled fit (one thread; CPU time,
  so other work on the machine does not count); ``marker_fit.fps_wall``: per wall-second;
- ``marker_fit.residual_median_mm``: median marker residual (noise floor ~0.8 mm);
- ``marker_fit.compile_s``: building the compiled function (0 when cached).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

GOALS = {
    "marker_fit.mpjpe_mm": ("<=", 5.0),
    "marker_fit.mpvpe_mm": ("<=", 8.0),
    "marker_fit.fps_per_core": (">=", 100.0),
}
FRAMES, FPS, SEED = 150, 50.0, 11


def run(work: Path) -> dict[str, float]:  # noqa: ARG001 - nothing written to disk
    from bench import fitting_synth as S

    studio = S.studio_session()
    if studio is not None:
        return _run_studio(*studio)

    from body import load_model
    from body.lbs import rest_state
    from fitting import compiled, marker_fit, priors, shape, skinned
    from fitting.marker_graph import GraphSpec, MarkerGraph

    rng = np.random.default_rng(SEED)
    model = load_model("anny")
    betas = S.subject_betas(model, rng)
    tpl, _ = S.template(model)
    pl = S.slide(model, tpl, rng)
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    X = S.motion(skel, FRAMES, FPS, rng)
    rest = rest_state(model, betas)
    truth = S.posed(model, betas, skel, X, rest)
    obs, vis = S.observe(S.true_markers(model, truth.vertices, pl), rng)

    t0 = time.perf_counter()
    graph = MarkerGraph(GraphSpec(skel.topology, shape.marker_support(model, skel, tpl)),
                        compiled.CompileOptions(mode="compiled"))
    t_build = time.perf_counter() - t0
    u, _ = skinned.reduced_offsets(model, rest, skel)
    Hm = shape.marker_coeffs(model, rest, skel, pl)
    solver = marker_fit.FrameSolver(graph, skel, u, Hm, priors.default_prior(skel.names[1:]),
                                    marker_fit.MarkerFitOptions())
    t0, c0 = time.perf_counter(), time.thread_time()
    fit = marker_fit.fit_sequence(solver, obs, vis.astype(float))
    t_fit, c_fit = time.perf_counter() - t0, time.thread_time() - c0
    est = S.posed(model, betas, skel, fit.x, rest)
    jerr = np.linalg.norm(est.joints - truth.joints, axis=2)[:, skel.joints] * 1000
    verr = np.linalg.norm(est.vertices - truth.vertices, axis=2) * 1000
    return {
        "marker_fit.mpjpe_mm": float(jerr.mean()),
        "marker_fit.mpvpe_mm": float(verr.mean()),
        "marker_fit.fps_per_core": float(FRAMES / c_fit),
        "marker_fit.fps_wall": float(FRAMES / t_fit),
        "marker_fit.residual_median_mm": float(np.nanmedian(fit.marker_residual_m) * 1000),
        "marker_fit.compile_s": float(t_build),
    }


def _run_studio(recipe, gt: Path) -> dict[str, float]:
    """Every sequence of a generated studio session: the marker wearer's C3D resampled to the
    video frames, fitted with the subject's true shape and marker placement (gt), scored on
    the true joints (all 52 fit joints, fingers included: they are not observed without hand
    keypoints) and vertices."""
    from body import load_model
    from body.lbs import forward, rest_state
    from body.markers import load_json
    from fitting import compiled, marker_fit, mocap, priors, shape, skinned
    from fitting.marker_graph import GraphSpec, MarkerGraph
    from formats.c3d import read_c3d
    from stages.marker_fit import template_placement

    model = load_model("anny")
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    tpl = template_placement(model, "plug-in-gait")
    graph = MarkerGraph(GraphSpec(skel.topology, shape.marker_support(model, skel, tpl)),
                        compiled.CompileOptions(mode="compiled"))
    prior = priors.default_prior(skel.names[1:])
    jerr, verr, frames, t_fit = [], [], 0, 0.0
    for sid, seq in recipe.sequences.items():
        g = dict(np.load(gt / sid.split("/")[0] / f"{sid.split('/')[1]}.npz"))
        betas = g["betas"][0]
        ms = load_json(gt / "subjects" / f"{seq.markers_on}_markers.json")
        pl = shape.Placement(tuple(ms.names), np.asarray(ms.faces), np.asarray(ms.bary),
                             np.asarray(ms.offsets))
        rest = rest_state(model, betas)
        u, _ = skinned.reduced_offsets(model, rest, skel)
        Hm = shape.marker_coeffs(model, rest, skel, pl)
        mk = read_c3d(seq.c3d, markers=list(pl.names), allow_missing=True)
        F = len(g["frames"])
        obs, vis = mocap.resample(mk.times_s, mk.xyz,
                                  mocap.frame_times(F, seq.fps, seq.mocap.sync_offset_s))
        solver = marker_fit.FrameSolver(graph, skel, u, Hm, prior, marker_fit.MarkerFitOptions())
        c0 = time.thread_time()
        fit = marker_fit.fit_sequence(solver, obs, vis.astype(float))
        t_fit += time.thread_time() - c0
        pose, R, T = marker_fit.unpack(skel, model.num_joints, fit.x)
        est = forward(model, betas, pose, R, T, rest=rest)
        jerr.append(np.linalg.norm(est.joints - g["joints"][0], axis=2)[:, skel.joints])
        verr.append(np.linalg.norm(est.vertices - g["vertices"][0], axis=2))
        frames += F
    return {
        "marker_fit.mpjpe_mm": float(np.concatenate(jerr).mean() * 1000),
        "marker_fit.mpvpe_mm": float(np.concatenate(verr).mean() * 1000),
        "marker_fit.fps_per_core": float(frames / t_fit),
        "marker_fit.studio_frames": float(frames),
    }
