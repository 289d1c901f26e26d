"""Stage ``shape_fit`` (per subject): body shape from the scan, marker placement from captures.

Thin adapter around ``fitting.shape.fit_shape``: reads the subject's scan (PLY/OBJ mesh or
point cloud, ``formats.scan``) and the C3D of every sequence in which the subject wears
markers (``formats.c3d``), and writes

- ``shape.npz``: an ``artifacts.ShapeFit`` (``betas (S,)``; the marker placement
  ``marker_names (M,)``, ``marker_face (M,)``, ``marker_bary (M, 3)``, ``marker_offset (M,)``
  metres; ``shape_source``, ``placement_source``);
- ``report.json``: where the shape comes from (``scan``, ``markers`` or ``mean``), scan
  distances and marker residuals in mm, the frames used.

A subject without a scan gets a marker-based shape (MoSh++ stage I) and the report says so;
a subject with neither (an unmarked partner without scan) keeps the mean shape, also reported.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fitting.shape import ShapeFitOptions as Options
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "subject.markerset", "subject.label_prefix",
         "subject.marker_labels", "subject.static_frames")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    subj = recipe.subjects[unit]
    out: dict[str, Path] = {"body_model": common.body_model_file(recipe)}
    if subj.scan is not None:
        out["scan"] = Path(subj.scan)
    out.update(common.markerset_file(subj))
    for i, trial in enumerate(subj.static):
        out[f"static:{i}"] = Path(trial.c3d)
    for sid in recipe.sequences_of(unit):
        seq = recipe.sequences[sid]
        if seq.markers_on == unit:
            out[f"c3d:{sid}"] = Path(seq.c3d)
    return out


def read_captures(raw: dict[str, Path], names, prefix: str | None = None,
                  static_frames=(), labels=None) -> list[tuple[str, object]]:
    """The subject's captures, static trials first (``static[i]``, cut to their frame range)
    then the sequences (keys ``c3d:<sequence>``, in key order): ``[(name, formats.c3d.Markers
    of the markers ``names``, metres, NaN gaps)]``. ``static_frames``: per static trial
    ``[first, last]`` C3D frame numbers (1-based, inclusive) or None; ``prefix``, ``labels``:
    ``stages.common.read_subject_markers``."""
    from formats.c3d import Markers
    from formats.errors import InputError

    out = []
    statics = sorted((int(k.split(":", 1)[1]), p) for k, p in raw.items() if k.startswith("static:"))
    for i, path in statics:
        m = common.read_subject_markers(path, names, prefix, labels)
        rng = static_frames[i] if i < len(static_frames) else None
        if rng is not None:
            first = m.first_frame + 1  # the C3D frame number of sample 0
            a, b = int(rng[0]) - first, int(rng[1]) - first + 1
            if a < 0 or b > len(m.xyz):
                raise InputError(path, f"subjects.<id>.static[{i}].frames",
                                 f"frames {list(rng)} outside the capture's frames {first}.."
                                 f"{first + len(m.xyz) - 1}")
            m = Markers(m.names, m.xyz[a:b], m.rate_hz, m.first_frame + a, m.subject)
        out.append((f"static[{i}] {Path(path).name}", m))
    for key, path in sorted(raw.items()):
        if key.startswith("c3d:"):
            out.append((key[4:], common.read_subject_markers(path, names, prefix, labels)))
    return out


def run(ctx: StageContext) -> None:
    from fitting.shape import fit_shape
    from formats.plausibility import check_scan_scale
    from formats.scan import read_scan

    o: Options = ctx.params or Options()
    model = common.load_body(ctx)
    template = common.marker_template(ctx, ctx.recipe.subject.markerset, model)
    scan = read_scan(ctx.raw["scan"]) if "scan" in ctx.raw else None
    if scan is not None:  # a scan in mm read as metres is a 1.8 km person: an error, not a fit
        check_scan_scale(scan[0], ctx.raw["scan"], "scan")
    rv = ctx.recipe.subject
    named = read_captures(ctx.raw, template.names, rv.label_prefix, rv.static_frames,
                          rv.marker_labels)
    cleaned = {}
    for i, (n, m) in enumerate(named):  # ghosts, spikes, swaps out before frames are chosen
        m, cleaned[n] = common.clean_capture(m, n, ctx.log)
        named[i] = (n, m)
    statics = [(n, m) for n, m in named if n.startswith("static[")]
    moves = [(n, m) for n, m in named if not n.startswith("static[")]
    shape, report = fit_shape(model, template, scan, [m.xyz for _, m in moves], o,
                              np.random.default_rng(o.seed),
                              log=lambda s: ctx.log(f"{ctx.unit}: {s}"),
                              static=[m.xyz for _, m in statics], names=[n for n, _ in moves],
                              static_names=[n for n, _ in statics])
    shape.save(ctx.out)
    ctx.out.save_json("report", {
        "subject": ctx.unit, "captures": [
            {"name": n, "first_frame": int(m.first_frame) + 1, "frames": int(len(m.xyz)),
             "rate_hz": float(m.rate_hz)} for n, m in named],
        "marker_sequences": [n for n, _ in named if not n.startswith("static[")],
        "cleaned": {n: {k: c[k] for k in ("removed_samples", "removed_fraction",
                                          "removed_by_reason", "unswapped")}
                    for n, c in cleaned.items()}, **report, "warnings": shape_warnings(report)})
    for w in shape_warnings(report):
        ctx.log(f"{ctx.unit}: WARNING {w}")


# the shape_fit report warns about a marker slid further than this from the template (a lab's
# placement can differ by ~10 cm, beyond it the marker may sit on another landmark) ...
WARN_SLIDE_MM = 100.0
# ... a skin offset this close to the 35 mm bound, and a placement residual above this
WARN_OFFSET_MM = 30.0
WARN_PLACEMENT_MM = 15.0


def shape_warnings(report: dict) -> list[str]:
    """Sentences for what a person must look at in a shape_fit report: markers that left their
    body segment (flagged by the placement and refitted), slid far or sit far off the skin,
    markers the placement frames could not fit, a mean shape standing in for a subject."""
    out = []
    off = report.get("markers_off_segment") or []
    if off:
        out.append(f"markers off their body segment (refitted near the template, check their "
                   f"labels and placement): {', '.join(off)}")
    for n, v in (report.get("placement_slide_mm") or {}).items():
        if v is not None and v > WARN_SLIDE_MM:
            out.append(f"marker {n}: placed {v:.0f} mm from the marker set's template position")
    for n, v in (report.get("placement_offset_mm") or {}).items():
        if v is not None and v > WARN_OFFSET_MM:
            out.append(f"marker {n}: {v:.0f} mm off the skin (skin offset near its bound)")
    per = (report.get("placement_residual_mm") or {}).get("per_marker_median") or {}
    for n, v in per.items():
        if v is not None and v > WARN_PLACEMENT_MM:
            out.append(f"marker {n}: {v:.0f} mm median residual in the placement frames "
                       f"({', '.join(str(f['capture']) + ' sample ' + str(f['frame']) for f in (report.get('placement_frames') or [])[:3])}...)")
    if report.get("shape_source") == "mean":
        out.append("no scan and no marker capture: the subject has the mean shape")
    return out


STAGE = Stage(name="shape_fit", func=run, per="subject", upstream=(), params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="body shape (scan or markers) and marker placement per subject")
