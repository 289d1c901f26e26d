"""The benchmark protocol on loaded sequences (pure: no file I/O).

Per sequence: project both people's ``joints3d_25`` into the truth's camera (pinhole, as the
public tools' ``intrinsics_wo_distortion``), box them, match predicted to true people per frame
(Hungarian on IoU), then compute each metric per person and frame, and average over the
person-frames the truth marks valid (all frames, and the contact frames). Over sequences: the
plain mean of the per-sequence figures (each sequence weighs the same).

Contact frames: ``start_fr..end_fr`` of the truth's contact signature (both ends included),
``fr_id`` alone when the file has no interval, both people. The public code's ``*_c`` is the
metric at ``fr_id`` only and, after it concatenates the persons along the frame axis, of
person 0 only; that figure is reported too, as ``fr_id_person0``.
"""
from __future__ import annotations

import math

import numpy as np

from calib.camera import project
from evaluate import constants as K
from evaluate import metrics as M
from evaluate.folders import SequenceData
from formats.errors import InputError

GROUPS = ("all", "contact", "fr_id_person0")

PROTOCOL = {
    "units": "mm",
    "joints": "14 LSP joints from the H36M 17 (H36M_TO_J17[:14]), each skeleton minus its pelvis",
    "pa": "per-frame similarity Procrustes (rotation det +1, scale, translation) of the "
          "prediction onto the truth",
    "vertices": "centred on the model's joint 0",
    "transl_err": "distance of joint 0 (pelvis), world",
    "matching": "per frame, Hungarian assignment of predicted to true people on the IoU of "
                "the boxes of their projected joints3d_25 (first camera of the sequence, "
                "pinhole); the same assignment serves every metric",
    "averaging": "mean over the valid person-frames of a sequence (both people together, as "
                 "the public code concatenates them), then mean over sequences",
    "contact": "start_fr..end_fr of interaction_contact_signature.json (fr_id when no "
               "interval), both people",
    "fr_id_person0": "the public code's *_c convention: frame fr_id, person 0 only",
    "validity": "person-frames marked false in the truth's valid/<action>.json are excluded; "
                "so are those the prediction's own valid/<action>.json does not publish (a "
                "release's frames without evidence), counted as not published",
    "mesh": "vertex metrics on the Anny mesh when both sides have anny/<action>.json, else "
            "SMPL-X from smplx/<action>.json with a model file, else vertices/<action>.npz",
}

#: the contact-frame convention, said in every report
CONTACT_NOTE = ("contact frames = start_fr..end_fr of interaction_contact_signature.json, both "
                "people; the public code's *_c figures are frame fr_id of person 0 only (its "
                "persons are concatenated along the frame axis), reported as fr_id_person0")


def contact_frames(gt: SequenceData) -> np.ndarray | None:
    """(F,) bool of the contact interval, or None without a contact signature."""
    if gt.contact is None:
        return None
    F = gt.joints.shape[1]
    c = gt.contact
    lo = c.start_fr if c.start_fr is not None else c.fr_id
    hi = c.end_fr if c.end_fr is not None else c.fr_id
    if gt.frame_ids is not None:  # a truth cut to a release's frames: by frame number
        return (gt.frame_ids >= lo) & (gt.frame_ids <= hi)
    m = np.zeros(F, bool)
    m[lo: hi + 1] = True
    return m


def person_order(pred: SequenceData, gt: SequenceData) -> np.ndarray:
    """(F, P) matching of :func:`evaluate.metrics.match_people` on the truth's camera."""
    def boxes(joints):
        return np.swapaxes(M.boxes_from_points(project(gt.camera, joints, distorted=False)), 0, 1)
    return M.match_people(boxes(pred.joints), boxes(gt.joints))


def _mean(err: np.ndarray, mask: np.ndarray) -> float | None:
    return float(err[mask].mean() * K.MM_PER_M) if mask.any() else None


