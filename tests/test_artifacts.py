"""Typed artifacts: ShapeFit and BodyFit through a folder (and an engine artifact), and every
kind of bad file rejected with an ArtifactError naming the file, the field and the frame."""
from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from artifacts import REASON_CODE, ArtifactError, BodyFit, ShapeFit
from formats.errors import InputError
from pipeline.store import StoredArtifact, Writer


def _rot(rng, F):
    from body.rotations import rodrigues

    return rodrigues(rng.normal(0, 1.0, (F, 3)))


def shape_fit(rng, M=6, S=12) -> ShapeFit:
    bary = rng.uniform(0.05, 1, (M, 3))
    return ShapeFit(betas=rng.normal(size=S), marker_names=np.array([f"M{i}" for i in range(M)]),
                    marker_face=rng.integers(0, 1000, M), marker_bary=bary / bary.sum(1, keepdims=True),
                    marker_offset=np.full(M, 0.0095), shape_source="scan",
                    placement_source="refined")


def body_fit(rng, F=10, J=7, M=5) -> BodyFit:
    vis = rng.uniform(size=(F, M)) > 0.2
    res = np.where(vis, rng.uniform(0, 0.01, (F, M)), np.nan)
    reason = np.zeros(F, np.int8)
    reason[:2] = REASON_CODE["held_before_first_marker"]
    reason[6] = REASON_CODE["too_few_markers"]
    return BodyFit(body_pose=rng.normal(0, 0.3, (F, J, 3)), global_orient=_rot(rng, F),
                   transl=rng.normal(0, 1, (F, 3)), betas=rng.normal(size=8),
                   frames=np.arange(0, 2 * F, 2), valid=reason == 0, invalid_reason=reason,
                   marker_names=np.array([f"m{i}" for i in range(M)]), marker_residual_m=res,
                   marker_weight=np.where(vis, rng.uniform(0, 1, (F, M)), np.nan), visible=vis)


def _write(folder: Path, arrays: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "fit.npz", **arrays)
    return folder


def test_shape_fit_round_trip_through_a_folder_and_an_engine_artifact(tmp_path):
    sf = shape_fit(np.random.default_rng(0))
    path = sf.save(Writer(tmp_path))
    assert path == tmp_path / "shape.npz"
    for src in (tmp_path, path, StoredArtifact(dir=tmp_path, key="k", unit="s1", stage="shape_fit", manifest={})):
        got = ShapeFit.load(src)
        assert got.names == sf.names
        for f in ShapeFit.FIELDS:
            np.testing.assert_array_equal(getattr(got, f.name), getattr(sf, f.name))
    raw = np.load(path)
    assert str(raw["artifact_kind"]) == "shape_fit" and int(raw["artifact_version"]) == 1


def test_body_fit_round_trip_keeps_the_valid_mask_and_reasons(tmp_path):
    bf = body_fit(np.random.default_rng(1))
    bf.save(Writer(tmp_path))
    got = BodyFit.load(tmp_path)
    np.testing.assert_array_equal(got.valid, bf.valid)
    np.testing.assert_array_equal(got.invalid_reason, bf.invalid_reason)
    assert got.invalid_reason.dtype == np.int8
    from artifacts.body_fit import INVALID_REASONS

    want = {"fitted": 7, "held_before_first_marker": 2, "too_few_markers": 1}
    assert got.reasons() == {n: want.get(n, 0) for n in INVALID_REASONS}  # every reason named
    np.testing.assert_array_equal(np.isnan(got.marker_residual_m), np.isnan(bf.marker_residual_m))
    np.testing.assert_allclose(got.global_orient, bf.global_orient)
    assert INVALID_REASONS[0] == "fitted"


def test_body_fit_without_markers_is_a_valid_kind(tmp_path):
    bf = replace(body_fit(np.random.default_rng(2)), marker_names=None, marker_residual_m=None,
                 marker_weight=None, visible=None)
    bf.save(Writer(tmp_path))
    got = BodyFit.load(tmp_path)
    assert not got.has_markers and got.num_frames == 10
    assert "visible" not in np.load(tmp_path / "fit.npz").files


def _bad(tmp_path, change) -> str:
    arrays = body_fit(np.random.default_rng(3)).arrays()
    change(arrays)
    folder = _write(tmp_path / "a", arrays)
    with pytest.raises(ArtifactError) as e:
        BodyFit.load(folder)
    assert isinstance(e.value, InputError)
    assert str(folder / "fit.npz") in str(e.value)
    return str(e.value)


