"""Finding both people in a view with a stand-in single-person detector, and the worker pool.

The stand-in behaves like mediapipe where it matters for the logic: it sees only pixels (a
person is drawn as coloured discs at its keypoints; painting them over hides it), and it
returns ONE person per image or crop: the one with the most visible keypoints in it. A
multi-person variant stands for precomputed detections.
"""
from dataclasses import dataclass

import cv2
import numpy as np

from detect import layout
from detect.base import Detections
from detect.crops import box_from_points, crop_window, expand_box
from detect.hints import PIG_ANCHORS, WearerHints
from detect.people import PeopleOptions, find_people
from detect.run import ArraySource, chunks, detect_sequence

BG = (200, 200, 200)
COLOURS = ((200, 40, 40), (40, 40, 200))
R = 3


def stick(centre, scale=1.0):
    """(65, 3) a person in pixels: body on a 23-point frame, hands as 21-point fans."""
    body = np.array([
        [0, -110], [-6, -115], [6, -115], [-12, -112], [12, -112],  # head
        [-30, -85], [30, -85], [-45, -45], [45, -45], [-55, -5], [55, -5],  # arms
        [-18, 0], [18, 0], [-20, 55], [20, 55], [-22, 110], [22, 110],  # legs
        [-26, 122], [-34, 118], [-18, 114], [26, 122], [34, 118], [18, 114],  # feet
    ], float)
    kp = np.zeros((layout.N, 3))
    kp[layout.BODY, :2] = body * scale + centre
    for side, wrist in ((0, 9), (1, 10)):
        ang = np.linspace(-0.8, 0.8, 21)
        rad = np.linspace(0, 18, 21) * scale
        kp[layout.HANDS[side], :2] = kp[wrist, :2] + np.stack([np.sin(ang) * rad, np.cos(ang) * rad], 1)
    kp[:, 2] = 1.0
    return kp


def draw(shape, people):
    img = np.full((*shape, 3), BG, np.uint8)
    for p, col in zip(people, COLOURS, strict=False):
        for x, y, _ in p:
            cv2.circle(img, (int(round(x)), int(round(y))), R, col, -1)
    return img


def hints_for(wearer, margin=0.15, markers_frac=1.0):
    """WearerHints built from the wearer's true keypoints (markers = its body keypoints)."""
    box = expand_box(box_from_points(wearer[layout.BODY, :2]), margin, square=True)
    anchors = np.full((layout.N, 2), np.nan)
    for name in PIG_ANCHORS:
        anchors[layout.IDX[name]] = wearer[layout.IDX[name], :2]
    hb = np.stack([expand_box(box_from_points(wearer[s, :2]), 0.3, square=True) for s in layout.HANDS])
    wr = wearer[[layout.HANDS[0].start, layout.HANDS[1].start], :2]
    n = int(round(23 * markers_frac))
    return WearerHints(box, hb, wr, anchors, wearer[:n, :2].copy())


@dataclass(frozen=True)
class Painted:
    """Stand-in detector over images drawn by ``draw``; truth (C, F, P, 65, 3) tells it where
    each person's discs are. single: one person per call (the most visible); else all."""

    truth: np.ndarray
    frames: tuple[int, ...]
    single: bool = True
    name: str = "painted"

    @property
    def needs_pixels(self):
        return True

    def build(self):
        return self

    def close(self):
        pass

    def _visible(self, image, p_kp, colour, win):
        x0, y0, x1, y1 = win
        xy = np.round(p_kp[:, :2]).astype(int)
        inside = (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)
        vis = np.zeros(len(p_kp), bool)
        vis[inside] = np.all(image[xy[inside, 1], xy[inside, 0]] == colour, axis=1)
        return vis

    def detect(self, image, *, kind, box=None, cam=0, frame=0):
        h, w = image.shape[:2]
        win = (0, 0, w, h) if box is None else crop_window(box, w, h)
        if win is None:
            return Detections.empty()
        people = self.truth[cam, self.frames.index(frame)]
        out = []
        for p, col in zip(people, COLOURS, strict=False):
            vis = self._visible(image, p, col, win)
            if kind == "body":
                if vis[layout.BODY].sum() >= 5:
                    kp = np.zeros((layout.N, 3))
                    kp[layout.BODY] = p[layout.BODY]
                    kp[layout.BODY, 2] = np.where(vis[layout.BODY], 0.9, 0.0)
                    ys = p[layout.BODY][vis[layout.BODY], 1]
                    out.append((vis[layout.BODY].sum() * np.ptp(ys), kp))  # bigger = more salient
            else:
                for sl in layout.HANDS:
                    if vis[sl].sum() >= 10 and vis[sl.start]:
                        kp = np.zeros((layout.N, 3))
                        kp[sl] = p[sl]
                        kp[sl, 2] = 0.8
                        out.append((vis[sl].sum(), kp))
        if not out:
            return Detections.empty()
        if self.single and kind == "body":
            out = [max(out, key=lambda t: t[0])]
        return Detections(np.stack([k for _, k in out]))


