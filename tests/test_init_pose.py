"""The partner's first-frame initialisation (fitting.init_pose) on a synthetic capture: an Anny
body at a known rotation and translation seen by 4 cameras, 2 px noise, one view's detection
wrong (another place): rotation within 10 degrees, translation within 5 cm, the wrong view
rejected; too few views or no torso -> None with a reason."""
from __future__ import annotations

import numpy as np
import pytest

from artifacts.keypoints import Keypoints2D
from body import forward, load_model
from body.joints import keypoints as model_keypoints
from body.rotations import rodrigues
from calib import look_at, project
from calib.geometry import TriangulateOptions
from fitting.init_pose import InitOptions, init_from_keypoints, init_pose
from fitting.marker_fit import unpack
from fitting.skinned import fit_skeleton
from formats.errors import InputError
from formats.skeletons import KP65

R_TRUE = rodrigues(np.array([0.05, -0.08, 2.3]))
T_TRUE = np.array([0.4, -0.3, 0.02])
BENDS = {"lowerarm01.L": [0.0, 0.0, 0.9], "lowerarm01.R": [0.9, 0.0, 0.0],
         "upperarm01.R": [0.0, 0.5, 0.0], "lowerleg01.L": [0.7, 0.0, 0.0],
         "upperleg01.R": [-0.5, 0.0, 0.0]}
LIMB_KP = [KP65.index(n) for n in ("l_elbow", "r_elbow", "l_wrist", "r_wrist", "l_knee", "r_knee",
                                   "l_ankle", "r_ankle")]


@pytest.fixture(scope="module")
def scene():
    model = load_model("anny")
    J = model.num_joints
    pose = np.zeros((1, J, 3))
    for n, r in BENDS.items():
        pose[0, model.joint_names.index(n)] = r
    betas = np.zeros(8)
    betas[:3] = [0.8, -0.5, 0.3]
    out = forward(model, betas, pose, R_TRUE[None], T_TRUE[None])
    X = model_keypoints(model, out, "kp65")[0]
    cams = [look_at(f"c{i}", [4.0 * np.cos(a), 4.0 * np.sin(a), 1.6], [0.4, -0.3, 1.0], (1000.0, 1000.0),
                    (450.0, 450.0), 900, 900) for i, a in enumerate(np.linspace(0.3, 2 * np.pi + 0.3, 4, endpoint=False))]
    rng = np.random.default_rng(0)
    kp = np.zeros((4, len(KP65), 3))
    for i, c in enumerate(cams):
        kp[i, :, :2] = project(c, X) + rng.normal(0, 2.0, (len(KP65), 2))
        kp[i, :, 2] = 0.9
    # view 3 detected someone else: the same body 0.6 m away, turned
    wrong = (X - T_TRUE) @ rodrigues(np.array([0, 0, 1.2])).T + T_TRUE + [0.6, 0.4, 0.0]
    kp[3, :, :2] = project(cams[3], wrong)
    return model, betas, cams, kp, X


def _rot_err_deg(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def _keypoints_of(model, betas, x):
    skel = fit_skeleton(model)
    pose, R, T = unpack(skel, model.num_joints, x[None])
    return model_keypoints(model, forward(model, betas, pose, R, T), "kp65")[0]


def test_recovers_rotation_translation_and_rejects_the_wrong_view(scene):
    model, betas, cams, kp, X = scene
    res = init_pose(model, betas, cams, kp)
    assert res.ok and res.reason == ""
    assert res.x.shape == (fit_skeleton(model).n,)
    assert _rot_err_deg(rodrigues(res.x[:3]), R_TRUE) < 10.0
    assert np.linalg.norm(res.x[3:6] - T_TRUE) < 0.05
    # the wrong view's observations are outliers, the three others are kept
    assert res.view_inlier_rate[3] < 0.1 and np.all(res.view_inlier_rate[:3] > 0.9)
    assert not res.inliers[:, 3].any()
    assert res.n_triangulated >= 60 and res.reproj_rms_px < 5.0
    ok = np.isfinite(res.points).all(1)
    assert np.median(np.linalg.norm(res.points[ok] - X[ok], axis=1)) < 0.02
    # without RANSAC the wrong view drags the points: the rejection is what makes it work
    plain = init_pose(model, betas, cams, kp,
                      opts=InitOptions(limbs=False, triangulation=TriangulateOptions(ransac=False)))
    assert plain.ok and np.linalg.norm(plain.x[3:6] - T_TRUE) > 0.10


def test_limb_directions_bring_the_limbs_closer(scene):
    model, betas, cams, kp, X = scene
    rigid = init_pose(model, betas, cams, kp, opts=InitOptions(limbs=False))
    limbs = init_pose(model, betas, cams, kp)
    assert len(limbs.limbs_set) == 8 and rigid.limbs_set == ()
    assert np.allclose(rigid.x[:6], limbs.x[:6]) and not np.any(rigid.x[6:])
    e_rigid = np.linalg.norm(_keypoints_of(model, betas, rigid.x)[LIMB_KP] - X[LIMB_KP], axis=1)
    e_limbs = np.linalg.norm(_keypoints_of(model, betas, limbs.x)[LIMB_KP] - X[LIMB_KP], axis=1)
    assert e_limbs.mean() < 0.5 * e_rigid.mean() and e_limbs.max() < 0.06, (e_rigid, e_limbs)


def test_from_keypoints_artifact_picks_the_partner_and_matches_cameras(scene):
    model, betas, cams, kp, X = scene
    C, K = kp.shape[:2]
    both = np.zeros((C, 2, 2, K, 3), np.float32)
    both[:, 1, 1] = kp  # the partner at detected frame index 1 (video frame 10)
    both[:, 1, 0] = kp[::-1]  # the wearer slot: something else
    order = [2, 0, 3, 1]  # the artifact's camera order differs from ours
    both = both[order]
    art = Keypoints2D(kp=both, boxes=np.full((C, 2, 2, 4), np.nan, np.float32),
                      hand_boxes=np.full((C, 2, 2, 2, 4), np.nan, np.float32),
                      frames=np.array([5, 10]), wearer_retry=np.zeros((C, 2), bool),
                      partner_mode=np.zeros((C, 2), np.int8),
                      cross_view_outlier=np.zeros((C, 2, 2, K), bool), conf_raw=both[..., 2].copy(),
                      cameras=np.array([cams[i].name for i in order]))
    res = init_from_keypoints(art, 10, model, betas, cams)
    assert res.ok and np.linalg.norm(res.x[3:6] - T_TRUE) < 0.05
    assert res.view_inlier_rate[3] < 0.1  # in our camera order
    with pytest.raises(InputError, match="frame 7"):
        init_from_keypoints(art, 7, model, betas, cams, file="kp.npz")


def test_too_few_views_or_no_torso_gives_none_with_a_reason(scene):
    model, betas, cams, kp, _ = scene
    one = kp.copy()
    one[1:, :, 2] = 0.0
    res = init_pose(model, betas, cams, one)
    assert res.x is None and not res.ok and "1 view" in res.reason and res.n_triangulated == 0
    # the torso hidden in all but one good view (hips and a shoulder): no rigid fit
    hidden = kp.copy()
    for n in ("l_hip", "r_hip", "l_shoulder"):
        hidden[1:, KP65.index(n), 2] = 0.0
    res = init_pose(model, betas, cams, hidden)
    assert res.x is None and "torso" in res.reason and res.n_triangulated > 0
