"""The partner fit (fitting/partner_fit.py, stages/partner_fit.py).

Fast tests run the domain function on synthetic projections of a posed Anny seen by four
cameras (no mediapipe): the exact Jacobian of skinned points against finite differences, the
pose recovered to a few cm, one view's wrong detections not dragging the body, frames
without detections held and not valid, a foot below the floor lifted by L_gp, a body pushed
out of the wearer by L_ic; the stage's bad contact file fails with file, action and field
and leaves no artifact. The slow test runs the engine on the cached small studio session.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from formats.errors import InputError
from pipeline.store import Writer

F_SYN = 6
FPS = 25.0


def FakeWriter(folder: Path) -> Writer:
    """The engine's own writer, into a folder of the test's (created)."""
    folder.mkdir(parents=True, exist_ok=True)
    return Writer(folder)


def _cams():
    from calib import look_at

    return [look_at(f"cam{k}", [4 * np.cos(a), 4 * np.sin(a), 2.0], [0, 0, 1.0], (1100, 1100),
                    (450, 450), 900, 900) for k, a in enumerate([0.5, 2.1, 3.7, 5.3])]


def _keypoints(kp: np.ndarray, frames, cams):
    from artifacts.keypoints import Keypoints2D

    C, F = kp.shape[:2]
    return Keypoints2D(kp=kp.astype(np.float32), boxes=np.full((C, F, 2, 4), np.nan, np.float32),
                       hand_boxes=np.full((C, F, 2, 2, 4), np.nan, np.float32),
                       frames=np.asarray(frames, np.int64), wearer_retry=np.zeros((C, F), bool),
                       partner_mode=np.ones((C, F), np.int8),
                       cross_view_outlier=np.zeros((C, F, 2, 65), bool),
                       conf_raw=kp[..., 2].astype(np.float32), cameras=np.array([c.name for c in cams]))


@pytest.fixture(scope="module")
def scene(anny):
    """A partner walking slowly (body joints), its KP65 keypoints projected into 4 views with
    1.5 px noise (person 1), a wearer at 1.2 m."""
    from bench import fitting_synth as S
    from body.joints import regressor
    from calib import project
    from fitting import skinned
    from fitting.marker_graph import body_joints, template_placement, to_shape_fit

    rng = np.random.default_rng(3)
    model = anny
    betas = S.subject_betas(model, rng)[:40]
    skel = skinned.fit_skeleton(model, body_joints(model))
    X = S.motion(skel, F_SYN, FPS, rng)
    X[:, 6:] *= 0.5
    truth = S.posed(model, betas, skel, X)
    R = regressor(model, "kp65")
    kp3 = np.stack([R @ np.concatenate([truth.vertices[f], truth.joints[f]]) for f in range(F_SYN)])
    cams = _cams()
    kp = np.zeros((4, F_SYN, 2, 65, 3))
    for c, cam in enumerate(cams):
        kp[c, :, 1, :, :2] = project(cam, kp3) + rng.normal(0, 1.5, (F_SYN, 65, 2))
        kp[c, :, 1, :, 2] = 0.9
    shape = to_shape_fit(betas, template_placement(model, "plug-in-gait"), "given", "given")
    return SimpleNamespace(model=model, betas=betas, skel=skel, X=X, truth=truth, kp=kp,
                           kp3=kp3, cams=cams, shape=shape, frames=np.arange(F_SYN) * 2)


def _fit(scene, kp, **kw):
    from fitting.partner_fit import PartnerFitOptions, fit_partner

    opts = PartnerFitOptions(**{"use_hands": False, **kw.pop("opts", {})})
    return fit_partner(scene.model, scene.shape, _keypoints(kp, scene.frames, scene.cams),
                       scene.cams, opts=opts, **kw)


def _joint_err_mm(scene, fit):
    from body import forward

    est = forward(scene.model, scene.betas, fit.body_pose, fit.global_orient, fit.transl)
    j = scene.skel.joints
    return np.linalg.norm(est.joints[:, j] - scene.truth.joints[:, j], axis=-1).mean(1) * 1000, est


def test_point_jacobian_matches_finite_differences(anny):
    from body.lbs import rest_state
    from fitting import skinned
    from fitting.partner_fit import point_jacobian

    rng = np.random.default_rng(0)
    skel = skinned.fit_skeleton(anny)
    rest = rest_state(anny, rng.normal(0, 0.5, 10))
    u, _ = skinned.reduced_offsets(anny, rest, skel)
    vids = rng.choice(anny.num_vertices, 12, replace=False)
    H = skinned.vertex_coeffs(anny, rest, skel, anny.weights[vids], rest.vertices[0, vids])
    x = rng.normal(0, 0.4, skel.n)
    x[:3] = [0.3, -1.9, 1.2]  # a large global rotation
    pos, J = point_jacobian(skel, u, H, x)
    assert np.allclose(pos, skinned.slot_positions_np(skel, u, H, x), atol=1e-12)
    h = 1e-6
    Jfd = np.stack([(skinned.slot_positions_np(skel, u, H, x + h * e)
                     - skinned.slot_positions_np(skel, u, H, x - h * e)) / (2 * h)
                    for e in np.eye(skel.n)], axis=-1)
    assert np.abs(J - Jfd).max() < 1e-6, np.abs(J - Jfd).max()


def test_sparse_jacobian_pattern_equals_the_dense_formula(anny):
    """JacobianPattern evaluates only the (ancestor joint, point) pairs that can be nonzero:
    positions and Jacobian equal the dense formula's for mesh vertices (a few skinning
    joints each), regressed keypoints (many) and a slot of zeros (a point skinned to none)."""
    from body.joints import regressor
    from body.lbs import rest_state
    from fitting import skinned

    rng = np.random.default_rng(3)
    skel = skinned.fit_skeleton(anny)
    rest = rest_state(anny, rng.normal(0, 0.5, 10))
    u, _ = skinned.reduced_offsets(anny, rest, skel)
    sub = skinned.subtree(skel)
    vids = rng.choice(anny.num_vertices, 40, replace=False)
    Hv = skinned.vertex_coeffs(anny, rest, skel, anny.weights[vids], rest.vertices[0, vids])
    Hk = skinned.regressed_coeffs(anny, rest, skel, regressor(anny, "kp65"))
    H = np.concatenate([Hv, Hk, np.zeros((1,) + Hv.shape[1:])])
    pat = skinned.JacobianPattern(skel, H, sub)
    assert len(pat.i_f) < 0.5 * len(H) * len(skel.joints)  # it is sparse
    for _ in range(3):
        x = rng.normal(0, 0.5, skel.n)
        pos, J = skinned.point_jacobian(skel, u, H, x, sub)
        pos_s, J_s = skinned.point_jacobian(skel, u, H, x, sub, pattern=pat)
        assert np.abs(pos_s - pos).max() < 1e-12
        assert np.abs(J_s - J).max() < 1e-12
    assert not J_s[-1].any() and not pos_s[-1].any()


def test_recovers_the_pose_from_four_views(scene):
    fit, rep = _fit(scene, scene.kp)
    err, _ = _joint_err_mm(scene, fit)
    assert fit.valid.all(), rep["frames_not_valid"]
    assert err.max() < 30.0, err  # mm, every frame
    assert np.median(err) < 20.0, err
    assert rep["reprojection_px"]["median"] < 4.0
    assert np.array_equal(fit.frames, scene.frames)


def test_one_wrong_view_does_not_drag_the_body(scene):
    kp = scene.kp.copy()
    rng = np.random.default_rng(5)
    bad = rng.choice(23, 10, replace=False)  # view 2: 10 body keypoints somewhere else
    kp[2, :, 1, bad, :2] += rng.uniform(80, 160, (len(bad), 1, 2)) * rng.choice([-1, 1], (len(bad), 1, 2))
    fit, rep = _fit(scene, kp)
    err, _ = _joint_err_mm(scene, fit)
    assert err.max() < 35.0, err
    clean, _ = _joint_err_mm(scene, _fit(scene, scene.kp)[0])
    assert err.mean() < clean.mean() + 10.0, (err, clean)


def test_frames_without_detections_are_held_and_not_valid(scene):
    from artifacts import INVALID_REASONS

    kp = scene.kp.copy()
    kp[:, 0, 1, :, 2] = 0  # frame 0: nothing -> before the first detection
    kp[:, 3, 1, :, 2] = 0  # frame 3: nothing -> held
    kp[1:, 4, 1, :, 2] = 0  # frame 4: one view only -> held
    fit, rep = _fit(scene, kp)
    names = [INVALID_REASONS[c] for c in fit.invalid_reason]
    assert names == ["held_before_first_keypoints", "fitted", "fitted", "too_few_keypoints",
                     "too_few_keypoints", "fitted"], names
    assert np.array_equal(fit.valid, fit.invalid_reason == 0)
    assert np.allclose(fit.transl[3], fit.transl[2]) and np.allclose(fit.transl[0], fit.transl[1])
    assert rep["frames_not_valid"]["too_few_keypoints"] == 2


def test_ground_term_lifts_a_foot_below_the_floor(scene):
    """The plane 3 cm above the true lowest vertex: with L_gp the fitted body's lowest
    vertex comes up to the plane (the keypoints pull it down), without it it stays below."""
    low = scene.truth.vertices[..., 2].min(1)  # (F,)
    plane = (np.array([0.0, 0.0, 1.0]), float(low.min()) + 0.03)
    _, est = _joint_err_mm(scene, _fit(scene, scene.kp)[0])
    fit, rep = _fit(scene, scene.kp, ground=plane)
    _, est_gp = _joint_err_mm(scene, fit)
    depth = plane[1] - est.vertices[..., 2].min(1)
    depth_gp = plane[1] - est_gp.vertices[..., 2].min(1)
    worst = int(np.argmax(depth))
    assert depth[worst] > 0.02, depth
    assert depth_gp[worst] < 0.006, depth_gp
    assert rep["frames_with"]["L_gp"] >= 1


def test_interpenetration_term_pushes_the_partner_out_of_the_wearer(scene):
    """The wearer: the partner's own body turned to face it, its root 18 cm in front, so the
    true bodies overlap by ~8 cm (the keypoints pull the partner into the wearer): with L_ic
    every frame ends shallower, and on average less than half as deep."""
    from artifacts import BodyFit
    from body import forward
    from body.rotations import rodrigues
    from geometry import interpenetration

    F = F_SYN

    Rz = rodrigues(np.array([0.0, 0.0, np.pi]))
    R = np.einsum("ab,fbc->fac", Rz, rodrigues(scene.X[:, :3]))
    pose = np.zeros((F, scene.model.num_joints, 3))
    pose[:, scene.skel.joints[1:]] = scene.X[:, 6:].reshape(F, -1, 3)
    fwd = scene.X[:, 3:6]
    root = forward(scene.model, scene.betas, pose[:1], R[:1], fwd[:1]).joints[0, 0]
    # put the wearer's root 18 cm in front of the partner's (along the partner's facing -y)
    facing = rodrigues(scene.X[:, :3]) @ np.array([0.0, -1.0, 0.0])
    T = fwd + 0.18 * facing - (root - scene.truth.joints[0, 0])
    wearer = BodyFit(body_pose=pose, global_orient=R, transl=T, betas=scene.betas,
                     frames=scene.frames, valid=np.ones(F, bool), invalid_reason=np.zeros(F, np.int8))
    WV = forward(scene.model, scene.betas, pose, R, T).vertices
    truth_depth = np.array([interpenetration(scene.truth.vertices[f], WV[f], scene.model.faces).depth
                            for f in range(F)])
    assert truth_depth.max() > 0.02, truth_depth  # the scene does overlap
    fit, rep = _fit(scene, scene.kp, wearer=wearer, opts={"weights": {"L_ic": 1e4}})
    _, est = _joint_err_mm(scene, fit)
    depth = np.array([interpenetration(est.vertices[f], WV[f], scene.model.faces).depth
                      for f in range(F)])
    assert rep["frames_with"]["L_ic"] >= 1
    assert np.all(depth < truth_depth) and depth.mean() < 0.5 * truth_depth.mean(), (depth, truth_depth)
    # the temporal pass re-solves in temporal_rounds rounds (1), the forward pass in
    # outer_rounds (3: L_ic finds points in every frame here); three temporal rounds also end
    # out of the wearer
    assert rep["mean_rounds"] == 3 and rep["mean_rounds_temporal"] == 1, rep
    fit3, rep3 = _fit(scene, scene.kp, wearer=wearer,
                      opts={"weights": {"L_ic": 1e4}, "temporal_rounds": 3})
    assert rep3["mean_rounds_temporal"] == 3
    _, est3 = _joint_err_mm(scene, fit3)
    depth3 = np.array([interpenetration(est3.vertices[f], WV[f], scene.model.faces).depth
                       for f in range(F)])
    assert np.all(depth3 < truth_depth) and depth3.mean() < 0.5 * truth_depth.mean()


def _contact_json(rmap, regions=(("l_palm", "r_palm"),), start=2, end=4, fr=3):
    faces, regs = [], []
    for a, b in regions:
        f0, f1 = int(rmap.faces_of(a)[0]), int(rmap.faces_of(b)[0])
        faces.append([f0, f1])
        regs.append([int(rmap.face_region[f0]), int(rmap.face_region[f1])])
    return {"fr_id": fr, "start_fr": start, "end_fr": end,
            "smplx_signature": {"region_id": [], "face_id": []},
            "ghum_signature": {"region_id": [], "face_id": []},
            "anny_signature": {"region_id": regs, "face_id": faces,
                               "region_names": [[rmap.names[a], rmap.names[b]] for a, b in regs]}}


@pytest.fixture(scope="module")
def stage_files(scene, tmp_path_factory):
    """Files and upstream artifact folders of a stage run on the synthetic scene."""
    from body.regions import region_map
    from calib.io import write_chi3d_camera
    from formats.video import write_mp4
    from stages import common

    tmp = tmp_path_factory.mktemp("partner_stage")
    cams = {c.name: write_chi3d_camera(tmp / "cams" / c.name / "take.json", c) for c in scene.cams}
    n_video = int(scene.frames[-1]) + 1
    video = tmp / "video.mp4"
    write_mp4(video, np.zeros((n_video, 64, 64, 3), np.uint8), FPS)
    scene.shape.save(FakeWriter(tmp / "shape_fit"))
    _keypoints(scene.kp, scene.frames, scene.cams).save(FakeWriter(tmp / "keypoints"))
    from artifacts.capture import CameraRig

    CameraRig.from_cameras(scene.cams).save(FakeWriter(tmp / "capture"))  # the capture's rig
    from artifacts import BodyFit

    F, J = F_SYN, scene.model.num_joints
    BodyFit(body_pose=np.zeros((F, J, 3)), global_orient=np.repeat(np.eye(3)[None], F, 0),
            transl=np.tile([1.5, 0.0, 0.0], (F, 1)), betas=scene.betas, frames=scene.frames,
            valid=np.ones(F, bool), invalid_reason=np.zeros(F, np.int8)).save(
        FakeWriter(tmp / "marker_fit"))  # the wearer, 1.5 m away
    rmap = region_map(scene.model)
    good = _contact_json(rmap)
    body_file = common.body_model_file(SimpleNamespace(body_model=SimpleNamespace(kind="anny", path=None)))
    raw = {"body_model": body_file, **{f"video:{c}": video for c in cams}}
    return SimpleNamespace(tmp=tmp, raw=raw, good=good, rmap=rmap, cams=list(cams))


def _stage_ctx(files, out: Path, contact: dict, params=None):
    import stages.partner_fit as stage
    from pipeline.spec import RecipeView, build_view_tree

    p = out.parent / f"{out.name}_contact.json"
    p.write_text(json.dumps({"take": contact}))
    values = {"body_model.kind": "anny", "cameras": files.cams, "sequence.fps": FPS,
              "sequence.has_keypoints": True,  # precomputed: no second detection pass
              "ground_plane": {"normal": [0.0, 0.0, 1.0], "offset": -1.0},
              "sequence.markers_on": "s1", "sequence.partner": "s2",
              "sequence.markerless": False, "sequence.people": ["s1", "s2"]}
    view = RecipeView(build_view_tree({k: values[k] for k in stage.STAGE.reads}), "partner_fit")
    return SimpleNamespace(stage="partner_fit", unit="g/take", recipe=view,
                           params=params or stage.Options(use_hands=False), out=FakeWriter(out),
                           raw={**files.raw, "contact": p}, log=lambda m: None,
                           inputs={"shape_fit": {"s1": files.tmp / "shape_fit",
                                                 "s2": files.tmp / "shape_fit"},
                                   "capture": files.tmp / "capture",
                                   "keypoints": files.tmp / "keypoints",
                                   "marker_fit": files.tmp / "marker_fit"},
                           progress=lambda it, **k: it), p


@pytest.mark.parametrize("case, field", [("region", "take.anny_signature.region_names"),
                                         ("interval", "take.end_fr")])
def test_a_bad_contact_file_fails_before_anything_is_written(stage_files, tmp_path, case, field):
    from stages.partner_fit import run

    bad = json.loads(json.dumps(stage_files.good))
    if case == "region":
        bad["anny_signature"]["region_names"][0][1] = "l_tail"
    else:
        bad["end_fr"] = 500
    ctx, path = _stage_ctx(stage_files, tmp_path / "out", bad)
    with pytest.raises(InputError) as e:
        run(ctx)
    msg = str(e.value)
    assert str(path) in msg and field.split(".")[0] in msg and field.split(".")[-1] in msg, msg
    assert list(ctx.out.dir.iterdir()) == []


def test_stage_writes_fit_terms_report_and_plot(stage_files, tmp_path, scene):
    from artifacts import BodyFit
    from stages.partner_fit import run

    # the annotated palms are 1.5 m apart (a made-up signature): L_G must not drag the
    # partner there (contact_max_gap_m), and the report names the frames it left alone
    ctx, _ = _stage_ctx(stage_files, tmp_path / "out", stage_files.good)
    run(ctx)
    d = ctx.out.dir
    fit = BodyFit.load(d)
    assert fit.valid.all() and not fit.has_markers
    t = dict(np.load(d / "terms.npz"))
    assert t["reproj_px"].shape == (F_SYN, 4) and t["term_active"].shape[0] == F_SYN
    assert list(t["terms"][:3]) == ["L_2d", "L_theta", "L_s"]
    rep = json.loads((d / "report.json").read_text())
    assert rep["frames_valid"] == F_SYN and rep["contact"]["interval"] == [2, 4]
    assert rep["second_pass"] == {"run": False, "why_not": "precomputed keypoints"}
    assert "chains bending together (spine05-spine03-spine01)" in rep["prior"]  # L_theta's coupling
    # clean keypoints: all of the partner's body keypoints given, none on the wearer; the one
    # warning is the contact's: both contact frames kept the regions apart (fitted without L_G)
    assert rep["body_keypoints_detected"] == int((scene.kp[:, :, 1, :23, 2] > 0).sum())
    assert rep["keypoints_dropped_as_wearer"]["keypoints"] == 0
    ct = rep["contact_terms"]
    assert ct["terms"] == ["L_D", "L_N"] and ct["frames"] == 2  # video frames 2 and 4
    assert sorted({f for fs in ct["pairs_too_far"].values() for f in fs}) == [2, 4]
    assert ct["frames_released"] == [2, 4] and min(ct["released_gap_m"]) > 0.5
    (w,) = rep["warnings"]
    assert w.startswith("contact: 2 of the 2 fitted frames") and "video frames 2, 4" in w, w
    # contact distance only in the annotated interval (frames 2..4 -> fitted frame 2 = video 4)
    inside = (scene.frames >= 2) & (scene.frames <= 4)
    assert np.isfinite(t["contact_m"][inside]).all() and np.isnan(t["contact_m"][~inside]).all()
    assert np.all(t["contact_m"][inside] > 0.5)  # 1.5 m apart: palms far from each other
    assert np.all(t["penetration_m"] == 0) and rep["penetration"]["max_mm"] == 0
    assert (d / "partner_fit.png").stat().st_size > 5000


@pytest.mark.slow
def test_engine_on_the_small_session(small_session, tmp_path):
    """Through the engine (keypoints with a stride, shape_fit, marker_fit, partner_fit) on
    the studio session: the partner's joints near the truth, and a frame whose partner
    keypoints are zeroed is not valid."""
    import yaml

    from artifacts import INVALID_REASONS, BodyFit
    from artifacts.keypoints import Keypoints2D
    from body import forward, load_model
    from pipeline.cli import main
    from recipes import load_recipe

    root = Path(small_session).parent
    raw = yaml.safe_load(Path(small_session).read_text())

    def absolute(v):
        if isinstance(v, dict):
            return {k: absolute(x) for k, x in v.items()}
        if isinstance(v, list):
            return [absolute(x) for x in v]
        if isinstance(v, str) and (root / v).exists() and not Path(v).is_absolute():
            return str((root / v).resolve())
        return v

    rec = absolute(raw)
    rec["stages"] = {"keypoints": {"stride": 6}, "partner_fit": {"use_hands": False}}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    sid = next(s for s in load_recipe(path).sequences if "Handshake" in s)
    logs = []
    rc = main(["sequence", sid, "--recipe", str(path), "--outputs", str(tmp_path / "out"),
               "--until", "partner_fit"], log=logs.append)
    assert rc == 0, "\n".join(logs)
    pf = next((tmp_path / "out").glob("*/*/*/partner_fit"))
    fit = BodyFit.load(pf)
    group, action = sid.split("/")
    gt = np.load(root / "gt" / group / f"{action}.npz")
    model = load_model("anny")
    est = forward(model, fit.betas, fit.body_pose, fit.global_orient, fit.transl)
    from body.joints import regressor
    from evaluate import metrics as M

    R = regressor(model, "h36m17")
    def h36(V, J):
        return np.stack([R @ np.concatenate([V[i], J[i]]) for i in range(len(V))])
    fr = fit.frames
    pred = h36(est.vertices, est.joints)
    true = h36(gt["vertices"][1][fr].astype(float), gt["joints"][1][fr])
    ok = fit.valid
    assert ok.all(), [INVALID_REASONS[c] for c in fit.invalid_reason]
    mpjpe = M.mpjpe(pred[ok], true[ok]) * 1000
    print(f"small session {sid}: MPJPE {np.mean(mpjpe):.1f} mm over {ok.sum()}/{len(ok)} valid frames")
    assert np.mean(mpjpe) < 40.0, mpjpe  # mm: mediapipe keypoints (measured 26.7)
    # the second detection pass ran on the stage's own detections and never lost any
    report = json.loads((pf / "report.json").read_text())
    sp = report["second_pass"]
    assert sp["run"] and sp["view_frames"] == 4 * len(fr)
    # the light first fit only placed the crops: the published fit is the full one
    from fitting.partner_fit import DEFAULT_WEIGHTS

    assert sp["first_fit"] == "light" and "first_fit_cpu_s" in sp
    assert report["weights"]["L_sc"] == DEFAULT_WEIGHTS["L_sc"] > 0
    for g in ("body", "hands"):
        assert sp["detected_after"][g] >= sp["detected_before"][g], sp
    refined = Keypoints2D.load(pf)  # the keypoints the fit used: a valid artifact
    assert refined.kp.shape == Keypoints2D.load(next((tmp_path / "out").glob("*/*/*/keypoints"))).kp.shape
    # the honest mask: zero the partner's keypoints of one frame, refit from the same artifacts
    kp = Keypoints2D.load(next((tmp_path / "out").glob("*/*/*/keypoints")))
    from artifacts import ShapeFit
    from calib.io import read_chi3d_camera
    from fitting.partner_fit import PartnerFitOptions, fit_partner

    seq = load_recipe(path).sequences[sid]
    cams = [read_chi3d_camera(seq.calibration[c], name=c) for c in load_recipe(path).cameras]
    arr = np.array(kp.kp)
    arr[:, 2, 1, :, 2] = 0
    raw = np.array(kp.conf_raw)
    raw[:, 2, 1] = 0
    kp0 = dataclasses.replace(kp, kp=arr, conf_raw=raw)
    shape = ShapeFit.load(next((tmp_path / "out").glob(f"*/{seq.partner}/shape_fit")))
    fit0, _ = fit_partner(model, shape, kp0, cams, opts=PartnerFitOptions(use_hands=False))
    assert not fit0.valid[2] and INVALID_REASONS[fit0.invalid_reason[2]] == "too_few_keypoints"
    assert fit0.valid[[0, 1, 3]].all()


def test_joint_limits_hold_against_keypoints_that_pull_past_them(scene):
    """L_theta's joint-limit hinge (``limit_weight``): keypoints of a body whose right clavicle
    is turned 100 degrees (its limit is 35) pull the fit past the limit when the hinge has
    the Gaussian's weight (0.02, as before), and not at the default weight."""
    from bench import fitting_synth as S
    from body.joints import regressor
    from calib import project
    from fitting import priors
    from fitting.partner_fit import LIMIT_WEIGHT

    model, skel = scene.model, scene.skel
    j = list(skel.names).index("clavicle.R")
    X = scene.X.copy()
    X[:, 6 + 3 * (j - 1) + 2] = np.deg2rad(100.0)
    truth = S.posed(model, scene.betas, skel, X)
    R = regressor(model, "kp65")
    kp = np.zeros_like(scene.kp)
    for c, cam in enumerate(scene.cams):
        kp3 = np.stack([R @ np.concatenate([truth.vertices[f], truth.joints[f]])
                        for f in range(len(X))])
        kp[c, :, 1, :, :2] = project(cam, kp3)
        kp[c, :, 1, :, 2] = 0.9
    lim = np.deg2rad(priors.joint_limit_deg("clavicle.R"))
    jid = model.joint_index("clavicle.R")
    over = {}
    for w in (0.02, LIMIT_WEIGHT):
        fit, _ = _fit(scene, kp, opts={"limit_weight": w})
        over[w] = float(np.abs(np.asarray(fit.body_pose)[:, jid]).max() - lim)
    assert over[0.02] > np.deg2rad(20), over    # the old weight: the keypoints win
    assert over[LIMIT_WEIGHT] < np.deg2rad(5), over  # the hinge holds the limit
    with pytest.raises(ValueError, match="limit_weight"):
        _fit(scene, kp, opts={"limit_weight": -1.0})


