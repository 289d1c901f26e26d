"""The partner fit's L_sc and L_G = L_D + L_N terms as wired into the seam
(``fitting/partner_fit.py``: ``SelfCollisionTerm``, ``ContactTerm`` over ``FacetMatches``).

Each new Block's Jacobian (through ``Block.evaluate``, the path LM takes) is checked against
central differences in the unknowns x, and L_N's derivative of the unit normal against
differences in the corners; small LM loops over the real blocks (``Augmented`` on a graph with
no rows, re-detecting between rounds as ``PartnerSolver`` does, with a weak pull to the start
pose) check that each term does its job: an elbow folded into the own belly pushed out, a
hand's back brought onto the other's upper back with opposite normals. ``fit_partner`` reports
the terms it used.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from body.lbs import rest_state
from body.regions import region_map
from fitting import collision as C
from fitting import lm, skinned
from fitting import terms as T
from fitting.contact_signature import ContactAnnotation
from fitting.marker_graph import body_joints
from fitting.partner_fit import (
    CONTACT_MARGIN_M,
    Augmented,
    ContactTerm,
    FacetMatches,
    PartnerFitOptions,
    Posed,
    SelfCollisionTerm,
    _BodyCtx,
    contact_selection,
    extra_terms,
    normal_residual,
)
from geometry import face_centroids, face_normals, facet_distances

# the terms' behaviour, at fixed weights (not the defaults, which the bench tunes)
WEIGHTS = PartnerFitOptions(weights={"L_sc": 1e4, "L_D": 1e5, "L_N": 1e4}).weights

# ---------------------------------------------------------------------------- helpers


class _NoRows:
    """The residual-function interface of ``fitting.lm.solve`` with no rows of its own: the
    extra blocks alone (``Augmented`` appends them)."""

    compiled = False

    def __init__(self, n: int):
        self.n_x, self.n_p, self.n_r = n, 0, 0
        self._flat = np.zeros(0, np.int64)

    def __call__(self, x, p):
        return np.zeros(0), np.zeros(0)


def _solve(body, terms_, x0, w_s=10.0, rounds=6, iters=15):
    """LM rounds over the blocks of ``terms_`` (re-detected before each round, weights of
    ``PartnerFitOptions``) plus ``w_s |x - x0|^2`` (L_s toward the start pose)."""
    x = np.array(x0, float)
    quad = T.quadratic_L_s(len(x), np.arange(len(x)), x0, w_s)
    for _ in range(rounds):
        posed = Posed(body, x, 0)
        blocks = [b for t in terms_ for b in t(posed)]
        if not blocks:
            break
        fun = Augmented(_NoRows(len(x)), blocks, body)
        scale = np.concatenate([np.full(m, np.sqrt(WEIGHTS[b.name]))
                                for b, m in zip(blocks, fun.sizes, strict=True)])
        x = lm.solve(fun, np.zeros(0), x, row_scale=scale, quad=quad,
                     opts=lm.LMOptions(max_iters=iters)).x
    return x


def _check_block_jacobian(body, block, x, h=1e-6, tol=1e-6):
    """Block.evaluate's J against central differences of its r in x (targets fixed)."""
    r, J = block.evaluate(body.skel, body.u, x, body.sub)
    assert r.shape == (J.shape[0],) and J.shape[1] == len(x) and np.isfinite(J).all()
    Jfd = np.stack([(block.evaluate(body.skel, body.u, x + h * e, body.sub)[0]
                     - block.evaluate(body.skel, body.u, x - h * e, body.sub)[0]) / (2 * h)
                    for e in np.eye(len(x))], axis=1)
    err = np.abs(J - Jfd).max()
    assert err < tol * max(1.0, np.abs(J).max()), err
    assert np.abs(J).max() > 1e-3  # not trivially zero
    return J


def _rot_a_to_b(a, b):
    """The smallest rotation taking unit vector a to unit vector b (not opposite)."""
    v, c = np.cross(a, b), float(a @ b)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


@pytest.fixture(scope="module")
def body(anny):
    skel = skinned.fit_skeleton(anny, body_joints(anny))
    return _BodyCtx(anny, np.zeros(0), rest_state(anny, np.zeros(0)), skel)


@pytest.fixture(scope="module")
def proxy(anny):
    return C.ProxyMesh.from_model(anny, PartnerFitOptions().proxy_vertices)


