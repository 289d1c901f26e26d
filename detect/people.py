"""Both people in one view of one frame: the marker wearer from its crops, the partner by the
paper's rule.

The marker wearer (person 0): body from a tight crop around its projected markers
(:class:`detect.hints.WearerHints`), hands from crops around its projected hand markers.
The detection is checked against where the markers put some keypoints (median distance, and
not mirrored: a person facing the other way matches the markers' left/right swapped); if the
detector locked onto the partner standing in the crop (hugs, or a partner nearer the camera),
the crop is retried "isolated": everything far from the wearer's markers painted out. The plain
crop is tried first because painting can clip the wearer's extremities. When neither passes,
the wearer is reported missing in that view (never a guess that could be the partner).

The partner (person 1): the paper runs a multi-person detector on the whole image and, per
keypoint type, drops candidates close to the wearer's keypoint and keeps the most confident
(:func:`detect.rule.select_partner`). mediapipe is single-person, so it would often return the
wearer again. Two images are tried, and the rule rejects the wearer found again:

- the wearer painted out (:mod:`detect.mask`): finds a partner the wearer would hide from
  the detector (partner behind or beside the wearer);
- the plain image: needed when the partner stands in front of the wearer, since painting the
  wearer's silhouette would then paint over the partner too.

Whichever worked in a view is tried first there in the next frame (painted first at the
start). Where to look:

1. around the partner's box from the previous frame (when there is one): a crop gives the
   detector more pixels than the whole image, and the box is nearly always right at video
   rates;
2. otherwise over the whole image, then once more in a crop around what it found.

Tracking alone could not start or recover; the whole image alone would run the detector at a
lower resolution. Precomputed multi-person detections go through the same code: painting does
not apply to them and the rule does the separating, exactly as in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detect import constants as K
from detect import layout
from detect.base import Detector, call_detector, forget_stream
from detect.crops import box_from_points, expand_box, hand_box_from_arm
from detect.hints import WearerHints
from detect.mask import paint_out, silhouette_mask
from detect.rule import (
    anchor_error,
    box_support,
    is_same_person,
    pick_hand,
    select_partner,
)


@dataclass(frozen=True)
class PeopleOptions:
    """Knobs of :func:`find_people` (defaults in detect/constants.py, documented there).

    track : search around the previous frame's partner box first.
    mask_wearer : paint the wearer out before looking for the partner (pixel detectors).
    hands : run the hand detector (False: body keypoints only).
    """

    near_frac: float = K.NEAR_FRAC
    mask_radius_frac: float = K.MASK_RADIUS_FRAC
    mask_head_frac: float = K.MASK_HEAD_FRAC
    isolate_radius_frac: float = K.ISOLATE_RADIUS_FRAC
    track_margin: float = K.TRACK_MARGIN
    body_margin: float = K.BODY_MARGIN
    anchor_frac: float = K.ANCHOR_FRAC
    hand_anchor_frac: float = K.HAND_ANCHOR_FRAC
    min_partner_kp: int = K.MIN_PARTNER_KP
    accept_conf: float = K.ACCEPT_CONF
    track: bool = True
    mask_wearer: bool = True
    hands: bool = True


@dataclass(frozen=True)
class ViewPeople:
    """Result for one view and frame (pixels of the full image; NaN box = none).

    kp : (2, 65, 3) float32, person 0 = marker wearer, 1 = partner.
    boxes : (2, 4) the body crops used (partner: the search box, or the whole image).
    hand_boxes : (2, 2, 4) hand crops (person, side).
    partner_box : (4,) the partner's keypoint box + margin (the next frame's search box).
    wearer_retry : the wearer's keypoints come from its isolated crop (the plain crop's
        detection failed the marker check: the partner stood in it).
    partner_mode : 0 not found, 1 found by tracking, 2 found over the whole image.
    partner_masked : the partner was found with the wearer painted out.
    """

    kp: np.ndarray
    boxes: np.ndarray
    hand_boxes: np.ndarray
    partner_box: np.ndarray
    wearer_retry: bool
    partner_mode: int
    partner_masked: bool = False


def _height(box: np.ndarray) -> float:
    return float(box[3] - box[1]) if np.all(np.isfinite(box)) else np.nan


def _n_good(kp: np.ndarray, conf: float) -> int:
    return int((kp[layout.BODY, 2] >= conf).sum())


def _person_box(kp: np.ndarray, conf: float, margin: float) -> np.ndarray:
    ok = kp[layout.BODY, 2] >= conf
    return expand_box(box_from_points(kp[layout.BODY, :2], ok), margin,
                      min_side=K.MIN_BODY_BOX_PX, square=True)


def wearer_check(cands: np.ndarray, anchors: np.ndarray, box_height: float, o: PeopleOptions
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Does each candidate match the wearer's markers? cands (N, 65, 3), anchors (65, 2).

    Returns (err (N,) median pixel distance to the anchors, NaN without 3 shared keypoints;
    ok (N,) bool: not mirrored and inside the ellipse (err / (anchor_frac x box height))^2 +
    (log size / log WEARER_SCALE_TOL)^2 <= 1, size = :func:`anchor_scale`: a candidate off
    in both position and size is rejected even when each alone would pass). Mirrored = its
    left/right-swapped keypoints lie nearer the anchors by more than FLIP_MARGIN_FRAC x the
    box height: a person facing the other way (the partner facing the wearer, or the
    detector's left/right swapped on the wearer's back). Mirrored candidates are rejected,
    never flipped back: a partner facing us would then pass for the wearer.
    """
    cands = np.asarray(cands)
    err = anchor_error(cands, anchors)
    flip = anchor_error(cands[:, layout.FLIP], anchors)
    scale = anchor_scale(cands, anchors)
    with np.errstate(invalid="ignore", divide="ignore"):
        mirrored = flip + max(K.FLIP_MARGIN_FRAC * box_height, 3.0) < err
        a = err / (o.anchor_frac * box_height)
        s = np.nan_to_num(np.abs(np.log(scale)) / np.log(K.WEARER_SCALE_TOL), nan=0.0)
        ok = (a ** 2 + s ** 2 <= 1.0) & ~mirrored
    return err, ok