def _shifted_kp(scene, shift_m) -> np.ndarray:
    """(F, 65, 3) world keypoints of the truth moved by ``shift_m`` (3,)."""
    return scene.kp3 + np.asarray(shift_m, float)


def test_a_hand_that_is_not_the_partners_is_gated_out(scene):
    """Only two views see the right hand and one of them found another hand 25 cm away (21
    keypoints against the body's one wrist): with the gate off it drags the fitted arm; the
    default fit solves the body first, leaves that hand out, and the wrist stays on the truth."""
    from calib import project
    from formats.skeletons import KP65, RIGHT_HAND

    kp = scene.kp.copy()
    kp[2:, :, 1, RIGHT_HAND, 2] = 0.0  # views 2 and 3 do not see the right hand
    wrong = _shifted_kp(scene, (0.215, 0.125, 0.0))[:, RIGHT_HAND]  # across view 1's line of sight
    kp[1, :, 1, RIGHT_HAND, :2] = project(scene.cams[1], wrong)
    wrist = KP65.index("r_wrist")

    def wrist_err_mm(fit):
        from fitting.heldout import fitted_keypoints

        X = fitted_keypoints(scene.model, fit)
        return np.linalg.norm(X[:, wrist] - scene.kp3[:, wrist], axis=-1) * 1000

    off, rep_off = _fit(scene, kp, opts={"use_hands": True, "hand_gate_px": 0.0})
    on, rep_on = _fit(scene, kp, opts={"use_hands": True})
    assert rep_off["hands_gated"]["views"] == 0
    assert rep_on["hands_gated"]["views"] >= F_SYN  # view 1's right hand, every frame
    gated = rep_on["per_frame"]["hands_gated"]
    assert gated[:, 1, 1].all() and not gated[:, 0].any()  # only that hand, not the good one
    assert np.median(wrist_err_mm(off)) > 40.0, wrist_err_mm(off)
    assert np.median(wrist_err_mm(on)) < 20.0, wrist_err_mm(on)


