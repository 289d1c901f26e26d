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
    from body.lbs import forward, rest_state
    from fitting import marker_fit, mocap, shape, skinned
    from formats.c3d import Markers

    rng = np.random.default_rng(SEED)
    model = load_model("anny")
    betas = S.subject_betas(model, rng)
    tpl, _ = S.template(model)
    pl = S.slide(model, tpl, rng)
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    X = S.motion(skel, FRAMES, FPS, rng)
    rest = rest_state(model, betas)
    truth = S.posed(model, betas, skel, X, rest)
    obs, _ = S.observe(S.true_markers(model, truth.vertices, pl), rng)

    # the capture sampled at the video frames (gaps NaN), the true shape and placement
    capture = Markers(pl.names, obs, FPS)
    fit, rep = marker_fit.fit_markers(model, shape.to_shape_fit(betas, pl, "given", "given"), tpl,
                                      capture, mocap.VideoClock(FPS), np.arange(FRAMES),
                                      opts=marker_fit.MarkerFitOptions(compile="compiled"))
    est = forward(model, betas, fit.body_pose, fit.global_orient, fit.transl, rest=rest)
    jerr = np.linalg.norm(est.joints - truth.joints, axis=2)[:, skel.joints] * 1000
    verr = np.linalg.norm(est.vertices - truth.vertices, axis=2) * 1000
    fitted = FRAMES - rep["first_fitted_frame"]
    return {
        "marker_fit.mpjpe_mm": float(jerr.mean()),
        "marker_fit.mpvpe_mm": float(verr.mean()),
        "marker_fit.fps_per_core": float(fitted / rep["fit_cpu_s"]),
        "marker_fit.fps_wall": float(fitted / rep["fit_s"]),
        "marker_fit.residual_median_mm": float(rep["residual_mm"]["median"]),
        "marker_fit.compile_s": float(rep["build_s"]),
    }


def _run_studio(recipe, gt: Path) -> dict[str, float]:
    """Every sequence of a generated studio session: the marker wearer's C3D resampled to the
    video frames, fitted with the subject's true shape and marker placement (gt), scored on
    the true joints (all 52 fit joints, fingers included: they are not observed without hand
    keypoints) and vertices of the valid frames."""
    from body import load_model
    from body.lbs import forward
    from body.markers import load_json
    from fitting import marker_fit, mocap, shape, skinned
    from fitting.marker_graph import template_placement
    from formats.c3d import read_c3d

    model = load_model("anny")
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    tpl = template_placement(model, "plug-in-gait")
    opts = marker_fit.MarkerFitOptions(compile="compiled")
    jerr, verr, frames, t_fit = [], [], 0, 0.0
    for sid, seq in recipe.sequences.items():
        g = dict(np.load(gt / sid.split("/")[0] / f"{sid.split('/')[1]}.npz"))
        betas = g["betas"][0]
        given = shape.to_shape_fit(betas, template_placement(
            model, load_json(gt / "subjects" / f"{seq.markers_on}_markers.json")), "given", "given")
        mk = read_c3d(seq.c3d, markers=list(given.names), allow_missing=True)
        F = len(g["frames"])
        fit, rep = marker_fit.fit_markers(
            model, given, tpl, mk, mocap.VideoClock(seq.fps, seq.mocap.sync_offset_s),
            np.arange(F), opts=opts, source=str(seq.c3d))
        t_fit += rep["fit_cpu_s"]
        est = forward(model, betas, fit.body_pose, fit.global_orient, fit.transl)
        ok = fit.valid
        jerr.append(np.linalg.norm(est.joints - g["joints"][0], axis=2)[ok][:, skel.joints])
        verr.append(np.linalg.norm(est.vertices - g["vertices"][0], axis=2)[ok])
        frames += int(ok.sum())
    return {
        "marker_fit.mpjpe_mm": float(np.concatenate(jerr).mean() * 1000),
        "marker_fit.mpvpe_mm": float(np.concatenate(verr).mean() * 1000),
        "marker_fit.fps_per_core": float(frames / t_fit),
        "marker_fit.studio_frames": float(frames),
    }
