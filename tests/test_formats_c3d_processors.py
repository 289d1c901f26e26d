"""C3D files of every processor type: Intel (PC), DEC and SGI/MIPS (big-endian), int and real.

Data: ``../shared/real/c3d_format_suite/`` (the C3D format's own sample suite: one 89-frame,
36-marker capture written six ways; ezc3d 1.7 refuses the SGI files).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from formats.c3d import read_c3d
from formats.c3d_bigendian import dec_to_ieee, processor_type, read_c3d_dict
from formats.errors import InputError

SUITE = Path(__file__).resolve().parents[2] / "shared" / "real" / "c3d_format_suite"
FILES = [f"{p}_{t}" for p in ("pc", "dec", "sgi") for t in ("int", "real")]
PROC = {"pc": 84, "dec": 85, "sgi": 86}

pytestmark = pytest.mark.skipif(not SUITE.is_dir(), reason="shared C3D sample suite not present")


def _path(name: str) -> Path:
    return SUITE / f"{name}.c3d"


def test_processor_bytes_are_what_the_names_say():
    for name in FILES:
        assert processor_type(_path(name)) == PROC[name.split("_")[0]], name


def test_every_processor_reads_the_same_markers():
    ref = read_c3d(_path("pc_real"))
    scale_m = abs(float(read_c3d_dict(_path("pc_int"))["parameters"]["POINT"]["SCALE"]["value"][0])) / 1000
    assert 2e-4 < scale_m < 3e-4  # the integer files' quantum, 0.28 mm
    assert len(ref.names) == 36 and ref.xyz.shape == (89, 36, 3)
    assert 0.02 < np.isnan(ref.xyz[..., 0]).mean() < 0.2  # real gaps, same in every file
    for name in FILES:
        m = read_c3d(_path(name))
        assert m.names == ref.names, name
        assert (m.rate_hz, m.first_frame, m.unit) == (50.0, 0, "mm"), name
        assert np.array_equal(np.isnan(m.xyz), np.isnan(ref.xyz)), name
        d = np.nanmax(np.abs(m.xyz - ref.xyz))
        assert d <= scale_m * 1.001, (name, d)
        if name.endswith("real"):  # float files hold the very same numbers
            assert d < 1e-9, (name, d)


def test_sgi_matches_pc_bit_for_bit():
    for t in ("int", "real"):
        sgi, pc = read_c3d_dict(_path(f"sgi_{t}")), read_c3d_dict(_path(f"pc_{t}"))
        assert sgi["processor"] == 86 and pc["processor"] == 84
        np.testing.assert_array_equal(sgi["data"]["points"], pc["data"]["points"])
        np.testing.assert_array_equal(sgi["data"]["meta_points"]["residuals"],
                                      pc["data"]["meta_points"]["residuals"])
        assert sgi["parameters"]["POINT"]["LABELS"]["value"] == pc["parameters"]["POINT"]["LABELS"]["value"]
        np.testing.assert_allclose(sgi["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"],
                                   pc["parameters"]["FORCE_PLATFORM"]["CORNERS"]["value"])


@pytest.mark.parametrize("name", ["pc_int", "pc_real", "dec_int", "dec_real"])
def test_own_parser_agrees_with_ezc3d(name):
    """The big-endian parser is one parser for all processors: on the files ezc3d reads it must
    give ezc3d's points, residuals, camera masks and parameters."""
    import ezc3d

    ours, ref = read_c3d_dict(_path(name)), ezc3d.c3d(str(_path(name)))
    np.testing.assert_array_equal(ours["data"]["points"], ref["data"]["points"])
    res_o, res_r = ours["data"]["meta_points"]["residuals"], ref["data"]["meta_points"]["residuals"]
    np.testing.assert_allclose(res_o, res_r, rtol=1e-6)
    valid = res_r[0] >= 0  # ezc3d reports masks of invalid points too; ours are empty there
    np.testing.assert_array_equal(ours["data"]["meta_points"]["camera_masks"][:, valid],
                                  ref["data"]["meta_points"]["camera_masks"][:, valid])
    assert ours["header"]["points"]["first_frame"] == ref["header"]["points"]["first_frame"]
    assert ours["header"]["points"]["frame_rate"] == ref["header"]["points"]["frame_rate"]
    n = 0
    for g, params in ref["parameters"].items():
        if g.startswith("__"):
            continue
        for p, v in params.items():
            if p.startswith("__") or len(v["value"]) == 0:
                continue  # ezc3d adds empty defaults (ANALOG:BITS, ...) the file does not hold
            mine = ours["parameters"][g][p]["value"]
            if isinstance(v["value"], list):
                assert [s.strip() for s in mine] == [s.strip() for s in v["value"]], (g, p)
            else:
                np.testing.assert_allclose(mine, v["value"], rtol=1e-6, err_msg=f"{g}:{p}")
            n += 1
    assert n > 40


def test_dec_floats():
    """VAX F-floating: 1.0 is 0x4080 0x0000 (word order high first, little-endian words)."""
    assert dec_to_ieee(bytes([0x80, 0x40, 0, 0]))[0] == 1.0
    assert dec_to_ieee(bytes([0x80, 0xC0, 0, 0]))[0] == -1.0
    assert dec_to_ieee(bytes([0x48, 0x43, 0, 0]))[0] == 50.0  # IEEE bits of 200.0
    # The header scale of the DEC files decodes to the PC files' POINT:SCALE.
    pc = read_c3d_dict(_path("pc_int"))["parameters"]["POINT"]["SCALE"]["value"][0]
    head = _path("dec_int").read_bytes()[12:16]
    assert dec_to_ieee(head)[0] == pytest.approx(pc, rel=1e-7)


@pytest.mark.parametrize("name", ["sgi_int", "sgi_real"])
def test_truncated_sgi_file_names_file_frame_and_processor(tmp_path, name):
    p = tmp_path / f"{name}.c3d"
    data = _path(name).read_bytes()
    p.write_bytes(data[: len(data) - len(data) // 3])
    with pytest.raises(InputError) as e:
        read_c3d(p)
    assert e.value.file == str(p) and e.value.field == "<data>"
    assert isinstance(e.value.frame, int) and 0 < e.value.frame < 89
    assert "SGI/MIPS" in str(e.value)
    with pytest.raises(InputError) as e:  # the parser alone says the same
        read_c3d_dict(p)
    assert e.value.field == "<data>" and "SGI/MIPS" in str(e.value)


def test_corrupt_sgi_parameter_names_processor(tmp_path):
    p = tmp_path / "bad.c3d"
    shutil.copy(_path("sgi_int"), p)
    raw = bytearray(p.read_bytes())
    # The first parameter record after the POINT group: its type byte -> 7 (no such type).
    sec = raw[512:]

    def s8(b):
        return b - 256 if b > 127 else b

    pos = 4
    while s8(sec[pos + 1]) < 0:  # skip group records (negative id)
        nl = abs(s8(sec[pos]))
        pos = pos + 2 + nl + int.from_bytes(sec[pos + 2 + nl:pos + 4 + nl], "big", signed=True)
    nl = abs(s8(sec[pos]))
    raw[512 + pos + 4 + nl] = 7
    p.chmod(0o644)
    p.write_bytes(bytes(raw))
    for reader in (read_c3d, read_c3d_dict):
        with pytest.raises(InputError) as e:
            reader(p)
        assert e.value.file == str(p) and e.value.field.startswith("<parameters>")
        assert "SGI/MIPS" in str(e.value) and "type 7" in str(e.value)