def test_a_bystander_is_never_taken_for_the_partner(scene):
    """One view's detection is somebody 2 m to the side (an operator behind the subjects, as
    in real labs): the view is dropped as a bystander in every frame and the fit stays where
    the other three views put the partner."""
    from calib import project

    kp = scene.kp.copy()
    kp[2, :, 1, :, :2] = project(scene.cams[2], _shifted_kp(scene, (1.4, -1.4, 0.0)))
    fit, rep = _fit(scene, kp)
    assert rep["views_dropped_as_bystander"] == F_SYN
    assert rep["per_frame"]["views_bystander"][:, 2].all()
    assert not rep["per_frame"]["views_bystander"][:, [0, 1, 3]].any()
    err, _ = _joint_err_mm(scene, fit)
    clean, _ = _joint_err_mm(scene, _fit(scene, scene.kp)[0])
    assert err.max() < clean.max() + 10.0, (err, clean)
    assert fit.valid.all()


def test_occlusion_option_leaves_out_what_the_wearer_hides(scene):
    """``occlusion``: with the wearer standing 1.2 m in front of the partner towards camera 0,
    the partner keypoints it hides are not used in that view, and in no other view."""
    from artifacts import BodyFit

    F = F_SYN
    c0 = scene.cams[0].T
    shift = np.array([c0[0], c0[1], 0.0]) / np.linalg.norm(c0[:2]) * 1.2
    pose = np.zeros((F, scene.model.num_joints, 3))
    pose[:, scene.skel.joints[1:]] = scene.X[:, 6:].reshape(F, -1, 3)
    from body.rotations import rodrigues

    wearer = BodyFit(body_pose=pose, global_orient=rodrigues(scene.X[:, :3]),
                     transl=scene.X[:, 3:6] + shift, betas=scene.betas, frames=scene.frames,
                     valid=np.ones(F, bool), invalid_reason=np.zeros(F, np.int8))
    _, off = _fit(scene, scene.kp, wearer=wearer, opts={"weights": {"L_ic": 0.0}})
    fit, on = _fit(scene, scene.kp, wearer=wearer, opts={"occlusion": True, "weights": {"L_ic": 0.0}})
    assert off["keypoints_hidden_by_wearer"] is None
    hid = on["per_frame"]["keypoints_hidden"]  # (F, C)
    assert hid[:, 0].min() >= 5 and not hid[:, 1:].any(), hid
    err, _ = _joint_err_mm(scene, fit)
    assert err.max() < 35.0, err  # three views and the unhidden rest of view 0 suffice


