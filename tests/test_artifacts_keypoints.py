"""Keypoints2D (artifacts/keypoints.py): the keypoints stage's keypoints.npz as a typed artifact."""
from pathlib import Path

import numpy as np
import pytest

from artifacts.base import ArtifactError
from artifacts.keypoints import PARTNER, WEARER, Keypoints2D
from formats import skeletons as S

C, F = 3, 4


class Writer:
    """The part of the engine's ArtifactWriter that save() uses."""

    def __init__(self, folder: Path):
        self.dir = folder

    def save_arrays(self, name, **arrays):
        p = self.dir / f"{name}.npz"
        np.savez(p, **arrays)
        return p


class Loaded:
    """The part of the engine's Artifact that load() uses."""

    def __init__(self, folder: Path):
        self.dir = folder

    def arrays(self, name):
        with np.load(self.dir / f"{name}.npz") as z:
            return {k: z[k] for k in z.files}


def make(rng=None, **over) -> Keypoints2D:
    """A consistent artifact whose keypoint (c, f, p, k) has x = 1000 c + 100 f + 10 p + k / 100
    (so a slice can be checked by value), a few cross-view outliers at confidence 0."""
    rng = rng or np.random.default_rng(0)
    c, f, p, k = np.meshgrid(np.arange(C), np.arange(F), np.arange(2), np.arange(65), indexing="ij")
    kp = np.zeros((C, F, 2, 65, 3), np.float32)
    kp[..., 0] = 1000 * c + 100 * f + 10 * p + k / 100
    kp[..., 1] = rng.uniform(0, 900, kp.shape[:-1])
    conf_raw = rng.uniform(0, 1, (C, F, 2, 65)).astype(np.float32)
    outlier = rng.uniform(size=conf_raw.shape) < 0.1
    kp[..., 2] = np.where(outlier, 0, conf_raw)
    boxes = np.sort(rng.uniform(0, 900, (C, F, 2, 2, 2)), axis=-2).transpose(0, 1, 2, 4, 3)
    boxes = boxes.reshape(C, F, 2, 4)[..., [0, 2, 1, 3]].astype(np.float32)  # x0 y0 x1 y1
    boxes[0, 1, 1] = np.nan  # partner not found there
    hand_boxes = np.repeat(boxes[:, :, :, None], 2, axis=3)
    args = dict(kp=kp, boxes=boxes, hand_boxes=hand_boxes, frames=np.array([0, 5, 10, 15]),
                wearer_retry=rng.uniform(size=(C, F)) < 0.3,
                partner_mode=rng.integers(0, 3, (C, F)).astype(np.int8),
                cross_view_outlier=outlier, conf_raw=conf_raw,
                cameras=np.array(["50591643", "58860488", "60457274"]))
    args.update(over)
    return Keypoints2D(**args)


def test_round_trip_through_a_writer_and_a_folder(tmp_path):
    a = make()
    path = a.save(Writer(tmp_path))
    assert path == tmp_path / "keypoints.npz"
    with np.load(path) as z:
        assert str(z["artifact_kind"]) == "keypoints2d" and int(z["artifact_version"]) == 1
        assert z["kp"].dtype == np.float32 and z["frames"].dtype == np.int64
        assert z["partner_mode"].dtype == np.int8 and z["cameras"].dtype.kind == "U"
    for src in (Loaded(tmp_path), tmp_path, path):
        b = Keypoints2D.load(src)
        for f in ("kp", "boxes", "hand_boxes", "frames", "wearer_retry", "partner_mode",
                  "cross_view_outlier", "conf_raw", "cameras"):
            np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    assert b.camera_ids == ["50591643", "58860488", "60457274"] and b.n_frames == F
    assert b.camera("58860488") == 1


def test_float64_input_is_stored_as_float32():
    a = make()
    b = make(kp=a.kp.astype(np.float64), frames=a.frames.astype(np.int32))
    assert b.kp.dtype == np.float32 and b.frames.dtype == np.int64


def _save_raw(folder: Path, **arrays) -> Path:
    p = folder / "keypoints.npz"
    np.savez(p, **arrays)
    return p


def test_wrong_shape_is_rejected_naming_the_file_and_the_field(tmp_path):
    arrays = make().arrays()
    arrays["conf_raw"] = arrays["conf_raw"][:, :3]  # F = 3, kp says 4
    p = _save_raw(tmp_path, **arrays)
    with pytest.raises(ArtifactError, match=r"keypoints\.npz: conf_raw: expected shape \(C F 2 65\) "
                                            r"with F = 4"):
        Keypoints2D.load(tmp_path)
    arrays = make().arrays()
    arrays["kp"] = arrays["kp"][..., :23, :]  # not KP65
    _save_raw(tmp_path, **arrays)
    with pytest.raises(ArtifactError, match=r"keypoints\.npz: kp: expected shape") as e:
        Keypoints2D.load(p)
    assert e.value.file == str(p) and e.value.field == "kp"