def evaluate_sequence(pred: SequenceData, gt: SequenceData) -> dict:
    """Figures of one sequence: ``{"frames", "people", "person_frames_not_valid",
    "frames_not_valid", "swapped_frames", "vertices", "all": {metric: mm | None},
    "contact": {...}, "fr_id_person0": {...}, "notes": [...]}`` (None = not computed: see
    ``notes``)."""
    P, F = gt.joints.shape[:2]
    order = person_order(pred, gt)
    pj = M.reorder_people(pred.joints, order)
    err = {"mpjpe": M.mpjpe(pj, gt.joints), "pa_mpjpe": M.pa_mpjpe(pj, gt.joints),
           "transl_err": M.translation_error(pj, gt.joints)}
    notes = []
    mesh = None
    if pred.vertices is not None and gt.vertices is not None:
        mesh = gt.vertices.mesh if gt.vertices.mesh == pred.vertices.mesh else \
            f"{pred.vertices.mesh} (prediction) / {gt.vertices.mesh} (truth)"
        pv, gv = pred.vertices, gt.vertices
        if pv.vertices.shape[2] != gv.vertices.shape[2]:
            raise InputError(pv.source, "vertices", f"{pv.vertices.shape[2]} vertices per mesh, "
                             f"the truth ({gv.source}) has {gv.vertices.shape[2]}")
        v, r = M.reorder_people(pv.vertices, order), M.reorder_people(pv.root, order)
        err["mpvpe"] = M.mpvpe(v, gv.vertices, r, gv.root)
        err["pa_mpvpe"] = M.pa_mpvpe(v, gv.vertices, r, gv.root)
    else:
        why = "; ".join(f"{side}: {s.vertices_note}" for side, s in (("prediction", pred),
                                                                     ("truth", gt))
                        if s.vertices is None)
        notes.append(f"vertex metrics not computed ({why})")
    truth_valid = gt.valid if gt.valid is not None else np.ones((P, F), bool)
    # the prediction's published person-frames, in the truth's person order
    published = (M.reorder_people(pred.valid, order) if pred.valid is not None
                 else np.ones((P, F), bool))
    valid = truth_valid & published
    masks = {"all": valid}
    cf = contact_frames(gt)
    if cf is None:
        notes.append(f"contact metrics not computed ({gt.contact_note})")
        masks["contact"] = masks["fr_id_person0"] = np.zeros((P, F), bool)
    else:
        masks["contact"] = valid & cf[None, :]
        one = np.zeros((P, F), bool)
        ids = gt.frame_ids if gt.frame_ids is not None else np.arange(F)
        one[0] = ids == gt.contact.fr_id
        masks["fr_id_person0"] = valid & one
        if not masks["contact"].any():
            notes.append("no valid person-frame in the contact interval")
    not_pub = truth_valid & ~published
    if not_pub.any():
        notes.append(f"{int(not_pub.sum())} person-frames valid in the truth are not published by "
                     f"the prediction ({pred.files.get('valid')}): not scored")
    out = {"frames": F, "people": P,
           "person_frames": P * F,
           "person_frames_scored": int(valid.sum()),
           "person_frames_not_valid": int((~truth_valid).sum()),
           "person_frames_not_published": int(not_pub.sum()),
           "frames_scored": int(valid.any(axis=0).sum()),
           "frames_not_valid": int((~truth_valid).any(axis=0).sum()),
           "frames_not_published": int(not_pub.any(axis=0).sum()),
           "swapped_frames": int((order != np.arange(P)).any(axis=1).sum()),
           "contact_frames": None if cf is None else int(cf.sum()),
           "contact_person_frames_scored": int(masks["contact"].sum()),
           "vertices": {"mesh": mesh, "prediction": pred.files.get("vertices"),
                        "truth": gt.files.get("vertices")}}
    for g in GROUPS:
        out[g] = {m: (_mean(err[m], masks[g]) if m in err else None) for m in K.METRICS}
    out["notes"] = notes
    return out