def _joint(skel, name):
    q = list(skel.names).index(name)
    return slice(6 + 3 * (q - 1), 6 + 3 * q)


@pytest.fixture(scope="module")
def folded(body):
    """The left arm folded across the front, the forearm ~3 cm deep in the own belly."""
    x = np.zeros(body.skel.n)
    x[_joint(body.skel, "upperarm01.L")] = [0.0, 0.5, 0.0]
    x[_joint(body.skel, "lowerarm01.L")] = [0.0, 0.0, -1.5]
    return x


@pytest.fixture(scope="module")
def touch(anny, body):
    """The partner at rest (x = 0) with the back of its right hand on the wearer's upper back:
    the wearer is Anny's template turned and moved so its central ``l_upper_back`` facet lies
    on the partner's central ``r_hand_back`` facet, normals opposite. Annotated: that pair and
    a few partner facets around it with their nearest wearer facets. ``x0``: the partner 4 cm
    back from the contact, its wrist turned ~0.3 rad."""
    rm = region_map(anny)
    F = np.asarray(anny.faces)
    x_true = np.zeros(body.skel.n)
    VP = body.posed_vertices(x_true)
    V0 = np.asarray(anny.v_template)
    rp, rw = rm.names.index("r_hand_back"), rm.names.index("l_upper_back")
    cp, n_p = face_centroids(VP, F), face_normals(VP, F)
    cw, n_w = face_centroids(V0, F), face_normals(V0, F)
    fpr, fwr = rm.faces_of(rp), rm.faces_of(rw)
    fp0 = fpr[np.argmin(np.linalg.norm(cp[fpr] - cp[fpr].mean(0), axis=1))]
    fw0 = fwr[np.argmin(np.linalg.norm(cw[fwr] - cw[fwr].mean(0), axis=1))]
    R = _rot_a_to_b(n_w[fw0], -n_p[fp0])
    VW = V0 @ R.T + (cp[fp0] - R @ cw[fw0])
    near = fpr[np.linalg.norm(cp[fpr] - cp[fp0], axis=1) < 0.02]
    pick = np.unique(np.concatenate([[fp0], near[:: max(1, len(near) // 4)][:4]]))
    fd = facet_distances(VP, F, pick, VW, F, fwr)
    pairs = np.stack([fd.a_nearest, pick], 1).astype(np.int64)
    pairs[pick == fp0, 0] = fw0
    ann = ContactAnnotation("test.json", "Touch 1", "anny", (10, 20), 15, np.array([[rw, rp]]),
                            pairs, np.zeros(len(pairs), np.int64), (("l_upper_back", "r_hand_back"),))
    one = ContactAnnotation("test.json", "Touch 1", "anny", (10, 20), 15, np.array([[rw, rp]]),
                            np.array([[fw0, fp0]]), np.zeros(1, np.int64), ann.region_names)
    x0 = x_true.copy()
    x0[3:6] -= 0.04 * n_p[fp0]
    x0[_joint(body.skel, "wrist.R")] += [0.25, 0.0, 0.2]
    return SimpleNamespace(VW=VW, F=F, rm=rm, rw=rw, rp=rp, fw0=fw0, fp0=fp0, pairs=pairs, ann=ann,
                           one=one, x0=x0, x_true=x_true, R=R)


def _contact_terms(touch, names=("L_D", "L_N"), frames=(15,), ann=None):
    sel, modes = contact_selection(touch.ann if ann is None else ann, touch.rm)
    assert modes == ["annotated"]
    m = FacetMatches(touch.ann if ann is None else ann, np.array(frames), [touch.VW] * len(frames),
                     touch.F, sel)
    return [ContactTerm(n, m) for n in names]


def _contact_figures(body, touch, x):
    """(smallest wearer-region to partner-region facet distance (m), (P,) 1 + n1.n2 of the
    annotated pairs, that of the central pair)."""
    V = body.posed_vertices(x)
    d = facet_distances(touch.VW, touch.F, touch.rm.faces_of(touch.rw), V, touch.F,
                        touch.rm.faces_of(touch.rp)).a_to_b.min()
    phi = 1 + (face_normals(touch.VW, touch.F)[touch.pairs[:, 0]]
               * face_normals(V, touch.F)[touch.pairs[:, 1]]).sum(1)
    return d, phi, float(phi[touch.pairs[:, 1] == touch.fp0][0])


# ---------------------------------------------------------------------------- Jacobians


def test_L_N_residual_derivative_in_the_corners():
    rng = np.random.default_rng(0)
    P = 5
    fixed = rng.normal(size=(P, 3, 3))
    w = rng.uniform(0.5, 2.0, P)
    res = normal_residual(fixed, w)
    pos = rng.normal(size=(3 * P, 3))
    r, dr, point = res(pos)
    assert r.shape == (P,) and dr.shape == (P, 3, 3) and point.shape == (P, 3)
    np.testing.assert_allclose(r, T.L_N(fixed, pos.reshape(P, 3, 3), w), rtol=1e-12)
    h = 1e-6
    for i in range(P):
        for k in range(3):
            for a in range(3):
                e = np.zeros_like(pos)
                e[point[i, k], a] = h
                fd = (res(pos + e)[0][i] - res(pos - e)[0][i]) / (2 * h)
                assert abs(fd - dr[i, k, a]) < 1e-7, (i, k, a, fd, dr[i, k, a])
    # rows depend on their own triangle only
    e = np.zeros_like(pos)
    e[point[0, 1], 2] = 1e-3
    assert np.all(res(pos + e)[0][1:] == r[1:])


def test_L_sc_block_jacobian(body, proxy, folded):
    blocks = SelfCollisionTerm(proxy)(Posed(body, folded, 0))
    assert len(blocks) == 1 and blocks[0].name == "L_sc" and blocks[0].points > 5
    _check_block_jacobian(body, blocks[0], folded)


def test_L_D_and_L_N_block_jacobians(body, touch):
    posed = Posed(body, touch.x0, 0)
    blocks = [b for t in _contact_terms(touch) for b in t(posed)]
    assert [b.name for b in blocks] == ["L_D", "L_N"]
    # both directions of the match: every selected facet of either side once
    P = len(np.unique(touch.pairs[:, 0])) + len(np.unique(touch.pairs[:, 1]))
    assert blocks[0].points == P and blocks[1].points == 3 * P
    for b in blocks:
        _check_block_jacobian(body, b, touch.x0)
    # L_D: weights 1/P of the region pair: |r|^2 is the mean squared centre gap
    r, _ = blocks[0].evaluate(body.skel, body.u, touch.x0, body.sub)
    gaps = np.linalg.norm(r.reshape(-1, 3), axis=1) * np.sqrt(blocks[0].points)
    assert 0.02 < np.sqrt(r @ r) < 0.08 and gaps.max() < 0.1


# ---------------------------------------------------------------------------- L_sc


def test_L_sc_pushes_a_folded_elbow_out_of_the_belly(body, proxy, folded):
    rmap = region_map(body.model)
    P0 = proxy.points(body.posed_vertices(folded))
    c0 = C.self_collisions(proxy, P0)
    names = {rmap.names[r] for r in proxy.vertex_region[c0.index]}
    assert c0.deepest > 0.02 and names & {"l_forearm_front", "l_forearm_back", "l_elbow_inner"}
    x = _solve(body, [SelfCollisionTerm(proxy)], folded)
    c = C.self_collisions(proxy, proxy.points(body.posed_vertices(x)))
    assert c.deepest < 0.3 * c0.deepest and c.deepest < 2e-3, (c0.deepest, c.deepest)
    assert np.linalg.norm(x - folded) < 0.5  # pushed out, not thrown away
    # at rest nothing self-collides: no block
    assert SelfCollisionTerm(proxy)(Posed(body, np.zeros(body.skel.n), 0)) == []


# ---------------------------------------------------------------------------- L_D, L_N


def test_L_G_brings_the_annotated_facets_together_with_opposite_normals(body, touch):
    d0, phi0, c0 = _contact_figures(body, touch, touch.x0)
    assert 0.03 < d0 < 0.06 and c0 > 0.03  # 4-5 cm apart, the central pair ~17 degrees off
    x = _solve(body, _contact_terms(touch), touch.x0, w_s=1.0, rounds=4)
    d, phi, c = _contact_figures(body, touch, x)
    assert d < 2e-3, d  # touching
    assert c < 0.2 * c0 and phi.mean() < 0.3 * phi0.mean(), (c, phi, phi0)  # facing each other


def test_L_N_turns_a_single_matched_pair_opposite(body, touch):
    """One annotated facet pair: L_D pulls its centres together but leaves the facet turned
    (one point fixes no orientation; the pull to the start pose keeps the wrist's turn);
    with L_N the normals end opposite."""
    c0 = _contact_figures(body, touch, touch.x0)[2]
    x_d = _solve(body, _contact_terms(touch, ("L_D",), ann=touch.one), touch.x0, w_s=1.0, rounds=4)
    x_g = _solve(body, _contact_terms(touch, ann=touch.one), touch.x0, w_s=1.0, rounds=4)
    V_d, V_g = body.posed_vertices(x_d), body.posed_vertices(x_g)
    for V in (V_d, V_g):
        gap = np.linalg.norm(face_centroids(V, touch.F)[touch.fp0]
                             - face_centroids(touch.VW, touch.F)[touch.fw0])
        assert abs(gap - CONTACT_MARGIN_M) < 1e-3, gap  # touching: the margin apart
    c_d, c_g = _contact_figures(body, touch, x_d)[2], _contact_figures(body, touch, x_g)[2]
    assert c_d > 0.5 * c0 and c_g < 1e-3, (c0, c_d, c_g)


def test_contact_terms_only_in_the_interval_and_with_the_wearer(body, touch):
    sel, _ = contact_selection(touch.ann, touch.rm)
    WV = [touch.VW, None, touch.VW]
    m = FacetMatches(touch.ann, np.array([5, 15, 20]), WV, touch.F, sel)  # video frames
    assert [m.active(f) for f in range(3)] == [False, False, True]
    terms_ = [ContactTerm(n, m) for n in ("L_D", "L_N")]
    for f, want in ((0, 0), (1, 0), (2, 2)):
        posed = Posed(body, touch.x0, f)
        assert len([b for t in terms_ for b in t(posed)]) == want
    # the two halves share one match per posed state
    posed = Posed(body, touch.x0, 2)
    assert m(posed) is m(posed)


def test_selection_modes(anny, touch):
    rm = touch.rm
    sel, modes = contact_selection(touch.ann, rm, "all")
    assert modes == ["all"] and len(sel[0][0]) == len(rm.faces_of(touch.rw))
    sel, modes = contact_selection(touch.ann, rm, "uniform", 7, np.random.default_rng(1))
    assert modes == ["uniform"] and len(sel[0][0]) == len(sel[0][1]) == 7
    # a pair without annotated facets falls back to all facets of both regions
    bare = ContactAnnotation("t", "A", "anny", (0, 1), 0, np.array([[touch.rw, touch.rp]]),
                             np.zeros((0, 2), np.int64), np.zeros(0, np.int64), (("a", "b"),))
    sel, modes = contact_selection(bare, rm)
    assert modes == ["all"] and len(sel[0][1]) == len(rm.faces_of(touch.rp))


# ---------------------------------------------------------------------------- options, wiring


def test_options_accept_the_new_weights_and_reject_bad_ones():
    o = PartnerFitOptions(weights={"L_sc": 1e3, "L_D": 1e4, "L_N": 2e3})
    assert o.weights["L_sc"] == 1e3 and o.weights["L_D"] == 1e4 and o.weights["L_N"] == 2e3
    d = PartnerFitOptions().weights
    assert d["L_sc"] > 0 and d["L_D"] > 0 and d["L_N"] > 0
    with pytest.raises(ValueError, match="L_foo: unknown term"):
        PartnerFitOptions(weights={"L_foo": 1.0})
    with pytest.raises(ValueError, match="weights.L_D: must be >= 0"):
        PartnerFitOptions(weights={"L_D": -1.0})
    with pytest.raises(ValueError, match="contact_selection"):
        PartnerFitOptions(contact_selection="some")
    with pytest.raises(ValueError, match="contact_facets_n"):
        PartnerFitOptions(contact_facets_n=0)


def test_extra_terms_builds_what_the_weights_and_inputs_allow(anny, touch):
    frames = np.array([5, 15])
    WV = [touch.VW, touch.VW]
    extra, info = extra_terms(anny, frames, WV, touch.ann, (np.array([0, 0, 1.0]), -2.0))
    assert [t.name for t in extra] == ["L_gp", "L_ic", "L_sc", "L_D", "L_N"]
    assert info["terms"] == ["L_D", "L_N"] and info["selection"] == "annotated"
    assert info["frames"] == 1
    assert info["pairs"] == [{"regions": ["l_upper_back", "r_hand_back"], "selection": "annotated",
                              "facets": [len(np.unique(touch.pairs[:, 0])), len(touch.pairs)]}]
    extra, info = extra_terms(anny, frames, None, touch.ann)
    assert [t.name for t in extra] == ["L_sc"] and info["why_not"] == "no wearer fit"
    extra, info = extra_terms(anny, frames, WV, None)
    assert [t.name for t in extra] == ["L_ic", "L_sc"] and info["why_not"] == "no contact annotation"
    off = PartnerFitOptions(weights={"L_sc": 0.0, "L_N": 0.0})
    extra, info = extra_terms(anny, frames, WV, touch.ann, opts=off)
    assert [t.name for t in extra] == ["L_ic", "L_D"] and info["terms"] == ["L_D"]


def _touch_scene(anny, body, touch, X):
    """Video frames 5, 10, 15 of ``touch``'s wearer, four views of the partner at unknowns
    ``X (3, n)`` (``touch.x_true``'s pose, any translation) projected as clean keypoints:
    ``(frames, cams, Keypoints2D, the wearer's BodyFit, the partner's ShapeFit)``."""
    from artifacts import BodyFit
    from artifacts.keypoints import Keypoints2D
    from body import forward
    from body.joints import regressor
    from calib import look_at, project
    from fitting.marker_graph import template_placement, to_shape_fit

    frames = np.array([5, 10, 15])
    Fn = len(frames)
    cams = [look_at(f"cam{k}", [4 * np.cos(a), 4 * np.sin(a), 1.0], [0, 0, 0.0], (1100, 1100),
                    (450, 450), 900, 900) for k, a in enumerate([0.5, 2.1, 3.7, 5.3])]
    J0 = forward(anny, np.zeros(0), np.zeros((1, anny.num_joints, 3)), np.eye(3)[None],
                 np.zeros((1, 3))).joints[0]
    R65 = regressor(anny, "kp65")
    kp = np.zeros((4, Fn, 2, 65, 3))
    for f in range(Fn):
        kp3 = R65 @ np.concatenate([body.posed_vertices(X[f]),
                                    J0 + (X[f, 3:6] - touch.x_true[3:6])])
        for c, cam in enumerate(cams):
            kp[c, f, 1, :, :2] = project(cam, kp3)
            kp[c, f, 1, :, 2] = 0.9
    keypoints = Keypoints2D(kp=kp.astype(np.float32), boxes=np.full((4, Fn, 2, 4), np.nan, np.float32),
                            hand_boxes=np.full((4, Fn, 2, 2, 4), np.nan, np.float32), frames=frames,
                            wearer_retry=np.zeros((4, Fn), bool), partner_mode=np.ones((4, Fn), np.int8),
                            cross_view_outlier=np.zeros((4, Fn, 2, 65), bool),
                            conf_raw=kp[..., 2].astype(np.float32),
                            cameras=np.array([c.name for c in cams]))
    R = np.repeat(touch.R[None], Fn, 0)
    pose = np.zeros((Fn, anny.num_joints, 3))
    T0 = forward(anny, np.zeros(0), pose[:1], R[:1], np.zeros((1, 3))).vertices[0, 0]
    wearer = BodyFit(body_pose=pose, global_orient=R, transl=np.tile(touch.VW[0] - T0, (Fn, 1)),
                     betas=np.zeros(0), frames=frames, valid=np.ones(Fn, bool),
                     invalid_reason=np.zeros(Fn, np.int8))
    shape = to_shape_fit(np.zeros(0), template_placement(anny, "plug-in-gait"), "given", "given")
    return frames, cams, keypoints, wearer, shape


def test_fit_partner_reports_the_contact_terms(anny, body, touch):
    """fit_partner on projections of the touching partner (4 views, 3 frames, the contact
    interval covering video frames 10..20 = fit frames 1, 2): L_sc, L_D and L_N are in the
    report's terms, active (with points and cost) in the contact frames only, and the hand
    stays on the back."""
    from body import forward
    from fitting.partner_fit import fit_partner

    Fn = 3
    frames, cams, keypoints, wearer, shape = _touch_scene(anny, body, touch,
                                                          np.repeat(touch.x_true[None], Fn, 0))
    fit, rep = fit_partner(anny, shape, keypoints, cams, wearer, touch.ann,
                           opts=PartnerFitOptions(use_hands=False))
    names = rep["terms"]
    assert names == ["L_2d", "L_theta", "L_s", "L_ic", "L_sc", "L_D", "L_N"], names
    per = rep["per_frame"]
    for n in ("L_D", "L_N"):
        j = names.index(n)
        assert per["term_active"][:, j].tolist() == [False, True, True]
        assert np.all(per["term_points"][1:, j] > 0) and per["term_points"][0, j] == 0
        assert np.all(per["term_cost"][1:, j] > 0) and per["term_cost"][0, j] == 0
    assert rep["frames_with"]["L_D"] == 2 and rep["contact_terms"]["frames"] == 2
    assert rep["contact_terms"]["pairs"][0]["regions"] == ["l_upper_back", "r_hand_back"]
    assert fit.valid.all(), rep["frames_not_valid"]
    est = forward(anny, np.zeros(0), fit.body_pose, fit.global_orient, fit.transl).vertices
    d = [facet_distances(touch.VW, touch.F, touch.rm.faces_of(touch.rw), est[f], touch.F,
                         touch.rm.faces_of(touch.rp)).a_to_b.min() for f in range(Fn)]
    assert max(d[1:]) < 5e-3, d


def test_a_contact_frame_the_images_hold_apart_is_fitted_without_L_G(anny, body, touch):
    """The annotation says the hand touches the back in video frames 10..20, but in frame 15
    the detections are those of the partner 15 cm back (the annotated interval holds a frame
    whose regions are apart, as the studio's Hug does): with L_G, the fit ends there with the
    regions apart by more than ``contact_release_m``, so that frame is fitted again without it
    (``contact_terms.frames_released``, L_D / L_N not active there, a warning that names it)
    and lands where the images put it; frame 10, which touches, keeps L_G. With the release
    off, L_G pulls frame 15's hand toward the back, off its detections. (L_D at 1e2: one region pair, the hand, which
    the arm can reach at the cost of two or three saturated keypoints, is pulled all the way
    at the default weight; the studio's Hug, four pairs over the body, is held off at it.)"""
    from body import forward
    from fitting.partner_fit import contact_warnings, fit_partner

    Fn = 3
    n_p = face_normals(body.posed_vertices(touch.x_true), touch.F)[touch.fp0]
    X = np.repeat(touch.x_true[None], Fn, 0)
    X[2, 3:6] -= 0.15 * n_p  # frame 15: 15 cm back along the hand's normal
    frames, cams, keypoints, wearer, shape = _touch_scene(anny, body, touch, X)
    gaps, reps = {}, {}
    for release in (PartnerFitOptions().contact_release_m, 0.0):
        fit, rep = fit_partner(anny, shape, keypoints, cams, wearer, touch.ann,
                               opts=PartnerFitOptions(use_hands=False, contact_release_m=release,
                                                      weights={"L_D": 1e2, "L_N": 10.0}))
        est = forward(anny, np.zeros(0), fit.body_pose, fit.global_orient, fit.transl).vertices
        gaps[release] = [facet_distances(touch.VW, touch.F, touch.rm.faces_of(touch.rw), est[f],
                                         touch.F, touch.rm.faces_of(touch.rp)).a_to_b.min()
                         for f in range(Fn)]
        reps[release] = rep
    on, off = PartnerFitOptions().contact_release_m, 0.0
    assert reps[on]["contact_terms"]["frames_released"] == [15]
    assert reps[off]["contact_terms"]["frames_released"] == []
    assert reps[on]["contact_terms"]["released_gap_m"][0] > on
    (w,) = contact_warnings(reps[on])  # the lab is told, with the frames
    assert "1 of the 2 fitted frames" in w and "video frames 15" in w, w
    assert contact_warnings(reps[off]) == []
    j = reps[on]["terms"].index("L_D")
    assert reps[on]["per_frame"]["term_active"][:, j].tolist() == [False, True, False]
    true_gap = facet_distances(touch.VW, touch.F, touch.rm.faces_of(touch.rw),
                               body.posed_vertices(X[2]), touch.F,
                               touch.rm.faces_of(touch.rp)).a_to_b.min()
    assert abs(gaps[on][2] - true_gap) < 0.01, (gaps[on], true_gap)
    assert gaps[on][1] < 5e-3 and gaps[off][1] < 5e-3, (gaps[on], gaps[off])
    assert gaps[off][2] < true_gap - 0.02, (gaps[off], true_gap)  # pulled off the images
