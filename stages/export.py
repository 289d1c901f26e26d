"""Stage ``export`` (per sequence): the sequence's files in the CHI3D layout (``shared/FORMATS.md``).

Under ``<group>/`` in the stage folder, for the sequence's action (person 0 = the marker
wearer, person 1 = the partner; P = 1 on a sequence without partner):

- ``smplx/<action>.json``: convert's SMPL-X parameters (``formats.chi3d.write_smplx``:
  rotation matrices, leading person axis, betas and expression repeated per frame);
- ``anny/<action>.json``: the fitted model's own parameters (``formats.anny_json``; the folder
  is named after the fitted model, ``smplx_fit`` when that is SMPL-X itself);
- ``joints3d_25/<action>.json``: the 25 CHI3D joints regressed from the fitted mesh
  (``body.joints.regressor(model, "joints3d_25")`` on ``body.forward``, as the studio's truth);
- ``camera_parameters/<camera>/<action>.json`` and ``videos/<camera>/<action>.mp4`` (cut to the
  exported frames) when the sequence was filmed;
- ``valid/<action>.json``: per person and frame whether it is ground truth, and the reason
  when not: ``artifacts.INVALID_REASONS`` of the fit; else ``qa:<reason>`` where the stage
  ``qa`` flagged the frame for a reason of the option ``withhold`` (the reasons that mean the
  fit is wrong, ``qa.constants.FIT_WRONG`` by default: :func:`qa_withheld`; a ``<person>.``
  metric withholds that person, a pair metric both, except that with ``trust_markers`` the
  reasons ``qa.constants.MARKER_FIT_SPARED`` (cross-view reprojection, interpenetration,
  contact) spare the marker-fitted wearer when the partner is fitted from the video: they
  fall on the video fit); else ``not_converted`` where convert
  marks the SMPL-X frame not valid. Every file's arrays are dense (frames that are not valid
  are written too): the mask says which are ground truth;
- ``interaction_contact_signature.json``: this action's entry with the signature in every
  released model: ``anny_signature`` as annotated, ``smplx_signature`` with each Anny facet
  mapped to its nearest SMPL-X facet through convert's ``correspondence.npz``
  (``src_face_tgt_face``) and the region of each pair taken from the official
  ``contact_regions.json`` (option ``contact_regions``: ``rid_to_smplx_fids``) when given, else
  the Anny facet's region in our 75-region map (``body.regions``); ``ghum_signature`` empty;
- ``text_annotations.json``: ``{action: sentence}`` (the recipe's ``text``).

Beside them ``figures.json`` (``artifacts.SequenceFigures``: the fitting figures of marker_fit,
partner_fit and convert that the release's datasheet lists) and ``export.json``
(``artifacts.SequenceExport``: frames, every file written, what is absent and why, the
per-reason counts of frames that are not valid, the person-frames withheld per QA reason,
camera conversions, contact mapping notes).
convert's outputs are read through ``artifacts.SMPLXFit``, ``SurfaceCorrespondence`` and
``ConversionReport``.

Frames are convert's frames (marker_fit's frames that partner_fit also has). Contact frames
(``fr_id``, ``start_fr``, ``end_fr``) index the exported frame axis: they are kept as they are
when the exported frames are ``0..F-1`` of the video, else moved onto the exported frames
(the original values are in ``export.json``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.spec import Stage, StageContext
from qa import constants as QK
from stages import common

READS = ("body_model.kind", "cameras", "sequence.fps", "sequence.text", "sequence.markers_on",
         "sequence.partner", "sequence.has_video")

NOT_CONVERTED = "not_converted"  # fit valid, but the SMPL-X conversion of the frame is not


#: the QA reasons a flagged person-frame is withheld for by default: those meaning the fit is
#: wrong (``qa.constants.FIT_WRONG`` says why each; ``NOT_FIT_WRONG`` why the others are not)
DEFAULT_WITHHOLD = tuple(QK.FIT_WRONG)


@dataclass(frozen=True)
class Options:
    """contact_regions : path of CHI3D's official ``info/contact_regions.json``
    (``rid_to_smplx_fids``): the SMPL-X signature's regions are then the official region of
    each mapped SMPL-X facet (relative paths: from the recipe's folder). None: our regions.
    withhold : QA reasons (``qa.metrics.QAOptions`` threshold names, ``qa.metrics.REASON_KINDS``)
    for which a frame the stage ``qa`` flags is published not valid (reason ``qa:<name>``) for
    the person the metric is about (both people for the pair metrics); default
    ``DEFAULT_WITHHOLD``; empty: QA withholds nothing.
    trust_markers : a person fitted to markers (the wearer) is not withheld for the reasons
    ``qa.constants.MARKER_FIT_SPARED`` (cross-view reprojection, interpenetration, contact)
    when the other person is fitted from the video alone: those fall on the video fit (its
    own marker reasons judge the wearer's fit). False: every reason withholds everyone it is
    about."""

    contact_regions: str | None = None
    withhold: tuple[str, ...] = DEFAULT_WITHHOLD
    trust_markers: bool = True

    def __post_init__(self):
        from qa.metrics import REASON_KINDS

        w = tuple(str(x) for x in self.withhold)
        bad = [x for x in w if x not in REASON_KINDS]
        if bad:
            raise ValueError(f"withhold: unknown QA reason(s) {bad} (known: "
                             f"{', '.join(REASON_KINDS)})")
        if len(set(w)) != len(w):
            raise ValueError(f"withhold: a reason listed twice in {list(w)}")
        object.__setattr__(self, "withhold", w)


def _contact_regions_path(recipe) -> Path | None:
    p = (recipe.stages.get("export") or {}).get("contact_regions")
    if not p:
        return None
    p = Path(p)
    src = getattr(recipe, "source", None)
    return p if p.is_absolute() or src is None else Path(src).parent / p


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe)}
    for cam in recipe.cameras:
        if cam in seq.videos:
            out[f"video:{cam}"] = Path(seq.videos[cam])
    if seq.contact is not None:
        out["contact"] = Path(seq.contact)
    cr = _contact_regions_path(recipe)
    if cr is not None:
        out["contact_regions"] = cr
    return out


# ------------------------------------------------------------------------------ pure helpers
def frame_index(fit_frames, frames, file, who: str) -> np.ndarray:
    """Positions of ``frames`` in a fit's ``fit_frames``; InputError naming the first missing."""
    from formats.errors import InputError

    fit_frames = np.asarray(fit_frames)
    idx = np.searchsorted(fit_frames, frames)
    ok = (idx < len(fit_frames)) & (fit_frames[np.minimum(idx, len(fit_frames) - 1)] == frames)
    if not ok.all():
        raise InputError(file, "frames", f"frame not fitted by {who}",
                         frame=int(np.asarray(frames)[~ok][0]))
    return idx


def qa_withheld(qa, frames, roles, withhold, marker_fitted=()) -> np.ndarray:
    """(P, F) str: per exported person (``roles``: ``"wearer"`` / ``"partner"`` in person
    order) and frame (``frames``: video frame indices) the QA reason it is withheld for,
    ``"qa:<name>"`` (``formats.release.QA_REASON_PREFIX``), or ``""``. ``qa``: the sequence's
    ``artifacts.QAResult`` or its ``QAMetrics`` (``frames``, ``reasons``, ``flagged``); a
    flagged reason (a metric name) counts when its threshold name
    (``qa.metrics.threshold_name``) is in ``withhold``, for the people it is about
    (``qa.metrics.reason_people``: a ``<person>.`` metric that person, the others both). Of
    several, the first in ``withhold``'s order. Frames QA did not measure are not withheld.
    ``marker_fitted``: the roles fitted to markers; when another person is not, the reasons
    ``qa.constants.MARKER_FIT_SPARED`` (cross-view reprojection, the pair reasons) withhold
    only the video-fitted people (option ``trust_markers``)."""
    from formats.release import QA_REASON_PREFIX
    from qa.metrics import reason_people, threshold_name

    m = getattr(qa, "metrics", qa)
    frames = np.asarray(frames)
    out = np.full((len(roles), len(frames)), "", dtype=object)
    qf = np.asarray(m.frames)
    rows = np.searchsorted(qf, frames)
    ok = (rows < len(qf)) & (qf[np.minimum(rows, max(len(qf) - 1, 0))] == frames) if len(qf) \
        else np.zeros(len(frames), bool)
    flagged = np.asarray(m.flagged, bool)
    reasons = [str(r) for r in m.reasons]
    spared = set(marker_fitted) if set(roles) - set(marker_fitted) else set()
    for kind in reversed(tuple(withhold)):  # the first in withhold's order is written last
        for c, r in enumerate(reasons):
            if threshold_name(r) != kind:
                continue
            hit = np.zeros(len(frames), bool)
            hit[ok] = flagged[rows[ok], c]
            for p, role in enumerate(roles):
                if role in spared and kind in QK.MARKER_FIT_SPARED:
                    continue
                if role in reason_people(r):
                    out[p, hit] = QA_REASON_PREFIX + kind
    return out.astype(str)


def marker_fitted(fits, roles) -> tuple[str, ...]:
    """The roles whose ``artifacts.BodyFit`` was fitted to markers (it carries marker names)."""
    return tuple(r for f, r in zip(fits, roles, strict=True)
                 if getattr(f, "marker_names", None) is not None and len(f.marker_names))


def withheld_by_qa(qa, frames, fits, roles, o: "Options") -> np.ndarray:
    """:func:`qa_withheld` under the export options ``o`` (its ``withhold`` reasons; with
    ``trust_markers``, the marker-fitted people of ``fits`` spared the video fit's reasons):
    the rule the export applies, and the one the bench's qa case counts published frames by."""
    return qa_withheld(qa, frames, roles, o.withhold,
                       marker_fitted(fits, roles) if o.trust_markers else ())


def validity(fits_valid, fits_reason, converted=None, withheld=None) -> tuple[np.ndarray, np.ndarray]:
    """(P, F) valid and reason names from each person's fit (``valid``, ``invalid_reason``
    codes at the exported frames), the QA reasons it is withheld for (``withheld`` (P, F) str,
    ``""`` = none: :func:`qa_withheld`; None: no QA) and convert's ``valid`` (P, F) (None: no
    conversion). A frame the fit does not call valid keeps the fit's reason; one QA withholds
    gets its QA reason (the fit is wrong, whatever the conversion made of it); then
    ``not_converted``."""
    from artifacts import INVALID_REASONS

    valid = np.asarray(fits_valid, bool).copy()
    reason = np.array([[INVALID_REASONS[int(c)] for c in row] for row in fits_reason], dtype=object)
    if withheld is not None:
        held = valid & (np.asarray(withheld, str) != "")
        reason[held] = np.asarray(withheld, object)[held]
        valid &= ~held
    if converted is not None:
        lost = valid & ~np.asarray(converted, bool)
        reason[lost] = NOT_CONVERTED
        valid &= ~lost
    return valid, reason.astype(str)


def smplx_release(sm: dict, P: int) -> dict[str, np.ndarray]:
    """convert's ``smplx.npz`` -> the CHI3D per-frame shapes (``formats.chi3d.SMPLX_SHAPES``)."""
    F = sm["transl"].shape[1]
    out = {"transl": sm["transl"], "body_pose": sm["body_pose"],
           "left_hand_pose": sm["left_hand_pose"], "right_hand_pose": sm["right_hand_pose"]}
    for k in ("global_orient", "jaw_pose", "leye_pose", "reye_pose"):
        out[k] = np.asarray(sm[k]).reshape(P, F, 1, 3, 3)
    for k in ("betas", "expression"):
        a = np.asarray(sm[k], float)
        out[k] = np.repeat(a[:, None, :10], F, axis=1) if a.ndim == 2 else a
    return {k: np.asarray(v, float) for k, v in out.items()}


def move_contact_frames(frames: np.ndarray, fr_id: int, start: int | None, end: int | None):
    """The contact frames on the exported frame axis (positions into ``frames``): the frame
    itself when ``frames`` is ``0..F-1``; else ``fr_id`` to the nearest exported frame,
    ``start`` to the first exported frame at or after it, ``end`` to the last at or before it
    (each clamped so that start <= fr_id <= end)."""
    frames = np.asarray(frames)
    if np.array_equal(frames, np.arange(len(frames))):
        return fr_id, start, end
    fr = int(np.argmin(np.abs(frames - fr_id)))
    s = None if start is None else min(int(np.searchsorted(frames, start, "left")), fr)
    e = None if end is None else max(int(np.searchsorted(frames, end, "right")) - 1, fr)
    return fr, s, e


def map_signature(sig, src_family: str, src_face_tgt_face, src_face_region, tgt_face_region=None):
    """``formats.chi3d.ContactSignature`` with the SMPL-X signature made from the source
    family's (``anny``): facets through ``src_face_tgt_face``; regions = ``tgt_face_region`` of
    the mapped facets (official map) when given, else ``src_face_region`` of the source facets.
    Without facet pairs the source's region pairs carry over (our map only)."""
    import dataclasses

    faces = np.asarray(sig.faces(src_family), np.int64).reshape(-1, 2)
    tgt = np.asarray(src_face_tgt_face, np.int64)[faces]
    if len(faces):
        regions = (np.asarray(tgt_face_region)[tgt] if tgt_face_region is not None
                   else np.asarray(src_face_region)[faces])
    elif tgt_face_region is None:
        regions = np.asarray(sig.regions(src_family), np.int64).reshape(-1, 2)
    else:
        regions = np.zeros((0, 2), np.int64)  # region ids of another map cannot be carried over
    return dataclasses.replace(sig, smplx_faces=tgt.reshape(-1, 2),
                               smplx_regions=np.asarray(regions, np.int64).reshape(-1, 2))


# ------------------------------------------------------------------------------------- stage
def run(ctx: StageContext) -> None:
    from artifacts import (
        BodyFit,
        ConversionReport,
        FitSummary,
        QAResult,
        SequenceExport,
        SequenceFigures,
        ShapeFit,
        SMPLXFit,
        SurfaceCorrespondence,
    )
    from artifacts.base import JsonFields
    from artifacts.export import ContactNote
    from body import forward
    from body.joints import regress, regressor
    from body.rotations import rodrigues
    from calib.convert import convert_distortion
    from calib.io import write_chi3d_camera
    from fitting.marker_graph import fit_points_observed
    from formats import anny_json, chi3d
    from formats import release as R
    from formats.errors import InputError

    # the option contact_regions acts through the raw input of that name (keyed by content)
    rv = ctx.recipe
    group, action = ctx.unit.split("/", 1)
    model = common.load_body(ctx)
    subjects = [rv.sequence.markers_on] + ([rv.sequence.partner] if rv.sequence.partner else [])
    people = common.fitted_people(ctx)  # markerless: both from partner_fit
    mf_art, pf_art = people[0][0], (people[1][0] if len(people) > 1 else None)
    cv_art = ctx.inputs.get("convert")
    fits = [BodyFit.load(mf_art)] + ([BodyFit.load(pf_art)] if pf_art is not None else [])
    subjects = subjects[:len(fits)]
    P = len(fits)
    absent: dict[str, str] = {}
    if pf_art is None:
        absent["person 1"] = ("no partner_fit (a sequence without partner or without video): "
                              "one person (P = 1)")
    sm = corr = None
    if cv_art is not None:
        sm = SMPLXFit.load(cv_art)
        frames = np.asarray(sm.frames, np.int64)
        if sm.num_persons != P:
            raise InputError(Path(cv_art.dir) / SMPLXFit.file_name(), "transl",
                             f"{sm.num_persons} persons, the fits have {P}")
        corr = SurfaceCorrespondence.load(cv_art)
    else:
        frames = np.asarray(fits[0].frames, np.int64)
        for f in fits[1:]:
            frames = np.intersect1d(frames, f.frames)
        absent["smplx"] = "no convert artifact: no SMPL-X parameters"
    if not len(frames):
        raise InputError(common.artifact_folder(mf_art), "frames",
                         "no frame fitted by every person to export")
    F = len(frames)
    idx = [frame_index(f.frames, frames, common.artifact_folder(a) / "fit.npz", name)
           for f, (a, name) in zip(fits, people, strict=True)]
    out_dir = Path(ctx.out.dir).resolve()
    written: list[str] = []

    def rel(name: str) -> Path:
        p = ctx.out.path(f"{group}/{name}")
        written.append(Path(p).resolve().relative_to(out_dir).as_posix())
        return p

    # validity: the fits' masks, the QA flags that say a fit is wrong, the conversion's mask
    o: Options = ctx.params or Options()
    qa_art = ctx.inputs.get("qa")
    withheld = withhold = None
    if qa_art is not None:
        withhold = o.withhold
        withheld = withheld_by_qa(QAResult.load(qa_art), frames, fits, ["wearer", "partner"][:P], o)
    else:
        absent["qa"] = "no qa artifact: no frame withheld for a QA flag"
    valid, reason = validity([f.valid[i] for f, i in zip(fits, idx, strict=True)],
                             [f.invalid_reason[i] for f, i in zip(fits, idx, strict=True)],
                             None if sm is None else sm.valid, withheld)
    # per joints3d_25 joint: ground truth where the frame is and every joint it hangs on was
    # observed by a marker or a view (BodyFit.observed; e.g. not the arms of a lower-body set),
    # and a joint at a keypoint (an elbow) where the fit agrees with it in two views
    reg25 = regressor(model, "joints3d_25")
    joints_valid = np.stack([fit_points_observed(model, f)[i]
                             for f, i in zip(fits, idx, strict=True)]) & valid[..., None]
    R.write_valid(rel(f"{R.VALID_DIR}/{action}.json"), valid, reason, frames, joints_valid,
                  qa_withhold=withhold)
    # the fitted model's own parameters, and the joints from its mesh
    S = max(len(f.betas) for f in fits)
    betas = np.stack([np.pad(np.asarray(f.betas, float), (0, S - len(f.betas))) for f in fits])
    pose = np.stack([np.asarray(f.body_pose, float)[i] for f, i in zip(fits, idx, strict=True)])
    orient = np.stack([np.asarray(f.global_orient, float)[i] for f, i in zip(fits, idx, strict=True)])
    transl = np.stack([np.asarray(f.transl, float)[i] for f, i in zip(fits, idx, strict=True)])
    own = model.name if model.name != "smplx" else "smplx_fit"  # never over convert's smplx/
    anny_json.write_anny(rel(f"{own}/{action}.json"), transl, orient, rodrigues(pose),
                         np.repeat(betas[:, None], F, axis=1), list(model.joint_names))
    j25 = []
    for p in range(P):
        b = forward(model, betas[p], pose[p], orient[p], transl[p])
        j25.append(regress(reg25, b.vertices, b.joints))
    chi3d.write_joints3d_25(rel(f"joints3d_25/{action}.json"), np.stack(j25))
    if sm is not None:
        if (sm.num_persons, sm.num_frames) != (P, F):
            raise InputError(Path(cv_art.dir) / SMPLXFit.file_name(), "transl",
                             f"(persons, frames) {(sm.num_persons, sm.num_frames)} != {(P, F)}")
        chi3d.write_smplx(rel(f"smplx/{action}.json"), smplx_release(sm.params(), P))
    # cameras and videos
    cameras: dict[str, dict] = {}
    fps = None
    rig_cams, rig_sources = common.capture_rig(ctx) or ([], [])  # as the capture stage read them
    for cam, src in zip(rig_cams, rig_sources, strict=True):
        c = cam.name
        info = {"source": src, "model": cam.model}
        if cam.model != "h36m" and np.any(cam.p):
            conv = convert_distortion(cam, "h36m")
            cam = conv.camera
            info.update(converted_to="h36m", rms_px=conv.rms_px, max_px=conv.max_px)
        write_chi3d_camera(rel(f"camera_parameters/{c}/{action}.json"), cam)
        cameras[c] = info
    if not cameras:
        absent["camera_parameters"] = "the sequence has no calibration (marker-only)"
    videos = [c for c in rv.cameras if f"video:{c}" in ctx.raw]
    if videos:
        fps = common.sequence_fps(rv.sequence.fps, ctx.raw[f"video:{videos[0]}"])
        step = np.diff(frames)
        if len(step) and np.all(step == step[0]) and step[0] > 1:
            fps = fps / float(step[0])  # every k-th frame: the cut video keeps real time
        for c in ctx.progress(videos, total=len(videos), desc="videos"):
            R.cut_video(ctx.raw[f"video:{c}"], rel(f"videos/{c}/{action}.mp4"), frames, fps)
    else:
        absent["videos"] = "the sequence was not filmed (marker-only)"
    # contact signature
    contact_note = None
    if "contact" in ctx.raw:
        contact_note = _export_contact(ctx, model, action, frames, corr, rel)
    else:
        absent["interaction_contact_signature"] = "the recipe gives no contact file"
    # text
    text = (rv.sequence.text or "").strip()
    if text:
        R.write_text_annotations(rel(R.TEXT_FILE), {action: text})
    else:
        absent["text_annotations"] = "the recipe gives no text for the sequence"
    # figures of the fits, for the datasheet
    shape = ctx.inputs.get("shape_fit") or {}
    figures = SequenceFigures(
        sequence=ctx.unit, subjects=tuple(subjects),
        marker_fit=FitSummary.load(mf_art).published() if "marker_fit" in ctx.inputs else None,
        partner_fit=None if ctx.inputs.get("partner_fit") is None
        else FitSummary.load(ctx.inputs["partner_fit"]).published(),
        convert=None if cv_art is None else ConversionReport.load(cv_art).figures(),
        shape_source={s: str(ShapeFit.load(shape[s]).shape_source) for s in subjects if s in shape})
    counts = R.reason_counts(reason)
    named = {k: f"{group}/{n}" for k, n in (("valid", f"{R.VALID_DIR}/{action}.json"),
                                             ("contact", "interaction_contact_signature.json"),
                                             ("text", R.TEXT_FILE))}
    SequenceExport(
        sequence=ctx.unit, group=group, action=action, persons=tuple(subjects), model=model.name,
        frames=int(F), first_frame=int(frames[0]), last_frame=int(frames[-1]),
        video_fps=None if fps is None else float(fps),
        person_frames_not_valid=int((~valid).sum()),
        not_valid_by_reason=tuple({"subject": s, **c} for s, c in zip(subjects, counts, strict=True)),
        cameras=cameras, contact=None if contact_note is None else ContactNote.from_json(
            JsonFields(contact_note, "export.json", "contact")),
        absent=absent, files=tuple(written), valid_file=named["valid"],
        contact_file=named["contact"] if named["contact"] in written else None,
        text_file=named["text"] if named["text"] in written else None,
        withhold=withhold, withheld=R.withheld_counts(reason), figures=figures).save(ctx.out)
    held = R.withheld_counts(reason)
    ctx.log(f"{ctx.unit}: exported {F} frames x {P} persons, {int((~valid).sum())} person-frames "
            f"not valid ({sum(held.values())} withheld for QA flags"
            + (": " + ", ".join(f"{k} {n}" for k, n in held.items()) if held else "") + "), "
            f"{int((valid[..., None] & ~joints_valid).sum())} joint-frames of valid "
            f"frames not observed, {len(written)} files")


def _export_contact(ctx, model, action: str, frames, corr, rel) -> dict:
    import dataclasses

    from body.regions import load_official, region_map
    from fitting.contact_signature import model_family
    from formats.chi3d import read_contact_signatures, write_contact_signatures
    from formats.errors import InputError

    path = Path(ctx.raw["contact"])
    sigs = read_contact_signatures(path)
    if action not in sigs:
        raise InputError(path, action, f"action missing (the file has: {sorted(sigs)})")
    sig = sigs[action]
    fam = model_family(model) or model.name
    note: dict = {"source": path.name, "family": fam,
                  "original_frames": {"fr_id": sig.fr_id, "start_fr": sig.start_fr,
                                      "end_fr": sig.end_fr}}
    T = len(model.faces)
    faces = sig.faces(fam) if fam in ("anny", "smplx", "ghum") else np.zeros((0, 2), np.int64)
    if len(faces) and faces.max() >= T:
        raise InputError(path, f"{action}.{fam}_signature.face_id",
                         f"facet {int(faces.max())} outside the model's {T} faces", sig.fr_id)
    if fam != "smplx" and not len(sig.faces(fam)) and not len(sig.regions(fam)):
        note["smplx"] = f"no {fam} pairs in the file: its SMPL-X signature is kept as given"
    elif fam != "smplx":
        if corr is None:
            note["smplx"] = "no convert artifact: the SMPL-X signature is left empty"
            sig = dataclasses.replace(sig, smplx_faces=np.zeros((0, 2), np.int64),
                                      smplx_regions=np.zeros((0, 2), np.int64))
        else:
            m = np.asarray(corr.src_face_tgt_face)
            if len(m) != T:
                raise InputError("correspondence.npz", "src_face_tgt_face",
                                 f"{len(m)} source facets, the fitted model has {T}")
            official = None
            if "contact_regions" in ctx.raw:
                official = load_official(ctx.raw["contact_regions"], "smplx",
                                         num_faces=len(corr.tgt_faces)).face_region
                note["smplx_regions"] = ("official contact_regions.json (rid_to_smplx_fids) "
                                         "region of each mapped SMPL-X facet")
            else:
                note["smplx_regions"] = (f"our 75-region map: the region of each {fam} facet "
                                         "(body.regions.region_map)")
            src_region = region_map(model).face_region if len(faces) else None
            sig = map_signature(sig, fam, m, src_region, official)
            if official is not None and (sig.smplx_regions < 0).any():
                bad = int(np.flatnonzero((sig.smplx_regions < 0).any(axis=1))[0])
                note.setdefault("warnings", []).append(
                    f"pair {bad}: a mapped SMPL-X facet lies in no official region (-1)")
            note["smplx_facets"] = "nearest SMPL-X facet of each facet (src_face_tgt_face)"
    fr, s, e = move_contact_frames(frames, sig.fr_id, sig.start_fr, sig.end_fr)
    note["moved_to_exported_frames"] = (fr, s, e) != (sig.fr_id, sig.start_fr, sig.end_fr)
    sig = dataclasses.replace(sig, fr_id=fr, start_fr=s, end_fr=e)
    if (sig.smplx_regions < 0).any():  # not writable as ids: drop the pairs without a region
        keep = ~(sig.smplx_regions < 0).any(axis=1)
        sig = dataclasses.replace(sig, smplx_regions=sig.smplx_regions[keep],
                                  smplx_faces=sig.smplx_faces[keep])
    write_contact_signatures(rel("interaction_contact_signature.json"), {action: sig})
    note["pairs"] = {f: int(len(sig.faces(f))) for f in ("anny", "smplx", "ghum")}
    return note


STAGE = Stage(name="export", func=run, per="sequence",
              upstream=("capture", "shape_fit", "keypoints", "rig", "marker_fit", "partner_fit",
                        "convert", "qa"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="CHI3D-layout files of the sequence (SMPL-X, Anny, joints, cameras, videos, "
                  "validity, contact signature, text)")
