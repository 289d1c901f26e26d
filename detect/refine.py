"""The partner's second detection pass: tight crops around where a first fit puts the partner.

The first pass (:mod:`detect.people`) finds the marker wearer in a crop around its projected
markers and the partner over the rest of the image. Where the two overlap in a view (one
behind the other, a hug) the partner is often missed there, or found only in part; from two
opposite views the depth of a limb is then free and the partner fit goes wrong by decimetres
(bench, Posing: views 1 and 3 without the partner, the raised arm 0.4 m off).

Once the partner has been fitted from the views that did see it, its body projects into every
view. This pass runs the detector the way the wearer gets it (``detect.people._find_wearer``):
in a square crop around the projected first-fit keypoints, first with everything far from the
partner's projected body painted out, accepting only a person whose keypoints match the
projection (``people.wearer_check``: position, size, not mirrored) and that is not the wearer
(its body nearer the wearer's keypoints of that view than the projection: dropped); then the
hands in crops from the projected forearms, the wearer's hands excluded.

Only the views that need it are redone (``need``: too few body keypoints of the partner, or
missing hands whose projection lies in the image), so the cost is a fraction of the first pass.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from detect import constants as K
from detect import layout
from detect.base import DetectorFactory
from detect.crops import box_from_points, expand_box, hand_box_from_arm
from detect.hints import WearerHints
from detect.people import PeopleOptions, _find_wearer, _hands
from detect.run import FrameSource, _Metered

IDX = layout.IDX
ELBOWS = (IDX["l_elbow"], IDX["r_elbow"])
WRISTS = (IDX["l_wrist"], IDX["r_wrist"])
MIN_HAND_KP = 5  # a hand with fewer confident keypoints is missing
RATE_BODY_KP = 12  # detection_rates: a body counts as detected with this many of 23
RATE_CONF = 0.2  # ... keypoints at least this confident (the partner fit's min_conf)
N_BODY = len(range(layout.N)[layout.BODY])  # the body keypoints of KP65


@dataclass
class Refined:
    """kp (C, F, 65, 3) the partner's keypoints after the pass (unchanged where not redone or
    nothing better was found); redone (C, F) bool views run again; improved (C, F) bool views
    whose keypoints were replaced; calls: detector calls by kind; cpu_s: CPU seconds of the whole pass;
    on_wearer (C, F) int: body keypoints of the found person left out as the wearer's
    (:func:`on_wearer`)."""

    kp: np.ndarray
    redone: np.ndarray
    improved: np.ndarray
    calls: dict
    cpu_s: float
    on_wearer: np.ndarray


def _n_body(kp: np.ndarray, conf: float) -> np.ndarray:
    return (kp[..., layout.BODY, 2] >= conf).sum(-1)


def views_to_redo(kp: np.ndarray, projected: np.ndarray, shape_hw: tuple[int, int],
                  min_body: int = K.MIN_PARTNER_KP, conf: float = K.MIN_CONF) -> np.ndarray:
    """(C, F) bool: views where the partner's first-pass keypoints ``kp (C, F, 65, 3)`` have
    fewer than ``min_body`` body keypoints, or a hand missing whose projected wrist
    (``projected (C, F, 65, 2)``, the first fit) lies in the image."""
    h, w = shape_hw
    few = _n_body(kp, conf) < min_body
    inside = np.all(np.isfinite(projected), -1) & (projected[..., 0] >= 0) & (projected[..., 0] < w) \
        & (projected[..., 1] >= 0) & (projected[..., 1] < h)
    hands = []
    for s, sl in enumerate(layout.HANDS):
        missing = (kp[..., sl, 2] >= conf).sum(-1) < MIN_HAND_KP
        hands.append(missing & inside[..., WRISTS[s]])
    body_in = inside[..., layout.BODY].sum(-1) >= min_body
    return body_in & (few | hands[0] | hands[1])


def detection_rates(kp: np.ndarray, min_body: int = RATE_BODY_KP, conf: float = RATE_CONF) -> dict:
    """Fractions of the view-frames of one person's keypoints ``kp (..., 65, 3)`` with its
    body (``min_body`` of the 23 keypoints at ``conf``) and each hand (``MIN_HAND_KP`` of 21)
    detected: ``{"body", "hands"}`` (hands: the mean over the two)."""
    c = np.asarray(kp)[..., 2] >= conf
    return {"body": float((c[..., layout.BODY].sum(-1) >= min_body).mean()),
            "hands": float(np.mean([(c[..., sl].sum(-1) >= MIN_HAND_KP).mean()
                                    for sl in layout.HANDS]))}


def _hints(uv: np.ndarray, outline: np.ndarray, o: PeopleOptions) -> WearerHints:
    """Crop hints of one view from the partner's projected keypoints ``uv (65, 2)`` and
    projected surface points ``outline (P, 2)`` (the isolation mask keeps their
    neighbourhood)."""
    body = uv[layout.BODY]
    box = expand_box(box_from_points(body), o.body_margin, square=True)
    height = float(box[3] - box[1]) if np.all(np.isfinite(box)) else np.nan
    hb = np.stack([hand_box_from_arm(uv[ELBOWS[s]], uv[WRISTS[s]], height) for s in (0, 1)])
    wrists = uv[list(WRISTS)]
    anchors = np.full((layout.N, 2), np.nan)
    anchors[layout.BODY] = body
    return WearerHints(box=box, hand_boxes=hb, wrists=wrists, anchors=anchors, markers=outline)


def _is_wearer(cand: np.ndarray, proj: np.ndarray, wearer: np.ndarray, conf: float) -> bool:
    """The candidate's body lies nearer the wearer's detected body than the projection."""
    b = layout.BODY
    ok = (cand[b, 2] >= conf) & (wearer[b, 2] >= conf) & np.all(np.isfinite(proj[b]), -1)
    if ok.sum() < 4:
        return False
    dw = np.median(np.linalg.norm(cand[b][ok, :2] - wearer[b][ok, :2], axis=-1))
    dp = np.median(np.linalg.norm(cand[b][ok, :2] - proj[b][ok], axis=-1))
    return bool(dw < dp)


def on_wearer(cand: np.ndarray, proj: np.ndarray, wearer: np.ndarray, conf: float,
              min_px: float = K.REFINE_WEARER_MIN_PX,
              ratio: float = K.REFINE_WEARER_RATIO) -> np.ndarray:
    """(23,) bool: the body keypoints of the candidate ``cand (65, 3)`` that are the
    wearer's joints read as the partner's: farther than ``min_px`` from the first fit's
    projection ``proj (65, 2)`` and nearer the wearer's detected keypoint of the same name,
    either side (``wearer (65, 3)``, confident at ``conf``), than ``ratio`` x that distance.
    Every found candidate keypoint is judged; a joint near the wearer's other joints (a hand
    on the wearer's chest) is kept."""
    b = np.arange(N_BODY)
    c = np.asarray(cand, float)[b]
    w = np.asarray(wearer, float)
    d = np.linalg.norm(c[:, :2] - np.asarray(proj, float)[b], axis=-1)
    d_w = np.full(N_BODY, np.inf)
    for idx in (b, layout.FLIP[b]):
        ok = w[idx, 2] >= conf
        d_w = np.where(ok, np.minimum(d_w, np.linalg.norm(c[:, :2] - w[idx, :2], axis=-1)), d_w)
    with np.errstate(invalid="ignore"):
        return (c[:, 2] > 0) & (d > min_px) & (d_w < ratio * d)


