"""CHI3D joints3d_25 / smplx / contact-signature files: round trips, camera frame, bad input."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calib_camera import random_camera

from formats.chi3d import (
    SMPLX_SHAPES,
    ContactSignature,
    read_contact_signatures,
    read_joints3d_25,
    read_smplx,
    smplx_in_camera,
    write_contact_signatures,
    write_joints3d_25,
    write_smplx,
)
from formats.errors import InputError


def random_smplx(rng, F=4):
    out = {}
    for k, tail in SMPLX_SHAPES.items():
        if tail[-2:] == (3, 3):
            n = int(np.prod(tail[:-2]))
            out[k] = Rotation.random(2 * F * n, random_state=rng.integers(1 << 30)).as_matrix().reshape(
                (2, F) + tail)
        else:
            out[k] = rng.normal(size=(2, F) + tail)
    return out


def test_joints_round_trip_and_release_loader(tmp_path):
    rng = np.random.default_rng(0)
    j = rng.normal(size=(2, 7, 25, 3))
    p = write_joints3d_25(tmp_path / "joints3d_25" / "Hug 1.json", j)
    assert np.array_equal(read_joints3d_25(p), j)
    # how the public tools read it: np.array(json.load(f)['joints3d_25'])
    assert np.array(json.loads(p.read_text())["joints3d_25"]).shape == (2, 7, 25, 3)


@pytest.mark.parametrize("value, match, frame", [
    (np.zeros((2, 5, 24, 3)).tolist(), "expected shape", None),
    ([[[[0, 0, 0]] * 25] * 3, [[[0, 0, 0]] * 25] * 2], "rectangular", None),
])
def test_joints_bad_shapes(tmp_path, value, match, frame):
    (tmp_path / "j.json").write_text(json.dumps({"joints3d_25": value}))
    with pytest.raises(InputError, match=match) as e:
        read_joints3d_25(tmp_path / "j.json")
    assert e.value.field == "joints3d_25" and e.value.frame == frame


def test_joints_nan_missing_truncated(tmp_path):
    j = np.zeros((2, 6, 25, 3))
    j[1, 4, 3, 0] = np.nan
    (tmp_path / "j.json").write_text(json.dumps({"joints3d_25": j.tolist()}))
    with pytest.raises(InputError) as e:
        read_joints3d_25(tmp_path / "j.json")
    assert e.value.frame == 4 and e.value.file == str(tmp_path / "j.json")
    (tmp_path / "j.json").write_text(json.dumps({"joints": []}))
    with pytest.raises(InputError, match="missing"):
        read_joints3d_25(tmp_path / "j.json")
    (tmp_path / "j.json").write_text(json.dumps({"joints3d_25": np.zeros((2, 3, 25, 3)).tolist()})[:-30])
    with pytest.raises(InputError, match="truncated"):
        read_joints3d_25(tmp_path / "j.json")
    with pytest.raises(InputError):
        write_joints3d_25(tmp_path / "w.json", j)


def test_smplx_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(1)
    prm = random_smplx(rng)
    p = write_smplx(tmp_path / "smplx" / "Grab 4.json", prm)
    back = read_smplx(p)
    for k in SMPLX_SHAPES:
        assert np.allclose(back[k], prm[k], atol=1e-15)
    d = json.loads(p.read_text())
    d["body_pose"][1][2][5] = (np.array(d["body_pose"][1][2][5]) * 1.1).tolist()  # not a rotation
    p.write_text(json.dumps(d))
    with pytest.raises(InputError) as e:
        read_smplx(p)
    assert (e.value.field, e.value.frame) == ("body_pose", 2)
    d = json.loads(json.dumps({k: v.tolist() for k, v in prm.items()}))
    d["betas"] = np.zeros((2, 3, 10)).tolist()  # 3 frames instead of 4
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match="frames") as e:
        read_smplx(p)
    assert e.value.field == "betas"
    del d["expression"]
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match="missing") as e:
        read_smplx(p)
    assert e.value.field == "expression"


def test_smplx_in_camera_matches_transforming_the_body():
    rng = np.random.default_rng(2)
    cam = random_camera(rng)
    G = Rotation.random(random_state=3).as_matrix()
    transl = rng.normal(size=3)
    J0 = rng.normal(size=3) * 0.2
    v = rng.normal(size=(50, 3))  # rest-pose vertices of some body
    world = (v - J0) @ G.T + J0 + transl  # SMPL: R (v - J0) + J0 + transl
    Gc, tc = smplx_in_camera(G, transl, J0, cam)
    in_cam = (v - J0) @ Gc.T + J0 + tc
    assert np.allclose(in_cam, (world - cam.T) @ cam.R.T, atol=1e-12)


def test_contact_signatures_round_trip(tmp_path):
    sig = {"Hug 1": ContactSignature(fr_id=52, start_fr=40, end_fr=90,
                                     smplx_regions=np.array([[3, 10], [4, 11]]),
                                     smplx_faces=np.array([[1200, 5400]])),
           "Push 2": ContactSignature(fr_id=7, smplx_regions=np.zeros((0, 2), int),
                                      smplx_faces=np.zeros((0, 2), int))}
    p = write_contact_signatures(tmp_path / "interaction_contact_signature.json", sig)
    back = read_contact_signatures(p)
    assert back["Hug 1"].fr_id == 52 and (back["Hug 1"].start_fr, back["Hug 1"].end_fr) == (40, 90)
    assert np.array_equal(back["Hug 1"].smplx_regions, [[3, 10], [4, 11]])
    assert back["Push 2"].start_fr is None and back["Push 2"].smplx_faces.shape == (0, 2)
    raw = json.loads(p.read_text())
    assert raw["Hug 1"]["ghum_signature"] == {"region_id": [], "face_id": []}


@pytest.mark.parametrize("entry, field, frame", [
    ({"smplx_signature": {"region_id": [], "face_id": []}}, "A.fr_id", None),
    ({"fr_id": 3}, "A.smplx_signature", 3),
    ({"fr_id": 3, "smplx_signature": {"region_id": [[1, 2, 3]], "face_id": []}},
     "A.smplx_signature.region_id", 3),
    ({"fr_id": 3, "smplx_signature": {"region_id": [[1, -2]], "face_id": []}},
     "A.smplx_signature.region_id", 3),
    ({"fr_id": 3, "smplx_signature": {"region_id": []}}, "A.smplx_signature.face_id", 3),
    ({"fr_id": 3.5, "smplx_signature": {"region_id": [], "face_id": []}}, "A.fr_id", None),
    ({"fr_id": 3, "start_fr": 5, "smplx_signature": {"region_id": [], "face_id": []}},
     "A.start_fr/end_fr", 3),
    ({"fr_id": 3, "smplx_signature": {"region_id": [], "face_id": []},
      "anny_signature": {"region_id": [[1, 2]], "face_id": [[4, -5]]}},
     "A.anny_signature.face_id", 3),
    ({"fr_id": 3, "smplx_signature": {"region_id": [], "face_id": []},
      "anny_signature": {"region_id": [[1, 2]], "face_id": [], "region_names": [["a", "b"], ["c", "d"]]}},
     "A.anny_signature.region_names", 3),
])
def test_contact_signatures_bad_input(tmp_path, entry, field, frame):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"A": entry}))
    with pytest.raises(InputError) as e:
        read_contact_signatures(p)
    assert (e.value.file, e.value.field, e.value.frame) == (str(p), field, frame)


def test_smplx_with_three_frames_is_not_mistaken_for_rotations(tmp_path):
    """transl (P, 3, 3) for 3 frames is a translation per frame, not a rotation matrix."""
    from formats.chi3d import SMPLX_SHAPES, read_smplx, write_smplx

    rng = np.random.default_rng(0)
    P, F = 2, 3
    params = {}
    for key, tail in SMPLX_SHAPES.items():
        if tail[-2:] == (3, 3):
            params[key] = np.broadcast_to(np.eye(3), (P, F) + tail).copy()
        else:
            params[key] = rng.normal(size=(P, F) + tail)
    write_smplx(tmp_path / "a.json", params)
    back = read_smplx(tmp_path / "a.json")
    np.testing.assert_allclose(back["transl"], params["transl"])