def anchor_scale(cands: np.ndarray, anchors: np.ndarray, min_conf: float = K.MIN_CONF) -> np.ndarray:
    """(N,) size of each candidate relative to the anchors: RMS spread of its keypoints about
    their mean over the RMS spread of the matching anchors (NaN with fewer than 4 shared).
    The partner standing between the camera and the wearer, lined up with it, can match the
    anchors' positions but is nearer the camera, so larger."""
    cands = np.asarray(cands, dtype=np.float64)
    anchors = np.asarray(anchors, dtype=np.float64)
    out = np.full(len(cands), np.nan)
    has = np.all(np.isfinite(anchors), axis=1)
    for i, c in enumerate(cands):
        ok = has & (c[:, 2] >= min_conf)
        if ok.sum() < 4:
            continue
        d = c[ok, :2] - c[ok, :2].mean(axis=0)
        a = anchors[ok] - anchors[ok].mean(axis=0)
        sa = (a ** 2).sum()
        if sa > 0:
            out[i] = np.sqrt((d ** 2).sum() / sa)
    return out


def _on_mask_frac(cands: np.ndarray, mask: np.ndarray, conf: float = K.ACCEPT_CONF) -> np.ndarray:
    """(N,) fraction of each candidate's confident body keypoints on ``mask`` (H, W) pixels."""
    h, w = mask.shape
    out = np.zeros(len(cands))
    for i, c in enumerate(cands):
        ok = c[layout.BODY, 2] >= conf
        if not ok.any():
            continue
        xy = np.round(c[layout.BODY][ok, :2]).astype(int)
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
        on = np.zeros(len(xy), bool)
        on[inside] = mask[xy[inside, 1], xy[inside, 0]]
        out[i] = on.mean()
    return out


def _find_wearer(image, hints: WearerHints, det: Detector, o: PeopleOptions, cam: int, frame: int,
                 isolated_first: bool):
    """(kp (65, 3), isolated): the wearer's body keypoints, and whether they came from the
    crop with everything far from its markers painted out ("isolated")."""
    kp = np.zeros((layout.N, 3), np.float32)
    h = _height(hints.box)

    def best(cands):
        """(kp, ok) of the candidate nearest the anchors; ok = it passes the check."""
        if len(cands) == 0:
            return None, False
        err, ok = wearer_check(cands.kp, hints.anchors, h, o)
        if np.any(np.isfinite(err)):
            i = int(np.nanargmin(err))
            return cands.kp[i], bool(ok[i])
        i = int(np.argmax(box_support(cands.kp, hints.box)))
        return cands.kp[i], True  # no anchors to check against: accept

    def attempt(isolated: bool):
        img = image
        if isolated:
            # Keep only the neighbourhood of the wearer's markers: the partner in the crop goes.
            near = silhouette_mask(image.shape[:2], np.zeros((layout.N, 3)), layout.EDGES,
                                   o.isolate_radius_frac * h, points=hints.markers)
            img = paint_out(image, ~near)
        return best(call_detector(det, img, kind="body", box=hints.box, cam=cam, frame=frame,
                                  stream=stream))

    stream = ("wearer",)  # the crop follows the wearer (in this view): a tracking detector too
    order = (True, False) if isolated_first else (False, True)
    if not det.needs_pixels:
        order = (False,)
    for isolated in order:
        cand, ok = attempt(isolated)
        if cand is not None and ok:
            kp[layout.BODY] = cand[layout.BODY]
            return kp, isolated
        forget_stream(det, stream)  # never track on from a rejected person
    # Nothing matched the markers: report the wearer missing in this view rather than risk
    # the partner's (or mirrored) keypoints as the wearer's.
    return kp, False