def refine_partner(source: FrameSource, factory: DetectorFactory, frames: np.ndarray,
                   kp: np.ndarray, projected: np.ndarray, outline: np.ndarray,
                   need: np.ndarray, opts: PeopleOptions | None = None,
                   progress=lambda it, **_: it) -> Refined:
    """The second pass over the views ``need (C, F)``.

    frames : (F,) video frames; kp : (C, F, 2, 65, 3) the first pass (both people);
    projected : (C, F, 65, 2) the partner's first-fit keypoints in each view; outline :
    (C, F, P, 2) projected points of its surface; opts : the first pass's options.
    A redone view's body keypoints replace the first pass's when they have more confident
    body keypoints, except a confident first-pass keypoint the redone body did not find
    confidently (kept); its hands fill hands the first pass did not find."""
    o = PeopleOptions() if opts is None else opts
    out = np.array(kp[:, :, 1], np.float32)
    C, F = need.shape
    redone = np.zeros((C, F), bool)
    improved = np.zeros((C, F), bool)
    on_wearer_n = np.zeros((C, F), np.int64)
    if not need.any():
        return Refined(out, redone, improved, {"body": 0, "hands": 0}, 0.0, on_wearer_n)
    t0 = time.process_time()  # everything: the detector's build, decoding, the calls
    det = _Metered(factory.build())  # the first pass's meter: calls per kind
    reader = source.open() if det.needs_pixels else None
    conf = o.accept_conf
    try:
        todo = [(i, c) for i in range(F) for c in range(C) if need[c, i]]
        for i, c in progress(todo, total=len(todo), desc="partner crops"):
            fr = int(frames[i])
            img = reader.read(c, fr) if reader is not None else None
            hints = _hints(projected[c, i], outline[c, i], o)
            if not np.all(np.isfinite(hints.box)):
                continue
            redone[c, i] = True
            first = out[c, i]
            new = first.copy()
            # only what can be bettered is detected again (the detector runs on stills, so a
            # call left out changes no other): a body with every keypoint cannot be replaced
            # by one with more, a hand the first pass found is kept
            if _n_body(first, conf) < N_BODY:
                cand, _ = _find_wearer(img, hints, det, o, c, fr, True)
                if _n_body(cand, conf) > _n_body(first, conf) and not _is_wearer(
                        cand, projected[c, i], kp[c, i, 0], conf):
                    bad = on_wearer(cand, projected[c, i], kp[c, i, 0], conf)
                    cand[layout.BODY][bad, 2] = 0.0
                    on_wearer_n[c, i] = int(bad.sum())
                    # keypoint by keypoint: a confident first-pass keypoint the redone body
                    # lost is kept (the second pass can drop a right joint and add a wrong
                    # one; the bench's Posing arm was lost so)
                    body = cand[layout.BODY].copy()
                    keep = (body[:, 2] < conf) & (first[layout.BODY][:, 2] >= conf)
                    body[keep] = first[layout.BODY][keep]
                    new[layout.BODY] = body
                    improved[c, i] = True
            if o.hands:
                before = new.copy()
                found = [(before[sl, 2] >= conf).sum() >= MIN_HAND_KP for sl in layout.HANDS]
                boxes = np.where(np.array(found)[:, None], np.nan, hints.hand_boxes)
                _hands(img, new, boxes, hints.wrists, det, o, c, fr,
                       avoid=kp[c, i, 0], avoid_wrists=kp[c, i, 0, list(WRISTS), :2],
                       radius=o.near_frac * float(hints.box[3] - hints.box[1]))
                improved[c, i] |= not np.array_equal(new, before)
            out[c, i] = new
    finally:
        if reader is not None:
            reader.close()
        det.close()
    return Refined(out, redone, improved, dict(det.calls), time.process_time() - t0, on_wearer_n)
