"""Stage ``capture`` (per sequence): the sequence's capture read, checked and cleaned once.

Every stage that needs the markers or the cameras reads this stage's typed artifacts, never
the C3D or the calibration files (``docs/ARCHITECTURE.md``, "Capture"). Thin adapter around
``fitting.capture.read_capture`` / ``prepare_capture``. Writes

- ``markers.npz``: ``artifacts.capture.Markers``: the marker wearer's markers in its marker
  set's order (metres, NaN = not observed or removed), ``raw_observed``, ``repair`` codes per
  marker and sample, rate, first frame, unit scale;
- ``rig.npz``: ``artifacts.capture.CameraRig`` (recipe camera order), when the sequence has
  calibration files;
- ``report.json``: per marker observed share, gaps, repairs; the cleaning's runs; warnings;
- ``capture.png``: per sample the markers observed and repaired (what the fit gets).

Bad input stops here, before anything is fitted or detected: a C3D whose units are wrong (a
person 1.8 km or 1.8 mm tall), a label prefix or marker set that finds no marker, a
calibration file that does not parse (any format of ``calib.io.read_camera``, the recipe's
``calibration_format`` or the suffix's): an ``InputError`` naming the file, the field and, where
it applies, the frame.
"""
from __future__ import annotations

from pathlib import Path

from fitting.capture import CaptureOptions as Options
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "cameras", "sequence.markers_on", "wearer.markerset",
         "wearer.label_prefix", "wearer.marker_labels", "sequence.calibration_format")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe), "c3d": Path(seq.c3d)}
    out.update(common.markerset_file(recipe.subjects[seq.markers_on]))
    out.update(common.calibration_inputs(recipe, seq))
    return out


def compute(view, raw: dict[str, Path], o: Options, log=lambda _msg: None):
    """The stage without the artifact store (used by :func:`run`, the bench and tests):
    ``view`` the stage's recipe view, ``raw`` its :func:`raw_inputs`. Returns
    ``(artifacts.capture.Markers, CameraRig or None, report)``."""
    from types import SimpleNamespace

    from artifacts.capture import CameraRig
    from body import load_model
    from calib.io import read_camera
    from fitting.capture import prepare_capture, read_capture
    from fitting.marker_clean import default_segments

    model = load_model(view.body_model.kind, raw["body_model"])
    template = common.marker_template(SimpleNamespace(raw=raw), view.wearer.markerset, model)
    names = template.names
    lab = common.marker_labels(template, view.wearer.marker_labels)  # file's labels + recipe's
    data, labels, scale = read_capture(raw["c3d"], names, view.wearer.label_prefix, lab)
    markers, report = prepare_capture(data, labels, scale, str(raw["c3d"]), o,
                                      segments=template.segments or default_segments(names),
                                      log=log)
    cams = [(c, raw[f"calibration:{c}"]) for c in view.cameras if f"calibration:{c}" in raw]
    rig = None
    if cams:
        fmt = view.sequence.calibration_format
        rig = CameraRig.from_cameras([read_camera(p, c, fmt) for c, p in cams],
                                     [Path(p).name for _, p in cams])
        report["cameras"] = [c for c, _ in cams]
    return markers, rig, {"subject": view.sequence.markers_on, **report}


def capture_of(recipe, unit: str, o: Options | None = None):
    """:func:`compute` for a loaded recipe's sequence (bench and tests, outside the engine):
    ``(artifacts.capture.Markers, [calib.Camera], report)``."""
    from stages import view_for

    markers, rig, report = compute(view_for(recipe, "capture", unit), raw_inputs(recipe, unit),
                                   o or Options())
    return markers, (rig.cameras() if rig is not None else []), report


def run(ctx: StageContext) -> None:
    from drawing.capture_plot import capture_plot

    o: Options = ctx.params or Options()
    markers, rig, report = compute(ctx.recipe, ctx.raw, o, log=lambda s: ctx.log(f"{ctx.unit}: {s}"))
    markers.save(ctx.out)
    if rig is not None:
        rig.save(ctx.out)
    ctx.out.save_json("report", {"sequence": ctx.unit, **report})
    capture_plot(ctx.out.path("capture.png"), markers.raw_observed, markers.repaired,
                 markers.marker_names, first_frame=int(markers.first_frame),
                 title=f"{ctx.unit}: markers observed and repaired "
                       f"({report['repaired_samples']} samples repaired)")
    for w in report["warnings"]:
        ctx.log(f"{ctx.unit}: WARNING {w}")


STAGE = Stage(name="capture", func=run, per="sequence", upstream=(), params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="the capture read, unit-checked and cleaned once; the camera rig")
