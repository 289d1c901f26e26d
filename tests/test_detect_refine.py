"""The partner's second detection pass (detect/refine.py) with the painted stand-in detector
of tests/test_detect_people.py: a partner the first pass missed is found in the crop around
its projected first fit, the wearer standing in that crop is not taken for it, views that
had the partner are left alone, and ``views_to_redo`` picks the views that need it."""
from __future__ import annotations

import numpy as np
from test_detect_people import Painted, draw, stick

from detect import layout
from detect.refine import refine_partner, views_to_redo
from detect.run import ArraySource

SHAPE = (400, 600)


def _scene(partner_at, wearer_at=(300.0, 200.0)):
    w, p = stick(np.array(wearer_at)), stick(np.array(partner_at), 0.95)
    truth = np.stack([w, p])[None, None]  # (C=1, F=1, 2, 65, 3)
    img = draw(SHAPE, [w, p])[None, None]
    return w, p, truth, img


def _first_pass(w):
    kp = np.zeros((1, 1, 2, layout.N, 3))
    kp[0, 0, 0] = w  # the wearer found, the partner not
    return kp


def test_missed_partner_found_around_its_projected_fit_and_not_the_wearer():
    w, p, truth, img = _scene(partner_at=(420.0, 210.0))
    kp = _first_pass(w)
    proj = (p[:, :2] + [6.0, -4.0])[None, None]  # the first fit, a few pixels off
    outline = proj.copy()
    need = views_to_redo(kp[:, :, 1], proj, SHAPE)
    assert need.all()
    r = refine_partner(ArraySource(img, (0,)), Painted(truth, (0,)), np.array([0]), kp, proj,
                       outline, need)
    got = r.kp[0, 0]
    assert r.redone.all() and r.improved.all()
    ok = got[layout.BODY, 2] > 0.5
    assert ok.sum() >= 15
    assert np.abs(got[layout.BODY][ok, :2] - p[layout.BODY][ok, :2]).max() < 1e-3  # the partner (float32)
    assert r.calls["body"] == 1


def test_a_crop_that_only_shows_the_wearer_finds_nothing():
    """The projection lands on the wearer (a wrong first fit): the person found there matches
    the wearer's own detections better than the projection, so nothing replaces the first
    pass (a swap is never created)."""
    w, p, truth, img = _scene(partner_at=(1500.0, 210.0))  # the partner outside the image
    kp = _first_pass(w)
    proj = (w[:, :2] + [25.0, 0.0])[None, None]  # off the wearer by a quarter of its width
    need = np.ones((1, 1), bool)
    r = refine_partner(ArraySource(img, (0,)), Painted(truth, (0,)), np.array([0]), kp, proj,
                       proj.copy(), need)
    assert not r.improved.any()
    assert (r.kp[0, 0, layout.BODY, 2] == 0).all()


def test_views_that_have_the_partner_are_not_redone():
    w, p, truth, img = _scene(partner_at=(420.0, 210.0))
    kp = _first_pass(w)
    kp[0, 0, 1] = p  # the first pass found the whole partner, hands included
    proj = p[:, :2][None, None]
    assert not views_to_redo(kp[:, :, 1], proj, SHAPE).any()
    off = proj + [2000.0, 0.0]  # and a projection outside the image is never a reason
    kp[0, 0, 1] = 0
    assert not views_to_redo(kp[:, :, 1], off, SHAPE).any()


def test_detection_rates_count_bodies_and_hands():
    from detect.refine import detection_rates

    w, p, _, _ = _scene(partner_at=(420.0, 210.0))
    kp = np.stack([p, np.zeros_like(p)])  # two view-frames: all found, nothing found
    kp[0, layout.HANDS[1], 2] = 0.0  # the right hand missing in the first
    r = detection_rates(kp)
    assert r == {"body": 0.5, "hands": 0.25}  # left 1/2, right 0/2


def test_only_what_can_be_bettered_is_detected_again():
    """A view with the partner's whole body and its left hand but not its right: the body and
    the left hand cannot be bettered, so the pass spends one hand call (the right hand's crop)
    and no body call, and finds the right hand."""
    w, p, truth, img = _scene(partner_at=(420.0, 210.0))
    kp = _first_pass(w)
    kp[0, 0, 1] = p
    kp[0, 0, 1, layout.HANDS[1]] = 0.0
    proj = p[:, :2][None, None]
    need = views_to_redo(kp[:, :, 1], proj, SHAPE)
    assert need.all()
    r = refine_partner(ArraySource(img, (0,)), Painted(truth, (0,)), np.array([0]), kp, proj,
                       proj.copy(), need)
    assert r.calls.get("body", 0) == 0 and r.calls["hands"] == 1, r.calls
    got = r.kp[0, 0]
    assert r.improved.all() and (got[layout.HANDS[1], 2] > 0.5).sum() >= 5
    np.testing.assert_array_equal(got[layout.BODY], p[layout.BODY].astype(np.float32))
    np.testing.assert_array_equal(got[layout.HANDS[0]], p[layout.HANDS[0]].astype(np.float32))


