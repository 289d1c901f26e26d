"""fitting.marker_clean: injected ghosts, spikes and label swaps (10 and 150 samples) are found
in real captures, a 300-sample ghost is removed, real fast motion and soft tissue (tennis serve
at 50 Hz, jogging at 300 Hz) are left (almost) alone, and the report says per marker and sample
what was repaired."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from body.markers import PLUG_IN_GAIT_NAMES
from fitting.marker_clean import (
    CMU41_SEGMENTS,
    PLUG_IN_GAIT_SEGMENTS,
    REPAIR_CODES,
    CleanOptions,
    clean_markers,
    default_segments,
)
from formats.c3d import Markers, read_c3d

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"
# measured removal fractions (removed / observed marker samples): 0 on every file but the
# tennis serve (6.1e-4 Derrick, 9.4e-4 Derrick of the 2-player file, 2.6e-4 Viktor), whose
# fastest samples hold real labelling errors (the 13 cm RFRM-RWRB distance jumps to 29 cm)
MAX_REMOVED_FRACTION = 0.002
#: (marker, displacement m, samples): ghosts 5 m and 0.3 m off, one-sample spikes
INJECTED = (("LTHI", 5.0, 4), ("RFHD", 0.3, 3), ("LASI", 0.3, 6), ("RKNE", 0.3, 1),
            ("LTOE", 0.1, 1), ("RWRB", 0.1, 1), ("CLAV", 0.15, 1))
SWAP = ("LELB", "LFRM", 10)
LONG_SWAP = 150  # samples of the planted long swaps
#: neighbouring pairs swapped for LONG_SWAP samples in the real captures: wrist bar, pelvis
#: (mirror pair), knee-ankle (two segments, 40 cm apart), head, forearm-wrist, toe-heel
LONG_SWAP_PAIRS = (("LWRA", "LWRB"), ("RWRA", "RWRB"), ("LASI", "RASI"), ("RKNE", "RANK"),
                   ("LFHD", "LBHD"), ("RFRM", "RWRA"), ("LTOE", "LHEE"))
LONG_GHOST = ("RKNE", 0.3, 300)  # (marker, displacement m, samples)
#: the tennis serve's left forearm pronates at samples 930-1090 (after the ball is hit): LWRA
#: comes 25 mm nearer LFRM and LWRB 8 mm further, which looks like a wrist-bar swap against
#: LFRM alone; LFIN keeps both at their own distances (99 and 123 mm), so it is not one
KTK_PRONATION = (930, 1069)  # 140 samples
MAX_CLEAN_REPAIRED_FRACTION = 0.005  # the brief's bound on smooth real data (removed or un-swapped)


#: opensim's jogging labels the forearm marker FRA (LFRA, RFRA); read as Plug-in Gait's FRM
JOGGING_NAMES = tuple(n.replace("FRM", "FRA") for n in PLUG_IN_GAIT_NAMES)


def _real(name, **kw) -> Markers:
    if not (REAL / name).is_file():
        pytest.skip(f"{REAL / name} not available")
    m = read_c3d(REAL / name, allow_missing=True, **kw)
    return Markers(tuple(n.replace("FRA", "FRM") for n in m.names), m.xyz, m.rate_hz,
                   m.first_frame, m.subject)


def _with(m: Markers, xyz) -> Markers:
    return Markers(m.names, xyz, m.rate_hz, m.first_frame, m.subject)


def _inject(m: Markers, rng):
    """Artefacts in 8 disjoint slots of the capture: returns (markers, truth (F, M) bool,
    swap (first, last))."""
    x = m.xyz.copy()
    F = len(x)
    truth = np.zeros(x.shape[:2], bool)
    slots = list(rng.permutation(len(INJECTED) + 1))
    W = (F - 40) // (len(INJECTED) + 1)

    def start(L):
        return 20 + slots.pop() * W + int(rng.integers(0, W - L - 2))

    for name, off, L in INJECTED:
        s, k = start(L), m.names.index(name)
        d = rng.normal(size=3)
        x[s:s + L, k] += d * off / np.linalg.norm(d)
        truth[s:s + L, k] = True
    a, b, L = SWAP
    s = start(L)
    i, j = m.names.index(a), m.names.index(b)
    x[s:s + L, [i, j]] = x[s:s + L, [j, i]]
    return Markers(m.names, x, m.rate_hz, m.first_frame, m.subject), truth, (s, s + L - 1)


def _removed(clean: Markers, ref: Markers) -> np.ndarray:
    return np.isnan(clean.xyz[..., 0]) & ~np.isnan(ref.xyz[..., 0])


@pytest.mark.parametrize("name, kw", [("pycgm_movement_trial.c3d", {}),
                                      ("ktk_tennis_serve.c3d", {"subject": "Derrick"})])
def test_injected_ghosts_spikes_and_swap_are_found(name, kw):
    m = _real(name, markers=PLUG_IN_GAIT_NAMES, **kw)
    base, _ = clean_markers(m)  # the capture's own labelling errors (none in pycgm)
    known = _removed(base, m)
    i, j = m.names.index(SWAP[0]), m.names.index(SWAP[1])
    for seed in range(3):
        mi, truth, (s, e) = _inject(m, np.random.default_rng(seed))
        c, rep = clean_markers(mi)
        removed = _removed(c, m)
        assert removed[truth].all(), f"seed {seed}: missed {np.argwhere(truth & ~removed)}"
        new = removed & ~known
        assert (new & truth).sum() / new.sum() >= 0.95
        # the swap is exchanged back, exactly
        np.testing.assert_array_equal(c.xyz[s:e + 1][:, [i, j]], m.xyz[s:e + 1][:, [i, j]])
        swaps = [r for r in rep.runs if r["reason"] == "swap"]
        assert {(r["marker"], r["first_sample"], r["last_sample"], r["action"]) for r in swaps} \
            == {(SWAP[0], s, e, "unswapped"), (SWAP[1], s, e, "unswapped")}
        assert rep.unswapped == {SWAP[0]: SWAP[2], SWAP[1]: SWAP[2]}
        # reasons: one-sample artefacts are spikes, the 0.3 m runs ghosts, the 5 m one is
        # implausibly fast at any capture rate
        by_marker = {}
        for r in rep.runs:
            by_marker.setdefault(r["marker"], set()).add(r["reason"])
        assert "implausible_speed" in by_marker["LTHI"]
        for k in ("RFHD", "LASI"):  # 0.3 m in one sample: 36 m/s at 120 Hz, 15 m/s at 50 Hz
            assert by_marker[k] == ({"ghost"} if m.rate_hz < 100 else {"implausible_speed"})
        for k in ("RKNE", "LTOE", "RWRB", "CLAV"):
            assert "spike" in by_marker[k]
        doc = json.loads(json.dumps(rep.to_json()))
        assert doc["removed_samples"] == int(removed.sum())
        assert sum(doc["removed_by_reason"].values()) == doc["removed_samples"]


def _real_files():
    cmu = tuple(sorted({n for v in CMU41_SEGMENTS.values() for n in v} | {"RBAC"}))
    out = [("pycgm_static_trial.c3d", {"markers": PLUG_IN_GAIT_NAMES}),
           ("pycgm_movement_trial.c3d", {"markers": PLUG_IN_GAIT_NAMES}),
           ("ktk_tennis_serve.c3d", {"markers": PLUG_IN_GAIT_NAMES, "subject": "Derrick"}),
           ("ktk_tennis_serve_2player.c3d", {"markers": PLUG_IN_GAIT_NAMES, "subject": "Derrick"}),
           ("ktk_tennis_serve_2player.c3d", {"markers": PLUG_IN_GAIT_NAMES, "subject": "Viktor"}),
           ("nimble_cmu_02_05.c3d", {"markers": cmu}),
           ("opensim_jogging.c3d", {"markers": JOGGING_NAMES})]
    out += [(f"c3d_format_suite/{p}_{k}.c3d", {}) for p in ("pc", "dec") for k in ("int", "real")]
    return out


@pytest.mark.parametrize("name, kw", _real_files(), ids=lambda v: v if isinstance(v, str) else "")
def test_real_captures_come_out_almost_untouched(name, kw):
    from formats.errors import InputError

    try:
        m = _real(name, **kw)
    except InputError as e:  # dec_int.c3d: truncated, the reader says so
        pytest.skip(str(e))
    c, rep = clean_markers(m)
    assert rep.removed_fraction <= MAX_REMOVED_FRACTION, rep.to_json()["removed_by_reason"]
    assert rep.repaired_fraction <= MAX_CLEAN_REPAIRED_FRACTION
    assert not rep.unswapped  # no capture here holds a label swap (see test_ktk_forearm...)
    kept = ~np.isnan(c.xyz)
    np.testing.assert_array_equal(c.xyz[kept], m.xyz[kept])  # what is kept is not changed
    if "jogging" in name or "pycgm" in name or "nimble" in name:
        assert rep.removed_samples == 0


def test_segments_options_and_report_shape():
    assert default_segments(PLUG_IN_GAIT_NAMES) == PLUG_IN_GAIT_SEGMENTS
    cmu_names = [n for v in CMU41_SEGMENTS.values() for n in v]
    assert set(default_segments(cmu_names)) == set(CMU41_SEGMENTS)
    # names absent from the capture are ignored; a group left with one marker dropped
    assert default_segments(("LFHD", "RFHD", "LASI")) == {"head": ("LFHD", "RFHD")}
    with pytest.raises(ValueError, match="max_speed_m_s"):
        CleanOptions(max_speed_m_s=0)
    # one error naming every bad field
    with pytest.raises(ValueError) as err:
        CleanOptions(max_speed_m_s=-1.0, speed_max_run=2.5, swap_cap=float("nan"),
                     drift_window="51")
    for name in ("max_speed_m_s", "speed_max_run", "swap_cap", "drift_window"):
        assert name in str(err.value)
    assert "swap_switch" not in str(err.value)
    assert CleanOptions(speed_max_run=10, swap_switch=20).speed_max_run == 10
    # a lone ghost on a custom 4-marker rigid body, 50 Hz
    rng = np.random.default_rng(3)
    F = 200
    t = np.arange(F) / 50.0
    body = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.12, 0], [0, 0, 0.09]], float)
    R = [np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
         for a in 3 * np.sin(2 * np.pi * 0.7 * t)]
    xyz = np.stack([body @ r.T + [np.sin(t_), 0.5 * t_, 1.0] for r, t_ in zip(R, t, strict=True)])
    xyz += rng.normal(0, 0.0005, xyz.shape)
    xyz[80:83, 2] += [0.0, 0.0, 0.25]
    m = Markers(("A", "B", "C", "D"), xyz, 50.0, 7, None)
    c, rep = clean_markers(m, {"rb": ("A", "B", "C", "D", "absent")})
    assert np.isnan(c.xyz[80:83, 2]).all() and rep.removed_samples == 3
    assert rep.runs == [{"marker": "C", "reason": "ghost", "first_sample": 80,
                         "last_sample": 82, "action": "removed"}]
    assert rep.removed == {"C": {"ghost": 3}}
    assert c.first_frame == 7 and c.rate_hz == 50.0 and c.names == m.names


# ----------------------------------------------------------------- swaps and ghosts of any length


@pytest.mark.parametrize("name, kw", [("ktk_tennis_serve.c3d", {"subject": "Derrick"}),
                                      ("nimble_cmu_02_05.c3d", {})])
def test_a_long_swap_of_real_neighbours_is_unswapped_exactly(name, kw):
    """150 samples (3 s at 50 Hz, 1.25 s at 120 Hz) of two neighbouring markers exchanged:
    found from their distances to their segment neighbours, whatever the length, and both
    markers' samples restored exactly; the report names the run and codes it per sample."""
    m = _real(name, **kw)
    base, _ = clean_markers(m)
    rng = np.random.default_rng(4)
    pairs = [(a, b) for a, b in LONG_SWAP_PAIRS if a in m.names and b in m.names]
    assert len(pairs) >= 5
    for a, b in pairs:
        i, j = m.names.index(a), m.names.index(b)
        s = int(rng.integers(10, len(m.xyz) - LONG_SWAP - 10))
        e = s + LONG_SWAP - 1
        xyz = m.xyz.copy()
        xyz[s:e + 1, [i, j]] = xyz[s:e + 1, [j, i]]
        c, rep = clean_markers(_with(m, xyz))
        np.testing.assert_array_equal(c.xyz[s:e + 1][:, [i, j]], base.xyz[s:e + 1][:, [i, j]],
                                      err_msg=f"{a}/{b} at {s}")
        swaps = {(r["marker"], r["first_sample"], r["last_sample"], r["action"], r["partner"])
                 for r in rep.runs if r["reason"] == "swap"}
        assert swaps == {(a, s, e, "unswapped", b), (b, s, e, "unswapped", a)}, (a, b, s)
        codes = rep.codes(m.names)[s:e + 1][:, [i, j]]
        kept = ~np.isnan(base.xyz[s:e + 1][:, [i, j], 0])  # the capture's own ghosts stay removed
        assert (codes[kept] == REPAIR_CODES.index("unswapped")).all()
        assert (codes[~kept] != 0).all()
        # nothing else changes: the rest is cleaned as the capture without the swap
        np.testing.assert_array_equal(np.isnan(c.xyz), np.isnan(base.xyz))