def test_wrong_kind_version_or_missing_field_is_rejected(tmp_path):
    arrays = make().arrays()
    _save_raw(tmp_path, **{**arrays, "artifact_kind": np.array("body_fit")})
    with pytest.raises(ArtifactError, match=r"artifact_kind: is 'body_fit', expected 'keypoints2d'"):
        Keypoints2D.load(tmp_path)
    _save_raw(tmp_path, **{**arrays, "artifact_version": np.array(7)})
    with pytest.raises(ArtifactError, match=r"artifact_version: is 7"):
        Keypoints2D.load(tmp_path)
    _save_raw(tmp_path, **{k: v for k, v in arrays.items() if k != "hand_boxes"})
    with pytest.raises(ArtifactError, match=r"keypoints\.npz: hand_boxes: missing"):
        Keypoints2D.load(tmp_path)
    old = {k: v for k, v in arrays.items() if not k.startswith("artifact_")}  # pre-typed file
    _save_raw(tmp_path, **old)
    with pytest.raises(ArtifactError, match=r"artifact_kind: missing"):
        Keypoints2D.load(tmp_path)
    _save_raw(tmp_path, **{**arrays, "wearer_retry": arrays["wearer_retry"].astype(np.float32)})
    with pytest.raises(ArtifactError, match=r"wearer_retry: dtype float32 is not bool"):
        Keypoints2D.load(tmp_path)


def test_implausible_values_name_the_field_and_the_video_frame(tmp_path):
    a = make()
    kp = a.kp.copy()
    kp[1, 2, 0, 5, 2] = 1.5
    raw = a.conf_raw.copy()
    raw[1, 2, 0, 5] = 1.5
    with pytest.raises(ArtifactError, match=r"kp \[frame 10\]: confidence outside \[0, 1\]"):
        make(kp=kp, conf_raw=raw).validate(tmp_path / "keypoints.npz")
    # a confidence that is not conf_raw with the outliers at 0
    kp = a.kp.copy()
    k = np.argwhere(~a.cross_view_outlier)[0]
    kp[tuple(k)][2] = kp[tuple(k)][2] / 2
    with pytest.raises(ArtifactError, match=r"kp \[frame \d+\]: confidence differs from conf_raw"):
        make(kp=kp).validate()
    with pytest.raises(ArtifactError, match=r"frames \[frame 5\]: not increasing: 10 then 5"):
        make(frames=np.array([0, 10, 5, 15])).validate()
    boxes = a.boxes.copy()
    boxes[2, 3, 0, 0] = boxes[2, 3, 0, 2] + 1  # x0 > x1
    with pytest.raises(ArtifactError, match=r"boxes \[frame 15\]: a box with x1 < x0"):
        make(boxes=boxes).validate()
    pm = a.partner_mode.copy()
    pm[0, 0] = 3
    with pytest.raises(ArtifactError, match=r"partner_mode \[frame 0\]: code 3"):
        make(partner_mode=pm).validate()
    with pytest.raises(ArtifactError, match=r"cameras: camera ids must be unique"):
        make(cameras=np.array(["a", "b", "a"])).validate()
    # save validates first and writes nothing
    with pytest.raises(ArtifactError):
        make(partner_mode=pm).save(Writer(tmp_path))
    assert not (tmp_path / "keypoints.npz").exists()


def test_person_body_and_hand_slices_return_the_named_keypoints():
    a = make()
    x = lambda arr: arr[..., 0]  # noqa: E731  x encodes (camera, frame, person, keypoint)
    c, f = np.meshgrid(np.arange(C), np.arange(F), indexing="ij")
    base = (1000 * c + 100 * f)[..., None]
    for person in (WEARER, PARTNER):
        np.testing.assert_allclose(x(a.person(person)), base + 10 * person + np.arange(65) / 100,
                                   atol=1e-3)
        np.testing.assert_allclose(x(a.body(person)), base + 10 * person + np.arange(23) / 100,
                                   atol=1e-3)
        hands = a.hands(person)
        assert hands.shape == (C, F, 42, 3)
        np.testing.assert_allclose(x(hands), base + 10 * person + np.arange(23, 65) / 100, atol=1e-3)
        left, right = a.hand(person, "left"), a.hand(person, "right")
        np.testing.assert_array_equal(left, hands[:, :, :21])
        np.testing.assert_array_equal(right, hands[:, :, 21:])
    # the blocks are the ones formats.skeletons names
    i = S.KP65.index("r_hand_wrist")
    np.testing.assert_allclose(a.hand(PARTNER, "right")[..., 0, 0], base[..., 0] + 10 + i / 100, atol=1e-3)
    assert S.KP65[22] == "r_heel" and S.KP65[23] == "l_hand_wrist"
    with pytest.raises(ValueError, match="person"):
        a.hands(2)
    with pytest.raises(ValueError, match="side"):
        a.hand(0, "middle")


def test_kp65_flip_is_the_left_right_mirror():
    from formats.skeletons import KP65, KP65_FLIP

    f = np.asarray(KP65_FLIP)
    assert np.array_equal(f[f], np.arange(len(KP65)))  # an involution
    for i, n in enumerate(KP65):
        m = KP65[f[i]]
        if n.startswith(("l_", "r_")):
            assert m[2:] == n[2:] and m[:2] != n[:2], (n, m)
        else:
            assert m == n, (n, m)
