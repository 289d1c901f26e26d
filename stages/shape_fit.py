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
    for i, trial in enumerate(subj.static):  # the static trials only this stage reads
        out[f"static:{i}"] = Path(trial.c3d)
    return out  # the movement captures come cleaned from the ``capture`` stage


def read_statics(raw: dict[str, Path], names, prefix: str | None = None,
                 static_frames=(), labels=None, opts=None, log=None,
                 segments=None) -> list[tuple[str, object, dict]]:
    """The subject's static trials (raw inputs ``static:<i>``), each read, unit-checked and
    cleaned like a sequence's capture (``fitting.capture``), cut to its frame range:
    ``[(name, formats.c3d.Markers of the markers ``names``, cleaning report)]``.
    ``static_frames``: per static trial ``[first, last]`` C3D frame numbers (1-based,
    inclusive) or None; ``prefix``, ``labels``: ``fitting.capture.read_capture``."""
    from fitting.capture import CaptureOptions, prepare_capture, read_capture
    from fitting.marker_clean import default_segments
    from formats.c3d import Markers
    from formats.errors import InputError

    out = []
    statics = sorted((int(k.split(":", 1)[1]), p) for k, p in raw.items() if k.startswith("static:"))
    for i, path in statics:
        m, read_as, scale = read_capture(path, names, prefix, labels)
        rng = static_frames[i] if i < len(static_frames) else None
        if rng is not None:
            first = m.first_frame + 1  # the C3D frame number of sample 0
            a, b = int(rng[0]) - first, int(rng[1]) - first + 1
            if a < 0 or b > len(m.xyz):
                raise InputError(path, f"subjects.<id>.static[{i}].frames",
                                 f"frames {list(rng)} outside the capture's frames {first}.."
                                 f"{first + len(m.xyz) - 1}")
            m = Markers(m.names, m.xyz[a:b], m.rate_hz, m.first_frame + a, m.subject, m.unit)
        name = f"static[{i}] {Path(path).name}"
        art, rep = prepare_capture(m, read_as, scale, name, opts or CaptureOptions(),
                                   segments=segments or default_segments(names), log=log)
        out.append((name, art.capture(), rep))
    return out


def run(ctx: StageContext) -> None:
    from artifacts.capture import Markers
    from fitting.shape import fit_shape
    from formats.errors import InputError
    from formats.plausibility import check_scan_scale
    from formats.scan import read_scan

    o: Options = ctx.params or Options()
    model = common.load_body(ctx)
    template = common.marker_template(ctx, ctx.recipe.subject.markerset, model)
    scan = read_scan(ctx.raw["scan"]) if "scan" in ctx.raw else None
    if scan is not None:  # a scan in mm read as metres is a 1.8 km person: an error, not a fit
        check_scan_scale(scan[0], ctx.raw["scan"], "scan")
    rv = ctx.recipe.subject
    # ghosts, spikes, swaps out before frames are chosen: the static trials cleaned here, the
    # sequences' captures by their ``capture`` stage
    statics = read_statics(ctx.raw, template.names, rv.label_prefix, rv.static_frames,
                           common.marker_labels(template, rv.marker_labels), log=ctx.log,
                           segments=template.segments)
    cleaned = {n: rep.get("cleaning", {}) for n, _, rep in statics}
    named = [(n, m) for n, m, _ in statics]
    for sid, art in sorted((ctx.inputs.get("capture") or {}).items()):
        mk = Markers.load(art)
        if mk.marker_names != tuple(template.names):
            raise InputError(common.artifact_folder(art) / "markers.npz", "names",
                             f"the capture of {sid} has markers {list(mk.marker_names)}, the "
                             f"subject's marker set {list(template.names)}")
        named.append((sid, mk.capture()))
        cleaned[sid] = {"removed_samples": int((mk.repaired & ~mk.observed).sum()),
                        "repaired_samples": int(mk.repaired.sum()),
                        "repaired_by_code": mk.repairs_by_code()}
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
        "cleaned": cleaned, **report, "warnings": shape_warnings(report)})
    for w in shape_warnings(report):
        ctx.log(f"{ctx.unit}: WARNING {w}")


# the shape_fit report warns about a marker slid further than this from the template (a lab's
# placement can differ by ~10 cm, beyond it the marker may sit on another landmark) ...
WARN_SLIDE_MM = 100.0
# ... a skin offset this close to the 35 mm bound, and a placement residual above this
WARN_OFFSET_MM = 30.0
WARN_PLACEMENT_MM = 15.0
# ... and a scan fit that leaves 1 % of the scan this far from the body (a part not fitted: a
# 2.34 m synthetic body kept its head 30 cm above the fit, at a 3.3 mm median)
WARN_SCAN_P99_MM = 20.0


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
    p99 = (report.get("scan_to_model_mm") or {}).get("p99")
    if p99 is not None and p99 > WARN_SCAN_P99_MM:
        out.append(f"the scan fit leaves 1 % of the scan points more than {p99:.0f} mm from the "
                   f"body (a body part not fitted: check the scan and its pose)")
    if report.get("shape_source") == "mean":
        out.append("no scan and no marker capture: the subject has the mean shape")
    return out


STAGE = Stage(name="shape_fit", func=run, per="subject", upstream=("capture",), params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="body shape (scan or markers) and marker placement per subject")
