"""Stage ``partner_fit`` (per sequence): the person without markers, frame after frame from the
four views.

Thin adapter around ``fitting.partner_fit.fit_partner``: reads the cameras (``calib.io``),
the sequence's contact signature (``fitting.contact_signature.load_contact``: a bad file fails
here, before anything is computed or written), the partner's own ``shape_fit``
(``artifacts.ShapeFit``; the sequence reads the shape fits of ``[markers_on, partner]``), the
``keypoints`` artifact (person 1; its video frames are the frames fitted) and the wearer's
``marker_fit`` (``artifacts.BodyFit``: the other body of ``L_ic``), and the ``silhouettes``
masks (``artifacts.silhouettes.Silhouettes``: ``L_sil``, when the stage ran and the weight is
> 0). After the first fit, the
second detection pass (``detect.refine``, option ``second_pass``) runs the detector again in
tight crops around the fitted partner in the views that lacked it (the videos are raw inputs),
and the partner is fitted again on the merged keypoints. Writes

- ``fit.npz``: an ``artifacts.BodyFit`` (the layout of marker_fit's, without the marker
  fields): ``valid`` / ``invalid_reason`` (``too_few_keypoints``,
  ``held_before_first_keypoints``, ``poor_reprojection``, ``too_few_views``: fewer views
  than ``min_valid_views`` see the partner; the first fit before the second pass is not held
  to it, so that the second pass crops those frames too);
- ``terms.npz``: per frame ``reproj_px (F, C)`` median 2D error per view (NaN: no
  detection), ``views_seeing (F,)`` the views holding
  ``fitting.partner_fit.VIEW_MIN_KEYPOINTS`` of the partner's body keypoints, ``detections
  (F,)`` body keypoint detections over the views, ``term_cost (F, T)`` weighted cost of
  each term at the solution, ``term_active (F, T)`` the frames where each term was active,
  ``term_points (F, T)`` offending points of the extra terms, ``terms (T,)`` their names,
  ``penetration_m (F,)``, ``contact_m (F,)``, ``ground_m (F,)``
  (``fitting.partner_fit.contact_figures``), ``frames (F,)``;
- ``keypoints.npz``: the keypoints the fit used (``artifacts.keypoints.Keypoints2D``, the
  partner refined by the second pass; only when it ran);
- ``report.json``: frames valid / not valid and why, initialisations, reprojection medians,
  ``second_pass`` (views redone / improved, partner detection rates before and after, body
  keypoints of the found person left out as the wearer's: ``detect.refine.on_wearer``),
  ``warnings`` (more than ``fitting.partner_fit.WEARER_DROP_WARN_SHARE`` of the partner's body
  keypoints left out as the wearer's, by the second pass and ``check_views`` together: the
  QA report lists it at its top; contact frames fitted without ``L_G`` because the images
  held the annotated regions apart: ``fitting.partner_fit.contact_warnings``), summary
  figures of penetration, contact distance and ground penetration (mm), speed;
- ``partner_fit.png``: those curves over the sequence (``drawing.plots.partner_fit_plot``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from artifacts import FitSummary
from fitting.partner_fit import PartnerFitOptions
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "cameras", "ground_plane", "sequence.fps", "sequence.markers_on",
         "sequence.partner", "sequence.has_keypoints", "sequence.markerless", "sequence.people")


@dataclass(frozen=True)
class Options(PartnerFitOptions):
    """The partner fit's options (``fitting.partner_fit.PartnerFitOptions``) and the second
    detection pass: second_pass : after a first fit, run the detector again in tight crops
    around the fitted partner in the views that lacked it (``detect.refine``; only for
    sequences whose keypoints the stage detected itself, not precomputed ones), then fit again
    on the merged keypoints; pose_min_conf / hand_min_conf : its mediapipe thresholds;
    first_fit : the fit before the second pass, whose only use is to place its crops:
    "light" (``LIGHT_FIRST_FIT``: one round per frame, without the temporal pass, the second
    forward pass of ``reliability_px`` and the two costliest hooks,
    ``L_sc`` and ``L_sil``; the final fit is always the full one, also when the pass improved
    no view) or "full" (the final fit's options: when the pass improves no view, the first
    fit is kept as the final one).
    A markerless sequence (:func:`run_markerless`): shape_frames : the first frames where a
    person without scan is seen, whose triangulated bones give its shape
    (``fitting.partner_fit.shape_from_views``); ic_rounds : after each person is fitted
    (person 1 against person 0 with ``L_ic``), person 0 is fitted again against person 1 this
    many times."""

    second_pass: bool = True
    first_fit: Literal["light", "full"] = "light"
    pose_min_conf: float = 0.3
    hand_min_conf: float = 0.3
    shape_frames: int = 20
    ic_rounds: int = 1

    def __post_init__(self):
        super().__post_init__()
        if self.shape_frames < 1:
            raise ValueError(f"shape_frames: must be >= 1, got {self.shape_frames}")
        if self.ic_rounds < 0:
            raise ValueError(f"ic_rounds: must be >= 0, got {self.ic_rounds}")
        if self.first_fit not in ("light", "full"):
            raise ValueError(f"first_fit: must be 'light' or 'full', got {self.first_fit!r}")


#: what the light first fit leaves out (``Options.first_fit``): the second pass needs only
#: where the partner projects (crops of a few hundred pixels), not its last millimetres
LIGHT_FIRST_FIT = {"temporal_passes": 0, "outer_rounds": 1, "reliability_px": 0.0,
                   "weights": {"L_sc": 0.0, "L_sil": 0.0}}


def first_fit_options(o: Options) -> Options:
    """The options of the fit before the second pass (``o.first_fit``)."""
    import dataclasses

    if o.first_fit == "full":
        return o
    return dataclasses.replace(o, temporal_passes=LIGHT_FIRST_FIT["temporal_passes"],
                               outer_rounds=LIGHT_FIRST_FIT["outer_rounds"],
                               reliability_px=LIGHT_FIRST_FIT["reliability_px"],
                               weights={**o.weights, **LIGHT_FIRST_FIT["weights"]})


#: the report's headline figures the export republishes (``artifacts.FitSummary``)
PUBLISHED = ("reprojection_px", "penetration", "contact_distance", "ground_penetration",
             "contact_frames", "fit_cpu_s", "fps")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe)}
    for cam in recipe.cameras:  # the cameras come from the ``capture`` stage's rig
        out[f"video:{cam}"] = Path(seq.videos[cam])  # the second pass; frame count
    if seq.contact is not None:
        out["contact"] = Path(seq.contact)
    return out


OUTLINE_POINTS = 240  # projected surface points that keep the partner in its isolated crop


def _summary(values_m: np.ndarray) -> dict:
    v = np.asarray(values_m, float)
    v = v[np.isfinite(v)] * 1000
    if not len(v):
        return {"frames": 0}
    return {"frames": int(len(v)), "median_mm": float(np.median(v)), "mean_mm": float(v.mean()),
            "p95_mm": float(np.percentile(v, 95)), "max_mm": float(v.max())}


def run(ctx: StageContext) -> None:
    import dataclasses

    from artifacts import BodyFit, ShapeFit
    from artifacts.keypoints import Keypoints2D
    from drawing.plots import partner_fit_plot
    from fitting.contact_signature import load_contact
    from fitting.partner_fit import (
        apply_min_valid_views,
        contact_figures,
        contact_warnings,
        fit_partner,
        view_warnings,
        wearer_drop_warnings,
    )

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    model = common.load_body(ctx)
    cams = common.capture_cameras(ctx, list(rv.cameras))
    if rv.sequence.markerless:
        return run_markerless(ctx, o, model, cams)
    contact = None
    if "contact" in ctx.raw:  # fails (InputError: file, action, field) before anything is written
        action = ctx.unit.split("/", 1)[1]
        family = "smplx" if model.name == "smplx" else "anny"
        contact = load_contact(ctx.raw["contact"], action, model,
                               common.video_length([ctx.raw[f"video:{c}"] for c in rv.cameras])[0],
                               family=family)
    shape_art = ctx.inputs["shape_fit"]
    partner = rv.sequence.partner
    shape = ShapeFit.load(shape_art[partner] if isinstance(shape_art, dict) else shape_art)
    keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    wearer = BodyFit.load(ctx.inputs["marker_fit"]) if "marker_fit" in ctx.inputs else None
    ground = common.ground_of(rv)
    log = lambda s: ctx.log(f"{ctx.unit}: {s}")  # noqa: E731
    masks = None  # L_sil: the silhouettes stage's masks, when it ran and the weight is > 0
    if "silhouettes" in ctx.inputs and o.weights.get("L_sil", 0) > 0:
        from artifacts.silhouettes import Silhouettes

        masks = Silhouettes.load(ctx.inputs["silhouettes"])
    two = o.second_pass and not rv.sequence.has_keypoints
    o1 = first_fit_options(o) if two else o
    light = o1 is not o
    if two:  # the second pass's crops come from every frame the first fit trusts by its
        # reprojection, also those seen by fewer views than min_valid_views (it may find more)
        o1 = dataclasses.replace(o1, min_valid_views=1)
    fit, report = fit_partner(model, shape, keypoints, cams, wearer, contact, ground, o1,
                              progress=ctx.progress, log=log, silhouettes=None if light else masks)
    second = None
    if two:
        keypoints, second = _second_pass(ctx, model, cams, keypoints, fit, o)
        second["first_fit"] = o.first_fit
        if second["views_improved"] or light:
            second["first_fit_cpu_s"] = report["fit_cpu_s"]
            second["first_fit_frames_valid"] = report["frames_valid"]
            fit, report = fit_partner(model, shape, keypoints, cams, wearer, contact, ground, o,
                                      progress=ctx.progress, log=log, silhouettes=masks,
                                      start=fit)
        else:  # the first fit is the fit: its frames judged by the views as the options say
            fit, report = apply_min_valid_views(fit, report, o.min_valid_views, len(cams))
        keypoints.save(ctx.out)  # the keypoints the fit used (person 1 refined)
    report["second_pass"] = second or {"run": False, "why_not": (
        "option second_pass is off" if not o.second_pass else "precomputed keypoints")}
    report["warnings"] = wearer_drop_warnings(
        report["body_keypoints_detected"], report["keypoints_dropped_as_wearer"]["keypoints"],
        (second or {}).get("keypoints_dropped_as_wearer", 0))
    report["warnings"] += view_warnings(report, [c.name for c in cams]) + contact_warnings(report)
    for w in report["warnings"]:
        log(f"WARNING {w}")
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
    FitSummary.from_report("partner_fit", report, PUBLISHED).save(ctx.out)  # what export takes
    partner_fit_plot(ctx.out.path("partner_fit.png"), fit.frames,
                     common.sequence_fps(rv.sequence.fps, ctx.raw[f"video:{rv.cameras[0]}"]),
                     per["reproj_px"], fig["penetration_m"] * 1000, fig["contact_m"] * 1000,
                     fig["ground_m"] * 1000, fit.valid, f"{ctx.unit}: partner {partner}",
                     views=list(rv.cameras))


def _second_pass(ctx: StageContext, model, cams, keypoints, fit, o: Options):
    """The partner's second detection pass around the first fit (``detect.refine``). Returns
    the keypoints with person 1 refined, and the report entry (views redone and improved,
    detection rates before and after, detector calls and CPU seconds)."""
    import dataclasses

    from body import forward
    from body.joints import regressor
    from calib import project
    from detect.mediapipe_detector import MediapipeOptions
    from detect.refine import detection_rates, refine_partner, views_to_redo
    from detect.run import VideoSource

    ci = [keypoints.camera(c.name) for c in cams]
    K = np.asarray(keypoints.kp, float)[ci]  # (C, F, 2, 65, 3), cameras in recipe order
    frames = np.asarray(keypoints.frames)
    est = forward(model, np.asarray(fit.betas, float), fit.body_pose, fit.global_orient, fit.transl)
    R = regressor(model, "kp65")
    k3 = np.stack([R @ np.concatenate([v, j]) for v, j in zip(est.vertices, est.joints, strict=True)])
    outline_ids = np.arange(0, model.num_vertices, max(1, model.num_vertices // OUTLINE_POINTS))
    proj = np.stack([project(c, k3) for c in cams])  # (C, F, 65, 2)
    outline = np.stack([project(c, est.vertices[:, outline_ids]) for c in cams])
    proj[:, ~np.asarray(fit.valid)] = np.nan  # no crops from a frame the fit does not trust
    need = views_to_redo(K[:, :, 1], proj, (cams[0].height, cams[0].width))
    source = VideoSource(tuple(str(ctx.raw[f"video:{c.name}"]) for c in cams))
    factory = MediapipeOptions(pose_min_conf=o.pose_min_conf, hand_min_conf=o.hand_min_conf)
    ref = refine_partner(source, factory, frames, K, proj, outline, need, progress=ctx.progress)
    kp = np.array(keypoints.kp)
    kp[ci, :, 1] = ref.kp
    # a replaced view's confidences are the second pass's own, none of them a cross-view outlier
    raw, outl = np.array(keypoints.conf_raw), np.array(keypoints.cross_view_outlier)
    idx = np.asarray(ci)
    for c, f in zip(*np.nonzero(ref.improved), strict=True):
        raw[idx[c], f, 1] = ref.kp[c, f, :, 2]
        outl[idx[c], f, 1] = False
    before, after = detection_rates(K[:, :, 1]), detection_rates(ref.kp)
    out = dataclasses.replace(keypoints, kp=kp.astype(np.float32), conf_raw=raw,
                              cross_view_outlier=outl)
    return out, {"run": True, "views_redone": int(ref.redone.sum()),
                 "views_improved": int(ref.improved.sum()), "view_frames": int(need.size),
                 "detected_before": before, "detected_after": after,
                 "detector_calls": ref.calls, "cpu_s": round(ref.cpu_s, 2),
                 "keypoints_dropped_as_wearer": int(ref.on_wearer.sum())}


class _SubWriter:
    """Writes into a sub-folder of the artifact (``person0/``: person 0 of a markerless
    sequence)."""

    def __init__(self, out, sub: str):
        self.out, self.sub = out, sub
        self.dir = Path(out.dir) / sub

    def path(self, name: str) -> Path:
        return self.out.path(f"{self.sub}/{name}")

    def save_arrays(self, name: str, **arrays) -> Path:
        return self.out.save_arrays(f"{self.sub}/{name}", **arrays)

    def save_json(self, name: str, obj) -> Path:
        return self.out.save_json(f"{self.sub}/{name}", obj)


#: where person 0 of a markerless sequence is written in the artifact (person 1: the top)
PERSON0 = "person0"


def person_keypoints(keypoints, person: int):
    """The keypoints with ``person``'s slot in the partner's (the slot the fit reads)."""
    import dataclasses

    from artifacts.keypoints import PARTNER

    if person == PARTNER:
        return keypoints
    order = [1, 0]
    return dataclasses.replace(keypoints, kp=keypoints.kp[:, :, order],
                               boxes=keypoints.boxes[:, :, order],
                               hand_boxes=keypoints.hand_boxes[:, :, order],
                               cross_view_outlier=keypoints.cross_view_outlier[:, :, order],
                               conf_raw=keypoints.conf_raw[:, :, order])


def run_markerless(ctx: StageContext, o: Options, model, cams) -> None:
    """Every person of a markerless sequence fitted from the video with the partner fit's
    terms: person 0 alone (L_2d, L_theta, L_s, L_sc, L_gp), person 1 against person 0 (and
    L_ic, and L_D / L_N when a contact signature is given), then person 0 again against
    person 1 (``ic_rounds``). A person without scan gets its shape from the views
    (``fitting.partner_fit.shape_from_views``, the first ``shape_frames`` frames where it is
    seen; the betas then stay fixed). Person 1 is written as a partner's fit is (``fit.npz``,
    ``terms.npz``, ``summary.json``), person 0 the same in ``person0/``; ``report.json`` has
    each person's report under ``people``."""
    import dataclasses

    from artifacts import ShapeFit
    from artifacts.keypoints import Keypoints2D
    from drawing.plots import partner_fit_plot
    from fitting.contact_signature import load_contact
    from fitting.partner_fit import (
        contact_figures,
        contact_warnings,
        fit_partner,
        shape_from_views,
        view_warnings,
    )

    rv = ctx.recipe
    people = list(rv.sequence.people)
    contact = None
    if "contact" in ctx.raw and len(people) == 2:
        action = ctx.unit.split("/", 1)[1]
        family = "smplx" if model.name == "smplx" else "anny"
        contact = load_contact(ctx.raw["contact"], action, model,
                               common.video_length([ctx.raw[f"video:{c}"] for c in rv.cameras])[0],
                               family=family)
    keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    shape_art = ctx.inputs["shape_fit"]
    ground = common.ground_of(rv)
    shapes, shape_reports, kps = [], [], []
    for p, sid in enumerate(people):
        shape = ShapeFit.load(shape_art[sid] if isinstance(shape_art, dict) else shape_art)
        kp_p = person_keypoints(keypoints, p)
        if str(shape.shape_source) == "mean":  # no scan, no markers: the shape from the views
            vs = shape_from_views(model, kp_p, cams, frames=o.shape_frames)
            shape = dataclasses.replace(shape, betas=vs.betas)  # held fixed from here on
            shape_reports.append(vs.report())
            ctx.log(f"{ctx.unit}: {sid}: shape from the views ({vs.frames_used} frames): bone rms "
                    f"{vs.rms_before_mm:.1f} mm (mean shape) -> {vs.rms_after_mm:.1f} mm")
        else:
            shape_reports.append({"source": str(shape.shape_source)})
        shapes.append(shape)
        kps.append(kp_p)

    def fit(p, other, with_contact):
        def log(s):
            ctx.log(f"{ctx.unit}: {people[p]}: {s}")

        return fit_partner(model, shapes[p], kps[p], cams, other, contact if with_contact else None,
                           ground, o, progress=ctx.progress, log=log)

    fits, reports = [None] * len(people), [None] * len(people)
    fits[0], reports[0] = fit(0, None, False)
    if len(people) == 2:
        fits[1], reports[1] = fit(1, fits[0], True)
        for _ in range(o.ic_rounds):
            fits[0], reports[0] = fit(0, fits[1], False)
    fps = common.sequence_fps(rv.sequence.fps, ctx.raw[f"video:{rv.cameras[0]}"])
    summaries = {}
    for p, sid in enumerate(people):
        other = fits[1 - p] if len(people) == 2 else None
        writer = ctx.out if p == 1 else _SubWriter(ctx.out, PERSON0)
        rep = reports[p]
        fig = contact_figures(model, fits[p], other, contact if p == 1 else None, ground)
        per = rep.pop("per_frame")
        fits[p].save(writer)
        writer.save_arrays("terms", terms=np.array(rep["terms"]), **per, **fig)
        ok = fits[p].valid
        rep.update({"sequence": ctx.unit, "subject": sid, "person": p, "markerless": True,
                    "shape": shape_reports[p],
                    "penetration": _summary(fig["penetration_m"][ok]),
                    "contact_distance": _summary(fig["contact_m"][ok]),
                    "ground_penetration": _summary(fig["ground_m"][ok]),
                    "second_pass": {"run": False, "why_not": "a markerless sequence"},
                    "frames_not_valid_list": {str(int(f)): r for f, r in zip(
                        fits[p].frames[~ok], [_reason(c) for c in fits[p].invalid_reason[~ok]],
                        strict=True)}})
        rep["warnings"] = [f"{sid}: {w}" for w in view_warnings(rep, [c.name for c in cams])
                           + contact_warnings(rep)]
        for w in rep["warnings"]:
            ctx.log(f"{ctx.unit}: WARNING {w}")
        writer.save_json("report", rep)
        FitSummary.from_report("partner_fit", rep, PUBLISHED).save(writer)
        partner_fit_plot(writer.path("partner_fit.png"), fits[p].frames, fps, per["reproj_px"],
                         fig["penetration_m"] * 1000, fig["contact_m"] * 1000,
                         fig["ground_m"] * 1000, fits[p].valid, f"{ctx.unit}: {sid} (person {p})",
                         views=list(rv.cameras))
        summaries[sid] = rep
    top = dict(summaries[people[0]]) if len(people) == 1 else dict(summaries[people[1]])
    top["people"] = {sid: {k: r[k] for k in ("person", "frames_valid", "frames_not_valid",
                                             "reprojection_px", "shape", "fit_cpu_s", "fps")}
                     for sid, r in summaries.items()}
    top["warnings"] = [w for r in summaries.values() for w in r["warnings"]]
    top["people_files"] = {people[0]: f"{PERSON0}/"} | ({people[1]: ""} if len(people) == 2 else {})
    ctx.out.save_json("report", top)
    if len(people) == 1:
        FitSummary.from_report("partner_fit", top, PUBLISHED).save(ctx.out)


def _reason(code) -> str:
    from artifacts import INVALID_REASONS

    return INVALID_REASONS[int(code)]


STAGE = Stage(name="partner_fit", func=run, per="sequence",  # markerless: no marker_fit upstream
              upstream=("capture", "shape_fit", "keypoints", "rig", "marker_fit",
                        "silhouettes"),
              params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="pose of the unmarked partner (2D keypoints, contact, collisions, silhouettes)")
