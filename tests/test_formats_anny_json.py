"""formats/anny_json.py: round trip and bad input naming file, field and frame."""
import json

import numpy as np
import pytest

from body.rotations import rodrigues
from formats.anny_json import read_anny, write_anny
from formats.errors import InputError


def _params(P=2, F=3, J=4, S=5, seed=0):
    rng = np.random.default_rng(seed)
    return dict(
        transl=rng.normal(size=(P, F, 3)),
        global_orient=rodrigues(rng.normal(size=(P, F, 3))),
        body_pose=rodrigues(0.3 * rng.normal(size=(P, F, J, 3))),
        betas=rng.normal(size=(P, F, S)),
        joint_names=[f"j{i}" for i in range(J)],
    )


def test_round_trip(tmp_path):
    p = _params()
    path = write_anny(tmp_path / "anny" / "Hug 1.json", **p)
    d = read_anny(path)
    for k in ("transl", "global_orient", "body_pose", "betas"):
        np.testing.assert_allclose(d[k], p[k], atol=1e-12)
    assert d["joint_names"] == tuple(p["joint_names"])
    json.loads(path.read_text())  # strict JSON


def test_single_person_ok(tmp_path):
    d = read_anny(write_anny(tmp_path / "a.json", **_params(P=1)))
    assert d["transl"].shape == (1, 3, 3)


def _write_raw(tmp_path, **override):
    p = _params()
    doc = {k: (np.asarray(v).tolist() if k != "joint_names" else v) for k, v in p.items()}
    doc.update(override)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    return path, p


def test_wrong_shape_names_file_and_field(tmp_path):
    path, p = _write_raw(tmp_path, transl=np.zeros((2, 3, 2)).tolist())
    with pytest.raises(InputError) as e:
        read_anny(path)
    assert e.value.field == "transl" and e.value.file == str(path)


def test_frames_disagree(tmp_path):
    path, _ = _write_raw(tmp_path, betas=np.zeros((2, 4, 5)).tolist())
    with pytest.raises(InputError, match="betas"):
        read_anny(path)


def test_nan_names_frame(tmp_path):
    p = _params()
    bp = p["transl"].copy()
    bp[1, 2, 0] = np.nan
    path = tmp_path / "nan.json"
    doc = {k: (np.asarray(v).tolist() if k != "joint_names" else v) for k, v in p.items()}
    doc["transl"] = bp.tolist()
    path.write_text(json.dumps(doc))  # json writes NaN
    with pytest.raises(InputError) as e:
        read_anny(path)
    assert e.value.field == "transl" and e.value.frame == 2


def test_not_rotation_names_frame(tmp_path):
    p = _params()
    bp = p["body_pose"].copy()
    bp[0, 1, 2] *= 2.0
    path, _ = _write_raw(tmp_path, body_pose=bp.tolist())
    with pytest.raises(InputError) as e:
        read_anny(path)
    assert e.value.field == "body_pose" and e.value.frame == 1


def test_missing_key_and_joint_names(tmp_path):
    path, _ = _write_raw(tmp_path, joint_names=["a", "b"])
    with pytest.raises(InputError, match="joint_names"):
        read_anny(path)
    doc = json.loads(path.read_text())
    del doc["betas"]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="betas: missing"):
        read_anny(path)


def test_three_persons_rejected(tmp_path):
    with pytest.raises(InputError, match="transl"):
        write_anny(tmp_path / "x.json", **_params(P=3))


def test_truncated(tmp_path):
    path = tmp_path / "t.json"
    path.write_text('{"transl": [[')
    with pytest.raises(InputError, match="<json>"):
        read_anny(path)