def test_missing_field_is_named(tmp_path):
    msg = _bad(tmp_path, lambda a: a.pop("transl"))
    assert re.search(r"fit\.npz: transl: missing", msg), msg
    msg = _bad(tmp_path, lambda a: a.pop("visible"))  # one marker field without the others
    assert re.search(r"fit\.npz: visible: missing while", msg), msg


def test_wrong_shape_is_named(tmp_path):
    def short(a):
        a["transl"] = a["transl"][:-1]

    msg = _bad(tmp_path, short)
    assert re.search(r"fit\.npz: transl: expected shape \(F 3\) with F = 10 .*got \(9, 3\)", msg), msg

    def flat(a):
        a["betas"] = a["betas"][None]

    assert re.search(r"betas: expected shape \(S\)", _bad(tmp_path, flat))

    def dtype(a):
        a["valid"] = a["valid"].astype(float)

    assert re.search(r"valid: dtype float64 is not bool", _bad(tmp_path, dtype))


def test_wrong_kind_or_version_is_named(tmp_path):
    def kind(a):
        a["artifact_kind"] = np.array("shape_fit")

    assert re.search(r"fit\.npz: artifact_kind: is 'shape_fit', expected 'body_fit'",
                     _bad(tmp_path, kind))

    def version(a):
        a["artifact_version"] = np.array(7)

    assert re.search(r"artifact_version: is 7, this code reads version 1",
                     _bad(tmp_path, version))
    assert re.search(r"artifact_kind: missing", _bad(tmp_path, lambda a: a.pop("artifact_kind")))


def test_non_orthonormal_rotation_names_the_frame(tmp_path):
    def skew(a):
        a["global_orient"] = a["global_orient"].copy()
        a["global_orient"][4] *= 1.01  # scaled: not orthonormal

    msg = _bad(tmp_path, skew)
    assert re.search(r"global_orient \[frame 4\]: not a rotation matrix", msg), msg

    def nearly(a):  # within 1e-6: accepted
        a["global_orient"] = a["global_orient"] * (1 + 1e-8)

    arrays = body_fit(np.random.default_rng(3)).arrays()
    nearly(arrays)
    BodyFit.load(_write(tmp_path / "ok", arrays))


def test_translation_in_millimetres_is_rejected(tmp_path):
    def mm(a):
        a["transl"] = a["transl"] * 1000 + np.array([0, 0, 900.0])

    msg = _bad(tmp_path, mm)
    assert re.search(r"transl \[frame 0\]: \|value\| .* not metres", msg), msg


def test_mask_and_reasons_must_agree(tmp_path):
    def flip(a):
        a["valid"] = a["valid"].copy()
        a["valid"][0] = True  # reason 1 there

    assert re.search(r"valid \[frame 0\]: is True but invalid_reason is 1 "
                     r"\(held_before_first_marker\)", _bad(tmp_path, flip))

    def code(a):
        a["invalid_reason"] = a["invalid_reason"].copy()
        a["invalid_reason"][3] = 9

    assert re.search(r"invalid_reason \[frame 3\]: unknown code 9", _bad(tmp_path, code))

    def seen(a):  # a residual where the marker was not visible
        a["marker_residual_m"] = np.nan_to_num(a["marker_residual_m"])

    assert "not visible" in _bad(tmp_path, seen)


def test_save_validates_first_and_writes_nothing(tmp_path):
    sf = shape_fit(np.random.default_rng(4))
    bad = replace(sf, marker_offset=sf.marker_offset * 1000)  # mm
    with pytest.raises(ArtifactError, match=r"shape\.npz: marker_offset: marker M0: 9\.5 >= 0\.1"):
        bad.save(Writer(tmp_path))
    assert not (tmp_path / "shape.npz").exists()
    with pytest.raises(ArtifactError, match=r"shape_source: 'guess' is not one of"):
        replace(sf, shape_source="guess").validate()
    b = sf.marker_bary.copy()
    b[2] = 0.5
    with pytest.raises(ArtifactError, match=r"marker_bary: marker M2: coordinates sum to 1\.5"):
        replace(sf, marker_bary=b).validate()
    with pytest.raises(ArtifactError, match=r"no shape\.npz"):
        ShapeFit.load(tmp_path)
