"""Body-size plausibility: a capture or scan in the wrong unit is an error naming the unit."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from formats.c3d import Markers, read_c3d, write_c3d
from formats.errors import InputError
from formats.plausibility import (
    HUMAN_EXTENT_M,
    check_capture_scale,
    check_scan_scale,
    format_length,
    marker_extent,
)

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"


def _person(frames: int = 60, height: float = 1.75, seed: int = 0) -> np.ndarray:
    """(F, 39, 3) metres: a standing person's marker cloud (feet ~5 cm, head ~height - 5 cm),
    swaying and walking 1 m, with a few gaps."""
    rng = np.random.default_rng(seed)
    z = np.concatenate([[0.03, 0.03, 0.05, 0.05], rng.uniform(0.17, 0.83, 31) * height,
                        [height - 0.05] * 4])
    xy = rng.normal(scale=0.07 * height, size=(39, 2))
    base = np.concatenate([xy, z[:, None]], axis=1)
    t = np.linspace(0, 1, frames)[:, None, None]
    xyz = base[None] + t * np.array([1.0, 0, 0]) + rng.normal(scale=0.005, size=(frames, 39, 3))
    xyz[rng.random((frames, 39)) < 0.05] = np.nan
    return xyz


def _capture(tmp_path, xyz, unit_label: str | None = None) -> Path:
    """Write xyz (metres) with write_c3d (mm), then optionally relabel POINT:UNITS via ezc3d
    without touching the numbers (so a file in mm becomes 'metres' etc.)."""
    import ezc3d

    p = write_c3d(tmp_path / "cap.c3d", Markers([f"M{i}" for i in range(xyz.shape[1])], xyz, 100.0))
    if unit_label is not None:
        c = ezc3d.c3d(str(p))
        c["parameters"]["POINT"]["UNITS"]["value"] = [unit_label]
        c.write(str(p))
    return p


def test_normal_capture_passes_and_returns_its_size(tmp_path):
    xyz = _person()
    m = read_c3d(_capture(tmp_path, xyz))
    assert m.unit == "mm"
    size = check_capture_scale(m.xyz, "cap.c3d", declared_unit=m.unit)
    assert 1.55 < size < 1.8  # head markers to foot markers of a 1.75 m person


def test_capture_in_metres_labelled_mm(tmp_path):
    # numbers in metres (1.7) but the file says mm: reads as 1.7 mm
    p = _capture(tmp_path, _person() / 1000.0)
    m = read_c3d(p)
    with pytest.raises(InputError) as e:
        check_capture_scale(m.xyz, p, declared_unit=m.unit)
    err = e.value
    assert err.file == str(p) and err.field == "POINT:UNITS"
    assert "person is 1.7 mm tall" in str(err) or "person is 1.6 mm tall" in str(err)
    assert "look like metres" in str(err) and "the file says mm" in str(err)


def test_capture_in_mm_labelled_metres_reads_in_km(tmp_path):
    p = _capture(tmp_path, _person(), unit_label="m")  # mm numbers, file says m
    m = read_c3d(p)
    assert m.unit == "m"
    with pytest.raises(InputError) as e:
        check_capture_scale(m.xyz, p, declared_unit=m.unit)
    msg = str(e.value)
    assert " km tall" in msg and "look like millimetres" in msg and "the file says m " in msg


def test_capture_in_cm_labelled_mm(tmp_path):
    p = _capture(tmp_path, _person() / 10.0)  # 10x too small: cm numbers read as mm
    m = read_c3d(p)
    with pytest.raises(InputError, match="look like centimetres, the file says mm"):
        check_capture_scale(m.xyz, p, declared_unit=m.unit)


def test_ghost_point_five_metres_away_still_passes():
    xyz = _person()
    ghost = np.full((len(xyz), 1, 3), np.nan)
    ghost[:, 0] = [5.0, 0.0, 0.0]  # a reflection 5 m away, in every frame
    with_ghost = np.concatenate([xyz, ghost], axis=1)
    clean = check_capture_scale(xyz, "a.c3d")
    ghosted = check_capture_scale(with_ghost, "a.c3d")
    assert abs(ghosted - clean) < 0.05
    # and one that flickers in a few frames at 40 m
    flicker = with_ghost.copy()
    flicker[:, -1] = np.nan
    flicker[::15, -1] = [40.0, 3.0, 1.0]
    assert abs(check_capture_scale(flicker, "a.c3d") - clean) < 0.05
    # while a second person-size cloud is not an outlier: the verdict is about the whole cloud
    assert marker_extent(np.concatenate([xyz, xyz + [0.6, 0, 0]], axis=1)) > clean


def test_child_lying_and_tall_adult_pass():
    child = _person(height=0.55)  # a lying infant's markers span ~0.5 m
    assert check_capture_scale(child, "c.c3d") > HUMAN_EXTENT_M[0]
    lying = _person()[..., [2, 1, 0]]  # the same adult, lying along x
    assert 1.5 < check_capture_scale(lying, "l.c3d") < 1.9
    reach = _person(height=2.2)
    reach[:, :2, 2] = 2.85  # hands up
    assert check_capture_scale(reach, "r.c3d") < HUMAN_EXTENT_M[1]


def test_no_visible_marker_is_an_error():
    with pytest.raises(InputError, match="cannot judge"):
        check_capture_scale(np.full((5, 4, 3), np.nan), "empty.c3d")


def test_scan_in_mm_is_an_error_naming_the_unit():
    rng = np.random.default_rng(1)
    # A body-like surface: points on a 1.7 m tall ellipsoid, in metres
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    body = u * [0.2, 0.12, 0.85] + [0, 0, 0.85]
    assert 1.65 < check_scan_scale(body, "scan.ply") < 1.75
    ghosts = np.concatenate([body, rng.uniform(-10, 10, size=(20, 3))])  # floaters
    assert 1.65 < check_scan_scale(ghosts, "scan.ply") < 1.75
    with pytest.raises(InputError) as e:
        check_scan_scale(body * 1000.0, "scan.ply")
    err = e.value
    assert err.file == "scan.ply" and err.field == "scan"
    assert "person is 1.7 km tall" in str(err) and "look like millimetres" in str(err)
    with pytest.raises(InputError, match="look like centimetres"):
        check_scan_scale(body * 100.0, "scan.ply")


def test_format_length():
    assert format_length(0.0018) == "1.8 mm"
    assert format_length(1800.0) == "1.8 km"
    assert format_length(17.2) == "17 m"
    assert format_length(0.17) == "17 cm"


@pytest.mark.skipif(not REAL.is_dir(), reason="shared real captures not present")
def test_real_captures_pass_and_their_rescaled_copies_fail():
    for name, subject in (("ktk_tennis_serve.c3d", "Derrick"), ("nimble_cmu_02_05.c3d", None),
                          ("pycgm_static_trial.c3d", None)):
        m = read_c3d(REAL / name, subject=subject)
        size = check_capture_scale(m.xyz, name, declared_unit=m.unit)
        assert 1.4 < size < 2.2, (name, size)
        for factor in (1e-3, 1e-2, 0.1, 10.0, 1e3):
            with pytest.raises(InputError):
                check_capture_scale(m.xyz * factor, name, declared_unit=m.unit)
