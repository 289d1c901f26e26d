"""Identity guard and tracking (H8): a person mostly dropped by the cross-view check loses the
rest of it in that view when the rest looks like the other person; the wearer's face taken for
the partner's is dropped by the head markers; streams reach only detectors that track, a
rejected wearer is never tracked on and tracking state never crosses a chunk; hand crops out
of the picture are not run; mediapipe's video mode gives image mode's keypoints on a clip."""
from pathlib import Path

import numpy as np
import pytest

from detect import layout
from detect.base import Detections, call_detector, forget_stream
from detect.hints import PIG_ANCHORS, WearerHints
from detect.people import find_people
from detect.sequence import mostly_dropped

REPO = Path(__file__).resolve().parents[1]


def test_mostly_dropped_needs_a_majority_of_body_keypoints_to_survive():
    """A view's person goes when fewer than MIN_KEPT_FRAC of its confident body keypoints
    survive and at most MAX_LEFTOVER_KP are left (a few leftovers of a mixed skeleton)."""
    conf = np.zeros((1, 5, 2, layout.N))
    conf[0, :, :, :20] = 0.9            # 20 confident body keypoints per person
    conf[0, 3, 0, 12:23] = 0.0          # frame 3, wearer: 12 confident
    conf[0, 4, 0, 8:23] = 0.0           # frame 4, wearer: 8 confident
    conf[0, :, :, 30:40] = 0.9          # hand keypoints: not counted
    out = np.zeros(conf.shape, bool)
    out[0, 0, 0, :15] = True            # 5 of 20 left -> dropped
    out[0, 1, 1, :11] = True            # 9 of 20 left: under half, but 9 > 8 leftovers -> kept
    out[0, 2, 0, 30:40] = True          # only hand keypoints dropped -> kept
    out[0, 3, 0, :7] = True             # 5 of 12 left -> dropped
    out[0, 4, 0, :3] = True             # 5 of 8 left -> kept
    got = mostly_dropped(conf, out)
    want = np.zeros((1, 5, 2), bool)
    want[0, 0, 0] = want[0, 3, 0] = True
    np.testing.assert_array_equal(got, want)
    assert not mostly_dropped(np.zeros((1, 1, 2, layout.N)), np.ones((1, 1, 2, layout.N), bool)).any()
    assert mostly_dropped(conf, out, frac=0.7)[0, 4, 0]  # 5 of 8 < 0.7


class _Plain:
    """A detector that does not track: detect() takes no stream."""

    name, needs_pixels = "plain", False

    def __init__(self):
        self.calls = 0

    def detect(self, image, *, kind, box=None, cam=0, frame=0):
        self.calls += 1
        return Detections.empty()


class _Tracking(_Plain):
    """Records the streams it is called with and the ones it is told to forget; returns the
    person ``person`` for every body call."""

    streams = True

    def __init__(self, person):
        super().__init__()
        self.person = person
        self.seen, self.forgotten = [], []

    def detect(self, image, *, kind, box=None, cam=0, frame=0, stream=None):
        self.calls += 1
        self.seen.append((kind, stream))
        if kind == "body":
            return Detections(self.person[None])
        return Detections.empty()

    def forget(self, stream):
        self.forgotten.append(stream)

    def reset(self):
        self.forgotten.append("*")


def test_streams_go_only_to_tracking_detectors():
    plain = _Plain()
    call_detector(plain, None, kind="body", stream=("wearer", 0))   # no TypeError
    forget_stream(plain, ("wearer", 0))                              # no-op
    assert plain.calls == 1
    tr = _Tracking(np.zeros((layout.N, 3), np.float32))
    call_detector(tr, None, kind="body", stream=("wearer", 2))
    call_detector(tr, None, kind="body")
    assert tr.seen == [("body", ("wearer", 2)), ("body", None)]


def _person(dx):
    kp = np.zeros((layout.N, 3), np.float32)
    body = np.array([[0, -110], [-6, -115], [6, -115], [-12, -112], [12, -112], [-30, -85],
                     [30, -85], [-45, -45], [45, -45], [-55, -5], [55, -5], [-18, 0], [18, 0],
                     [-20, 55], [20, 55], [-22, 110], [22, 110], [-26, 122], [-34, 118],
                     [-18, 114], [26, 122], [34, 118], [18, 114]], float)
    kp[layout.BODY, :2] = body + (300 + dx, 300)
    kp[layout.BODY, 2] = 0.9
    return kp