def test_separate_people_found_and_tracked():
    shape = (480, 640)
    frames = tuple(range(4))
    truth = np.stack([[stick((200, 240)), stick((440 + 5 * f, 250), 0.9)] for f in frames])[None]
    images = np.stack([draw(shape, truth[0, f]) for f in range(len(frames))])[None]
    det = Painted(truth, frames)
    prev = None
    for i, f in enumerate(frames):
        r = find_people(images[0, i], hints_for(truth[0, i, 0]), prev, det, frame=f)
        for p in (0, 1):
            ok = r.kp[p, :, 2] > 0
            assert ok.sum() >= 60, (f, p, ok.sum())
            np.testing.assert_allclose(r.kp[p, ok, :2], truth[0, i, p, ok, :2], atol=1e-4)
        assert r.partner_mode == (2 if i == 0 else 1)
        assert not r.wearer_retry
        prev = r.partner_box
        # the partner's search box (tracked) holds the partner
        b = r.boxes[1]
        assert np.all(truth[0, i, 1, layout.BODY, :2] >= b[:2]) and np.all(truth[0, i, 1, layout.BODY, :2] <= b[2:])


def test_without_mask_the_single_person_detector_returns_the_wearer_again():
    """Why the wearer is painted out: the most visible person in the whole image is the
    wearer (drawn bigger), and the rule then leaves nothing for the partner."""
    shape = (480, 640)
    truth = np.stack([stick((220, 240), 1.2), stick((470, 250), 0.8)])[None, None]
    img = draw(shape, truth[0, 0])[None, None]
    det = Painted(truth, (0,))
    bad = find_people(img[0, 0], hints_for(truth[0, 0, 0]), None, det,
                      PeopleOptions(mask_wearer=False))
    assert bad.partner_mode == 0
    good = find_people(img[0, 0], hints_for(truth[0, 0, 0]), None, det)
    assert good.partner_mode == 2
    ok = good.kp[1, layout.BODY, 2] > 0
    np.testing.assert_allclose(good.kp[1, layout.BODY][ok, :2], truth[0, 0, 1, layout.BODY][ok, :2])