def aggregate(per_sequence: dict[str, dict]) -> dict:
    """Mean over sequences of each figure (sequences where it is None are left out):
    ``{group: {metric: mm | None}, "sequences": {group: {metric: count}}, frame counts}``."""
    out: dict = {"sequences": {}}
    for g in GROUPS:
        out[g], out["sequences"][g] = {}, {}
        for m in K.METRICS:
            vals = [s[g][m] for s in per_sequence.values() if s[g][m] is not None]
            out[g][m] = float(np.mean(vals)) if vals else None
            out["sequences"][g][m] = len(vals)
    for key in ("frames", "frames_scored", "frames_not_valid", "frames_not_published",
                "person_frames", "person_frames_scored", "person_frames_not_valid",
                "person_frames_not_published", "contact_person_frames_scored", "swapped_frames"):
        out[key] = int(sum(s[key] for s in per_sequence.values()))
    out["contact_frames"] = int(sum(s["contact_frames"] or 0 for s in per_sequence.values()))
    meshes = sorted({s["vertices"]["mesh"] for s in per_sequence.values() if s["vertices"]["mesh"]})
    out["vertices"] = {"mesh": ", ".join(meshes) if meshes else None}
    return out


def evaluate_pairs(pairs) -> dict:
    """[(pred, truth)] -> ``{"protocol", "sequences": {name: figures}, "overall": ...}``."""
    per = {gt.name: evaluate_sequence(pred, gt) for pred, gt in pairs}
    return {"protocol": PROTOCOL, "contact_convention": CONTACT_NOTE, "sequences": per,
            "overall": aggregate(per)}


# ------------------------------------------------------------------------------------- report
NAMES = {"mpjpe": "MPJPE", "pa_mpjpe": "PA-MPJPE", "transl_err": "transl", "mpvpe": "MPVPE",
         "pa_mpvpe": "PA-MPVPE"}


def _cell(v) -> str:
    return "n/c" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f}"


def markdown(result: dict) -> str:
    """The figures as markdown tables (mm): all frames, then contact frames; n/c = not
    computed (the notes say why). Columns: frames (of the sequence, or of its contact
    interval), scored (person-frames scored / person-frames), not valid (frames with a
    person-frame the truth marks not valid), not published (frames with a person-frame the
    prediction does not publish), swapped (frames where the matching swapped people)."""
    lines = []
    for g, title in (("all", "all valid frames"), ("contact", "contact frames")):
        lines += [f"**{title}** (mm)", "",
                  "| sequence | frames | scored | not valid | not published | swapped | "
                  + " | ".join(NAMES[m] for m in K.METRICS) + " |",
                  "|---" * (6 + len(K.METRICS)) + "|"]
        rows = list(result["sequences"].items()) + [("**mean over sequences**", result["overall"])]
        for name, s in rows:
            if g == "all":
                frames, scored = s["frames"], f"{s['person_frames_scored']}/{s['person_frames']}"
            else:
                frames = s.get("contact_frames") or "-"
                scored = s["contact_person_frames_scored"]
            lines.append(f"| {name} | {frames} | {scored} | {s['frames_not_valid']} | "
                         f"{s['frames_not_published']} | {s['swapped_frames']} | "
                         + " | ".join(_cell(s[g][m]) for m in K.METRICS) + " |")
        lines.append("")
    o = result["overall"]
    lines += [f"vertex metrics on: {o.get('vertices', {}).get('mesh') or 'n/c'}",
              f"contact convention: {CONTACT_NOTE}: "
              + ", ".join(f"{NAMES[m]} {_cell(o['fr_id_person0'][m])}" for m in K.METRICS), ""]
    notes = [f"- {n}: {x}" for n, s in result["sequences"].items() for x in s["notes"]]
    if notes:
        lines += ["notes:", *notes, ""]
    return "\n".join(lines)
