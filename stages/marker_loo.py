"""Stage ``marker_loo`` (per sequence): leave-one-out, the honest accuracy of the marker fit.

A marker's residual in ``marker_fit`` measures how well the fit follows the marker it was
fitted to; on real data, where no ground truth exists, the figure that says how well the body
is known is the error of a marker the fit did NOT see. For each marker of the set (or the
subset ``markers``) the sequence is refitted without it (``fitting.loo.leave_one_out``, every
``stride``-th frame) and the held-out marker is predicted through the placement. Writes

- ``report.json``: per marker ``median_mm``, ``p90_mm``, ``frames``; ``overall``; the
  markers whose prediction error exceeds ``WARN_LOO_MM`` as ``warnings``; CPU seconds;
- ``loo.npz``: ``error_mm (F', M)`` each held-out marker's error per fitted frame (NaN where
  not scored), ``frames (F',)``, ``marker_names (M,)``;
- ``loo.png``: the per-marker held-out error (``drawing.plots.marker_residual_plot``).

Run alone with ``make loo RECIPE=... SEQ=...`` (``--until marker_loo``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fitting.loo import DEFAULT_STRIDE
from pipeline.spec import Stage, StageContext
from stages import common

WARN_LOO_MM = 25.0  # a held-out marker predicted worse than this: its segment is poorly known

READS = ("body_model.kind", "sequence.fps", "sequence.mocap", "sequence.markers_on",
         "sequence.has_video", "wearer.markerset", "wearer.label_prefix", "wearer.marker_labels")


@dataclass(frozen=True)
class Options:
    """markers : names to hold out (empty: every marker of the set); stride : fit every n-th
    frame of marker_fit's frames (warm-started from the previous one)."""

    markers: list[str] = field(default_factory=list)
    stride: int = DEFAULT_STRIDE

    def __post_init__(self):
        if self.stride < 1:
            raise ValueError(f"stride: must be >= 1, got {self.stride}")
        object.__setattr__(self, "markers", [str(m) for m in self.markers])


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)  # the markers come cleaned from the ``capture`` stage
    out = {"body_model": common.body_model_file(recipe)}
    out.update(common.markerset_file(recipe.subjects[seq.markers_on]))
    if seq.videos:
        out["video"] = Path(seq.videos[recipe.cameras[0]])
    return out


def run(ctx: StageContext) -> None:
    import dataclasses

    from artifacts import BodyFit, ShapeFit
    from drawing.plots import marker_residual_plot
    from fitting.loo import leave_one_out
    from fitting.marker_fit import MarkerFitOptions
    from formats.errors import InputError

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    model = common.load_body(ctx)
    shape_art = ctx.inputs["shape_fit"]
    subject = rv.sequence.markers_on
    shape = ShapeFit.load(shape_art[subject] if isinstance(shape_art, dict) else shape_art)
    fit = BodyFit.load(ctx.inputs["marker_fit"])
    template = common.marker_template(ctx, rv.wearer.markerset, model)
    # the same cleaned observations marker_fit fitted (stage ``capture``): ghosts and spikes
    # neither enter the refits nor score the held-out marker
    markers = common.capture_markers(ctx, shape.names).capture()
    # the refits use the options marker_fit used (the recipe's ``stages.marker_fit``), hands
    # off: a held-out marker is predicted from the markers, not from keypoints
    fit_opts = dataclasses.replace(MarkerFitOptions.load(ctx.inputs["marker_fit"]), use_hands=False)
    unknown = [m for m in o.markers if m not in shape.names]
    if unknown:
        raise InputError(ctx.recipe_path or "<recipe>", "stages.marker_loo.markers",
                         f"not in the marker set: {unknown}")
    _, clock, timeline = common.marker_timeline(rv.sequence, ctx.raw, markers)
    frames = np.asarray(fit.frames)[fit.valid]  # frames fitted from evidence only
    res = leave_one_out(model, shape, template, markers, clock, frames,
                        held=o.markers or None, opts=fit_opts,
                        stride=o.stride, progress=ctx.progress)
    per = res["per_marker"]
    warnings = [f"marker {n}: predicted {m['median_mm']:.0f} mm off (median, p90 "
                f"{m['p90_mm']:.0f}) by a fit without it: its segment is poorly determined"
                for n, m in per.items() if m["median_mm"] is not None
                and m["median_mm"] > WARN_LOO_MM]
    for w in warnings:
        ctx.log(f"{ctx.unit}: WARNING {w}")
    err, fr = res.pop("error_mm"), res.pop("frames")
    ctx.out.save_arrays("loo", error_mm=err.astype(np.float32), frames=fr,
                        marker_names=np.array(list(per)))
    ctx.out.save_json("report", {
        "sequence": ctx.unit, "subject": subject, "frames_are": timeline, "warnings": warnings,
        "fit_options": dataclasses.asdict(fit_opts),
        "overall": {"median_mm": res.pop("median_mm"), "p90_mm": res.pop("p90_mm")}, **res})
    if np.isfinite(err).any():
        marker_residual_plot(ctx.out.path("loo.png"), err, list(per),
                             f"{ctx.unit}: leave-one-out error per marker (median "
                             f"{np.nanmedian(err):.1f} mm)", frames=fr, warn_mm=WARN_LOO_MM)


STAGE = Stage(name="marker_loo", func=run, per="sequence",
              upstream=("capture", "shape_fit", "marker_fit"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="leave-one-out check of the marker fit (held-out marker errors)")