def test_a_limb_seen_in_one_view_is_not_ground_truth(scene):
    """The right forearm's keypoints used in one view only (the depth is the model's guess):
    the fit's ``observed`` leaves the right wrist (and what hangs on it) out of the ground
    truth in those frames, and keeps the rest of the body. (The elbow stays: the upper arm
    moves the shoulder keypoint too, by the support rule the marker fit uses.)"""
    from body.joints import regressor
    from fitting.marker_graph import observed_points
    from formats.skeletons import JOINTS3D_25, KP65

    kp = scene.kp.copy()
    arm = [KP65.index(n) for n in ("r_elbow", "r_wrist")]
    kp[1:, 2:, 1, arm, 2] = 0.0  # from the third frame on, only view 0 sees them
    fit, rep = _fit(scene, kp)
    pts = observed_points(scene.model, regressor(scene.model, "joints3d_25"), fit.joints_observed())
    j = {n: JOINTS3D_25.index(n) for n in ("r_wrist", "r_elbow", "l_wrist", "pelvis", "head")}
    assert pts[:2, :17].all()  # every body joint seen in four views (no hand keypoints here:
    assert not pts[:, JOINTS3D_25.index("r_thumb")].any()  # the fingers are held, not observed)
    assert not pts[2:, j["r_wrist"]].any() and not pts[2:, JOINTS3D_25.index("r_wrist_end")].any()
    assert pts[2:, [j["l_wrist"], j["pelvis"], j["head"]]].all()
    assert rep["joints_observed"]["per_joint"]["r_wrist"] == pytest.approx(2 / F_SYN, abs=1e-3)


