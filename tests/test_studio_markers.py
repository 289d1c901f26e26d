"""The studio's realistic marker capture (``studio.mocap``) and the marker-only ``markers``
preset: hand placement a few cm off the template and on its segment, per-marker skin offsets,
soft-tissue artefact driven by the joints (none on bony markers), labelling faults recorded
exactly as written into the C3D, the rest of a Vicon file (model outputs, angles, unlabelled
points, analog channels, a non-zero first frame), and the demo/bench presets' realistic markers
(their committed recipes unchanged)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
HZ = 120.0
N = 240  # 2 s


@pytest.fixture(scope="module")
def model():
    from body import load_model

    return load_model("anny")


@pytest.fixture(scope="module")
def subject(model):
    from studio.subjects import make_subjects

    return make_subjects(model, ("m01a", "m02a"), np.random.default_rng([41, 2]))[0]


@pytest.fixture(scope="module")
def template(model):
    from body.markers import plug_in_gait

    return plug_in_gait(model)


@pytest.fixture(scope="module")
def placement(model, subject, template):
    from studio.mocap import realistic_placement
    from studio.session import rest_vertices

    return realistic_placement(model, rest_vertices(model, subject), template, np.random.default_rng(7))


@pytest.fixture(scope="module")
def motion(model, subject):
    """A static stance whose left knee and hip flex and extend twice (0.8 Hz), then the left
    arm swings up: the joints the thigh, shank and upper-arm markers follow."""
    from studio.session import skinned, static_track

    tr = static_track(subject.person, N, HZ, np.random.default_rng(8))
    t = np.arange(N) / HZ
    knee, hip = model.joint_index("lowerleg01.L"), model.joint_index("upperleg01.L")
    arm = model.joint_index("upperarm01.L")
    tr.pose[:, knee, 0] += 0.8 * (1 - np.cos(2 * np.pi * 0.8 * t))
    tr.pose[:, hip, 0] -= 0.4 * (1 - np.cos(2 * np.pi * 0.8 * t))
    tr.pose[:, arm, 1] += 0.9 * np.clip((t - 1.2) / 0.3, 0, 1)
    V, J, G = skinned(model, subject, tr)
    return tr, V, J, G


FAULTY = dict(swaps_per_min=240.0, ghosts_per_min=180.0, spikes_per_min=300.0)
FIRST = 1733


@pytest.fixture(scope="module")
def cap(model, placement, motion, tmp_path_factory):
    from studio.mocap import RealismOptions, capture

    tr, V, J, G = motion
    c = capture(model, placement.markerset, V, J, G, tr.pose, HZ, FIRST, "m01a",
                np.random.default_rng(9), RealismOptions(**FAULTY))
    path = tmp_path_factory.mktemp("cap") / "trial.c3d"
    c.write(path)
    return c, path


# ------------------------------------------------------------------------------ placement
def test_placement_differs_from_template_by_a_few_cm_and_stays_on_its_segment(model, subject, template,
                                                                              placement):
    from studio import constants as C
    from studio.mocap import surface_segments
    from studio.session import perturbed_markerset, rest_vertices

    slide = placement.slide_m
    assert 0.010 < np.median(slide) < 0.035, np.median(slide)
    assert slide.max() < 1.25 * C.MARKER_PLACE_SLIDE_MAX_M
    assert (slide > 0.02).sum() >= 8  # several markers are more than 2 cm off
    ms = placement.markerset
    assert surface_segments(model, ms.faces, ms.bary) == list(placement.segments)
    # the demo's placement only slides by millimetres
    V0 = rest_vertices(model, subject)
    demo = perturbed_markerset(model, subject, template, np.random.default_rng(7))
    from body.markers import marker_positions

    d_demo = np.linalg.norm(marker_positions(V0, model.faces, demo.with_offsets(0.0))
                            - placement.template_xyz, axis=1)
    assert np.median(d_demo) < 0.4 * np.median(slide)


def test_offsets_vary_per_marker_and_are_larger_on_pelvis_and_thigh(placement):
    from studio.mocap import place_class

    off = placement.markerset.offsets
    assert off.min() >= 0.005 and off.max() <= 0.025
    assert off.std() > 0.002
    cls = np.array([place_class(n) for n in placement.markerset.names])
    assert off[cls == "pelvis_thigh"].mean() > off[cls == "head"].mean() + 0.003


# ------------------------------------------------------------------------------ soft tissue
def test_soft_tissue_follows_the_joint_angles_and_spares_bony_markers(model, placement, motion, cap):
    c, _ = cap
    tr = motion[0]
    names = list(placement.markerset.names)
    sta = c.sta
    bony = sta.amplitude == 0
    assert {"LFHD", "RBHD", "LANK", "RHEE", "LASI", "RASI"} <= {n for n, b in zip(names, bony, strict=True) if b}
    assert np.all(sta.total[:, bony] == 0.0)
    m = names.index("LTHI")
    d = sta.joint[:, m]
    assert 0.002 < np.sqrt((np.linalg.norm(d, axis=1) ** 2).mean()) < 0.03
    # the joint term is a smooth function of the knee and hip rotations: a linear fit explains it
    th = tr.pose[:, [model.joint_index("upperleg01.L"), model.joint_index("lowerleg01.L")]].reshape(N, 6)
    X = np.c_[th, th ** 2, np.ones(N)]
    coef, *_ = np.linalg.lstsq(X, d, rcond=None)
    r2 = 1 - ((X @ coef - d) ** 2).sum() / ((d - d.mean(0)) ** 2).sum()
    assert r2 > 0.95, r2
    # and it follows the knee flexion: |STA| correlates with the flexion angle
    flex = np.linalg.norm(tr.pose[:, model.joint_index("lowerleg01.L")], axis=1)
    assert np.corrcoef(flex, np.linalg.norm(d, axis=1))[0, 1] > 0.8
    # the right leg does not move: its thigh marker's joint term stays what the stance gives
    r = names.index("RTHI")
    assert np.ptp(sta.joint[:, r], axis=0).max() < 1e-3


def test_wobble_rings_down_after_an_acceleration(model):
    from studio.mocap import soft_tissue

    F = 240
    names = ("LTHI", "LASI")
    # the marker moves at 2 m/s and stops dead at sample 60 (a heel strike)
    x = np.minimum(np.arange(F), 60) / HZ * 2.0
    rigid = np.zeros((F, 2, 3))
    rigid[:, :, 0] = x[:, None]
    frames = np.broadcast_to(np.eye(3), (F, 2, 3, 3))
    st = soft_tissue(names, np.zeros((F, model.num_joints, 3)), model.joint_names, frames, rigid, HZ,
                     np.random.default_rng(0))
    w = np.linalg.norm(st.wobble[:, 0], axis=1)
    assert np.all(st.total[:, 1] == 0)  # ASIS: bony
    assert w[:58].max() < 1e-9
    peak = w[60:75].max()
    assert 0.001 < peak < 0.02
    assert w[60 + int(0.5 * HZ):].max() < 0.1 * peak  # damped within half a second
    # it oscillates: the displacement changes sign after the stop
    assert (np.diff(np.sign(st.wobble[60:120, 0, 0])) != 0).sum() >= 2


# ------------------------------------------------------------------------------ faults
def test_faults_in_the_ground_truth_are_what_the_c3d_holds(placement, cap):
    from formats.c3d import read_c3d

    c, path = cap
    names = list(placement.markerset.names)
    got = read_c3d(path, markers=names)
    clean = c.clean_xyz
    f = c.faults
    assert len(f.swaps) >= 2 and len(f.ghosts) >= 2 and len(f.spikes) >= 3
    tol = 0.005
    for a, b, s, e in f.swaps:
        assert np.linalg.norm(clean[s, a] - clean[s, b]) > 0.01  # a visible exchange
        assert np.all(np.linalg.norm(got.xyz[s:e, a] - clean[s:e, b], axis=1) < tol)
        assert np.all(np.linalg.norm(got.xyz[s:e, b] - clean[s:e, a], axis=1) < tol)
    for (m, s, e), p in zip(f.ghosts, f.ghost_xyz, strict=True):
        assert np.allclose(got.xyz[s:e, m], p, atol=1e-4)
        assert np.linalg.norm(p - clean[s, m]) > 0.09
    for (m, s), o in zip(f.spikes, f.spike_offset, strict=True):
        assert np.linalg.norm(got.xyz[s, m] - clean[s, m] - o) < tol
        assert np.linalg.norm(o) >= 0.02
    fault = f.mask(N, len(names))
    assert np.array_equal(np.isnan(got.xyz[..., 0]), c.gap)
    assert not (fault & c.gap).any()
    ok = ~fault & ~c.gap
    assert np.linalg.norm(got.xyz - clean, axis=-1)[ok].max() < tol
    # the readable list names the markers and the C3D frames (1-based)
    js = f.as_json(names, FIRST)
    a, b, s, e = f.swaps[0]
    assert js["swaps"][0]["markers"] == [names[a], names[b]]
    assert js["swaps"][0]["frames"] == [FIRST + 1 + s, FIRST + e]


# ------------------------------------------------------------------------------ the file
def test_c3d_has_model_outputs_angles_unlabelled_points_analogs_and_a_first_frame(placement, cap):
    import ezc3d

    from formats.c3d import read_c3d

    c, path = cap
    raw = ezc3d.c3d(str(path))
    labels = list(raw["parameters"]["POINT"]["LABELS"]["value"])
    names = list(placement.markerset.names)
    assert labels[:len(names)] == [f"m01a:{n}" for n in names]
    for lab in ("m01a:PELO", "m01a:LFEA", "m01a:RTIO", "m01a:LKneeAngles"):
        assert lab in labels
    assert sum(lab.startswith("*") for lab in labels) >= 2  # unlabelled, no subject prefix
    assert "m01a:LKneeAngles" in raw["parameters"]["POINT"]["ANGLES"]["value"]
    assert raw["header"]["points"]["first_frame"] == FIRST
    ratio = int(round(raw["parameters"]["ANALOG"]["RATE"]["value"][0] / HZ))
    assert ratio >= 2
    an = raw["data"]["analogs"]
    alab = list(raw["parameters"]["ANALOG"]["LABELS"]["value"])
    assert an.shape == (1, len(alab), N * ratio) and "Force.Fz1" in alab
    assert raw["parameters"]["FORCE_PLATFORM"]["USED"]["value"][0] == 1
    fz = an[0, alab.index("Force.Fz1")]
    assert -1500 < np.median(fz) < -300  # standing on the plate: the body's weight
    # the reader with the marker list returns exactly the markers, with the first frame
    got = read_c3d(path, markers=names)
    assert got.names == tuple(names) and got.first_frame == FIRST and got.subject == "m01a"
    assert got.xyz.shape == (N, len(names), 3)
    # knee angles follow the true knee flexion (degrees)
    k = raw["data"]["points"][:3, labels.index("m01a:LKneeAngles")]
    assert np.ptp(k[0]) > 60


def test_write_c3d_rejects_analogs_that_are_not_a_multiple_of_the_frames(tmp_path):
    from formats.c3d import Markers, write_c3d
    from formats.errors import InputError

    mk = Markers(("A",), np.zeros((10, 1, 3)), 100.0)
    with pytest.raises(InputError, match=r"analogs\[EMG1\]"):
        write_c3d(tmp_path / "x.c3d", mk, analogs={"EMG1": np.zeros(25)})


# ------------------------------------------------------------------------------ presets
def test_demo_and_bench_presets_use_realistic_markers_and_kind_plans_do_not():
    from studio import constants as C
    from studio import plan as PL
    from studio import preset_recipe
    from studio.mocap import MocapOptions
    from studio.session import plan_dict

    for name in ("demo", "bench"):
        p = PL.make_plan(PL.PRESETS[name].seed, preset=name)
        assert isinstance(p, PL.SessionPlan) and p.marker_realism is True
        assert plan_dict(p)["marker_realism"] is True
        k = PL.make_plan(PL.PRESETS[name].seed, preset=name, realism=False)  # the kind studio
        assert k.marker_realism is False
        assert "marker_realism" not in plan_dict(k)  # what gt/session.json of kind data holds
        raw = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
        want = preset_recipe(name, ROOT / "recipes", ROOT / "data" / name)
        assert {k: v for k, v in want.items() if k != "stages"} == \
            {k: v for k, v in raw.items() if k != "stages"}
    o = MocapOptions()
    assert (o.noise_sd_m, o.gap_fraction, o.gaps_per_marker, o.gap_len) == \
        (C.MARKER_NOISE_SD_M, 0.3, (1, 3), (5, 50))
    assert (C.MARKER_SLIDE_SD_M, C.MARKER_OFFSET_SD_M, C.MOCAP_HZ) == (0.004, 0.001, 100.0)


def test_markers_preset_plan_and_committed_recipe():
    from studio import plan as PL
    from studio import preset_recipe

    p = PL.make_plan(PL.PRESETS["markers"].seed, preset="markers")
    assert isinstance(p, PL.MarkerSessionPlan) and len(p.subjects) == 2 and p.mocap_hz == 120.0
    for s in p.subjects:
        st = p.static_of(s)
        mo = [t for t in p.motion_trials if t.subject == s]
        assert len(st) == 1 and len(mo) == 2
        assert 1.5 <= st[0].samples / p.mocap_hz <= 2.5
        assert all(3.9 <= t.samples / p.mocap_hz <= 6.5 for t in mo)
        assert all(t.partner != s for t in mo)
    assert all(t.first_frame > 0 for t in p.trials)
    raw = yaml.safe_load((ROOT / "recipes" / "markers.yaml").read_text())
    want = preset_recipe("markers", ROOT / "recipes", ROOT / "data" / "markers")
    assert want == raw
    assert raw["cameras"] == [] and raw["session"] == "studio_markers"
    for q in raw["sequences"].values():
        assert set(q) == {"markers_on", "c3d", "fps"} and q["fps"] is None
    for s in raw["subjects"].values():
        assert "scan" not in s and s["static"][0]["frames"] is None
        assert s["static"][0]["c3d"].endswith("_static.c3d")
    from recipes import load_recipe

    r = load_recipe(ROOT / "recipes" / "markers.yaml", check_files=False)
    assert not r.cameras and all(q.partner is None and not q.videos for q in r.sequences.values())
    assert [len(s.static) for s in r.subjects.values()] == [1, 1]


def test_generate_markers_one_subject_one_trial(model, tmp_path):
    """The generation function end to end on 1 subject (a static and one short kick)."""
    from body.markers import load_json, marker_positions
    from formats.c3d import read_c3d
    from studio import plan as PL
    from studio.mocap import Faults
    from studio.session import generate

    p = PL.make_marker_plan(5, ("kick",), preset=None, n_subjects=1, trial_s=(2.5, 2.5), static_s=1.0)
    from recipes import load_recipe

    path = generate(tmp_path, p)
    load_recipe(path)  # every file it names exists
    recipe = yaml.safe_load(path.read_text())
    assert list(recipe["subjects"]) == ["m01a"] and list(recipe["sequences"]) == ["m01/Kick 1"]
    meta = json.loads((tmp_path / "gt" / "session.json").read_text())
    assert "first_frame + 1 + i" in meta["frame_convention"]
    ms = load_json(tmp_path / "gt" / "subjects" / "m01a_markers.json", num_faces=len(model.faces))
    for t in p.trials:
        g = np.load(tmp_path / PL.trial_gt_path(t))
        got = read_c3d(tmp_path / PL.trial_c3d_path(t), markers=list(ms.names))
        n = len(got.xyz)
        assert n == t.samples == len(g["vertices"]) == len(g["joints"]) == len(g["body_pose"])
        assert got.first_frame == t.first_frame == int(g["first_frame"]) > 0
        assert g["c3d_frames"][0] == t.first_frame + 1 and g["c3d_frames"][-1] == t.first_frame + n
        # the truth is the placement on the true mesh, sample by sample
        assert np.abs(marker_positions(g["vertices"][::25], model.faces, ms)
                      - g["markers_true"][::25]).max() < 1e-4
        clean = g["markers_true"] + g["markers_sta"]
        ok = ~g["markers_gap"] & ~g["markers_fault"]
        assert np.linalg.norm(got.xyz - clean, axis=-1)[ok].max() < 0.005
        f = Faults.from_arrays(g)
        assert np.array_equal(f.mask(n, len(ms)), g["markers_fault"])
    kick = np.load(tmp_path / "gt" / "m01" / "Kick 1.npz")
    assert np.linalg.norm(kick["markers_sta"], axis=-1).max() > 0.005


@pytest.mark.slow
def test_marker_trials_made_in_worker_processes_are_byte_for_byte_those_made_in_one(
        tmp_path, monkeypatch):
    """Each trial draws from its own random streams and runs on one BLAS thread, so a marker
    session made with its trials in two worker processes (their environment asking for another
    BLAS thread count than this process has) writes the very same C3D and truth files as one
    made in this process (the markers preset's trials go to workers: ``studio_workers``)."""
    import filecmp
    import os

    from studio import plan as PL
    from studio.session import generate, studio_workers

    monkeypatch.delenv("MOCAP_STUDIO_WORKERS", raising=False)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # the workers' BLAS told otherwise
        monkeypatch.setenv(var, "2" if os.environ.get(var) == "1" else "1")

    p = PL.make_marker_plan(5, ("kick", "grab"), preset=None, n_subjects=1, trial_s=(1.5, 1.5),
                            static_s=0.5)
    a, b = tmp_path / "one", tmp_path / "two"
    generate(a, p, workers=1)
    generate(b, p, workers=2)
    files = [f for f in a.rglob("*") if f.is_file() and f.name != "session.json"]
    assert sum(f.suffix == ".c3d" for f in files) == 3
    assert [str(f.relative_to(a)) for f in files
            if not filecmp.cmp(f, b / f.relative_to(a), shallow=False)] == []
    assert studio_workers(p) == 1  # 300 samples: not worth a worker's start
    preset = PL.make_plan(PL.PRESETS["markers"].seed, preset="markers")
    assert studio_workers(preset) == min(len(os.sched_getaffinity(0)), 4)  # 4 motion trials
    monkeypatch.setenv("MOCAP_STUDIO_WORKERS", "1")
    assert studio_workers(preset) == 1