def _synthetic_arm(F=600, rate=240.0, seed=0) -> Markers:
    """A right arm of Plug-in Gait markers (upper arm SHO UPA ELB, forearm FRM WRA WRB, hand
    FIN) walking forward while the elbow flexes 20-120 degrees and the forearm pronates; 0.5 mm
    noise and a 3 mm soft-tissue sway of the upper-arm markers."""
    rng = np.random.default_rng(seed)
    t = np.arange(F) / rate

    def rot(axis, a):
        c, s = np.cos(a), np.sin(a)
        k = {"x": (1, 2), "y": (0, 2), "z": (0, 1)}[axis]
        r = np.repeat(np.eye(3)[None], len(a), 0)
        r[:, k[0], k[0]] = c
        r[:, k[1], k[1]] = c
        r[:, k[0], k[1]] = -s
        r[:, k[1], k[0]] = s
        return r

    shoulder = np.stack([0.6 * t, 0.05 * np.sin(2 * np.pi * 0.5 * t), 1.4 + 0 * t], 1)
    R_up = rot("y", 0.4 * np.sin(2 * np.pi * 0.3 * t))
    elbow = shoulder + R_up @ np.array([0.0, 0.0, -0.30])
    flex = np.deg2rad(70 + 50 * np.sin(2 * np.pi * 0.4 * t))
    R_fo = R_up @ rot("y", flex) @ rot("z", 0.8 * np.sin(2 * np.pi * 0.25 * t))
    up = {"RSHO": [0.0, 0.0, 0.03], "RUPA": [0.05, 0.02, -0.15], "RELB": [0.0, 0.04, -0.30]}
    fo = {"RFRM": [0.03, 0.02, -0.12], "RWRA": [0.03, 0.0, -0.25], "RWRB": [-0.035, 0.0, -0.25],
          "RFIN": [-0.01, 0.01, -0.33]}
    names = tuple(up) + tuple(fo)
    xyz = np.zeros((F, len(names), 3))
    sway = 0.003 * np.sin(2 * np.pi * 1.1 * t)[:, None]
    for k, n in enumerate(names):
        if n in up:
            xyz[:, k] = shoulder + R_up @ np.array(up[n]) + (sway if n != "RSHO" else 0)
        else:
            xyz[:, k] = elbow + R_fo @ (np.array(fo[n]) - [0.0, 0.0, -0.0])
    xyz += rng.normal(0, 0.0005, xyz.shape)
    return Markers(names, xyz, rate, 1, None)