def test_partner_standing_in_the_wearer_crop_is_caught_by_the_marker_check():
    """Close contact: the partner (bigger, in front) fills the wearer's crop, the detector
    locks onto it; the anchors from the markers reject it and the retry finds the wearer."""
    shape = (480, 640)
    wearer = stick((300, 240), 0.8)
    partner = stick((330, 235), 1.3)
    truth = np.stack([wearer, partner])[None, None]
    img = draw(shape, truth[0, 0])
    # redraw the wearer on top so that it is entirely visible
    for x, y, _ in wearer:
        cv2.circle(img, (int(round(x)), int(round(y))), R, COLOURS[0], -1)
    det = Painted(truth, (0,))
    h = hints_for(wearer, margin=0.4)
    first = det.detect(img, kind="body", box=h.box)
    assert len(first) == 1 and np.allclose(first.kp[0, 5, :2], partner[5, :2])  # locked onto partner
    r = find_people(img, h, None, det)
    assert r.wearer_retry
    ok = r.kp[0, layout.BODY, 2] > 0
    assert ok.sum() >= 15
    np.testing.assert_allclose(r.kp[0, layout.BODY][ok, :2], wearer[layout.BODY][ok, :2])
    # the partner's keypoints are the partner's (where found), never the wearer's
    okp = r.kp[1, layout.BODY, 2] > 0
    assert okp.sum() >= 5
    np.testing.assert_allclose(r.kp[1, layout.BODY][okp, :2], partner[layout.BODY][okp, :2])
    # next frame, isolated crop first (as the chunk loop asks after a retry): one body call
    # for the wearer instead of two, same keypoints
    calls = []

    class Counting:
        needs_pixels = True

        def detect(self, image, *, kind, box=None, cam=0, frame=0):
            calls.append((kind, None if box is None else tuple(np.round(box, 1))))
            return det.detect(image, kind=kind, box=box, cam=cam, frame=frame)

    r2 = find_people(img, h, None, Counting(), wearer_isolated_first=True)
    wearer_calls = [c for c in calls if c[0] == "body" and c[1] == tuple(np.round(h.box, 1))]
    assert len(wearer_calls) == 1 and r2.wearer_retry
    np.testing.assert_array_equal(r2.kp[0], r.kp[0])


def test_multi_person_candidates_go_through_the_rule():
    shape = (480, 640)
    truth = np.stack([stick((220, 240)), stick((470, 250), 0.8)])[None, None]
    img = draw(shape, truth[0, 0])
    det = Painted(truth, (0,), single=False)
    r = find_people(img, hints_for(truth[0, 0, 0]), None, det, PeopleOptions(mask_wearer=False))
    for p in (0, 1):
        ok = r.kp[p, :, 2] > 0
        assert ok.sum() >= 60
        np.testing.assert_allclose(r.kp[p, ok, :2], truth[0, 0, p, ok, :2], atol=1e-4)


def test_chunks_cover_in_order():
    for n, m in ((0, 4), (5, 16), (100, 16), (100, 1), (7, 3)):
        parts = chunks(n, m)
        idx = np.concatenate([np.arange(n)[s] for s in parts]) if parts else np.zeros(0)
        np.testing.assert_array_equal(idx, np.arange(n))
        assert all(s.stop - s.start <= m for s in parts)
    assert len(chunks(100, 16)) == 7 and len(chunks(20, 16)) == 2


def test_sequence_same_with_one_or_two_workers():
    shape = (240, 320)
    frames = tuple(range(0, 24, 2))
    C = 2
    truth = np.zeros((C, len(frames), 2, layout.N, 3))
    for c in range(C):
        for i in range(len(frames)):
            truth[c, i, 0] = stick((100 + 2 * i + 10 * c, 120), 0.5)
            truth[c, i, 1] = stick((230 - 2 * i, 125), 0.45)
    images = np.stack([[draw(shape, truth[c, i]) for i in range(len(frames))] for c in range(C)])
    hs = [[hints_for(truth[c, i, 0]) for i in range(len(frames))] for c in range(C)]
    hints = WearerHints(*(np.array([[getattr(hs[c][i], k) for i in range(len(frames))] for c in range(C)])
                          for k in ("box", "hand_boxes", "wrists", "anchors", "markers")))
    src = ArraySource(images, frames)
    det = Painted(truth, frames)
    one = detect_sequence(src, det, hints, np.array(frames), workers=1, chunk=3)
    two = detect_sequence(src, det, hints, np.array(frames), workers=2, chunk=3)
    np.testing.assert_array_equal(one.kp, two.kp)
    np.testing.assert_array_equal(one.partner_mode, two.partner_mode)
    assert one.kp.shape == (C, len(frames), 2, layout.N, 3)
    found = one.kp[..., 2] > 0
    assert found.mean() > 0.9
    err = np.linalg.norm(one.kp[..., :2] - truth[..., :2], axis=-1)[found]
    assert err.max() < 1e-3
    # 4 chunks: each starts with a whole-image search, then tracks
    assert (one.partner_mode == 2).sum() == C * 4 and (one.partner_mode == 1).sum() == C * 8