def test_a_keypoint_the_fit_does_not_follow_is_not_ground_truth(scene):
    """The right elbow detected in every view, but from the third frame on 60 px off in views
    1-3, each in another direction (no point explains them; the rest of the arm holds the
    fit): the fitted body agrees with that elbow in view 0 alone, so the elbow is not ground
    truth there (``keypoints_observed``, ``fit_points_observed``), although every joint it
    hangs on is observed through other keypoints (``observed``); the right wrist, agreed
    with in four views, stays. With ``observed_px`` above the offsets (and the outliers kept:
    ``outlier_px`` 0) the elbow counts again. (``reliability_px`` 0: it would leave the three
    views' elbow out of every frame, the first two as well.)"""
    from body.joints import regressor
    from fitting.marker_graph import fit_points_observed, observed_points
    from formats.skeletons import JOINTS3D_25, KP65

    kp = scene.kp.copy()
    el = KP65.index("r_elbow")
    for c, shift in zip((1, 2, 3), ((60.0, 0.0), (0.0, 60.0), (-45.0, -40.0)), strict=True):
        kp[c, 2:, 1, el, :2] += shift
    fit, rep = _fit(scene, kp, opts={"reliability_px": 0.0})
    ko = np.asarray(fit.keypoints_observed)
    assert ko.shape == (F_SYN, len(KP65))
    assert ko[:2, el].all() and not ko[2:, el].any()
    assert ko[:, KP65.index("r_wrist")].all() and not ko[:, 23:].any()  # no hands fitted
    j = {n: JOINTS3D_25.index(n) for n in ("r_elbow", "r_wrist", "l_elbow")}
    chain = observed_points(scene.model, regressor(scene.model, "joints3d_25"), fit.joints_observed())
    assert chain[:, j["r_elbow"]].all()  # the joints it hangs on: observed by other keypoints
    pts = fit_points_observed(scene.model, fit)
    assert pts[:2, j["r_elbow"]].all() and not pts[2:, j["r_elbow"]].any()
    assert pts[:, j["r_wrist"]].all() and pts[:, j["l_elbow"]].all()
    assert rep["joints_observed"]["per_joint"]["r_elbow"] == pytest.approx(2 / F_SYN, abs=1e-3)
    loose, _ = _fit(scene, kp, opts={"observed_px": 200.0, "outlier_px": 0.0,
                                     "reliability_px": 0.0})
    assert np.asarray(loose.keypoints_observed)[:, el].all()


def test_a_detection_far_from_the_solved_frame_is_left_out(scene):
    """The right wrist detected 80 px off in view 1 in every frame (the other views right):
    after each frame's solve it lies farther than ``outlier_px`` from the fitted wrist, so it
    is left out and the frame solved again (counted per frame and view); the fit is at least
    as close to the truth as with it kept (outlier_px 0: nothing left out). (``reliability_px``
    0: that rule would leave the view's wrist out before any solve.)"""
    from formats.skeletons import KP65

    kp = scene.kp.copy()
    wr = KP65.index("r_wrist")
    kp[1, :, 1, wr, :2] += (80.0, 0.0)
    fit, rep = _fit(scene, kp, opts={"reliability_px": 0.0})
    n = rep["per_frame"]["keypoints_rejected"]  # (F, C)
    assert (n[:, 1] >= 1).all() and n[:, [0, 2, 3]].sum() == 0, n
    out = rep["keypoints_rejected_as_outliers"]
    assert out["keypoints"] == int(n.sum()) and out["outlier_px"] == 35.0
    # one keypoint of a view's many is not most of them: no view reported
    assert out["frames_view_lost_most"] == [0, 0, 0, 0] and out["frames_solved"] == F_SYN
    kept, rep0 = _fit(scene, kp, opts={"outlier_px": 0.0, "reliability_px": 0.0})
    assert rep0["keypoints_rejected_as_outliers"]["keypoints"] == 0
    assert rep0["keypoints_rejected_as_outliers"]["outlier_px"] is None
    err, _ = _joint_err_mm(scene, fit)
    err0, _ = _joint_err_mm(scene, kept)
    assert err.mean() <= err0.mean() + 0.1, (err, err0)


def test_a_view_that_loses_most_of_its_keypoints_as_outliers_is_reported(scene):
    """View 2's detections all 55 px off in every frame (its calibration wrong; less than
    ``bystander_px``, which would drop the view whole): the other three views fit the body,
    view 2's keypoints lie farther than ``outlier_px`` from it and are left out, most of them
    in every frame, so the report warns naming the view; the share threshold decides. With
    ``reliability_px`` on (the default), the view's keypoints are left out as its bias before
    the second forward pass, and the warning says so instead."""
    from fitting.partner_fit import (
        OUTLIER_WARN_SHARE,
        outlier_warnings,
        unreliable_warnings,
        view_warnings,
    )
    from formats.skeletons import KP65

    kp = scene.kp.copy()
    kp[2, :, 1, :, :2] += (55.0, 0.0)
    _, rel = _fit(scene, kp)
    assert rel["detections_unreliable"]["per_view"] == {"cam2": list(KP65[:23])}
    (w,) = unreliable_warnings(rel["detections_unreliable"])
    assert w.startswith("view cam2: 23 of the partner's 23 body keypoints") and "25.0 px" in w
    _, rep = _fit(scene, kp, opts={"reliability_px": 0.0})
    assert rep["detections_unreliable"] == {"reliability_px": None, "pairs": 0,
                                            "frames_kept_from_first_pass": 0, "per_view": {}}
    out = rep["keypoints_rejected_as_outliers"]
    lost = out["frames_view_lost_most"]
    assert lost[2] >= F_SYN - 1 and lost[0] == lost[1] == lost[3] == 0, out
    names = ["c0", "c1", "c2", "c3"]
    (w,) = outlier_warnings(out, names)
    assert w.startswith("view c2:") and "35.0 px" in w
    assert outlier_warnings(out, names, share=1.0) == []  # no view loses most in > all frames
    assert view_warnings(rep, names) == [w]  # what the stage's reports carry, both kinds
    both = view_warnings(rel, names)
    assert both == outlier_warnings(rel["keypoints_rejected_as_outliers"], names) + \
        unreliable_warnings(rel["detections_unreliable"]) and both[-1].startswith("view cam2:")
    assert OUTLIER_WARN_SHARE == 0.10
    assert outlier_warnings({**out, "frames_view_lost_most": [0, 2, 0, 0],
                             "frames_solved": 20}, names) == []  # 10 %: not more than 10 %
    (w,) = outlier_warnings({**out, "frames_view_lost_most": [0, 3, 0, 0],
                             "frames_solved": 20}, names)
    assert w.startswith("view c1: in 3 of 20 solved frames (15 %")