def test_a_150_sample_swap_on_a_synthetic_capture_is_unswapped_exactly():
    m = _synthetic_arm()
    base, rep0 = clean_markers(m)
    assert rep0.removed_samples == 0 and not rep0.unswapped
    for a, b, s in (("RWRA", "RWRB", 200), ("RFRM", "RWRA", 0), ("RELB", "RFRM", 449)):
        i, j = m.names.index(a), m.names.index(b)
        xyz = m.xyz.copy()
        xyz[s:s + LONG_SWAP, [i, j]] = xyz[s:s + LONG_SWAP, [j, i]]
        c, rep = clean_markers(_with(m, xyz))
        np.testing.assert_array_equal(c.xyz, m.xyz, err_msg=f"{a}/{b}")
        assert rep.unswapped == {a: LONG_SWAP, b: LONG_SWAP} and rep.removed_samples == 0


def test_a_long_ghost_is_removed_whole():
    """A knee marker 0.3 m off for 300 samples (2.5 s at 120 Hz: it fills the old running
    window, not the capture's median): removed, every sample of it, and little else."""
    m = _real("nimble_cmu_02_05.c3d")
    base, _ = clean_markers(m)
    name, off, L = LONG_GHOST
    k = m.names.index(name)
    xyz = m.xyz.copy()
    s = 700
    xyz[s:s + L, k] += [0.0, off, 0.0]
    c, rep = clean_markers(_with(m, xyz))
    removed = np.isnan(c.xyz[..., 0]) & ~np.isnan(base.xyz[..., 0])
    assert removed[s:s + L, k].all()
    assert removed.sum() <= L + 10, np.argwhere(removed)[:20]
    codes = rep.codes(m.names)
    assert set(np.unique(codes[s:s + L, k])) <= {REPAIR_CODES.index("ghost"),
                                                 REPAIR_CODES.index("implausible_speed")}