def test_precomputed_candidates_without_pixels():
    """Precomputed detections (three people: wearer, partner, a bystander with low scores;
    padded rows) run without images; the wearer is the candidate matching the markers."""
    from detect.precomputed import PrecomputedDetector

    wearer, partner = stick((220, 240)), stick((470, 250), 0.8)
    by = stick((620, 300), 0.5)  # a bystander, more confident on one keypoint
    by[:, 2] = 0.3
    partner[:, 2] = 0.7
    k = layout.IDX["l_knee"]
    partner[k, 2] = 0.2
    by[k, 2] = 0.9
    part = np.zeros_like(partner)  # a partial second detection of the partner's legs
    part[13:17] = partner[13:17] + [1.0, 1.0, 0.0]
    part[13:17, 2] = 0.6
    cands = np.stack([partner, by, part, wearer, np.zeros_like(wearer)])[None, None]
    det = PrecomputedDetector(cands, (7,))
    assert len(det.detect(None, kind="body", box=np.array([150.0, 100, 300, 400]), frame=7)) == 1
    assert len(det.detect(None, kind="body", frame=8)) == 0
    r = find_people(None, hints_for(wearer), None, det, frame=7)
    np.testing.assert_allclose(r.kp[0], wearer, atol=1e-4)
    # the paper's rule: per keypoint the most confident candidate not near the wearer (the
    # partial detection's knee), but not the far bystander's (coherence guard)
    np.testing.assert_allclose(r.kp[1, k], part[k], atol=1e-4)
    others = np.delete(np.arange(layout.N), k)
    np.testing.assert_allclose(r.kp[1, others], partner[others], atol=1e-4)
    assert r.partner_mode == 2


def test_no_markers_no_people():
    """Without the wearer's markers in a view nothing tells the two apart: report neither."""
    shape = (480, 640)
    truth = np.stack([stick((220, 240)), stick((470, 250), 0.8)])[None, None]
    img = draw(shape, truth[0, 0])
    h = hints_for(truth[0, 0, 0])
    h = WearerHints(np.full(4, np.nan), h.hand_boxes * np.nan, h.wrists * np.nan,
                    h.anchors * np.nan, h.markers * np.nan)
    r = find_people(img, h, np.array([400.0, 100, 560, 400]), Painted(truth, (0,)))
    assert not r.kp[..., 2].any() and r.partner_mode == 0


def test_mirrored_person_is_not_taken_for_the_wearer():
    """A person facing the other way right over the wearer's markers could be the partner
    facing it or the wearer with its left/right swapped by the detector: it is taken for
    neither (both missing in this view) rather than risk a swap. The same person nearer the
    camera (larger) is told apart by its size: the wearer is still missing (hidden behind it),
    the partner is found."""
    shape = (480, 640)
    wearer = stick((300, 240), 0.8)
    for scale, partner_found in ((0.8, False), (1.0, True)):
        partner = stick((302, 236), scale)[layout.FLIP]  # facing the other way, in front
        truth = np.stack([wearer, partner])[None, None]
        img = draw(shape, truth[0, 0])
        det = Painted(truth, (0,))
        r = find_people(img, hints_for(wearer, margin=0.3), None, det)
        assert not r.kp[0, layout.BODY, 2].any()
        ok = r.kp[1, layout.BODY, 2] > 0
        assert (r.partner_mode > 0) == partner_found
        if not partner_found:
            assert not ok.any()
            continue
        assert ok.sum() >= 15
        np.testing.assert_allclose(r.kp[1, layout.BODY][ok, :2], partner[layout.BODY][ok, :2])
    # lined up and facing the same way: the same size passes as the wearer (2D can't tell);
    # larger (nearer the camera, or taller) is caught by the size check
    for scale, passes in ((0.8, True), (1.0, False)):
        same = stick((302, 236), scale)
        img2 = draw(shape, [wearer, same])
        r2 = find_people(img2, hints_for(wearer, margin=0.3), None,
                         Painted(np.stack([wearer, same])[None, None], (0,)))
        assert r2.kp[0, layout.BODY, 2].all() == passes