def _hints(wearer):
    anchors = np.full((layout.N, 2), np.nan)
    for name in PIG_ANCHORS:
        anchors[layout.IDX[name]] = wearer[layout.IDX[name], :2]
    box = np.array([220.0, 170.0, 380.0, 440.0])
    nan = np.full((2, 4), np.nan)
    return WearerHints(box, nan, np.full((2, 2), np.nan), anchors, wearer[:23, :2].copy())


def test_a_rejected_wearer_is_not_tracked_on_and_an_accepted_one_is():
    wearer = _person(0)
    hints = _hints(wearer)
    # the detector keeps returning the partner (200 px to the side): the wearer's check fails,
    # so its stream is forgotten and the wearer reported missing
    # (streams name the person: detect.run runs one view at a time and resets them between)
    det = _Tracking(_person(200))
    r = find_people(None, hints, None, det, cam=3)
    assert ("wearer",) in det.forgotten
    assert r.kp[0, layout.BODY, 2].max() == 0
    assert ("body", ("wearer",)) in det.seen
    # the right person: kept, and its stream stays tracked
    det = _Tracking(wearer)
    r = find_people(None, hints, None, det, cam=1)
    assert ("wearer",) not in det.forgotten
    np.testing.assert_allclose(r.kp[0, layout.BODY, :2], wearer[layout.BODY, :2])


@pytest.mark.slow
def test_video_mode_matches_image_mode_on_a_clip():
    """Eight consecutive frames of a bench video, a crop following the person: video mode
    (tracking) lands within a few pixels of image mode, saves CPU per call, and after
    ``forget`` a call detects afresh (exactly image mode's result)."""
    import time

    from detect.mediapipe_detector import MediapipeOptions
    from formats.video import VideoReader

    path = REPO / "data" / "bench" / "s01" / "videos" / "58860488" / "Posing 1.mp4"
    if not path.exists():
        pytest.skip("bench data not generated (python -m studio --preset bench)")
    r = VideoReader(str(path))
    frames = [r[i] for i in range(8)]
    r.close()
    static = MediapipeOptions(video=False).build()
    video = MediapipeOptions(video=True).build()
    try:
        first = static.detect(frames[0], kind="body").kp
        assert len(first) == 1
        ok = first[0, layout.BODY, 2] >= 0.5
        xy = first[0, layout.BODY][ok, :2]
        box = np.r_[xy.min(0) - 80, xy.max(0) + 80]
        res_s, res_v, cpu = [], [], {}
        for name, det, out in (("s", static, res_s), ("v", video, res_v)):
            out.append(det.detect(frames[0], kind="body", box=box, stream="p").kp)
            t = time.process_time()  # after the first call (it builds the tracking graph)
            for f in frames[1:]:
                out.append(det.detect(f, kind="body", box=box, stream="p").kp)
            cpu[name] = time.process_time() - t
        assert video.tracked_calls == 8
        d = [np.median(np.linalg.norm(a[0, layout.BODY, :2] - b[0, layout.BODY, :2], axis=1))
             for a, b in zip(res_s, res_v, strict=True)]
        assert max(d) < 8.0, d  # the realistic bench session (noise, JPEG, blur): up to 6.5 px
        assert cpu["v"] < cpu["s"], cpu
        video.forget("p")
        again = video.detect(frames[3], kind="body", box=box, stream="p").kp
        np.testing.assert_allclose(again[0, :, :2], res_s[3][0, :, :2], atol=1e-3)
    finally:
        static.close()
        video.close()