def test_ktk_forearm_pronation_is_no_swap_and_a_planted_one_there_is_found():
    """The serve's left forearm pronates at KTK_PRONATION: LWRA-LFRM 25 mm short for 140
    samples while LFIN keeps the wrist bar's labels; the cleaner leaves it as recorded. The
    same 140 samples with LWRA and LWRB truly exchanged are un-swapped exactly."""
    m = _real("ktk_tennis_serve.c3d", markers=PLUG_IN_GAIT_NAMES, subject="Derrick")
    i, j, f, n = (m.names.index(k) for k in ("LWRA", "LWRB", "LFIN", "LFRM"))
    s, e = KTK_PRONATION
    x = m.xyz
    d = {k: np.linalg.norm(x[:, a] - x[:, b], axis=1) for k, a, b in
         (("af", i, f), ("bf", j, f), ("an", i, n))}
    med = {k: np.median(v) for k, v in d.items()}
    assert d["an"][s:e + 1].min() < med["an"] - 0.02  # the forearm marker drifted ...
    for k in ("af", "bf"):  # ... the hand kept the labels
        assert abs(np.median(d[k][s:e + 1]) - med[k]) < 0.01
    c, rep = clean_markers(m)
    assert not rep.unswapped
    assert not np.isnan(c.xyz[s:e + 1][:, [i, j]]).any()
    xyz = x.copy()
    xyz[s:e + 1, [i, j]] = xyz[s:e + 1, [j, i]]
    c2, rep2 = clean_markers(_with(m, xyz))
    np.testing.assert_array_equal(c2.xyz, c.xyz)
    assert rep2.unswapped == {"LWRA": e - s + 1, "LWRB": e - s + 1}


