"""Stage ``partner_fit`` (per sequence): the person without markers, frame after frame from the
four views.

Thin adapter around ``fitting.partner_fit.fit_partner``: reads the cameras (``calib.io``),
the sequence's contact signature (``fitting.contact_signature.load_contact``: a bad file fails
here, before anything is computed or written), the partner's own ``shape_fit``
(``artifacts.ShapeFit``; the sequence reads the shape fits of ``[markers_on, partner]``), the
``keypoints`` artifact (person 1; its video frames are the frames fitted) and the wearer's
``marker_fit`` (``artifacts.BodyFit``: the other body of ``L_ic``). Writes

- ``fit.npz``: an ``artifacts.BodyFit`` (the layout of marker_fit's, without the marker
  fields): ``valid`` / ``invalid_reason`` (``too_few_keypoints``,
  ``held_before_first_keypoints``, ``poor_reprojection``);
- ``terms.npz``: per frame ``reproj_px (F, C)`` median 2D error per view (NaN: no
  detection), ``detections (F,)`` body keypoint detections over the views, ``term_cost
  (F, T)`` weighted cost of each term at the solution, ``term_active (F, T)`` the frames where
  each term was active, ``term_points (F, T)`` offending points of the extra terms, ``terms
  (T,)`` their names, ``penetration_m (F,)``, ``contact_m (F,)``, ``ground_m (F,)``
  (``fitting.partner_fit.contact_figures``), ``frames (F,)``;
- ``report.json``: frames valid / not valid and why, initialisations, reprojection medians,
  summary figures of penetration, contact distance and ground penetration (mm), speed;
- ``partner_fit.png``: those curves over the sequence (``drawing.plots.partner_fit_plot``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fitting.partner_fit import PartnerFitOptions as Options
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "cameras", "ground_plane", "sequence.fps", "sequence.markers_on",
         "sequence.partner")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe)}
    for cam in recipe.cameras:
        out[f"calibration:{cam}"] = Path(seq.calibration[cam])
    if seq.contact is not None:
        out["contact"] = Path(seq.contact)
        out["video"] = Path(seq.videos[recipe.cameras[0]])  # frame count for the interval
    return out


def _summary(values_m: np.ndarray) -> dict:
    v = np.asarray(values_m, float)
    v = v[np.isfinite(v)] * 1000
    if not len(v):
        return {"frames": 0}
    return {"frames": int(len(v)), "median_mm": float(np.median(v)), "mean_mm": float(v.mean()),
            "p95_mm": float(np.percentile(v, 95)), "max_mm": float(v.max())}


def run(ctx: StageContext) -> None:
    from artifacts import BodyFit, ShapeFit
    from artifacts.keypoints import Keypoints2D
    from calib.io import read_chi3d_camera
    from drawing.plots import partner_fit_plot
    from fitting.contact_signature import load_contact
    from fitting.partner_fit import contact_figures, fit_partner
    from formats.video import video_info

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    model = common.load_body(ctx)
    cams = [read_chi3d_camera(ctx.raw[f"calibration:{c}"], name=c) for c in rv.cameras]
    contact = None
    if "contact" in ctx.raw:  # fails (InputError: file, action, field) before anything is written
        action = ctx.unit.split("/", 1)[1]
        family = "smplx" if model.name == "smplx" else "anny"
        contact = load_contact(ctx.raw["contact"], action, model,
                               video_info(ctx.raw["video"]).n_frames, family=family)
    shape_art = ctx.inputs["shape_fit"]
    partner = rv.sequence.partner
    shape = ShapeFit.load(shape_art[partner] if isinstance(shape_art, dict) else shape_art)
    keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    wearer = BodyFit.load(ctx.inputs["marker_fit"]) if "marker_fit" in ctx.inputs else None
    ground = (np.asarray(rv.ground_plane.normal, float), float(rv.ground_plane.offset))
    log = lambda s: ctx.log(f"{ctx.unit}: {s}")  # noqa: E731
    fit, report = fit_partner(model, shape, keypoints, cams, wearer, contact, ground, o,
                              progress=ctx.progress, log=log)
    fig = contact_figures(model, fit, wearer, contact, ground)
    per = report.pop("per_frame")
    fit.save(ctx.out)
    ctx.out.save_arrays("terms", terms=np.array(report["terms"]), **per, **fig)
    ok = fit.valid
    report.update({
        "sequence": ctx.unit, "subject": partner, "wearer": rv.sequence.markers_on,
        "contact": None if contact is None else {
            "has_contact": bool(contact.has_contact), "interval": list(map(int, contact.interval)),
            "region_pairs": [list(map(str, p)) for p in contact.region_names]},
        "penetration": _summary(fig["penetration_m"][ok]),
        "contact_distance": _summary(fig["contact_m"][ok]),
        "ground_penetration": _summary(fig["ground_m"][ok]),
        "frames_not_valid_list": {str(int(f)): r for f, r in zip(
            fit.frames[~ok], [_reason(c) for c in fit.invalid_reason[~ok]], strict=True)},
    })
    ctx.out.save_json("report", report)
    partner_fit_plot(ctx.out.path("partner_fit.png"), fit.frames, rv.sequence.fps,
                     per["reproj_px"], fig["penetration_m"] * 1000, fig["contact_m"] * 1000,
                     fig["ground_m"] * 1000, fit.valid, f"{ctx.unit}: partner {partner}",
                     views=list(rv.cameras))


def _reason(code) -> str:
    from artifacts import INVALID_REASONS

    return INVALID_REASONS[int(code)]


STAGE = Stage(name="partner_fit", func=run, per="sequence",
              upstream=("shape_fit", "keypoints", "marker_fit"), params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="pose of the unmarked partner (2D keypoints, contact, collisions)")