def test_partner_found_in_the_plain_image_when_painting_hides_it():
    """When painting the wearer out also hides the partner (partner in front), the plain
    image finds it; the next frame tries the plain image first (one body call)."""
    shape = (480, 640)
    wearer, partner = stick((220, 240)), stick((470, 250), 0.9)
    truth = np.stack([wearer, partner])[None, None]
    img = draw(shape, truth[0, 0])
    inner = Painted(truth, (0,), single=False)
    calls = []

    class HidesWhenPainted:
        """Multi-person stand-in that sees nobody in a painted image."""
        needs_pixels = True

        def detect(self, image, *, kind, box=None, cam=0, frame=0):
            calls.append((kind, image is img))
            if image is not img and kind == "body":
                return Detections.empty()
            return inner.detect(image, kind=kind, box=box, cam=cam, frame=frame)

    r = find_people(img, hints_for(wearer), None, HidesWhenPainted(), partner_masked_first=True)
    assert r.partner_mode == 2 and not r.partner_masked
    ok = r.kp[1, layout.BODY, 2] > 0
    np.testing.assert_allclose(r.kp[1, layout.BODY][ok, :2], partner[layout.BODY][ok, :2])
    assert ok.sum() >= 20
    calls.clear()
    r2 = find_people(img, hints_for(wearer), r.partner_box, HidesWhenPainted(),
                     partner_masked_first=False)
    assert r2.partner_mode == 1 and not r2.partner_masked
    body = [c for c in calls if c[0] == "body"]
    assert body == [("body", True), ("body", True)]  # the wearer's crop, then the partner's


def test_partner_hand_crop_drops_the_wearers_hand():
    """Handshake: the wearer's hand is nearer the partner's pose wrist than the partner's own
    hand; the wearer's wrist (marker) rules it out."""
    from detect.people import PeopleOptions, _hands

    wearer_hand = np.zeros((layout.N, 3))
    partner_hand = np.zeros((layout.N, 3))
    sl = layout.HANDS[1]
    wearer_hand[sl, :2] = [200.0, 200.0]
    wearer_hand[sl, 2] = 0.9
    partner_hand[sl, :2] = [215.0, 205.0]
    partner_hand[sl, 2] = 0.9

    class Two:
        needs_pixels = True

        def detect(self, image, *, kind, box=None, cam=0, frame=0):
            return Detections(np.stack([wearer_hand, partner_hand]))

    box = np.array([[0.0, 0, 1, 1], [150.0, 150, 260, 260]])
    anchors = np.array([[np.nan, np.nan], [203.0, 201.0]])  # partner's pose wrist: off by 12 px
    kp = np.zeros((layout.N, 3), np.float32)
    _hands(None, kp, box, anchors, Two(), PeopleOptions(), 0, 0)
    np.testing.assert_allclose(kp[sl.start, :2], [200, 200])  # without: the wearer's hand
    kp = np.zeros((layout.N, 3), np.float32)
    _hands(None, kp, box, anchors, Two(), PeopleOptions(), 0, 0, avoid_wrists=np.array([[199.0, 201.0]]),
           radius=8.0)
    np.testing.assert_allclose(kp[sl.start, :2], [215, 205])


def test_partner_looks_like_wearer_guard():
    from detect.people import partner_looks_like_wearer

    wearer = stick((300, 240), 0.8)
    other = stick((480, 240), 0.8)
    h = hints_for(wearer)
    hints = WearerHints(*(np.asarray(getattr(h, k))[None, None] for k in
                          ("box", "hand_boxes", "wrists", "anchors", "markers")))
    partner = np.stack([other, wearer, wearer[layout.FLIP]])[None]  # (1, 3, 65, 3): 3 "frames"
    hints = WearerHints(*(np.repeat(getattr(hints, k), 3, axis=1) for k in
                          ("box", "hand_boxes", "wrists", "anchors", "markers")))
    assert partner_looks_like_wearer(partner, hints).tolist() == [[False, True, True]]