def test_a_views_persistent_keypoint_bias_is_found_over_the_sequence(scene):
    """``unreliable_detections``: a (view, keypoint) is the view's bias where its detections
    lie farther than ``max_px`` from the fitted keypoints in the median over the frames that
    have both, judged on at least ``min_frames`` of them. View 1's right wrist 30 px off in
    every frame is; view 2's left knee 30 px off in 2 of 6 frames is not (its median is the
    noise); view 3's nose 30 px off but detected in 4 frames is not judged (5 needed), nor in
    6 where only 4 are fitted (None)."""
    from calib import project
    from fitting.partner_fit import unreliable_detections
    from formats.skeletons import KP65

    rng = np.random.default_rng(0)
    F, K = F_SYN, 23
    pts = [scene.kp3[f, :K] for f in range(F)]
    uv = np.stack([np.stack([project(c, pts[f]) for c in scene.cams]) for f in range(F)])
    uv += rng.normal(0, 2.0, uv.shape)
    conf = np.full((F, 4, K), 0.9)
    wr, kn, no = KP65.index("r_wrist"), KP65.index("l_knee"), KP65.index("nose")
    uv[:, 1, wr] += (30.0, 0.0)
    uv[:2, 2, kn] += (0.0, 30.0)
    uv[:, 3, no] += (30.0, 0.0)
    conf[4:, 3, no] = 0.0
    bad = unreliable_detections(scene.cams, pts, uv, conf, 25.0)
    assert bad.shape == (4, K) and np.argwhere(bad).tolist() == [[1, wr]]
    assert not unreliable_detections(scene.cams, pts, uv, conf, 35.0).any()  # 30 px < 35
    conf[4:, 3, no] = 0.9
    assert np.argwhere(unreliable_detections(scene.cams, pts, uv, conf, 25.0)).tolist() == [
        [1, wr], [3, no]]
    some = [p if f < 4 else None for f, p in enumerate(pts)]
    assert not unreliable_detections(scene.cams, some, uv, conf, 25.0).any()
    assert np.argwhere(unreliable_detections(scene.cams, some, uv, conf, 25.0, min_frames=4)
                       ).tolist() == [[1, wr], [3, no]]


def test_a_views_persistent_bias_below_outlier_px_is_left_out_and_fitted_without(scene):
    """View 1 reads the right wrist 28 px off in every frame: closer than ``outlier_px`` (35),
    so the per-frame rule keeps it and it pulls the wrist. Over the sequence it is the view's
    bias (``reliability_px`` 25): left out, named in the report, and the fit's wrist is closer
    to the truth than with the rule off; the three other views still make it observed."""
    from body import forward
    from body.joints import regressor
    from formats.skeletons import KP65

    kp = scene.kp.copy()
    wr = KP65.index("r_wrist")
    kp[1, :, 1, wr, :2] += (20.0, 19.0)
    R = regressor(scene.model, "kp65")

    def wrist_err_mm(fit):
        est = forward(scene.model, scene.betas, fit.body_pose, fit.global_orient, fit.transl)
        p = np.stack([(R @ np.concatenate([est.vertices[f], est.joints[f]]))[wr]
                      for f in range(F_SYN)])
        return float(np.linalg.norm(p - scene.kp3[:, wr], axis=-1).mean() * 1000)

    fit, rep = _fit(scene, kp)
    un = rep["detections_unreliable"]
    assert un["reliability_px"] == 25.0 and un["pairs"] == 1 and un["per_view"] == {
        "cam1": ["r_wrist"]}
    assert 0 <= un["frames_kept_from_first_pass"] <= F_SYN
    assert rep["keypoints_rejected_as_outliers"]["keypoints"] == 0
    assert np.asarray(fit.keypoints_observed)[:, wr].all()
    off, rep0 = _fit(scene, kp, opts={"reliability_px": 0.0})
    assert rep0["detections_unreliable"]["pairs"] == 0
    assert rep0["keypoints_rejected_as_outliers"]["keypoints"] == 0  # kept: it pulled
    e, e0 = wrist_err_mm(fit), wrist_err_mm(off)
    assert e < e0 - 1.0, (e, e0)
    with pytest.raises(ValueError, match="reliability_px"):
        _fit(scene, kp, opts={"reliability_px": -1.0})


def test_a_frame_that_keeps_its_first_pass_is_recorded_at_that_pose(scene):
    """``reliability_px``: view 1's left elbow read 28 px off in every frame is left out and
    the forward pass runs again; a frame whose first pass explains the detections left better
    keeps that pose (here one). Its records (the per-view reprojection error, and what makes
    joints observed) are of the pose it keeps, against the detections left: with no temporal
    pass to record it again, every solved frame's ``reproj_px`` is the fitted body's own."""
    from body import forward
    from body.joints import regressor
    from calib import project
    from formats.skeletons import KP65

    kp = scene.kp.copy()
    el = KP65.index("l_elbow")
    kp[1, :, 1, el, :2] += (-20.0, -20.0)
    fit, rep = _fit(scene, kp, opts={"temporal_passes": 0})
    un = rep["detections_unreliable"]
    assert un["per_view"] == {"cam1": ["l_elbow"]} and un["frames_kept_from_first_pass"] >= 1
    est = forward(scene.model, scene.betas, fit.body_pose, fit.global_orient, fit.transl)
    R = regressor(scene.model, "kp65")[:23]
    used = kp[:, :, 1, :23].copy()
    used[1, :, el, 2] = 0.0  # left out
    err = rep["per_frame"]["reproj_px"]
    for f in range(F_SYN):
        p = R @ np.concatenate([est.vertices[f], est.joints[f]])
        for c, cam in enumerate(scene.cams):
            ok = used[c, f, :, 2] > 0
            d = np.linalg.norm(project(cam, p[ok]) - used[c, f, ok, :2], axis=-1)
            assert abs(np.median(d) - err[f, c]) < 1e-3, (f, c, np.median(d), err[f, c])


def test_a_view_dropped_whole_as_somebody_else_is_reported(scene):
    """View 1's detections all 150 px off (farther than ``bystander_px``: a camera far off its
    calibration, or somebody else read there): the view is left out whole in the frames after
    the start, the count per view says which, and the report warns naming it; a view dropped
    in a quarter of the frames or fewer is not warned about."""
    from fitting.partner_fit import BYSTANDER_WARN_SHARE, bystander_warnings

    kp = scene.kp.copy()
    kp[1, :, 1, :, :2] += (150.0, 0.0)
    fit, rep = _fit(scene, kp)
    per_view = rep["views_dropped_as_bystander_per_view"]
    assert per_view[1] >= F_SYN - 1 and per_view[0] == per_view[2] == per_view[3] == 0, per_view
    assert rep["views_dropped_as_bystander"] == sum(per_view)
    names = ["c0", "c1", "c2", "c3"]
    n = rep["keypoints_rejected_as_outliers"]["frames_solved"]
    (w,) = bystander_warnings(per_view, n, names)
    assert w.startswith(f"view c1: in {per_view[1]} of {n} solved frames")
    assert "left out whole" in w
    assert BYSTANDER_WARN_SHARE == 0.25
    assert bystander_warnings([0, 5, 0, 0], 20, names) == []  # 25 %: not more than 25 %
    assert len(bystander_warnings([0, 6, 0, 0], 20, names)) == 1
    assert bystander_warnings([0, 0, 0, 0], 0, names) == []  # nothing solved
    clean = _fit(scene, scene.kp)[1]
    assert clean["views_dropped_as_bystander_per_view"] == [0, 0, 0, 0]


