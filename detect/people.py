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
(:func:`detect.rule.select_partner`). mediapipe is single-person, so we first paint the
wearer out (:mod:`detect.mask`) — otherwise it would often return the wearer again — and
then search:

1. around the partner's box from the previous frame (when there is one) — a crop gives the
   detector more pixels than the whole image, and the previous box is nearly always right at
   video rates;
2. otherwise over the whole (painted) image, then once more in a crop around what it found.

Painting out alone would work on the whole image but at lower resolution; tracking alone
could not start or recover. Precomputed multi-person detections go through the same code:
painting changes nothing for them and the rule does the separating, exactly as in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detect import constants as K
from detect import layout
from detect.base import Detector
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
    """

    kp: np.ndarray
    boxes: np.ndarray
    hand_boxes: np.ndarray
    partner_box: np.ndarray
    wearer_retry: bool
    partner_mode: int


def _height(box: np.ndarray) -> float:
    return float(box[3] - box[1]) if np.all(np.isfinite(box)) else np.nan


def _n_good(kp: np.ndarray, conf: float) -> int:
    return int((kp[layout.BODY, 2] >= conf).sum())


def _person_box(kp: np.ndarray, conf: float, margin: float) -> np.ndarray:
    ok = kp[layout.BODY, 2] >= conf
    return expand_box(box_from_points(kp[layout.BODY, :2], ok), margin,
                      min_side=K.MIN_BODY_BOX_PX, square=True)


def _find_wearer(image, hints: WearerHints, det: Detector, o: PeopleOptions, cam: int, frame: int,
                 isolated_first: bool):
    """(kp (65, 3), isolated): the wearer's body keypoints, and whether they came from the
    crop with everything far from its markers painted out ("isolated")."""
    kp = np.zeros((layout.N, 3), np.float32)
    h = _height(hints.box)
    tol = o.anchor_frac * h

    def best(cands):
        """(kp, err, ok) of the candidate nearest the anchors; ok = it passes the check."""
        if len(cands) == 0:
            return None, np.inf, False
        err = anchor_error(cands.kp, hints.anchors)
        if np.any(np.isfinite(err)):
            i = int(np.nanargmin(err))
            # Mirrored (a person facing the other way: the partner facing the wearer, or the
            # detector's left/right swapped on the wearer's back): its mirror matches the
            # anchors better by a clear margin. Rejected, never flipped back: a partner facing
            # us would then pass for the wearer.
            flip = anchor_error(cands.kp[i:i + 1, layout.FLIP], hints.anchors)[0]
            mirrored = np.isfinite(flip) and flip + max(K.FLIP_MARGIN_FRAC * h, 3.0) < err[i]
            return cands.kp[i], float(err[i]), bool(err[i] <= tol and not mirrored)
        i = int(np.argmax(box_support(cands.kp, hints.box)))
        return cands.kp[i], np.nan, True  # no anchors to check against: accept

    def attempt(isolated: bool):
        img = image
        if isolated:
            # Keep only the neighbourhood of the wearer's markers: the partner in the crop goes.
            near = silhouette_mask(image.shape[:2], np.zeros((layout.N, 3)), layout.EDGES,
                                   o.isolate_radius_frac * h, points=hints.markers)
            img = paint_out(image, ~near)
        return best(det.detect(img, kind="body", box=hints.box, cam=cam, frame=frame))

    order = (True, False) if isolated_first else (False, True)
    if not det.needs_pixels:
        order = (False,)
    for isolated in order:
        cand, _err, ok = attempt(isolated)
        if cand is not None and ok:
            kp[layout.BODY] = cand[layout.BODY]
            return kp, isolated
    # Nothing matched the markers: report the wearer missing in this view rather than risk
    # the partner's (or mirrored) keypoints as the wearer's.
    return kp, False


def _hands(image, person_kp: np.ndarray, boxes: np.ndarray, anchors: np.ndarray, det: Detector,
           o: PeopleOptions, cam: int, frame: int, avoid: np.ndarray | None, radius: float):
    """Fill person_kp's hand blocks from the hand crops ``boxes`` (2, 4) whose wrists are
    expected at ``anchors`` (2, 2); drop hands matching ``avoid`` (the wearer) first."""
    for side in (0, 1):
        box = boxes[side]
        if not np.all(np.isfinite(box)) or not np.all(np.isfinite(anchors[side])):
            continue
        cands = det.detect(image, kind="hands", box=box, cam=cam, frame=frame).kp
        if avoid is not None and len(cands):
            cands = cands[~is_same_person(cands, avoid, radius)]
        hand = pick_hand(cands, side, anchors[side], o.hand_anchor_frac * _height(box), layout.HANDS)
        if hand is not None:
            person_kp[layout.HANDS[side]] = hand


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
                frame: int = 0, wearer_isolated_first: bool = False) -> ViewPeople:
    """Both people in one view.

    image : (H, W, 3) uint8 RGB (None for detectors that don't need pixels; then the
        whole-image box is NaN). hints : one view's :meth:`WearerHints.view`.
    prev_partner_box : (4,) or None. wearer_isolated_first : try the wearer's isolated crop
        first (it was needed in this view in the previous frame: saves a detection per frame
        while the partner stands in the wearer's crop).
    """
    kp = np.zeros((2, layout.N, 3), np.float32)
    boxes = np.full((2, 4), np.nan)
    hand_boxes = np.full((2, 2, 4), np.nan)
    if not np.all(np.isfinite(hints.box)):
        # No markers in this view and frame: nothing tells the two people apart (the rule
        # needs the wearer's keypoints), so neither is reported rather than risk a swap.
        return ViewPeople(kp, boxes, hand_boxes, np.full(4, np.nan), False, 0)
    boxes[0] = hints.box

    # -- person 0: the marker wearer
    kp[0], isolated = _find_wearer(image, hints, det, o, cam, frame, wearer_isolated_first)
    hw = _height(hints.box)
    radius = o.near_frac * hw if np.isfinite(hw) else 0.0
    if o.hands:
        hand_boxes[0] = hints.hand_boxes
        anchors = np.where(np.isfinite(hints.wrists), hints.wrists,
                           kp[0, [layout.IDX["l_wrist"], layout.IDX["r_wrist"]], :2])
        _hands(image, kp[0], hints.hand_boxes, anchors, det, o, cam, frame, None, radius)

    # -- person 1: the partner
    # The rule's reference for the wearer: its detected keypoints, and where those are missing
    # the marker anchors (so the wearer's undetected parts still can't become the partner's).
    ref = kp[0].copy()
    fill = (ref[:, 2] < K.MIN_CONF) & np.all(np.isfinite(hints.anchors), axis=1)
    ref[fill, :2] = hints.anchors[fill]
    ref[fill, 2] = 1.0
    search = image
    if det.needs_pixels and o.mask_wearer and image is not None and np.isfinite(hw):
        m = silhouette_mask(image.shape[:2], kp[0], layout.EDGES, o.mask_radius_frac * hw,
                            points=hints.markers, polygons=(layout.TORSO,),
                            blobs=((layout.FACE, o.mask_head_frac * hw),))
        search = paint_out(image, m)

    def look(box):
        cands = det.detect(search, kind="body", box=box, cam=cam, frame=frame)
        p, _ = select_partner(cands.kp, ref, radius)
        p[layout.HANDS[0]] = 0.0  # hands come from the hand detector below
        p[layout.HANDS[1]] = 0.0
        return p

    partner, mode = np.zeros((layout.N, 3), np.float32), 0
    if o.track and prev_partner_box is not None and np.all(np.isfinite(prev_partner_box)):
        sb = expand_box(prev_partner_box, o.track_margin, min_side=K.MIN_BODY_BOX_PX, square=True)
        p = look(sb)
        if _n_good(p, o.accept_conf) >= o.min_partner_kp:
            partner, mode, boxes[1] = p, 1, sb
    if mode == 0:
        p = look(None)
        if image is not None:
            boxes[1] = (0.0, 0.0, float(image.shape[1]), float(image.shape[0]))
        if _n_good(p, o.accept_conf) >= o.min_partner_kp:
            partner, mode = p, 2
            if det.needs_pixels:  # refine in a crop around what the whole image gave
                rb = _person_box(p, o.accept_conf, o.body_margin)
                p2 = look(rb)
                if _n_good(p2, o.accept_conf) >= _n_good(p, o.accept_conf):
                    partner, boxes[1] = p2, rb
        elif _n_good(p, o.accept_conf) > 0:
            partner = p  # weak: keep what there is, but don't track from it
    kp[1] = partner
    if o.hands and mode:
        hb, wr = _partner_hand_boxes(kp[1], o.accept_conf)
        hand_boxes[1] = hb
        # the original image: hands are small and the hand detector returns two per crop, so
        # the wearer's hand next to the partner's (handshake) is told apart by the wrist
        # anchor and the rule; painting the wearer out would also paint the touching hand.
        _hands(image, kp[1], hb, wr, det, o, cam, frame, ref, radius)
    pbox = _person_box(kp[1], o.accept_conf, o.body_margin) if mode else np.full(4, np.nan)
    return ViewPeople(kp, boxes, hand_boxes, pbox, isolated, mode)
