"""Stage ``marker_fit`` (per sequence): the subject wearing markers, frame after frame.

Thin adapter around ``fitting.marker_fit.fit_markers``: reads the sequence's cleaned capture
and camera rig (stage ``capture``: ``artifacts.capture.Markers`` / ``CameraRig``; only the
markers of the subject's marker set), the subject's ``shape_fit``
(``artifacts.ShapeFit``) and the ``keypoints`` artifact (``artifacts.Keypoints2D``: its
video frames are the frames fitted, person 0's hand keypoints drive the fingers; without it
every video frame is fitted, without hands). Writes

- ``fit.npz``: an ``artifacts.BodyFit``: ``body_pose (F, J, 3)``, ``global_orient (F, 3, 3)``,
  ``transl (F, 3)`` metres, ``betas (S,)``, ``frames (F,)`` video frame indices,
  ``valid (F,)`` / ``invalid_reason (F,)`` (frames held before the first marker or with too
  few markers are not valid), ``marker_names (M,)``, ``marker_residual_m (F, M)`` (NaN where
  not observed), ``marker_weight (F, M)`` (robust weight: small = outlier), ``visible (F, M)``;
- ``report.json``: residual statistics in mm per marker and overall, ``first_fitted_frame``,
  ``frames_not_valid`` ({reason: count}), speed, prior source, whether hands were used;
- ``residuals.png``: residual per frame (median, p90, max; ``drawing.plots.residual_plot``);
- ``marker_residuals.png``: residual per marker on a log axis, the markers over the warning
  threshold in red, the worst frames named (``drawing.plots.marker_residual_plot``).

The report's ``warnings`` say in words what is off (``fitting.marker_fit.report_warnings``);
each is also logged. Speeds are frames per CPU-second (``fps_per_cpu_s``) and per wall-second.
"""
from __future__ import annotations

from pathlib import Path

from artifacts import FitSummary
from fitting.marker_fit import MarkerFitOptions as Options
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "cameras", "sequence.fps", "sequence.mocap", "sequence.markers_on",
         "sequence.has_video", "wearer.markerset", "wearer.label_prefix", "wearer.marker_labels")


#: the report's headline figures the export republishes (``artifacts.FitSummary``)
PUBLISHED = ("joint_frames_not_observed", "joints_never_observed", "residual_mm",
             "outlier_marker_frames", "fit_rate_hz", "fit_cpu_s", "fps_per_cpu_s")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)  # markers and cameras come from the ``capture`` stage
    out = {"body_model": common.body_model_file(recipe)}
    out.update(common.markerset_file(recipe.subjects[seq.markers_on]))
    if seq.videos:
        out["video"] = Path(seq.videos[recipe.cameras[0]])  # frame count when no keypoints
    return out


def run(ctx: StageContext) -> None:
    from artifacts import ShapeFit
    from artifacts.keypoints import Keypoints2D
    from drawing.plots import marker_residual_plot, residual_plot
    from fitting.marker_fit import WARN_MARKER_MEDIAN_MM, fit_markers, report_warnings

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    subject = rv.sequence.markers_on
    model = common.load_body(ctx)
    shape_art = ctx.inputs["shape_fit"]
    shape = ShapeFit.load(shape_art[subject] if isinstance(shape_art, dict) else shape_art)
    template = common.marker_template(ctx, rv.wearer.markerset, model)
    captured = common.capture_markers(ctx, shape.names)
    markers = captured.capture()
    cams = common.capture_cameras(ctx)
    kp_art = ctx.inputs.get("keypoints")
    keypoints = Keypoints2D.load(kp_art) if kp_art is not None else None
    frames, clock, timeline = common.marker_timeline(rv.sequence, ctx.raw, markers, keypoints)
    fps = clock.fps
    fit, report = fit_markers(model, shape, template, markers, clock, frames, cams, keypoints,
                              o, progress=ctx.progress,
                              log=lambda s: ctx.log(f"{ctx.unit}: {s}"), source=str(captured.source))
    fit.save(ctx.out)
    o.save(ctx.out)  # the options this fit used (marker_loo refits with them)
    # outliers on a marker the cleaning found swapped blame its labels, elsewhere the model
    report["warnings"] = report_warnings(report, captured.markers_repaired_as("unswapped",
                                                                           "swap_removed"))
    repaired = captured.repairs_by_code()
    report = {"sequence": ctx.unit, "subject": subject, "capture": Path(str(captured.source)).name,
              "capture_rate_hz": float(markers.rate_hz),
              "capture_first_frame": int(markers.first_frame) + 1, "frames_are": timeline,
              "fit_rate_hz": float(fps), "capture_repaired": repaired, **report}
    if repaired:
        report["warnings"].append(
            f"{sum(repaired.values())} marker samples repaired by the capture stage ("
            + ", ".join(f"{k} {v}" for k, v in repaired.items()) + "; its report: runs)")
    ctx.out.save_json("report", report)
    FitSummary.from_report("marker_fit", report, PUBLISHED).save(ctx.out)  # what export takes
    # plots name frames in the capture's own numbering: the C3D frame number of a
    # marker-only fit (its frames are 0-based capture frames), the video frame otherwise
    shown = fit.frames + (0 if rv.sequence.has_video else 1)
    residual_plot(ctx.out.path("residuals.png"), fit.marker_residual_m * 1000, fps,
                  f"{ctx.unit}: marker residuals ({'with' if report['hands'] else 'no'} hand "
                  "keypoints)", frames=shown)
    marker_residual_plot(ctx.out.path("marker_residuals.png"), fit.marker_residual_m * 1000,
                         fit.marker_names, f"{ctx.unit}: residual per marker "
                         f"({len(report['warnings'])} warnings)", frames=shown,
                         warn_mm=WARN_MARKER_MEDIAN_MM)
    for w in report["warnings"]:
        ctx.log(f"{ctx.unit}: WARNING {w}")


STAGE = Stage(name="marker_fit", func=run, per="sequence",
              upstream=("capture", "shape_fit", "keypoints", "rig"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="pose of the subject wearing markers, frame after frame")