class _ElbowOnWearer(Painted):
    """The painted detector, but the partner it finds has its left elbow read on the wearer's
    left elbow (what mediapipe did in the bench's Posing crops)."""

    def __init__(self, truth, frames, wearer):
        super().__init__(truth, frames)
        self.wearer = wearer

    def detect(self, image, *, kind, box=None, cam=0, frame=0):
        d = super().detect(image, kind=kind, box=box, cam=cam, frame=frame)
        if kind == "body" and len(d):
            kp = d.kp.copy()
            kp[:, layout.IDX["l_elbow"], :2] = self.wearer[layout.IDX["l_elbow"], :2]
            return type(d)(kp)
        return d


def test_a_partner_joint_read_on_the_wearers_joint_is_left_out():
    """The crop finds the partner, but its left elbow sits on the wearer's left elbow, far from
    the first fit's projection: that keypoint alone is left out (counted in ``on_wearer``);
    the partner's other keypoints, far from the wearer's, are kept as found."""
    from detect.refine import on_wearer

    w, p, truth, img = _scene(partner_at=(390.0, 210.0))
    kp = _first_pass(w)
    proj = p[:, :2][None, None]
    need = views_to_redo(kp[:, :, 1], proj, SHAPE)
    r = refine_partner(ArraySource(img, (0,)), _ElbowOnWearer(truth, (0,), w), np.array([0]),
                       kp, proj, proj.copy(), need)
    got = r.kp[0, 0]
    el = layout.IDX["l_elbow"]
    assert r.improved.all() and r.on_wearer[0, 0] == 1
    assert got[el, 2] == 0.0
    ok = got[layout.BODY, 2] > 0.5
    assert ok.sum() >= 15 and np.abs(got[layout.BODY][ok, :2] - p[layout.BODY][ok, :2]).max() < 1e-3
    # the rule itself: near the projection, or near only another joint of the wearer: kept
    cand = p.copy()
    cand[el, :2] = w[layout.IDX["l_knee"], :2]  # on the wearer's knee, not its elbow
    assert not on_wearer(cand, p[:, :2], w, 0.3).any()
    cand[el, :2] = w[el, :2]
    assert on_wearer(cand, p[:, :2], w, 0.3).tolist() == [i == el for i in range(23)]
    assert not on_wearer(cand, cand[:, :2], w, 0.3).any()  # where the first fit put it


class _LosesLeftWrist(Painted):
    """The painted detector, but the body it finds in a crop has lost the left wrist (what
    mediapipe's second pass did at the bench's Posing frame 24, view 0)."""

    def detect(self, image, *, kind, box=None, cam=0, frame=0):
        d = super().detect(image, kind=kind, box=box, cam=cam, frame=frame)
        if kind == "body" and len(d):
            kp = d.kp.copy()
            kp[:, layout.IDX["l_wrist"], 2] = 0.0
            return type(d)(kp)
        return d


def test_a_redone_body_keeps_a_confident_first_pass_keypoint_it_lost():
    """The first pass found part of the partner's body, its left wrist among it; the crop's
    body has more keypoints but not that wrist: the redone body replaces the first pass's
    keypoint by keypoint, and the first pass's confident wrist stays."""
    w, p, truth, img = _scene(partner_at=(420.0, 210.0))
    kp = _first_pass(w)
    wr, el = layout.IDX["l_wrist"], layout.IDX["l_elbow"]
    part = [wr, el, layout.IDX["l_shoulder"], layout.IDX["r_shoulder"]]
    kp[0, 0, 1, part] = p[part]
    kp[0, 0, 1, wr, 2] = 0.72
    proj = p[:, :2][None, None]
    need = views_to_redo(kp[:, :, 1], proj, SHAPE)
    assert need.all()
    r = refine_partner(ArraySource(img, (0,)), _LosesLeftWrist(truth, (0,)), np.array([0]),
                       kp, proj, proj.copy(), need)
    got = r.kp[0, 0]
    assert r.improved.all() and r.calls["body"] == 1
    assert got[wr, 2] == np.float32(0.72)  # the first pass's, not the crop's 0
    np.testing.assert_allclose(got[wr, :2], p[wr, :2], atol=1e-3)
    ok = got[layout.BODY, 2] > 0.5
    assert ok.sum() >= 15  # the crop's other keypoints replace the first pass's
    # without the first pass's wrist, the crop's body is taken as found (the wrist stays lost)
    kp[0, 0, 1, wr, 2] = 0.0
    r = refine_partner(ArraySource(img, (0,)), _LosesLeftWrist(truth, (0,)), np.array([0]),
                       kp, proj, proj.copy(), need)
    assert r.kp[0, 0, wr, 2] == 0.0