def test_hand_crops_out_of_the_picture_are_not_run():
    from detect.people import hand_crop_useful

    shape = (900, 900)
    assert hand_crop_useful(np.array([100.0, 100, 200, 200]), np.array([150.0, 150]), shape)
    # wrist outside the image
    assert not hand_crop_useful(np.array([850.0, 100, 950, 200]), np.array([910.0, 150]), shape)
    # wrist inside, but 3/4 of the box outside
    assert not hand_crop_useful(np.array([850.0, 850, 950, 950]), np.array([880.0, 880]), shape)
    # half inside: still run (threshold inclusive)
    assert hand_crop_useful(np.array([850.0, 100, 950, 200]), np.array([860.0, 150]), shape)
    assert not hand_crop_useful(np.array([850.0, 100, 950, 200]), np.array([860.0, 150]), shape,
                                min_inside=0.6)


def _rig():
    from calib import look_at

    return [look_at(f"c{k}", (4 * np.cos(a), 4 * np.sin(a), 1.8), (0, 0, 1), (1100, 1100),
                    (450, 450), 900, 900) for k, a in enumerate(np.radians([40, 130, 220, 310]))]


def test_head_centre_is_the_mean_of_the_head_markers_whatever_the_prefix():
    from detect.hints import head_centre

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(4, 6, 3))
    names = ["Bob:LFHD", "Bob:C7", "Bob:RFHD", "bob:lbhd", "Bob:RBHD", "Bob:LSHO"]
    np.testing.assert_allclose(head_centre(xyz, names), xyz[:, [0, 2, 3, 4]].mean(axis=1))
    xyz[2, 3] = np.nan  # a head marker unseen: the mean of the three others
    np.testing.assert_allclose(head_centre(xyz, names)[2], xyz[2, [0, 2, 4]].mean(axis=0))
    xyz[1, [0, 2, 3]] = np.nan  # one left: unknown in that frame only
    h = head_centre(xyz, names)
    assert np.isnan(h[1]).all() and np.isfinite(h[[0, 2, 3]]).all()
    assert np.isnan(head_centre(xyz, ["A", "B", "C", "D", "E", "F"])).all()  # no head markers


def _guard_inputs(face_offsets_m):
    """Cameras, keypoints (C, F, 2, 65, 3) and hints: the wearer (person 0) with 12 body
    keypoints and its head centre at (0, 0, 1.6); the partner (person 1) in every view with
    its five face keypoints at head + offset (one offset per frame) and a body 0.6 m away."""
    from calib import project
    from detect.hints import wearer_hints

    cams = _rig()
    F = len(face_offsets_m)
    head = np.array([0.0, 0.0, 1.6])
    wearer3 = head + np.array([[0, 0, -0.3 - 0.1 * k] for k in range(12)])
    partner_body3 = np.array([0.6, 0.0, 0.0]) + wearer3
    kp = np.zeros((4, F, 2, layout.N, 3))
    for f, off in enumerate(face_offsets_m):
        face3 = head + np.asarray(off) + np.array([[0, 0.01 * k, 0.0] for k in range(5)])
        for c, cam in enumerate(cams):
            kp[c, f, 0, 5:17, :2] = project(cam, wearer3)
            kp[c, f, 1, 0:5, :2] = project(cam, face3)
            kp[c, f, 1, 5:17, :2] = project(cam, partner_body3)
    kp[:, :, 0, 5:17, 2] = 0.9
    kp[:, :, 1, :17, 2] = 0.9
    markers = np.repeat(np.array([head + [0.05, 0.05, 0], head + [0.05, -0.05, 0],
                                  head + [-0.05, 0.05, 0], head + [-0.05, -0.05, 0],
                                  head + [0, 0, -1.5]])[None], F, axis=0)
    names = ["LFHD", "RFHD", "LBHD", "RBHD", "LTOE"]
    return cams, kp, wearer_hints(cams, markers, names), markers, names


def test_the_wearers_face_taken_for_the_partners_is_dropped_in_every_view():
    """Frame 0: the views agree on a partner face 4 cm from the wearer's head centre (the
    wearer's face): dropped everywhere, the partner's body kept. Frame 1: 0.3 m away (the
    partner's own face, beside the wearer's head): kept."""
    from detect.hints import head_centre
    from detect.sequence import SequenceOptions, cross_view_guard

    cams, kp, hints, markers, names = _guard_inputs([(0.04, 0.0, 0.0), (0.3, 0.0, 0.0)])
    out = cross_view_guard(cams, kp, hints, SequenceOptions(), head_centre(markers, names))
    assert out[:, 0, 1, layout.FACE].all()
    assert not out[:, 0, 1, 5:17].any()
    assert not out[:, 1, 1].any()
    assert not out[:, :, 0].any()
    # without the head centre nothing tells: nothing dropped
    out = cross_view_guard(cams, kp, hints, SequenceOptions())
    assert not out[:, 0, 1, layout.FACE].any()