def _hands(image, person_kp: np.ndarray, boxes: np.ndarray, anchors: np.ndarray, det: Detector,
           o: PeopleOptions, cam: int, frame: int, avoid: np.ndarray | None = None,
           avoid_wrists: np.ndarray | None = None, radius: float = 0.0, who: str = "wearer"):
    """Fill person_kp's hand blocks from the hand crops ``boxes`` (2, 4) whose wrists are
    expected at ``anchors`` (2, 2). Hands of the other person are dropped first: those
    matching ``avoid`` (65, 3) by the rule, and those whose wrist lies within ``radius`` of
    one of ``avoid_wrists`` (W, 2) (the wearer's wrists: in a handshake its hand sits in the
    partner's hand crop). Each crop follows one hand (``stream=("hand", who, side)``):
    a tracking detector's one tracked hand that is not the one wanted is looked for again in
    static mode (all hands in the crop)."""
    aw = None if avoid_wrists is None else np.asarray(avoid_wrists, float).reshape(-1, 2)
    if aw is not None:
        aw = aw[np.all(np.isfinite(aw), axis=1)]

    def pick(cands, side, box):
        if avoid is not None and len(cands):
            cands = cands[~is_same_person(cands, avoid, radius)]
        if aw is not None and len(aw) and len(cands):
            wr = np.stack([cands[:, sl.start] for sl in layout.HANDS], axis=1)  # (N, 2, 3)
            d = np.linalg.norm(wr[:, :, None, :2] - aw[None, None], axis=-1).min(axis=-1)
            near = ((wr[..., 2] >= K.MIN_CONF) & (d < radius)).any(axis=1)
            cands = cands[~near]
        return pick_hand(cands, side, anchors[side], o.hand_anchor_frac * _height(box), layout.HANDS)

    for side in (0, 1):
        box = boxes[side]
        if not np.all(np.isfinite(box)) or not np.all(np.isfinite(anchors[side])):
            continue
        if image is not None and not hand_crop_useful(box, anchors[side], image.shape[:2]):
            continue
        stream = ("hand", who, side)
        cands = call_detector(det, image, kind="hands", box=box, cam=cam, frame=frame,
                              stream=stream).kp
        hand = pick(cands, side, box)
        if hand is None and len(cands) and getattr(det, "streams", False):
            forget_stream(det, stream)  # it tracked a hand we do not want: look at all of them
            hand = pick(det.detect(image, kind="hands", box=box, cam=cam, frame=frame).kp, side, box)
        if hand is not None:
            person_kp[layout.HANDS[side]] = hand


def hand_crop_useful(box: np.ndarray, wrist: np.ndarray, shape: tuple[int, int],
                     min_inside: float = K.MIN_HAND_BOX_INSIDE) -> bool:
    """Can a hand crop ``box`` (4,) whose wrist is expected at ``wrist`` (2,) find a hand in an
    image of ``shape`` (H, W)? Not when the wrist lies outside the image or less than
    ``min_inside`` of the box's area does (the hand is out of the picture: a detector call
    for nothing)."""
    h, w = shape
    if not (0 <= wrist[0] < w and 0 <= wrist[1] < h):
        return False
    area = (box[2] - box[0]) * (box[3] - box[1])
    ix = max(0.0, min(box[2], w) - max(box[0], 0.0))
    iy = max(0.0, min(box[3], h) - max(box[1], 0.0))
    return bool(area > 0 and ix * iy >= min_inside * area)


