"""The identity check (detect/identity.py) on synthetic detections: two people facing each
other, seen by four calibrated views; one view has the two identities swapped, one has the
partner's left and right exchanged, one the wearer's. No detector runs (fast)."""
import numpy as np

from detect import layout
from detect.hints import PIG_ANCHORS

#: A person facing +x at the origin (metres: forward x, left y, up z), the 23 KP65 body
#: keypoints in order.
_BODY = np.array([
    [0.10, 0.00, 1.65], [0.08, 0.03, 1.68], [0.08, -0.03, 1.68], [0.00, 0.07, 1.65],
    [0.00, -0.07, 1.65], [0.00, 0.18, 1.42], [0.00, -0.18, 1.42], [0.05, 0.24, 1.12],
    [0.05, -0.24, 1.12], [0.20, 0.22, 0.95], [0.20, -0.22, 0.95], [0.00, 0.10, 0.95],
    [0.00, -0.10, 0.95], [0.03, 0.11, 0.52], [0.03, -0.11, 0.52], [0.00, 0.11, 0.08],
    [0.00, -0.11, 0.08], [0.15, 0.12, 0.02], [0.13, 0.16, 0.02], [-0.05, 0.11, 0.02],
    [0.15, -0.12, 0.02], [0.13, -0.16, 0.02], [-0.05, -0.11, 0.02],
])


def _rig():
    from calib import look_at

    return [look_at(f"c{k}", (4 * np.cos(a), 4 * np.sin(a), 1.8), (0, 0, 1), (1100, 1100),
                    (450, 450), 900, 900) for k, a in enumerate(np.radians([40, 130, 220, 310]))]


def _scene(F=4):
    """cams, kp (C, F, 2, 65, 3) exact projections (confidence 0.9), wearer anchors
    (C, F, 65, 2), frames: the wearer at x = -0.35 facing +x, the partner at x = +0.35 facing
    it, both moving 1 cm per frame along y."""
    from calib import project

    cams = _rig()
    kp = np.zeros((len(cams), F, 2, layout.N, 3))
    anchors = np.full((len(cams), F, layout.N, 2), np.nan)
    anchored = [layout.IDX[n] for n in PIG_ANCHORS]
    for f in range(F):
        wearer = _BODY + [-0.35, 0.01 * f, 0.0]
        partner = _BODY * [-1, -1, 1] + [0.35, 0.01 * f, 0.0]  # turned 180 degrees about z
        for c, cam in enumerate(cams):
            for p, X in enumerate((wearer, partner)):
                kp[c, f, p, layout.BODY, :2] = project(cam, X)
            anchors[c, f, anchored] = kp[c, f, 0, anchored, :2]
    kp[:, :, :, layout.BODY, 2] = 0.9
    return cams, kp, anchors, np.arange(F) * 2


def test_a_swapped_view_is_dropped_and_a_flipped_partner_relabelled():
    from detect.identity import VERDICTS, identity_check
    from detect.sequence import relabel_flipped

    cams, truth, anchors, frames = _scene()
    kp = truth.copy()
    kp[2, 0] = truth[2, 0, ::-1]                      # frame 0, view 2: the people swapped
    kp[1, 1, 1] = truth[1, 1, 1][layout.FLIP]         # frame 1, view 1: the partner mirrored
    kp[0, 2, 0] = truth[0, 2, 0][layout.FLIP]         # frame 2, view 0: the wearer mirrored
    ic = identity_check(cams, kp, np.zeros(kp.shape[:-1], bool), anchors, frames)

    expect = np.zeros(ic.verdict.shape, np.int8)
    expect[2, 0, :] = VERDICTS.index("swap")
    expect[1, 1, 1] = VERDICTS.index("flip")
    expect[0, 2, 0] = VERDICTS.index("flip_dropped")
    np.testing.assert_array_equal(ic.verdict, expect)

    body = np.zeros(ic.outlier.shape, bool)
    body[..., layout.BODY] = True
    gone = np.zeros(ic.outlier.shape, bool)
    gone[2, 0] = True
    gone[0, 2, 0] = True
    np.testing.assert_array_equal(ic.outlier, gone & body)  # nothing else dropped

    fixed, conf, _ = relabel_flipped(ic.flip, kp, kp[..., 2], np.zeros(kp.shape[:3] + (2, 2, 4)))
    np.testing.assert_allclose(fixed[1, 1, 1], truth[1, 1, 1], atol=1e-9)  # relabelled back
    np.testing.assert_array_equal(conf, fixed[..., 2])
    assert np.isfinite(ic.partner.xyz[:, layout.IDX["l_shoulder"]]).all()
    np.testing.assert_array_equal(ic.partner.source, 1)  # the views agree in every frame


def test_a_lone_view_is_judged_by_the_neighbouring_frames():
    """The partner seen by one view only in frame 1: that view's detection is the wearer's
    body moved aside (made up); the frames around it put the partner elsewhere: dropped.
    The same detection when it is right (the partner's own) is kept."""
    from detect.identity import VERDICTS, identity_check

    cams, truth, anchors, frames = _scene()
    kp = truth.copy()
    kp[[0, 2, 3], 1, 1, :, 2] = 0.0                     # frame 1: the partner in view 1 only
    ok = identity_check(cams, kp, np.zeros(kp.shape[:-1], bool), anchors, frames)
    assert ok.partner.source[1] == 2 and ok.verdict[1, 1, 1] == 0
    kp[1, 1, 1, layout.BODY, :2] = truth[1, 1, 0, layout.BODY, :2] + [0.0, -60.0]
    bad = identity_check(cams, kp, np.zeros(kp.shape[:-1], bool), anchors, frames)
    assert bad.verdict[1, 1, 1] in (VERDICTS.index("inconsistent"), VERDICTS.index("swap"))
    assert bad.outlier[1, 1, 1, layout.BODY].all()
    assert not bad.outlier[:, [0, 2, 3]].any()


def test_earlier_drops_are_kept_and_nothing_is_judged_without_enough_keypoints():
    from detect.identity import identity_check

    cams, truth, anchors, frames = _scene(F=2)
    out = np.zeros(truth.shape[:-1], bool)
    out[3, 0, 1, :5] = True  # what the cross-view check dropped stays dropped
    kp = truth.copy()
    kp[0, 1, 1, 3:, 2] = 0.0  # three keypoints left: not judged
    kp[0, 1, 1, :3, :2] += 200.0
    ic = identity_check(cams, kp, out, anchors, frames)
    assert ic.outlier[3, 0, 1, :5].all() and ic.outlier.sum() == 5
    assert ic.verdict[0, 1, 1] == 0