class StreamHistory:
    """A picklable tracking stand-in (no pixels) whose answer depends on its history: the
    wearer ``person`` with a confidence that grows with the calls made on the stream since
    it was built or told to forget. Detections would change if state leaked across chunks."""

    name, needs_pixels, streams = "history", False, True

    def __init__(self, person):
        self.person = person
        self.n = {}

    def build(self):
        return StreamHistory(self.person)

    def close(self):
        pass

    def forget(self, stream):
        self.n.pop(stream, None)

    def reset(self):
        self.n.clear()

    def detect(self, image, *, kind, box=None, cam=0, frame=0, stream=None):
        if kind != "body" or stream is None or stream[0] != "wearer":
            return Detections.empty()
        self.n[stream] = self.n.get(stream, 0) + 1
        kp = self.person.copy()
        kp[layout.BODY, 2] = 0.5 + 0.02 * self.n[stream]
        return Detections(kp[None])


def test_tracking_state_never_crosses_a_chunk_so_workers_do_not_matter():
    from detect.run import ArraySource, detect_sequence

    wearer = _person(0)
    h = _hints(wearer)
    F = 7
    hints = WearerHints(*(np.repeat(np.asarray(getattr(h, k))[None, None], F, axis=1) for k in
                          ("box", "hand_boxes", "wrists", "anchors", "markers")))
    frames = np.arange(F)
    src = ArraySource(np.zeros((1, F, 4, 4, 3), np.uint8), tuple(range(F)))
    det = StreamHistory(wearer)
    one = detect_sequence(src, det, hints, frames, workers=1, chunk=3)
    two = detect_sequence(src, det, hints, frames, workers=2, chunk=3)
    np.testing.assert_array_equal(one.kp, two.kp)
    conf = one.kp[0, :, 0, 0, 2]
    # the stream restarts with each chunk (frames 0-1, 2-4, 5-6 of np.linspace's split)
    np.testing.assert_allclose(conf, [0.52, 0.54, 0.52, 0.54, 0.56, 0.52, 0.54], atol=1e-6)
    other = detect_sequence(src, det, hints, frames, workers=1, chunk=4)
    assert not np.array_equal(other.kp, one.kp)  # the check could fail


def test_leftovers_are_judged_by_the_wearers_markers():
    """Frame 0: the wearer's leftovers on its anchors, the partner's 150 px from every wearer
    marker: both their own. Frame 1: the wearer's 0.1 box heights off its anchors, the
    partner's on the wearer's markers: both look like the other person's."""
    from detect.sequence import leftovers_look_swapped

    wearer = _person(0)
    h = _hints(wearer)
    hints = WearerHints(*(np.repeat(np.asarray(getattr(h, k))[None, None], 2, axis=1) for k in
                          ("box", "hand_boxes", "wrists", "anchors", "markers")))
    hw = h.box[3] - h.box[1]
    kp = np.zeros((1, 2, 2, layout.N, 3))
    kp[0, :, 0] = wearer
    kp[0, 1, 0, :, :2] += [0.1 * hw, 0.0]
    kp[0, 0, 1] = _person(150)
    kp[0, 1, 1] = wearer
    out = np.zeros(kp.shape[:-1], bool)
    out[..., 5:15] = True  # what the cross-view check dropped: judged on the rest
    got = leftovers_look_swapped(kp, out, hints)
    np.testing.assert_array_equal(got, [[[False, False], [True, True]]])
    # nothing to judge by (no anchors, no markers): never called swapped
    blind = WearerHints(hints.box, hints.hand_boxes, hints.wrists, hints.anchors * np.nan,
                        hints.markers * np.nan)
    assert not leftovers_look_swapped(kp, out, blind).any()