def test_a_frame_seen_by_two_views_is_fitted_but_not_valid(scene):
    """Two views can always be fitted, and a wrong reading both share leaves no residual
    (bench: every valid partner frame seen by two views was more than 10 cm off): a frame
    where fewer than min_valid_views views see the partner is fitted and reported
    ``too_few_views``; a view with fewer than VIEW_MIN_KEYPOINTS body keypoints does not
    count; the frames around stay valid; min_valid_views=2 keeps them all, and a rig of two
    cameras needs only its two."""
    from artifacts import REASON_CODE
    from fitting.partner_fit import VIEW_MIN_KEYPOINTS, apply_min_valid_views

    kp = scene.kp.copy()
    kp[2:, 2:4, 1, :, 2] = 0.0  # frames 2 and 3: views 2 and 3 see nothing of the partner
    kp[1, 3, 1, VIEW_MIN_KEYPOINTS - 1:23, 2] = 0.0  # frame 3, view 1: 4 body keypoints left
    fit, rep = _fit(scene, kp)
    assert list(rep["per_frame"]["views_seeing"]) == [4, 4, 2, 1, 4, 4]
    want = np.zeros(F_SYN, np.int8)
    want[2:4] = REASON_CODE["too_few_views"]
    assert np.array_equal(fit.invalid_reason, want) and fit.valid.sum() == F_SYN - 2
    assert rep["frames_not_valid"]["too_few_views"] == 2 and rep["frames_valid"] == F_SYN - 2
    assert rep["valid_views_required"] == 3
    # the frames are fitted all the same: the two views' keypoints are matched
    assert np.nanmax(rep["per_frame"]["reproj_px"][2]) < 5.0
    two, rep2 = apply_min_valid_views(fit, rep, 2, 4)  # frame 3 has one view left
    assert list(np.flatnonzero(~two.valid)) == [3] and rep2["frames_not_valid"]["too_few_views"] == 1
    loose, _ = _fit(scene, kp, opts={"min_valid_views": 1})
    assert loose.valid.all()
    rig2 = [scene.cams[0], scene.cams[1]]  # two cameras: both seeing is all there can be
    fit2, rep3 = _fit(SimpleNamespace(**{**vars(scene), "cams": rig2}), scene.kp[:2])
    assert rep3["valid_views_required"] == 2 and fit2.valid.all()


def test_the_light_first_fit_leaves_out_only_the_temporal_pass_rounds_and_costly_hooks():
    """The fit that places the second pass's crops (stages.partner_fit.first_fit_options):
    "light" drops the temporal pass, the outer rounds after the first, the second forward
    pass of reliability_px, L_sc and L_sil and
    keeps every other option and weight as given; "full" is the final fit's options; anything
    else is refused."""
    import dataclasses

    from stages.partner_fit import LIGHT_FIRST_FIT, Options, first_fit_options

    o = Options(weights={"L_ic": 5e3}, temporal_passes=2, max_iters=7, outer_rounds=4)
    light = first_fit_options(o)
    assert light.temporal_passes == 0 and light.max_iters == 7 and light.outer_rounds == 1
    assert light.reliability_px == 0 and o.reliability_px > 0  # no second forward pass
    assert light.weights["L_sc"] == 0 and light.weights["L_sil"] == 0
    kept = {k: v for k, v in o.weights.items() if k not in LIGHT_FIRST_FIT["weights"]}
    assert kept and all(light.weights[k] == v for k, v in kept.items())
    assert light.weights["L_ic"] == 5e3 and o.weights["L_sc"] > 0  # o itself is untouched
    full = dataclasses.replace(o, first_fit="full")
    assert first_fit_options(full) is full
    with pytest.raises(ValueError, match="first_fit"):
        Options(first_fit="half")


def test_a_bystander_is_dropped_where_one_view_sees_the_partner(scene):
    """The partner is seen by one view only (hidden behind the wearer in the others, as in a
    hug) and another view's detection is a bystander 1.2 m away: one view agreeing with the
    estimate is enough to drop the bystander's (on the bench's Hug it pulled the fit 1.25 m
    onto the bystander when two agreeing views were required); with no view agreeing nothing
    is dropped (the partner may have moved)."""
    from calib import project
    from fitting.partner_fit import check_views
    from formats.skeletons import KP65_FLIP

    f = 3
    pred = scene.kp3[f]
    uv, conf = scene.kp[:, f, 1, :, :2].copy(), scene.kp[:, f, 1, :, 2].copy()
    conf[[1, 3]] = 0.0
    uv[2] = project(scene.cams[2], _shifted_kp(scene, (-0.8, 0.9, 0.0))[f])
    flip = np.asarray(KP65_FLIP)
    vc = check_views(scene.cams, pred, uv, conf, flip, far_px=80.0, support=1)
    assert vc.far.tolist() == [False, False, True, False] and not vc.conf[2].any()
    assert np.array_equal(vc.conf[0], conf[0])
    old = check_views(scene.cams, pred, uv, conf, flip, far_px=80.0, support=2)
    assert not old.far.any() and np.array_equal(old.conf, conf)
    alone = conf.copy()
    alone[0] = 0.0  # only the far view: nothing to tell it from a partner who moved
    assert not check_views(scene.cams, pred, uv, alone, flip, far_px=80.0, support=1).far.any()
    # in the fit: after two clean frames, views 1 and 3 lose the partner and view 2 sees the
    # bystander; it is dropped in those frames only
    kp = scene.kp.copy()
    kp[[1, 3], 2:, 1, :, 2] = 0.0
    kp[2, 2:, 1, :, :2] = project(scene.cams[2], _shifted_kp(scene, (-0.8, 0.9, 0.0))[2:])
    fit, rep = _fit(scene, kp)
    byst = rep["per_frame"]["views_bystander"]
    assert byst[2:, 2].all() and not byst[:, [0, 1, 3]].any() and not byst[:2].any()
    assert rep["views_dropped_as_bystander"] == F_SYN - 2


def test_an_upper_body_read_mirrored_alone_is_mirrored_back(scene):
    """mediapipe mirrors the upper body alone of a person seen from behind (bench, Posing:
    shoulders, elbows and wrists swapped in one view while the legs stay right). The whole
    view's median, held by the legs, keeps the view; check_views mirrors the upper half back
    on its own and leaves the legs and the other views untouched."""
    from calib import project
    from fitting.partner_fit import BODY_PARTS, check_views
    from formats.skeletons import KP65_FLIP

    f = 4
    pred = scene.kp3[f]
    flip = np.asarray(KP65_FLIP)
    uv, conf = scene.kp[:, f, 1, :, :2].copy(), scene.kp[:, f, 1, :, 2].copy()
    judged, moved = BODY_PARTS[0]
    # the view where the mirrored arms lie farthest from the truth (a side view barely moves)
    errs = [np.median(np.linalg.norm(project(cam, pred[flip[judged]]) - project(cam, pred[judged]),
                                      axis=-1)) for cam in scene.cams]
    c = int(np.argmax(errs))
    assert errs[c] > 30.0  # the scene: a swap the check must see
    bad = uv.copy()
    bad[c, moved] = uv[c, flip[moved]]
    vc = check_views(scene.cams, pred, bad, conf, flip)
    assert not vc.flipped.any() and not vc.dropped.any()
    assert vc.parts_flipped[c].tolist() == [True, False]
    assert not np.delete(vc.parts_flipped, c, axis=0).any()
    assert np.allclose(vc.uv, uv) and np.array_equal(vc.conf, conf)
    assert not check_views(scene.cams, pred, uv, conf, flip).changed  # right as it is


