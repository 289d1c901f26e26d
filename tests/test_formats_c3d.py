"""C3D reading/writing through ezc3d: labels, prefixes, units, gaps, non-markers, bad files."""
import ezc3d
import numpy as np
import pytest

from formats.c3d import Markers, read_c3d, write_c3d
from formats.errors import InputError


def vicon_like(path, labels, xyz_mm, rate=100.0, units="mm", residuals=None, first_frame=0,
               angles=()):
    """A C3D written directly with ezc3d (independent of write_c3d). xyz_mm: (F, N, 3)."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    if angles:
        c.add_parameter("POINT", "ANGLES", list(angles))
    pts = np.ones((4, len(labels), len(xyz_mm)))
    pts[:3] = np.transpose(xyz_mm, (2, 1, 0))
    c["data"]["points"] = pts
    if residuals is not None:
        c["data"]["meta_points"] = {"residuals": residuals.T[None]}
    c["header"]["points"]["first_frame"] = first_frame
    c.write(str(path))
    return path


@pytest.fixture
def rng():
    return np.random.default_rng(5)


def test_labels2_prefix_units_gaps_and_non_markers(tmp_path, rng):
    F, N = 30, 300  # > 255 points: labels continue in LABELS2
    labels = [f"Sub1:M{i:03d}" for i in range(N - 3)] + ["Sub1:PELO", "Sub1:LKneeAngles", "Prop1"]
    xyz = rng.uniform(-1500, 1500, (F, N, 3))
    res = np.zeros((F, N))
    res[4, 10] = -1.0            # Vicon gap: negative residual
    xyz[7, 20] = 0.0             # gap written as all-zero
    xyz[8, 21, 0] = 0.0          # a single zero coordinate is data, not a gap
    path = vicon_like(tmp_path / "t.c3d", labels, xyz, rate=240, residuals=res, first_frame=99,
                      angles=["Sub1:LKneeAngles"])
    raw = ezc3d.c3d(str(path))["parameters"]["POINT"]
    assert len(raw["LABELS"]["value"]) == 255 and "LABELS2" in raw

    want = ["M296", "M010", "M020", "M021", "M280"]
    m = read_c3d(path, markers=want)
    assert m.names == tuple(want) and m.subject == "Sub1"
    assert m.rate_hz == 240 and m.first_frame == 99 and m.xyz.shape == (F, 5, 3)
    assert np.isclose(m.times_s[0], 99 / 240)
    cols = [296, 10, 20, 21, 280]
    ref = xyz[:, cols] / 1000.0
    ref[4, 1] = np.nan
    ref[7, 2] = np.nan
    assert np.allclose(m.xyz, ref, atol=1e-6, equal_nan=True)
    assert np.isnan(m.xyz).sum() == 6

    # No list: the model output declared under POINT:ANGLES is dropped, other points stay.
    allm = read_c3d(path)
    assert "LKneeAngles" not in allm.names and "PELO" in allm.names and len(allm.names) == N - 1


def test_units_metres_and_two_subjects(tmp_path, rng):
    labels = ["A:LASI", "A:RASI", "B:LASI", "B:RASI"]
    xyz = rng.uniform(-2, 2, (5, 4, 3))
    path = vicon_like(tmp_path / "m.c3d", labels, xyz, units="m")
    with pytest.raises(InputError, match="pass subject"):
        read_c3d(path, markers=["LASI", "RASI"])
    b = read_c3d(path, markers=["RASI", "LASI"], subject="B")
    assert np.allclose(b.xyz, xyz[:, [3, 2]], atol=1e-6) and b.subject == "B"
    with pytest.raises(InputError) as e:
        read_c3d(path, markers=["LASI", "STRN"], subject="A")
    assert e.value.field == "POINT:LABELS" and "STRN" in str(e.value)
    miss = read_c3d(path, markers=["LASI", "STRN"], subject="A", allow_missing=True)
    assert np.isnan(miss.xyz[:, 1]).all() and np.isfinite(miss.xyz[:, 0]).all()
    vicon_like(tmp_path / "u.c3d", labels, xyz, units="inch")
    with pytest.raises(InputError) as e:
        read_c3d(tmp_path / "u.c3d")
    assert e.value.field == "POINT:UNITS"


def test_write_read_round_trip(tmp_path, rng):
    F, M = 40, 260
    xyz = rng.normal(0, 0.5, (F, M, 3))
    xyz[rng.random((F, M)) < 0.05] = np.nan
    m = Markers([f"K{i}" for i in range(M)], xyz, 200.0, first_frame=70000, subject="s03")
    write_c3d(tmp_path / "w.c3d", m, extra_points={"LFEA": np.zeros((F, 3)) + 0.3})
    back = read_c3d(tmp_path / "w.c3d", markers=m.names)
    assert back.subject == "s03" and back.rate_hz == 200 and back.first_frame == 70000
    assert np.array_equal(np.isnan(back.xyz), np.isnan(xyz))
    assert np.nanmax(np.abs(back.xyz - xyz)) < 1e-6  # float32 mm in the file
    assert "LFEA" in read_c3d(tmp_path / "w.c3d").names


def test_select_and_markers_validation(rng):
    m = Markers(["a", "b", "c"], rng.normal(size=(4, 3, 3)), 100.0)
    assert np.array_equal(m.select(["c", "a"]).xyz, m.xyz[:, [2, 0]])
    with pytest.raises(KeyError, match="d"):
        m.select(["d"])
    with pytest.raises(InputError, match="xyz"):
        Markers(["a"], np.zeros((4, 2, 3)), 100.0)
    with pytest.raises(InputError, match="rate_hz"):
        Markers(["a"], np.zeros((4, 1, 3)), 0.0)


def test_truncated_corrupt_and_missing(tmp_path, rng):
    path = vicon_like(tmp_path / "t.c3d", ["A", "B"], rng.normal(size=(600, 2, 3)))
    raw = path.read_bytes()
    (tmp_path / "trunc.c3d").write_bytes(raw[: int(len(raw) * 0.7)])
    with pytest.raises(InputError, match="truncated") as e:
        read_c3d(tmp_path / "trunc.c3d")
    assert e.value.frame is not None and e.value.frame < 600
    (tmp_path / "head.c3d").write_bytes(raw[:700])
    with pytest.raises(InputError, match="corrupt"):
        read_c3d(tmp_path / "head.c3d")
    (tmp_path / "junk.c3d").write_bytes(b"not a c3d" * 100)
    with pytest.raises(InputError, match="corrupt"):
        read_c3d(tmp_path / "junk.c3d")
    with pytest.raises(InputError, match="missing"):
        read_c3d(tmp_path / "none.c3d")
    # NaN coordinates (non-standard, but seen) are gaps, not numbers.
    xyz = rng.normal(size=(3, 1, 3))
    xyz[1, 0, 2] = np.nan
    m = read_c3d(vicon_like(tmp_path / "nan.c3d", ["A"], xyz))
    assert np.isnan(m.xyz[1]).all() and np.isfinite(m.xyz[[0, 2]]).all()


@pytest.mark.timeout(60)
def test_corrupt_parameter_bytes_raise_input_error_or_read(tmp_path, rng):
    """Random byte flips in the parameter section: either a clean read or InputError (ezc3d
    alone loops forever on some of these; the layout check must catch them first)."""
    path = vicon_like(tmp_path / "t.c3d", ["A", "B"], rng.normal(size=(600, 2, 3)))
    raw = path.read_bytes()
    outcomes = set()
    for seed in range(40):
        r = np.random.default_rng(seed)
        b = bytearray(raw)
        for _ in range(r.integers(1, 5)):
            b[r.integers(512, 1536)] = r.integers(0, 256)
        f = tmp_path / f"f{seed}.c3d"
        f.write_bytes(bytes(b))
        try:
            read_c3d(f)
            outcomes.add("read")
        except InputError as e:
            assert e.file == str(f)
            outcomes.add("error")
    assert outcomes == {"read", "error"}


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_reads_files_of_an_independent_writer(tmp_path, rng):
    """The `c3d` package writes int16-scaled data (POINT:SCALE > 0) and its own parameter layout."""
    import c3d

    F = 20
    xyz = rng.uniform(-1000, 1000, (F, 3, 3))
    w = c3d.Writer(point_rate=100.0, point_scale=0.1)
    for i in range(F):
        pts = np.zeros((3, 5))
        pts[:, :3] = xyz[i]
        pts[:, 3] = 0.5 if i != 5 else -1.0  # residual; negative on frame 5 = gap everywhere
        w.add_frames([(pts, np.zeros((0, 0)))])
    w.set_point_labels(["Sub:A", "Sub:B", "Sub:PELO"])
    w.set_start_frame(7)  # 1-based in the file
    with open(tmp_path / "w.c3d", "wb") as h:
        w.write(h)
    m = read_c3d(tmp_path / "w.c3d", markers=["B", "A"])
    assert m.first_frame == 6 and m.rate_hz == 100 and m.subject == "Sub"
    assert np.isnan(m.xyz[5]).all()
    ok = np.arange(F) != 5
    assert np.abs(m.xyz[ok] - xyz[ok][:, [1, 0]] / 1000).max() < 1e-4  # 0.1 mm int16 steps
