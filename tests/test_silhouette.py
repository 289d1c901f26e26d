"""The silhouette term ``L_sil`` (``fitting/silhouette.py``) and the masks it reads
(``detect/silhouette.py``, stage ``silhouettes``, recipe ``clean_plates``).

- the term's Jacobian (through ``Block.evaluate``, the path LM takes; lens distortion on)
  against central differences in the unknowns, both parts present (points outside the people
  mask, partner pixels not covered);
- masks from a clean plate recover a person rendered in the lab room through a camera's look
  (gain, vignetting, noise, JPEG): IoU against the renderer's ids, the wearer rendered out;
- a synthetic fit whose left arm has no keypoints: the silhouette brings the arm where the
  keypoints alone leave it;
- a missing clean plate is an error naming the recipe field and the file; an unreadable one
  names the file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from artifacts.silhouettes import Silhouettes, pack

W_IMG, H_IMG = 480, 480


def _cams(k=(0.0, 0.0, 0.0)):
    from calib import look_at

    return [look_at(f"cam{i}", [3.5 * np.cos(a), 3.5 * np.sin(a), 1.6], [0, 0, 0.95], (430, 430),
                    (240, 240), W_IMG, H_IMG, k=k) for i, a in enumerate([0.4, 2.0, 3.6, 5.2])]


def _masks(cams, partner_V, faces, frames, wearer_V=None, scale=0.5):
    """Silhouettes of posed meshes rendered with ``detect.silhouette.body_mask``."""
    from detect.silhouette import body_mask, mask_size

    h, w = mask_size(W_IMG, H_IMG, scale)
    F, C = len(frames), len(cams)
    B = (h * w + 7) // 8
    ppl, par = np.zeros((F, C, B), np.uint8), np.zeros((F, C, B), np.uint8)
    for i in range(F):
        for c, cam in enumerate(cams):
            q = body_mask(cam, partner_V[i], faces, (h, w), scale)
            m = q | (body_mask(cam, wearer_V[i], faces, (h, w), scale) if wearer_V is not None
                     else False)
            ppl[i, c], par[i, c] = pack(m), pack(q)
    return Silhouettes(frames=np.asarray(frames, np.int64), cameras=np.array([c.name for c in cams]),
                       scale=np.float64(scale), size=np.array([h, w]), people=ppl, partner=par,
                       people_fraction=np.full((F, C), 0.1), partner_fraction=np.full((F, C), 0.1),
                       wearer_cover=np.full((F, C), np.nan),
                       usable=np.ones((F, C), bool), source=np.zeros(C, np.int8))


def _joint(skel, name):
    q = list(skel.names).index(name)
    return slice(6 + 3 * (q - 1), 6 + 3 * q)


@pytest.fixture(scope="module")
def arm(anny):
    """The partner (Anny's template, body joints) with the left arm raised sideways and the
    elbow bent: truth ``x``, its mesh, and the same body with the arm hanging (``x0``)."""
    from body.lbs import rest_state
    from fitting import skinned
    from fitting.marker_graph import body_joints
    from fitting.partner_fit import _BodyCtx

    skel = skinned.fit_skeleton(anny, body_joints(anny))
    body = _BodyCtx(anny, np.zeros(0), rest_state(anny, np.zeros(0)), skel)
    x = np.zeros(skel.n)
    x[_joint(skel, "upperarm01.L")] = [0.0, 0.0, 0.9]
    x[_joint(skel, "lowerarm01.L")] = [0.0, 0.0, 0.8]
    return body, x, body.posed_vertices(x)


# ---------------------------------------------------------------------------- Jacobian


def test_L_sil_block_jacobian_matches_finite_differences(anny, arm):
    from fitting.partner_fit import PartnerFitOptions, Posed
    from fitting.silhouette import SilhouetteInput, silhouette_term

    body, x_true, V = arm
    cams = _cams(k=(-0.12, 0.05, 0.0))  # barrel distortion: the chain rule through it
    masks = _masks(cams, [V], anny.faces, [0])
    term = silhouette_term(anny, np.array([0]), SilhouetteInput(masks, cams),
                           PartnerFitOptions().proxy_vertices)
    x = np.zeros(body.skel.n)  # the arm hanging, the body 6 cm aside: both parts offend
    x[3:6] = [0.06, 0.0, 0.0]
    blocks = term(Posed(body, x, 0))
    assert len(blocks) == 4 and all(b.name == "L_sil" for b in blocks)
    h = 1e-6
    for b in blocks:
        r, J = b.evaluate(body.skel, body.u, x, body.sub)
        assert r.shape == (J.shape[0],) and len(r) >= 20 and np.isfinite(J).all()
        Jfd = np.stack([(b.evaluate(body.skel, body.u, x + h * e, body.sub)[0]
                         - b.evaluate(body.skel, body.u, x - h * e, body.sub)[0]) / (2 * h)
                        for e in np.eye(len(x))], axis=1)
        assert np.abs(J - Jfd).max() < 1e-6 * max(1.0, np.abs(J).max()), np.abs(J - Jfd).max()
        assert np.abs(J).max() > 1e-3
    # at the truth nothing offends but the rasterisation's sub-pixel edges
    r_true = np.concatenate([b.evaluate(body.skel, body.u, x_true, body.sub)[0]
                             for b in term(Posed(body, x_true, 0))] or [np.zeros(0)])
    r_off = np.concatenate([b.evaluate(body.skel, body.u, x, body.sub)[0] for b in blocks])
    assert r_true @ r_true < 0.02 * (r_off @ r_off)


# ---------------------------------------------------------------------------- masks


@pytest.mark.slow
def test_masks_from_a_clean_plate_recover_rendered_people(anny, arm):
    """A lab room (textured, furniture) seen through each camera's look (gain, vignetting,
    noise, JPEG): the people mask from the clean plate matches the renderer's ids (IoU > 0.92
    per view; measured 0.94-0.95, the outline half a mask pixel wide; the gap between the two
    people stays open), and the partner's mask, with the wearer rendered out from its mesh,
    matches the partner's ids; the rasterised mesh (``body_mask``) matches the renderer's."""
    from detect.silhouette import SilhouetteOptions, body_mask, silhouettes
    from drawing.render import PersonMesh, Renderer
    from studio.lab import Developer, camera_looks, lab_room
    from studio.rig import make_rig

    _, _, V = arm
    V = V - [0.0, 0.0, V[:, 2].min()]  # standing on the floor
    rig = make_rig(np.random.default_rng([3, 1]))
    room = lab_room(np.random.default_rng(7), rig)
    looks = camera_looks(np.random.default_rng(0), len(rig))
    dev = Developer(looks, (rig[0].width, rig[0].height), np.random.default_rng(1))
    faces = np.asarray(anny.faces)
    partner = V + [0.35, 0.0, 0.0]
    wearer = V + [-0.35, 0.05, 0.0]
    red, blue = np.array([180, 50, 40], np.uint8), np.array([40, 60, 170], np.uint8)
    people = [PersonMesh(partner, faces, np.tile(red, (len(V), 1))),
              PersonMesh(wearer, faces, np.tile(blue, (len(V), 1)))]
    with Renderer(rig, room=room) as r:
        plate = r.render_room()
        rgb = r.render(people)
        ids = r.render_ids(people)
        ids_p = r.render_ids(people[:1])
    plates = {c: [dev(plate[c], c) for _ in range(3)] for c in range(len(rig))}
    frame = [dev(rgb[c], c) for c in range(len(rig))]
    opts = SilhouetteOptions()
    s, rep = silhouettes(lambda c, f: frame[c], rig, np.array([0]), plates, [wearer], faces, opts)
    assert rep["views_usable"] == len(rig)
    import cv2

    h, w = s.shape
    for c in range(len(rig)):
        def small(m):  # pixels at least half covered
            return cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5

        def iou(a, b):
            return (a & b).sum() / (a | b).sum()

        truth_all, truth_p = small(ids[c] >= 0), small(ids[c] == 0)
        m, q = s.mask(0, c, "people"), s.mask(0, c, "partner")
        assert iou(m, truth_all) > 0.92, (c, iou(m, truth_all))
        # the partner's visible pixels: what the wearer's dilated mask leaves of them
        assert iou(q, truth_p) > 0.8, (c, iou(q, truth_p))
        assert iou(body_mask(rig[c], partner, faces, (h, w), 0.5), small(ids_p[c] == 0)) > 0.9
        assert (q & small(ids[c] == 1)).sum() < 0.05 * q.sum()  # little of the wearer is left


# ---------------------------------------------------------------------------- the fit


@pytest.mark.slow
def test_silhouette_brings_an_arm_without_keypoints_where_it_is(anny, arm):
    """The partner's left arm raised sideways, its elbow and wrist keypoints missing in every
    view: the keypoints alone leave the arm where the prior puts it; L_sil, from the masks,
    raises it."""
    from artifacts.keypoints import Keypoints2D
    from body import forward
    from body.joints import regressor
    from calib import project
    from fitting.marker_fit import unpack
    from fitting.marker_graph import template_placement, to_shape_fit
    from fitting.partner_fit import PartnerFitOptions, fit_partner
    from formats.skeletons import KP65

    body, x_true, V = arm
    cams = _cams()
    F = 4  # the same pose held: each frame starts from the last (the arm rises over the frames)
    R = regressor(anny, "kp65")
    pose, Rg, T = unpack(body.skel, anny.num_joints, np.stack([x_true] * F))
    truth = forward(anny, np.zeros(0), pose, Rg, T)
    kp3 = np.stack([R @ np.concatenate([truth.vertices[f], truth.joints[f]]) for f in range(F)])
    drop = [KP65.index(n) for n in KP65 if n in ("l_elbow", "l_wrist")]
    kp = np.zeros((4, F, 2, 65, 3), np.float32)
    for c, cam in enumerate(cams):
        kp[c, :, 1, :, :2] = project(cam, kp3)
        kp[c, :, 1, :, 2] = 0.9
    kp[:, :, 1, drop, 2] = 0.0
    keypoints = Keypoints2D(kp=kp, boxes=np.full((4, F, 2, 4), np.nan, np.float32),
                            hand_boxes=np.full((4, F, 2, 2, 4), np.nan, np.float32),
                            frames=np.arange(F, dtype=np.int64), wearer_retry=np.zeros((4, F), bool),
                            partner_mode=np.ones((4, F), np.int8),
                            cross_view_outlier=np.zeros((4, F, 2, 65), bool),
                            conf_raw=kp[..., 2].copy(), cameras=np.array([c.name for c in cams]))
    shape = to_shape_fit(np.zeros(0), template_placement(anny, "plug-in-gait"), "given", "given")
    masks = _masks(cams, truth.vertices, anny.faces, np.arange(F))
    arm_j = [list(anny.joint_names).index(n) for n in ("lowerarm01.L", "wrist.L")]

    def arm_err_mm(**kw):
        fit, rep = fit_partner(anny, shape, keypoints, cams,
                               opts=PartnerFitOptions(use_hands=False, **kw.pop("opts", {})), **kw)
        est = forward(anny, np.zeros(0), fit.body_pose, fit.global_orient, fit.transl)
        e = np.linalg.norm(est.joints[:, arm_j] - truth.joints[:, arm_j], axis=-1) * 1000
        return e.mean(1), rep

    without, rep0 = arm_err_mm(opts={"weights": {"L_sil": 0.0}}, silhouettes=masks)
    default, rep_none = arm_err_mm()
    assert "L_sil" not in rep_none["terms"] and "L_sil" not in rep0["terms"]
    assert np.abs(default - without).max() < 1e-6  # no masks, or weight 0: the same fit
    with_sil, rep1 = arm_err_mm(silhouettes=masks)
    assert "L_sil" in rep1["terms"] and rep1["frames_with"]["L_sil"] == F
    assert without.min() > 200, without  # the keypoints alone leave the arm hanging
    # (measured: 308 mm in every frame without; with L_sil at 10: 173, 68, 57, 64 mm with
    # three LM rounds in the temporal pass, 139, 64, 66, 78 mm with one, the default since
    # session 18: the last frame's re-solve finds the silhouette's points once)
    assert with_sil.mean() < 0.4 * without.mean(), (with_sil, without)
    assert with_sil[-1] < 0.3 * without[-1], (with_sil, without)


# ---------------------------------------------------------------------------- clean plates


def _recipe(tmp_path: Path, plates: dict) -> Path:
    import yaml

    for f in ("a.c3d", "v.mp4", "cal.json"):
        (tmp_path / f).write_text("x")
    raw = {"session": "s", "cameras": ["c1", "c2"],
           "subjects": {"a": {}, "b": {}},
           "sequences": {"g/Hug 1": {"markers_on": "a", "partner": "b", "c3d": "a.c3d",
                                     "videos": {"c1": "v.mp4", "c2": "v.mp4"},
                                     "calibration": {"c1": "cal.json", "c2": "cal.json"},
                                     "clean_plates": plates}}}
    p = tmp_path / "r.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


def test_clean_plates_in_the_recipe_missing_or_unknown_camera_name_the_field(tmp_path):
    from recipes import RecipeError, load_recipe

    (tmp_path / "plate.mp4").write_text("x")
    s = load_recipe(_recipe(tmp_path, {"c1": "plate.mp4"}))  # a plate for some cameras only
    assert s.sequences["g/Hug 1"].clean_plates["c1"] == (tmp_path / "plate.mp4").resolve()
    with pytest.raises(RecipeError) as e:
        load_recipe(_recipe(tmp_path, {"c1": "gone.mp4", "c9": "plate.mp4"}))
    lines = e.value.problems
    assert any("sequences.g/Hug 1.clean_plates.c1: file not found" in ln and "gone.mp4" in ln
               for ln in lines), lines
    assert any("sequences.g/Hug 1.clean_plates: unknown cameras ['c9']" in ln for ln in lines), lines


def test_an_unreadable_clean_plate_names_the_file(tmp_path):
    from formats.errors import InputError
    from stages.silhouettes import read_plate

    bad = tmp_path / "clean_plate.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(InputError) as e:
        read_plate(bad, (W_IMG, H_IMG))
    assert str(bad) in str(e.value)
    with pytest.raises(InputError) as e:
        read_plate(tmp_path / "none.mp4", (W_IMG, H_IMG))
    assert "none.mp4" in str(e.value)


def test_views_whose_mask_misses_the_wearer_or_is_empty_are_not_used(anny, arm):
    """Three views of a textured room with the wearer painted in (its mesh rasterised): against
    the right clean plate the view is usable; against a "plate" that holds the wearer too the
    mask is empty; without a plate (MOG2) a wearer standing still all along is learnt as room.
    The last two are flagged and ``L_sil`` builds no block from them."""
    from detect.silhouette import SilhouetteOptions, body_mask, silhouettes
    from fitting.partner_fit import PartnerFitOptions, Posed
    from fitting.silhouette import SilhouetteInput, silhouette_term

    body, _, V = arm
    cams = _cams()[:3]
    rng = np.random.default_rng(0)
    room = rng.integers(60, 200, (H_IMG // 8, W_IMG // 8, 3)).astype(np.uint8)
    room = np.kron(room, np.ones((8, 8, 1), np.uint8))  # blocks of 8 px: a textured room
    frames = []
    for cam in cams:
        img = room.copy()
        img[body_mask(cam, V, anny.faces, (H_IMG, W_IMG), 1.0)] = (200, 40, 30)
        frames.append(img)
    plates = {0: [room] * 2, 1: [frames[1]] * 2}  # camera 2: none (MOG2)
    s, rep = silhouettes(lambda c, f: frames[c], cams, np.arange(4), plates, [V] * 4,
                         anny.faces, SilhouetteOptions())
    assert s.usable[:, 0].all() and not s.usable[:, 1:].any()
    assert s.wearer_cover[:, 0].min() > 0.9 and s.wearer_cover[:, 2].max() < 0.1
    cams_rep = rep["cameras"]
    assert cams_rep["cam1"]["not_usable"]["empty"] == [0, 1, 2, 3]
    assert cams_rep["cam2"]["source"] == "mog2" and len(cams_rep["cam2"]["not_usable"]["wearer_missing"]) == 4
    # the partner's mask is what is left of the people less the wearer: nothing here
    assert s.partner_fraction[:, 0].max() < 0.002
    term = silhouette_term(anny, np.arange(4), SilhouetteInput(s, cams),
                           PartnerFitOptions().proxy_vertices)
    x = np.zeros(body.skel.n)
    x[3:6] = [0.3, 0.0, 0.0]  # a partner beside the wearer: outside the people mask of view 0
    assert [len(b.H) > 0 for b in term(Posed(body, x, 0))] == [True]  # one block: view 0 only
