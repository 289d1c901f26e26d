"""Crop math, the paper's partner rule, the silhouette mask and the marker hints."""
import cv2
import numpy as np
import pytest

from calib import look_at, project, world_to_cam
from detect import layout
from detect.crops import (
    box_from_points,
    crop_to_image,
    crop_window,
    expand_box,
    hand_box_from_3d,
)
from detect.hints import wearer_hints
from detect.mask import border_colour, paint_out, silhouette_mask
from detect.rule import anchor_error, is_same_person, near_same_type, pick_hand, select_partner


def test_box_from_points_ignores_invalid_and_nan():
    uv = np.array([[[10, 20], [30, 5], [np.nan, 0], [100, 100]]], float)
    valid = np.array([[True, True, True, False]])
    np.testing.assert_array_equal(box_from_points(uv, valid)[0], [10, 5, 30, 20])
    assert np.all(np.isnan(box_from_points(uv[:, 2:3])))


def test_expand_box_margin_square_and_min_side():
    b = expand_box(np.array([0.0, 0.0, 100.0, 50.0]), 0.1)
    np.testing.assert_allclose(b, [-10, -10, 110, 60])
    s = expand_box(np.array([0.0, 0.0, 100.0, 50.0]), 0.0, square=True)
    np.testing.assert_allclose(s, [0, -25, 100, 75])
    m = expand_box(np.array([10.0, 10.0, 12.0, 11.0]), 0.0, min_side=20)
    np.testing.assert_allclose(m, [1, 0.5, 21, 20.5])


def test_crop_window_rounds_outwards_and_clips():
    assert crop_window(np.array([-5.2, 3.7, 20.1, 9.0]), 15, 100) == (0, 3, 15, 9)
    assert crop_window(np.array([np.nan, 0, 1, 1]), 10, 10) is None
    assert crop_window(np.array([50.0, 50, 60, 60]), 40, 40) is None  # outside


def test_crop_to_image_matches_a_detected_spot():
    """A blob found in a crop (normalised like mediapipe: centre x / crop width) maps back to
    where it was drawn in the full image."""
    img = np.zeros((240, 320), np.uint8)
    cv2.circle(img, (201, 77), 4, 255, -1)
    win = crop_window(np.array([150.3, 40.8, 260.0, 130.2]), 320, 240)
    crop = img[win[1]:win[3], win[0]:win[2]].astype(float)
    ys, xs = np.nonzero(crop)
    norm = np.array([xs.mean() / crop.shape[1], ys.mean() / crop.shape[0]])
    np.testing.assert_allclose(crop_to_image(norm, win), [201, 77], atol=1e-9)