def test_a_partner_joint_read_on_the_wearers_joint_is_dropped(scene):
    """A second-pass crop put the partner's left elbow on the wearer's elbow (bench, Posing:
    80-110 px from the truth at confidence 0.4-0.9, and the fit followed it along the depth
    two opposite views leave free). check_views drops that keypoint in that view alone; a
    partner's wrist on the wearer's shoulder (a push: another joint of the wearer) is kept,
    and so is everything without the wearer's keypoints."""
    from calib import project
    from fitting.partner_fit import check_views
    from formats.skeletons import KP65, KP65_FLIP

    f = 4
    pred = scene.kp3[f]
    el, wr, sh = KP65.index("l_elbow"), KP65.index("r_wrist"), KP65.index("l_shoulder")
    # the wearer stands so that its left shoulder is where the partner's right wrist is
    other = _shifted_kp(scene, pred[wr] - pred[sh])[f]
    flip = np.asarray(KP65_FLIP)
    uv, conf = scene.kp[:, f, 1, :, :2].copy(), scene.kp[:, f, 1, :, 2].copy()
    uv[1, el] = project(scene.cams[1], other[KP65.index("r_elbow")][None])[0]
    vc = check_views(scene.cams, pred, uv, conf, flip, other)
    assert np.linalg.norm(uv[1, el] - project(scene.cams[1], pred[el][None])[0]) > 15.0
    assert vc.keypoints_dropped[1, el] and vc.conf[1, el] == 0.0
    assert vc.keypoints_dropped.sum() == 1 and vc.changed
    keep = np.ones_like(conf, bool)
    keep[1, el] = False
    assert np.array_equal(vc.conf[keep], conf[keep])  # the wrist on the shoulder among them
    assert not vc.dropped.any() and not vc.flipped.any() and not vc.parts_flipped.any()
    alone = check_views(scene.cams, pred, uv, conf, flip)  # no wearer: nothing to judge by
    assert not alone.keypoints_dropped.any() and np.array_equal(alone.conf, conf)


def test_many_keypoints_left_out_as_the_wearers_are_reported():
    """The report warns when the second pass and check_views together left out more than
    WEARER_DROP_WARN_SHARE of the partner's body keypoints as the wearer's (the share of what
    the detector gave: those the fit got plus those the second pass left out)."""
    from fitting.partner_fit import WEARER_DROP_WARN_SHARE, wearer_drop_warnings

    assert WEARER_DROP_WARN_SHARE == 0.10
    assert wearer_drop_warnings(1000, 50, 40) == []          # 90 of 1040: 8.7 %
    assert wearer_drop_warnings(1000, 64, 40) == []          # 104 of 1040: exactly 10 %
    (w,) = wearer_drop_warnings(1000, 80, 40)                 # 120 of 1040: 11.5 %
    assert w.startswith("120 of 1040 partner body keypoints (12 %")
    assert "second pass 40, check_views 80" in w
    assert wearer_drop_warnings(1000, 80, 40, share=0.2) == []
    assert wearer_drop_warnings(0, 0, 0) == [] and len(wearer_drop_warnings(0, 0, 5)) == 1


def test_the_frames_before_the_first_initialisation_are_fitted_backwards(scene):
    """No torso keypoint (shoulders, hips) in the first three frames: the triangulated start
    fails there though 19 body keypoints are seen in four views. The fit starts at frame 3 and
    then fits frames 2, 1, 0 backwards from it, each from its own keypoints; with ``backfill``
    off they are held at frame 3's pose and not valid."""
    from artifacts import INVALID_REASONS
    from fitting.init_pose import TORSO

    kp = scene.kp.copy()
    kp[:, :3, 1, list(TORSO), 2] = 0.0
    fit, rep = _fit(scene, kp)
    assert rep["first_fitted_frame"] == int(scene.frames[0]) and rep["frames_backfilled"] == 3
    assert rep["initialisations"] == 1
    assert fit.valid.all(), rep["frames_not_valid"]
    err, _ = _joint_err_mm(scene, fit)
    assert err[:3].max() < 40.0, err
    held, rep_h = _fit(scene, kp, opts={"backfill": False})
    names = [INVALID_REASONS[c] for c in held.invalid_reason[:4]]
    assert names == ["held_before_first_keypoints"] * 3 + ["fitted"], names
    assert rep_h["frames_backfilled"] == 0 and rep_h["first_fitted_frame"] == int(scene.frames[3])


def test_an_earlier_fit_seeds_the_start_frame_and_its_views_are_checked_against_it(scene):
    """The stage's second fit (after the second detection pass) starts a sequence from the
    first fit's pose where that fit is valid (``fit_partner(start=...)``, ``seed_poses``), and
    checks the start frame's views against that pose before solving: a start triangulated
    from detections whose legs two of four views read mirrored crossed the legs (bench, Kick:
    every frame 28-41 cm off at the knees and ankles, all published valid). Planted: the legs
    of the two views where mirroring moves them most read mirrored in the first two frames;
    seeded, both views' legs are mirrored back in both frames (check_views: the view as a
    whole, then its arms on their own) and every frame stays near the truth. ``seed_poses`` packs the earlier fit's valid frames into the fit's unknowns
    (unpacked: the same pose) and gives None where it is not valid or has no frame."""
    from calib import project
    from fitting.marker_fit import unpack
    from fitting.partner_fit import BODY_PARTS, seed_poses
    from formats.skeletons import KP65_FLIP

    first, _ = _fit(scene, scene.kp)
    assert first.valid.all()
    flip = np.asarray(KP65_FLIP)
    judged, moved = BODY_PARTS[1]  # the legs
    errs = [np.median(np.linalg.norm(project(cam, scene.kp3[0][flip[judged]])
                                     - project(cam, scene.kp3[0][judged]), axis=-1))
            for cam in scene.cams]
    views = np.argsort(errs)[-2:]
    assert min(errs[c] for c in views) > 30.0  # the scene: mirrored legs the check must see
    kp = scene.kp.copy()
    for c in views:
        for f in (0, 1):
            kp[c, f, 1, moved] = scene.kp[c, f, 1, flip[moved]]
    fit, rep = _fit(scene, kp, start=first)
    err, _ = _joint_err_mm(scene, fit)
    assert rep["initialisations_from_start"] == 1 and rep["initialisations"] == 0
    # each planted view-frame (2 views x 2 frames; the legs hold its median: 12 of the 23
    # body keypoints) is mirrored back as a whole and then its arms alone: net, the legs
    assert rep["views_mirrored_back"] == 4, rep["views_mirrored_back"]
    assert rep["view_halves_mirrored_back"] == {"upper": 4, "lower": 0}
    assert fit.valid.all() and err.max() < 35.0, err

    # seed_poses: the earlier fit's pose as unknowns, where it is valid
    skel = scene.skel
    not_valid = dataclasses.replace(first, valid=np.r_[False, first.valid[1:]])
    seeds = seed_poses(not_valid, skel, np.r_[scene.frames, scene.frames[-1] + 2])
    assert seeds[0] is None and seeds[-1] is None
    assert all(s is not None for s in seeds[1:-1])
    bp, R, T = unpack(skel, scene.model.num_joints, np.stack(seeds[1:-1]))
    np.testing.assert_allclose(R, first.global_orient[1:], atol=1e-9)
    np.testing.assert_allclose(T, first.transl[1:], atol=1e-12)
    np.testing.assert_allclose(bp[:, skel.joints[1:]], np.asarray(first.body_pose)[1:, skel.joints[1:]],
                               atol=1e-9)
    assert seed_poses(None, skel, scene.frames) == [None] * F_SYN
