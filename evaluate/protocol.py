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
    "validity": "person-frames marked false in the truth's valid/<action>.json are excluded",
}


def contact_frames(gt: SequenceData) -> np.ndarray | None:
    """(F,) bool of the contact interval, or None without a contact signature."""
    if gt.contact is None:
        return None
    F = gt.joints.shape[1]
    c = gt.contact
    lo = c.start_fr if c.start_fr is not None else c.fr_id
    hi = c.end_fr if c.end_fr is not None else c.fr_id
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
    if pred.vertices is not None and gt.vertices is not None:
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
    valid = gt.valid if gt.valid is not None else np.ones((P, F), bool)
    masks = {"all": valid}
    cf = contact_frames(gt)
    if cf is None:
        notes.append(f"contact metrics not computed ({gt.contact_note})")
        masks["contact"] = masks["fr_id_person0"] = np.zeros((P, F), bool)
    else:
        masks["contact"] = valid & cf[None, :]
        one = np.zeros((P, F), bool)
        one[0, gt.contact.fr_id] = True
        masks["fr_id_person0"] = valid & one
        if not masks["contact"].any():
            notes.append("no valid person-frame in the contact interval")
    out = {"frames": F, "people": P,
           "person_frames_not_valid": int((~valid).sum()),
           "frames_not_valid": int((~valid).any(axis=0).sum()),
           "swapped_frames": int((order != np.arange(P)).any(axis=1).sum()),
           "contact_frames": None if cf is None else int(cf.sum()),
           "vertices": {"prediction": pred.files.get("vertices"), "truth": gt.files.get("vertices")}}
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
    for key in ("frames", "frames_not_valid", "person_frames_not_valid", "swapped_frames"):
        out[key] = int(sum(s[key] for s in per_sequence.values()))
    return out


def evaluate_pairs(pairs) -> dict:
    """[(pred, truth)] -> ``{"protocol", "sequences": {name: figures}, "overall": ...}``."""
    per = {gt.name: evaluate_sequence(pred, gt) for pred, gt in pairs}
    return {"protocol": PROTOCOL, "sequences": per, "overall": aggregate(per)}


# ------------------------------------------------------------------------------------- report
NAMES = {"mpjpe": "MPJPE", "pa_mpjpe": "PA-MPJPE", "transl_err": "transl", "mpvpe": "MPVPE",
         "pa_mpvpe": "PA-MPVPE"}


def _cell(v) -> str:
    return "n/c" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f}"


def markdown(result: dict) -> str:
    """The figures as markdown tables (mm): all frames, then contact frames; n/c = not
    computed (the notes say why)."""
    lines = []
    for g, title in (("all", "all valid frames"), ("contact", "contact frames")):
        lines += [f"**{title}** (mm)", "",
                  "| sequence | frames | not valid | swapped | "
                  + " | ".join(NAMES[m] for m in K.METRICS) + " |",
                  "|---" * (4 + len(K.METRICS)) + "|"]
        rows = list(result["sequences"].items()) + [("**mean over sequences**", result["overall"])]
        for name, s in rows:
            frames = s["frames"] if g == "all" else (s.get("contact_frames") or "-")
            lines.append(f"| {name} | {frames} | {s['frames_not_valid']} | {s['swapped_frames']} | "
                         + " | ".join(_cell(s[g][m]) for m in K.METRICS) + " |")
        lines.append("")
    notes = [f"- {n}: {x}" for n, s in result["sequences"].items() for x in s["notes"]]
    if notes:
        lines += ["notes:", *notes, ""]
    return "\n".join(lines)