def test_hand_box_is_the_image_of_the_hand_sphere():
    """Peer: project points of a sphere's silhouette with calib.project; the box must just
    contain them (pinhole camera, small sphere)."""
    cam = look_at("c", (2.0, -3.0, 1.5), (0, 0, 1), (1000, 1000), (450, 450), 900, 900)
    centre = np.array([0.3, 0.2, 1.1])
    depth = world_to_cam(cam, centre)[2]
    box = hand_box_from_3d(project(cam, centre), depth, float(np.mean(cam.f)))
    # the sphere's rim as seen from the camera: circle of radius r perpendicular to the ray
    from detect.constants import HAND_RADIUS_M
    ray = centre - cam.T
    ray /= np.linalg.norm(ray)
    a = np.cross(ray, [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(ray, a)
    t = np.linspace(0, 2 * np.pi, 64)
    rim = centre + HAND_RADIUS_M * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
    uv = project(cam, rim)
    half_true = 0.5 * (uv.max(0) - uv.min(0))
    half = 0.5 * (box[2:] - box[:2])
    np.testing.assert_allclose(half, half_true, rtol=0.03)


def _person(rng, centre, n=layout.N, conf=0.9):
    kp = np.zeros((n, 3))
    kp[:, :2] = centre + rng.normal(0, 40, (n, 2))
    kp[:, 2] = conf
    return kp


def test_select_partner_follows_the_paper_rule():
    rng = np.random.default_rng(0)
    wearer = _person(rng, np.array([300.0, 300.0]))
    partner = _person(rng, np.array([600.0, 300.0]), conf=0.6)
    # a second, more confident partner detection offset by 3 px: wins where it survives
    better = partner.copy()
    better[:, :2] += 3.0
    better[:, 2] = 0.8
    # keypoint 5 of `better` sits on the wearer's keypoint 5: must be dropped there only
    better[5, :2] = wearer[5, :2] + 1.0
    # a confident spurious detection of keypoint 7 only, on the wearer's keypoint 7
    spurious = np.zeros_like(partner)
    spurious[7] = [*(wearer[7, :2] + 2.0), 0.95]
    cands = np.stack([partner, better, spurious])
    out, src = select_partner(cands, wearer, radius=8.0)
    assert src[5] == 0 and np.allclose(out[5], partner[5])
    others = np.delete(np.arange(layout.N), 5)
    assert np.all(src[others] == 1)
    np.testing.assert_allclose(out[others], better[others], atol=1e-4)


def test_select_partner_drops_the_wearer_found_again():
    rng = np.random.default_rng(1)
    wearer = _person(rng, np.array([300.0, 300.0]), conf=0.7)
    again = wearer.copy()
    again[:, 2] = 0.99
    again[:10, :2] += 60.0  # differs on a few keypoints: per-keypoint rule alone keeps those
    partner = _person(rng, np.array([650.0, 300.0]), conf=0.5)
    out, src = select_partner(np.stack([again, partner]), wearer, radius=10.0)
    assert np.all(src == 1)
    out2, src2 = select_partner(np.stack([again, partner]), wearer, radius=10.0,
                                drop_same_person=False, coherent=False)
    assert np.all(src2[:10] == 0)  # the literal rule would have taken them


def test_select_partner_with_nothing_left():
    wearer = np.zeros((layout.N, 3))
    out, src = select_partner(np.zeros((0, layout.N, 3)), wearer, 5.0)
    assert np.all(out == 0) and np.all(src == -1)
    low = np.zeros((1, layout.N, 3))
    low[..., 2] = 0.01
    out, src = select_partner(low, wearer, 5.0)
    assert np.all(src == -1)


def test_near_and_same_person_need_confident_pairs():
    ref = np.zeros((layout.N, 3))
    ref[:4] = [[10, 10, 1], [20, 20, 1], [30, 30, 1], [40, 40, 0]]
    c = np.zeros((1, layout.N, 3))
    c[0, :4] = [[11, 10, 1], [20, 21, 1], [90, 90, 1], [40, 40, 1]]
    near = near_same_type(c, ref, 3.0)[0]
    assert near[:4].tolist() == [True, True, False, False]
    assert is_same_person(c, ref, 3.0, frac=0.6)[0]  # 2 of 3 shared
    assert not is_same_person(c, ref, 3.0, frac=0.7)[0]


def test_anchor_error_median_over_shared_keypoints():
    anchors = np.full((layout.N, 2), np.nan)
    anchors[:5] = np.arange(10).reshape(5, 2)
    c = np.zeros((2, layout.N, 3))
    c[0, :5, :2] = anchors[:5] + [[3, 4], [0, 1], [0, 2], [0, 100], [0, 0]]
    c[0, :5, 2] = 1
    c[1, :2, 2] = 1
    err = anchor_error(c, anchors)
    assert err[0] == pytest.approx(2.0) and np.isnan(err[1])


def test_pick_hand_by_wrist_and_label():
    c = np.zeros((2, layout.N, 3))
    left, right = layout.HANDS
    c[0, right, :2] = [100, 100]
    c[0, right, 2] = 0.9
    c[1, left, :2] = [104, 100]  # mislabelled: a left hand 4 px away
    c[1, left, 2] = 0.9
    h = pick_hand(c, 1, np.array([101.0, 100]), 40.0, layout.HANDS)
    assert h is not None and h[0, 0] == 100
    h = pick_hand(c, 0, np.array([101.0, 100]), 40.0, layout.HANDS)
    assert h[0, 0] == 104
    # only a right hand, far away: rejected; near: taken despite the label
    assert pick_hand(c[:1], 0, np.array([300.0, 300]), 40.0, layout.HANDS) is None
    assert pick_hand(c[:1], 0, np.array([101.0, 100]), 40.0, layout.HANDS) is not None


def test_silhouette_covers_bones_and_markers_only():
    kp = np.zeros((layout.N, 3))
    i, j = layout.IDX["l_shoulder"], layout.IDX["l_elbow"]
    kp[i] = [50, 50, 1]
    kp[j] = [150, 50, 1]
    m = silhouette_mask((200, 300), kp, layout.EDGES, 5, points=np.array([[250.0, 150], [np.nan, 0]]))
    assert m[50, 100] and m[54, 100] and not m[58, 100]
    assert m[150, 250] and not m[150, 240]
    assert m.sum() < 0.05 * m.size
    img = np.full((200, 300, 3), 200, np.uint8)
    img[40:60, 40:160] = (10, 20, 30)
    out = paint_out(img, m)
    np.testing.assert_array_equal(border_colour(img), [200, 200, 200])
    np.testing.assert_array_equal(out[50, 100], [200, 200, 200])
    np.testing.assert_array_equal(out[42, 45], [10, 20, 30])  # outside the capsule


def test_wearer_hints_boxes_contain_projected_markers():
    cams = [look_at(f"c{k}", (3 * np.cos(a), 3 * np.sin(a), 1.4), (0, 0, 1), (900, 900),
                    (450, 450), 900, 900) for k, a in enumerate((0.3, 2.0))]
    rng = np.random.default_rng(3)
    names = ["LSHO", "RSHO", "LWRA", "LWRB", "LFIN", "RWRA", "RWRB", "RFIN", "LANK", "RANK"]
    base = np.array([[0.2, 0, 1.45], [-0.2, 0, 1.45], [0.3, 0, 0.95], [0.33, 0.02, 0.95],
                     [0.32, 0, 0.86], [-0.3, 0, 0.95], [-0.33, 0.02, 0.95], [-0.32, 0, 0.86],
                     [0.1, 0, 0.08], [-0.1, 0, 0.08]])
    X = base[None] + rng.normal(0, 0.01, (3, len(names), 3))
    X[1, 2] = np.nan  # LWRA missing in frame 1: no left wrist there
    h = wearer_hints(cams, X, [f"Sub:{n}" for n in names], body_margin=0.1)
    assert h.box.shape == (2, 3, 4) and h.hand_boxes.shape == (2, 3, 2, 4)
    for c, cam in enumerate(cams):
        uv = project(cam, X)
        ok = np.isfinite(uv[..., 0])
        for f in range(3):
            u = uv[f][ok[f]]
            assert np.all(u >= h.box[c, f, :2]) and np.all(u <= h.box[c, f, 2:])
        np.testing.assert_allclose(h.wrists[c, 0, 0], project(cam, X[0, 2:4].mean(0)))
        np.testing.assert_allclose(h.anchors[c, 0, layout.IDX["r_shoulder"]], project(cam, X[0, 1]))
        # the right hand box contains the right finger marker
        fin = project(cam, X[0, 7])
        assert np.all(fin >= h.hand_boxes[c, 0, 1, :2]) and np.all(fin <= h.hand_boxes[c, 0, 1, 2:])
    assert np.all(np.isnan(h.wrists[:, 1, 0])) and np.all(np.isnan(h.hand_boxes[:, 1, 0]))
    assert np.all(np.isfinite(h.hand_boxes[:, 1, 1]))


def test_metrics_errors_groups_and_swaps():
    from detect.metrics import (
        group_summary,
        identity_swaps,
        keypoint_errors,
        lr_flips,
        somebody_else,
    )

    rng = np.random.default_rng(5)
    truth = np.zeros((1, 2, 2, layout.N, 2))
    truth[..., 0, :, :] = rng.uniform(100, 300, (layout.N, 2))
    truth[..., 1, :, :] = rng.uniform(500, 700, (layout.N, 2))
    kp = np.zeros((1, 2, 2, layout.N, 3))
    kp[..., :2] = truth + [3.0, 4.0]  # 5 px everywhere
    kp[..., 2] = 0.9
    kp[0, 0, 0, 23:, 2] = 0  # no hands for the wearer in frame 0
    kp[0, 0, 1, 17:23, :2] += [6.0, 8.0]  # feet of the partner 15 px off in frame 0
    err = keypoint_errors(kp, truth)
    assert np.isnan(err[0, 0, 0, 30]) and err[0, 0, 1, 18] == pytest.approx(15.0)
    s = group_summary(err, np.ones(err.shape, bool))
    assert s["median_px_body"] == pytest.approx(5.0) and s["median_px_hands"] == pytest.approx(5.0)
    assert s["median_px_feet"] == pytest.approx(5.0)  # 6 of 24 foot points are 15 px
    assert s["detected_hands"] == pytest.approx(1 - 42 / (4 * 42))
    assert not identity_swaps(kp, truth).any() and not lr_flips(kp, truth).any()
    kp[0, 1] = kp[0, 1, ::-1]  # frame 1: people swapped
    sw = identity_swaps(kp, truth)
    assert sw.tolist() == [[False, True]]
    assert not lr_flips(kp, truth).any()
    kp[0, 1] = kp[0, 1, ::-1]
    kp[0, 0, 1] = kp[0, 0, 1, layout.FLIP]  # frame 0: the partner's left and right swapped
    assert not identity_swaps(kp, truth).any()
    assert lr_flips(kp, truth).tolist() == [[[False, True], [False, False]]]
    kp[0, 0, 1] = kp[0, 0, 1, layout.FLIP]
    assert not somebody_else(kp, truth).any()
    # frame 1: the partner's place holds somebody 300 px from both people (a bystander,
    # a little nearer the wearer): neither a swap nor a flip, somebody else
    kp[0, 1, 1, :, :2] = truth[0, 1, 0] + [0.0, 300.0]
    assert not identity_swaps(kp, truth).any() and not lr_flips(kp, truth).any()
    assert somebody_else(kp, truth).tolist() == [[[False, False], [False, True]]]
    # ... and 60 px from the wearer, nearer it than its own truth: a swap
    kp[0, 1, 1, :, :2] = truth[0, 1, 0] + [0.0, 60.0]
    assert identity_swaps(kp, truth).tolist() == [[False, True]]
    assert not somebody_else(kp, truth).any()


def test_select_partner_coherence_guard_keeps_out_a_bystander():
    rng = np.random.default_rng(4)
    wearer = _person(rng, np.array([300.0, 300.0]))
    partner = _person(rng, np.array([420.0, 300.0]), conf=0.7)
    partner[3, :2] = wearer[3, :2] + 2.0  # touching: dropped by the rule
    half = partner.copy()  # a partial second detection of the partner, more confident
    half[:30, 2] = 0.0
    half[30:, 2] = 0.9
    half[30:, :2] += 1.5
    bystander = _person(rng, np.array([900.0, 300.0]), conf=0.3)
    cands = np.stack([partner, half, bystander])
    out, src = select_partner(cands, wearer, radius=8.0)
    assert src[3] == -1  # literal rule would take the bystander's keypoint 3
    assert np.all(src[30:] == 1) and np.all(src[:30][np.arange(30) != 3] == 0)
    _, src_lit = select_partner(cands, wearer, radius=8.0, coherent=False)
    assert src_lit[3] == 2


def test_cross_view_outliers_flag_the_view_that_disagrees():
    from detect.multiview import CrossViewOptions, cross_view_outliers

    rng = np.random.default_rng(8)
    cams = [look_at(f"c{k}", (4 * np.cos(a), 4 * np.sin(a), 1.8), (0, 0, 1), (1100, 1100),
                    (450, 450), 900, 900, k=(-0.08, 0.05, 0.0))
            for k, a in enumerate(np.radians([40, 130, 220, 310]))]
    X = rng.uniform([-0.5, -0.5, 0.1], [0.5, 0.5, 1.8], (30, 3))
    kp = np.ones((4, 30, 3))
    kp[..., :2] = np.stack([project(c, X) for c in cams]) + rng.normal(0, 1.5, (4, 30, 2))
    kp[2, :10, :2] += [45.0, -30.0]  # view 2 wrong on points 0-9
    kp[1, 10:20, 2] = 0.0  # points 10-19: view 1 missing (3 views left)
    kp[3, 10:13, :2] += [0.0, 60.0]  # ... and view 3 wrong on 10-12
    kp[[0, 1], 20:25, 2] = 0.0  # points 20-24: two views only, one of them wrong
    kp[2, 20:25, :2] += 80.0
    out = cross_view_outliers(cams, kp, CrossViewOptions(max_error_px=10.0))
    assert out.shape == (4, 30)
    assert out[2, :10].all() and out[3, 10:13].all()
    expected = np.zeros((4, 30), bool)
    expected[2, :10] = expected[3, 10:13] = True
    # two views that disagree: nobody can tell which is wrong -> not judged
    assert not out[:, 20:25].any()
    np.testing.assert_array_equal(out, expected)


def test_cross_view_check_confirms_agreeing_views():
    from detect.multiview import cross_view_check

    cams = [look_at(f"c{k}", (4 * np.cos(a), 4 * np.sin(a), 1.8), (0, 0, 1), (1100, 1100),
                    (450, 450), 900, 900) for k, a in enumerate(np.radians([40, 130, 220]))]
    X = np.array([[0.1, 0.2, 1.0], [0.0, -0.3, 1.5]])
    kp = np.ones((3, 2, 3))
    kp[..., :2] = np.stack([project(c, X) for c in cams])
    kp[0, 1, :2] += 70.0  # point 1: view 0 wrong
    kp[2, 1, 2] = 0.0  # ... and view 2 missing: two views that disagree
    xv = cross_view_check(cams, kp)
    assert xv.confirmed[:, 0].all() and not xv.outlier[:, 0].any()
    assert not xv.confirmed[:, 1].any() and not xv.outlier[:, 1].any()


def _feet_in_views(cams, feet_xyz):
    """(C, F, 2, 65, 3) keypoints with only person 1's ankles and heels, from (F, 4, 3)."""
    from detect.sequence import FEET

    F = len(feet_xyz)
    kp = np.zeros((len(cams), F, 2, layout.N, 3))
    for c, cam in enumerate(cams):
        person = kp[c, :, 1]  # a view: (F, 65, 3)
        person[:, FEET, :2] = project(cam, feet_xyz.reshape(-1, 3)).reshape(F, 4, 2)
        person[:, FEET, 2] = 0.9
    return kp


def test_standing_far_finds_somebody_out_of_the_wearers_reach():
    """The partner slot's feet back-projected onto the floor: a person 3 m from the wearer is
    somebody else, the partner 0.8 m away is not, nor is a kicking partner whose raised
    foot's ray meets the floor far away (the nearest foot counts); no wearer marker in the
    frame, or feet below the confidence, judge nothing."""
    from detect.sequence import standing_far

    cams = [look_at(f"c{i}", (4.5 * np.cos(a), 4.5 * np.sin(a), 2.2), (0, 0, 0.9), (900, 900),
                    (960, 540), 1920, 1080) for i, a in enumerate((0.3, 2.0, 4.1))]
    markers = np.tile(np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.3]]), (4, 1, 1))  # (F, M, 3)
    markers[3] = np.nan  # frame 3: no wearer marker
    h = 0.07  # ankle height (K.FOOT_HEIGHT_M)
    feet = np.array([[[0.0, 0.8, h], [0.2, 0.8, h], [0.0, 0.75, h], [0.2, 0.75, h]],  # partner
                     [[-3.0, 0.0, h], [-2.8, 0.0, h], [-3.0, -0.05, h], [-2.8, -0.05, h]],  # 3 m
                     # kicking partner: the right ankle and heel 0.6 m up in front of the wearer
                     [[0.0, 0.8, h], [0.1, 0.3, 0.6], [0.0, 0.75, h], [0.1, 0.28, 0.6]],
                     [[-3.0, 0.0, h], [-2.8, 0.0, h], [-3.0, -0.05, h], [-2.8, -0.05, h]]])
    kp = _feet_in_views(cams, feet)
    far = standing_far(cams, kp, markers, ((0.0, 0.0, 1.0), 0.0))
    assert far.shape == (3, 4)
    assert not far[:, 0].any() and far[:, 1].all() and not far[:, 2].any()
    assert not far[:, 3].any()  # nothing to compare with
    near = standing_far(cams, kp, markers, ((0.0, 0.0, 1.0), 0.0), reach_m=3.5)
    assert not near.any()  # the reach is the knob
    weak = kp.copy()
    weak[..., 2] = 0.2
    assert not standing_far(cams, weak, markers, ((0.0, 0.0, 1.0), 0.0)).any()