def test_codes_follow_the_runs():
    m = _synthetic_arm(F=300)
    xyz = m.xyz.copy()
    k = m.names.index("RFIN")
    xyz[100:104, k] += [0.0, 0.0, 0.08]  # a 4-sample ghost (19 m/s: not too fast at 240 Hz)
    xyz[200, m.names.index("RUPA")] += [0.1, 0.0, 0.0]  # a spike
    i, j = m.names.index("RWRA"), m.names.index("RWRB")
    xyz[20:60, [i, j]] = xyz[20:60, [j, i]]
    c, rep = clean_markers(_with(m, xyz))
    codes = rep.codes(m.names)
    assert codes.shape == (300, len(m.names)) and codes.dtype == np.int8
    want = np.zeros_like(codes)
    want[100:104, k] = REPAIR_CODES.index("ghost")
    want[200, m.names.index("RUPA")] = REPAIR_CODES.index("spike")
    want[20:60, [i, j]] = REPAIR_CODES.index("unswapped")
    np.testing.assert_array_equal(codes, want)
    # removed samples are exactly the NaNs the cleaner made
    assert ((codes > 0) & (codes != REPAIR_CODES.index("unswapped"))).sum() == rep.removed_samples
    # any column order; names the report does not know stay 0
    sub = rep.codes(("RWRB", "nobody", "RFIN"))
    np.testing.assert_array_equal(sub[:, 0], want[:, j])
    assert not sub[:, 1].any()
    np.testing.assert_array_equal(sub[:, 2], want[:, k])


def test_fit_warning_blames_labels_only_where_the_cleaning_found_a_swap():
    from fitting.marker_fit import report_warnings

    per = {"median": 5.0, "p90": 30.0, "max": 80.0, "worst_frame": 7, "outlier_share": 0.2,
           "visible": 1.0}
    report = {"per_marker": {"RUPA": per, "RWRA": per}, "residual_mm": {"median": 3.0, "p90": 5.0},
              "skin_weight_outside_support": 0.0, "markers_missing_from_c3d": [],
              "frames_not_valid": {}}
    soft = report_warnings(report)
    assert len(soft) == 2 and not any("swaps in it" in w for w in soft)
    assert all("soft tissue" in w for w in soft)
    found = report_warnings(report, swapped={"RWRA"})
    assert [("swaps in it" in w) for w in found] == [False, True]