def _partner_hand_boxes(kp: np.ndarray, conf: float) -> tuple[np.ndarray, np.ndarray]:
    """(boxes (2, 4), wrist anchors (2, 2)) from a person's body keypoints."""
    boxes = np.full((2, 4), np.nan)
    wrists = np.full((2, 2), np.nan)
    ok = kp[layout.BODY, 2] >= conf
    h = _height(box_from_points(kp[layout.BODY, :2], ok))
    for side, (e, w) in enumerate(((layout.IDX["l_elbow"], layout.IDX["l_wrist"]),
                                   (layout.IDX["r_elbow"], layout.IDX["r_wrist"]))):
        if kp[w, 2] >= conf and kp[e, 2] >= conf and np.isfinite(h):
            boxes[side] = hand_box_from_arm(kp[e, :2], kp[w, :2], h)
            wrists[side] = kp[w, :2]
    return boxes, wrists


def find_people(image: np.ndarray | None, hints: WearerHints, prev_partner_box: np.ndarray | None,
                det: Detector, o: PeopleOptions = PeopleOptions(), cam: int = 0,
                frame: int = 0, wearer_isolated_first: bool = False,
                partner_masked_first: bool = True) -> ViewPeople:
    """Both people in one view.

    image : (H, W, 3) uint8 RGB (None for detectors that don't need pixels; then the
        whole-image box is NaN). hints : one view's :meth:`WearerHints.view`.
    prev_partner_box : (4,) or None. wearer_isolated_first : try the wearer's isolated crop
        first (it was needed in this view in the previous frame: saves a detection per frame
        while the partner stands in the wearer's crop). partner_masked_first : look for the
        partner in the image with the wearer painted out before the plain image (what worked
        in this view in the previous frame; painting hides a partner standing in front).
    """
    kp = np.zeros((2, layout.N, 3), np.float32)
    boxes = np.full((2, 4), np.nan)
    hand_boxes = np.full((2, 2, 4), np.nan)
    if not np.all(np.isfinite(hints.box)):
        # No markers in this view and frame: nothing tells the two people apart (the rule
        # needs the wearer's keypoints), so neither is reported rather than risk a swap.
        return ViewPeople(kp, boxes, hand_boxes, np.full(4, np.nan), False, 0, False)
    boxes[0] = hints.box

    # -- person 0: the marker wearer
    kp[0], isolated = _find_wearer(image, hints, det, o, cam, frame, wearer_isolated_first)
    hw = _height(hints.box)
    radius = o.near_frac * hw if np.isfinite(hw) else 0.0
    if o.hands:
        hand_boxes[0] = hints.hand_boxes
        anchors = np.where(np.isfinite(hints.wrists), hints.wrists,
                           kp[0, [layout.IDX["l_wrist"], layout.IDX["r_wrist"]], :2])
        _hands(image, kp[0], hints.hand_boxes, anchors, det, o, cam, frame)

    # -- person 1: the partner
    # The rule's reference for the wearer: its detected keypoints, and where those are missing
    # the marker anchors (so the wearer's undetected parts still can't become the partner's).
    ref = kp[0].copy()
    fill = (ref[:, 2] < K.MIN_CONF) & np.all(np.isfinite(hints.anchors), axis=1)
    ref[fill, :2] = hints.anchors[fill]
    ref[fill, 2] = 1.0
    variants = [False]  # False: the plain image, True: the wearer painted out
    painted = None
    if det.needs_pixels and o.mask_wearer and image is not None and np.isfinite(hw):
        m = silhouette_mask(image.shape[:2], kp[0], layout.EDGES, o.mask_radius_frac * hw,
                            points=hints.markers, polygons=(layout.TORSO,),
                            blobs=((layout.FACE, o.mask_head_frac * hw),))
        painted = paint_out(image, m)
        variants = [True, False] if partner_masked_first else [False, True]

    def look(box, masked, stream=None):
        cands = call_detector(det, painted if masked else image, kind="body", box=box, cam=cam,
                              frame=frame, stream=stream).kp
        if len(cands):
            # The wearer found again, by the markers, as labelled or mirrored (back views fool
            # the detector's left/right): not the partner, whatever the rule says (the rule
            # only compares with the wearer's detected keypoints, which may be few).
            keep = ~wearer_check(cands, hints.anchors, hw, o)[1]
            keep &= ~wearer_check(cands[:, layout.FLIP], hints.anchors, hw, o)[1]
            if masked:
                # Mostly on painted pixels: the detector hallucinating a person from leftovers.
                keep &= _on_mask_frac(cands, m) <= K.HALLUCINATED_FRAC
            cands = cands[keep]
        p, _ = select_partner(cands, ref, radius)
        p[layout.HANDS[0]] = 0.0  # hands come from the hand detector below
        p[layout.HANDS[1]] = 0.0
        return p

    def found(p):
        """Enough confident body keypoints, spread over a person-sized extent (a crumpled
        skeleton made of the partner's visible bits is not a find)."""
        if _n_good(p, o.accept_conf) < o.min_partner_kp:
            return False
        ok = p[layout.BODY, 2] >= o.accept_conf
        span = np.ptp(p[layout.BODY][ok, :2], axis=0).max()
        return not np.isfinite(hw) or span >= K.MIN_PARTNER_SPAN_FRAC * hw

    partner, mode, used = np.zeros((layout.N, 3), np.float32), 0, variants[0]
    pstream = ("partner",)  # crops around the partner (tracked, refined) follow it
    if o.track and prev_partner_box is not None and np.all(np.isfinite(prev_partner_box)):
        sb = expand_box(prev_partner_box, o.track_margin, min_side=K.MIN_BODY_BOX_PX, square=True)
        for masked in variants:
            p = look(sb, masked, pstream)
            if found(p):
                partner, mode, used, boxes[1] = p, 1, masked, sb
                break
            forget_stream(det, pstream)
    if mode == 0:
        if image is not None:
            boxes[1] = (0.0, 0.0, float(image.shape[1]), float(image.shape[0]))
        weak = None
        for masked in variants:
            p = look(None, masked)
            if found(p):
                partner, mode, used = p, 2, masked
                break
            if weak is None or _n_good(p, o.accept_conf) > _n_good(weak, o.accept_conf):
                weak = p
        if mode == 2 and det.needs_pixels:  # refine in a crop around what the whole image gave
            rb = _person_box(partner, o.accept_conf, o.body_margin)
            p2 = look(rb, used, pstream)
            if not found(p2):
                forget_stream(det, pstream)
            if found(p2) and _n_good(p2, o.accept_conf) >= _n_good(partner, o.accept_conf):
                partner, boxes[1] = p2, rb
        elif mode == 0 and weak is not None and not det.needs_pixels:
            # Precomputed multi-person detections: a partial partner (cut by the image border,
            # half occluded) is real data and the paper's rule keeps it; don't track from it.
            # A single-person detector's weak result is mostly made-up limbs: not reported.
            partner = weak
    kp[1] = partner
    if o.hands and mode:
        hb, wr = _partner_hand_boxes(kp[1], o.accept_conf)
        hand_boxes[1] = hb
        # the original image: hands are small and the hand detector returns two per crop, so
        # the wearer's hand next to the partner's (handshake) is told apart by the wrist
        # anchor and the rule; painting the wearer out would also paint the touching hand.
        wi = [layout.IDX["l_wrist"], layout.IDX["r_wrist"], layout.HANDS[0].start,
              layout.HANDS[1].start]
        detected = np.where((kp[0, wi, 2] >= K.MIN_CONF)[:, None], kp[0, wi, :2], np.nan)
        wearer_wrists = np.concatenate([hints.wrists, detected])  # markers and detections
        _hands(image, kp[1], hb, wr, det, o, cam, frame, ref, wearer_wrists, radius, who="partner")
    pbox = _person_box(kp[1], o.accept_conf, o.body_margin) if mode else np.full(4, np.nan)
    return ViewPeople(kp, boxes, hand_boxes, pbox, isolated, mode, bool(mode and used))


def partner_looks_like_wearer(partner: np.ndarray, hints: WearerHints,
                              o: PeopleOptions = PeopleOptions()) -> np.ndarray:
    """(C, F) bool: the partner's keypoints (C, F, 65, 3) pass the wearer's marker check, as
    labelled or mirrored, in that view and frame (hints: the sequence's :class:`WearerHints`).

    A final guard after keypoints were dropped (detect/multiview.py): what remains of a
    candidate that mixed both people can turn out to be the wearer's part of it."""
    C, F = partner.shape[:2]
    out = np.zeros((C, F), bool)
    for c in range(C):
        for f in range(F):
            h = _height(hints.box[c, f])
            if not np.isfinite(h) or (partner[c, f, layout.BODY, 2] >= K.MIN_CONF).sum() < 4:
                continue
            p = partner[c, f][None]
            out[c, f] = (wearer_check(p, hints.anchors[c, f], h, o)[1][0]
                         or wearer_check(p[:, layout.FLIP], hints.anchors[c, f], h, o)[1][0])
    return out

