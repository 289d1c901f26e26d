"""Marker sets a lab can define (issue #26 item 2): ``markerset/2`` files naming markers by
anatomical landmark (``body.landmarks``), the built-in sets written that way, the lower-body
Plug-in Gait set, segment groups through ``body.markers.segments_of``, and the per-joint
``observed`` mask a lower-body capture gives (``BodyFit.observed`` -> ``joints_valid`` of the
export's ``valid/<action>.json``)."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from body import landmarks as L
from body import markers as M
from formats.errors import InputError

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"
PYCGM = REAL / "pycgm_movement_trial.c3d"


def positions(model, ms):
    return M.marker_positions(model.v_template, model.faces, ms)


# ----------------------------------------------------------------------------- built-in sets


@pytest.mark.parametrize("name,place", [("plug-in-gait", M.plug_in_gait), ("cmu", M.cmu41),
                                        ("plug-in-gait-lower", M.plug_in_gait_lower)])
def test_builtin_sets_written_as_markerset2_reproduce_their_placement(anny, tmp_path, name,
                                                                      place):
    doc = L.builtin_definition(name)
    assert doc["format"] == "markerset/2"
    assert all(v in L.LANDMARKS for v in doc["markers"].values())
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    got, ref = L.load_markerset(p, anny), place(anny)
    assert got.names == ref.names
    d = np.linalg.norm(positions(anny, got) - positions(anny, ref), axis=-1)
    assert d.max() < 0.003, dict(zip(got.names, d.round(4), strict=True))
    assert M.segments_of(got) == M.segments_of(name) == ref.segments
    np.testing.assert_allclose(got.offsets, M.DEFAULT_OFFSET_M)


def test_every_landmark_lands_on_the_skin_on_its_side(anny):
    f, b = L.landmark_points(anny, L.LANDMARKS)
    p = np.einsum("nk,nkd->nd", b, anny.v_template[anny.faces[f]])
    for n, x in zip(L.LANDMARKS, p, strict=True):  # Anny's left is +x
        if n.startswith("left_"):
            assert x[0] > 0.01, n
        elif n.startswith("right_"):
            assert x[0] < -0.01, n
    at = dict(zip(L.LANDMARKS, p, strict=True))
    for s in ("left", "right"):  # medial landmarks nearer the midline than the lateral ones
        for a, b_ in (("lateral_femoral_epicondyle", "medial_femoral_epicondyle"),
                      ("lateral_malleolus", "medial_malleolus"),
                      ("lateral_epicondyle_humerus", "medial_epicondyle_humerus")):
            gap = abs(at[f"{s}_{a}"][0]) - abs(at[f"{s}_{b_}"][0])
            assert 0.03 < gap < 0.15, (s, a, gap)


# ----------------------------------------------------------------------------- a lab's file

LAB = {
    "format": "markerset/2",
    "model": "anny",
    "markers": {
        "P_LASIS": "left_asis",
        "P_RANKLE": {"landmark": "right_lateral_malleolus", "label": "R_Ankle"},
        "P_C7": "c7",
        "P_LELB": {"landmark": "left_lateral_epicondyle_humerus", "offset_mm": 14},
        "P_LKNE": {"segment": "left_shank", "along": 0.0, "side": "lateral"},
        "P_RANK": {"segment": "right_shank", "along": 1.0, "side": "lateral"},
        "P_LTIB": {"between": ["left_lateral_femoral_epicondyle", "left_lateral_malleolus"],
                   "at": 0.6},
        "P_LMKNE": {"landmark": "left_medial_femoral_epicondyle"},
    },
    "segments": {"left_leg": ["P_LKNE", "P_LTIB", "P_LMKNE"]},
}
# the Plug-in Gait marker at the same place
SAME = {"P_LASIS": "LASI", "P_RANKLE": "RANK", "P_C7": "C7", "P_LELB": "LELB",
        "P_LKNE": "LKNE", "P_RANK": "RANK", "P_LTIB": "LTIB"}


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".json"])
def test_lab_file_lands_where_plug_in_gait_puts_the_same_landmarks(anny, tmp_path, suffix):
    p = tmp_path / f"lab{suffix}"
    p.write_text(json.dumps(LAB) if suffix == ".json" else yaml.safe_dump(LAB, sort_keys=False))
    ms = L.load_markerset(p, anny)
    assert ms.names == tuple(LAB["markers"])
    pig = M.plug_in_gait(anny).with_offsets(0.0)
    ref = dict(zip(pig.names, positions(anny, pig), strict=True))
    skin = dict(zip(ms.names, positions(anny, ms.with_offsets(0.0)), strict=True))
    for lab, pg in SAME.items():
        tol = 0.012 if lab == "P_LTIB" else 0.003  # between two landmarks: on the skin line
        d = np.linalg.norm(skin[lab] - ref[pg])
        assert d < tol, f"{lab} is {1000 * d:.1f} mm from {pg}"
    # the medial knee is across the knee from the lateral one, at the same height
    k = skin["P_LMKNE"] - skin["P_LKNE"]
    assert -0.15 < k[0] < -0.05 and abs(k[2]) < 0.03
    # offsets (default 9.5 mm, or the marker's), labels and segment groups
    off = dict(zip(ms.names, ms.offsets, strict=True))
    assert off["P_LELB"] == pytest.approx(0.014) and off["P_C7"] == pytest.approx(0.0095)
    assert ms.labels == {"P_RANKLE": "R_Ankle"}
    assert M.segments_of(ms) == {"left_leg": ("P_LKNE", "P_LTIB", "P_LMKNE")}
    # with its offset, each marker sits that far out along its face normal
    d = np.linalg.norm(positions(anny, ms) - positions(anny, ms.with_offsets(0.0)), axis=1)
    np.testing.assert_allclose(d, ms.offsets, atol=1e-9)


def test_list_form_and_file_wide_offset(anny, tmp_path):
    p = tmp_path / "lab.yaml"
    p.write_text(yaml.safe_dump({"format": "markerset/2", "offset_mm": 7, "markers": [
        {"name": "A", "landmark": "left_asis"}, {"name": "B", "landmark": "right_asis",
                                                   "offset_mm": 12}]}))
    ms = L.load_markerset(p, anny)
    assert ms.names == ("A", "B")
    np.testing.assert_allclose(ms.offsets, [0.007, 0.012])
    assert ms.segments is None
    assert M.segments_of(ms) == {}  # its names match no built-in group: none guessed


def test_markerset1_json_still_reads(anny, tmp_path):
    ms = M.plug_in_gait(anny).subset(["LASI", "RKNE"])
    p = tmp_path / "old.json"
    M.save_json(ms, p, model="anny", num_faces=len(anny.faces))
    got = L.load_markerset(p, anny)
    assert got.names == ms.names and np.array_equal(got.faces, ms.faces)


BAD = [
    ({"markers": {"A": "left_asis"}}, "format", "markerset/2"),
    ({"markers": {"LKNE": "left_knee"}}, "markers.LKNE.landmark",
     "left_lateral_femoral_epicondyle"),
    ({"markers": {"X": {"segment": "left_forearm", "along": 1.5}}}, "markers.X.along",
     "[0, 1]"),
    ({"markers": {"X": {"segment": "left_forarm", "along": 0.5}}}, "markers.X.segment",
     "left_forearm"),
    ({"markers": {"X": {"segment": "left_forearm"}}}, "markers.X.along", "missing"),
    ({"markers": {"X": {"segment": "trunk", "along": 0.5, "side": "lateral"}}},
     "markers.X.side", "not a side of trunk"),
    ({"markers": {"X": {"segment": "left_thigh", "along": 0.5, "side": "superior"}}},
     "markers.X.side", "along"),
    ({"markers": {"X": {"landmark": "c7", "offset_mm": 250}}}, "markers.X.offset_mm", "mm"),
    ({"markers": {"X": {"landmark": "c7", "segment": "trunk"}}}, "markers.X", "exactly one"),
    ({"markers": {"X": {"landmark": "c7", "colour": "red"}}}, "markers.X.colour",
     "unknown key"),
    ({"markers": {"X": {"between": ["c7"], "at": 0.2}}}, "markers.X.between", "two"),
    ({"markers": {"X": {"between": ["c7", "t11"], "at": 0.2}}}, "markers.X.between[1]",
     "t10"),
    ({"markers": [{"name": "A", "landmark": "c7"}, {"name": "A", "landmark": "t10"}]},
     "markers.A", "duplicate"),
    ({"markers": {"A": "c7", "B": "t10"}, "segments": {"back": ["A", "C"]}}, "segments.back",
     "'C'"),
    ({"markers": {}}, "markers", "no markers"),
    ({"markers": {"A": "c7"}, "model": "smplx"}, "model", "anny"),
]


@pytest.mark.parametrize("body,field,words", BAD)
def test_bad_files_name_file_marker_and_field(anny, tmp_path, body, field, words):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump({"format": "markerset/2", **body} if "format" not in body
                                and field != "format" else body))
    with pytest.raises(InputError) as e:
        L.load_markerset(p, anny)
    msg = str(e.value)
    assert str(p) in msg and f": {field}" in msg and words in msg, msg


def test_unreadable_file_names_the_file(anny, tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("format: markerset/2\nmarkers: {A: [unclosed\n")
    with pytest.raises(InputError, match="bad.yaml"):
        L.load_markerset(p, anny)
    with pytest.raises(InputError, match="ends in"):
        L.load_markerset(tmp_path / "set.txt", anny)


# ----------------------------------------------------------------------------- lower-body set


def test_lower_body_set_and_segment_groups_for_every_builtin(anny):
    from fitting.marker_clean import MARKERSET_SEGMENTS, default_segments
    from fitting.marker_graph import template_placement

    pl = template_placement(anny, "plug-in-gait-lower")
    assert pl.names == M.PLUG_IN_GAIT_LOWER_NAMES and len(pl.names) == 16
    full = M.plug_in_gait(anny)
    for i, n in enumerate(pl.names):  # the same places as the full set's markers
        assert pl.face[i] == full.faces[full.index(n)]
    low = M.segments_of("plug-in-gait-lower")
    assert set(low) == {"pelvis", "L_thigh", "R_thigh", "L_shank", "R_shank", "L_foot", "R_foot"}
    assert pl.segments == low
    for name in ("plug-in-gait", "cmu", "plug-in-gait-lower"):
        groups = M.segments_of(name)
        assert groups and all(set(v) <= set(M.BUILTIN_NAMES[name]) for v in groups.values())
        assert MARKERSET_SEGMENTS[name] == groups  # the cleaner's groups are the same
    assert default_segments(M.PLUG_IN_GAIT_LOWER_NAMES) == low
    assert default_segments(M.PLUG_IN_GAIT_NAMES) == M.segments_of("plug-in-gait")
    with pytest.raises(ValueError, match="plug-in-gait-lower"):
        M.segments_of("vicon-fullbody")


def test_recipe_takes_yaml_marker_set_files(anny, tmp_path):
    from recipes import RecipeError, load_recipe
    from recipes.schema import BUILTIN_MARKERSETS
    from stages import _subject_fields, common

    assert set(BUILTIN_MARKERSETS) == set(M.BUILTIN_NAMES)
    (tmp_path / "lab.yml").write_text(yaml.safe_dump(LAB, sort_keys=False))
    (tmp_path / "t.c3d").write_text("x")
    rec = {"session": "s", "cameras": [],
           "subjects": {"a": {"markerset": "lab.yml"}, "b": {"markerset": "plug-in-gait-lower"}},
           "sequences": {"g/t": {"markers_on": "a", "c3d": "t.c3d"}}}
    p = tmp_path / "r.yaml"
    p.write_text(yaml.safe_dump(rec))
    r = load_recipe(p)
    assert r.subjects["a"].markerset == str((tmp_path / "lab.yml").resolve())
    assert _subject_fields(r, "a")["markerset"] == "file"
    assert _subject_fields(r, "b")["markerset"] == "plug-in-gait-lower"
    raw = common.markerset_file(r.subjects["a"])
    assert raw == {"markerset": (tmp_path / "lab.yml").resolve()}
    assert common.markerset_file(r.subjects["b"]) == {}
    pl = common.marker_template(SimpleNamespace(raw=raw), "file", anny)
    assert pl.names == tuple(LAB["markers"]) and pl.labels == {"P_RANKLE": "R_Ankle"}
    assert common.marker_labels(pl, {"P_C7": "C7"}) == {"P_RANKLE": "R_Ankle", "P_C7": "C7"}
    rec["subjects"]["b"]["markerset"] = "plug-in-gait-full"
    p.write_text(yaml.safe_dump(rec))
    with pytest.raises(RecipeError, match="plug-in-gait-full"):
        load_recipe(p)


# ----------------------------------------------------------------------------- observed joints


@pytest.fixture(scope="module")
def lower_fit(anny):
    """The lower-body set fitted to the first 30 frames of a real Plug-in Gait capture reduced
    to its 16 lower-body markers (pycgm_movement_trial.c3d)."""
    from fitting import mocap
    from fitting.marker_fit import MarkerFitOptions, fit_markers
    from fitting.marker_graph import template_placement, to_shape_fit
    from formats.c3d import read_c3d

    if not PYCGM.is_file():
        pytest.skip(f"{PYCGM} not available")
    mk = read_c3d(PYCGM, markers=M.PLUG_IN_GAIT_LOWER_NAMES, allow_missing=True)
    assert mk.names == M.PLUG_IN_GAIT_LOWER_NAMES
    mk.xyz[10:14, :] = np.nan  # four frames with no marker: held, not valid
    tpl = template_placement(anny, "plug-in-gait-lower")
    clock = mocap.VideoClock(mk.rate_hz, -mk.first_frame / mk.rate_hz)
    return fit_markers(anny, to_shape_fit(np.zeros(1), tpl, "mean", "template"), tpl, mk,
                       clock, np.arange(30), opts=MarkerFitOptions())


def _joints(model, *prefixes):
    return [j for j, n in enumerate(model.joint_names) if n.startswith(prefixes)]


def test_lower_body_fit_observes_legs_not_arms_or_head(anny, lower_fit, tmp_path):
    from artifacts import BodyFit

    fit, rep = lower_fit
    assert fit.observed.shape == (30, anny.num_joints) and fit.observed.dtype == bool
    legs = _joints(anny, "root", "pelvis", "upperleg", "lowerleg", "foot", "toe")
    upper = _joints(anny, "clavicle", "shoulder", "upperarm", "lowerarm", "wrist", "finger",
                    "metacarpal", "neck", "head", "eye")
    seen = np.ones(30, bool)
    seen[10:14] = False
    assert fit.observed[np.ix_(seen, legs)].all()
    assert not fit.observed[:, upper].any()
    assert not fit.observed[~seen].any()  # no marker, nothing observed
    assert not fit.valid[10:14].any() and fit.valid[seen].all()
    assert {"head", "wrist.L", "upperarm01.R"} <= set(rep["joints_never_observed"])
    assert not {"upperleg01.L", "foot.R", "root"} & set(rep["joints_never_observed"])
    fitted_upper = [j for j in upper if j in set(int(x) for x in anny.fit_joints)]
    assert rep["joint_frames_not_observed"] >= 26 * len(fitted_upper)
    def save_arrays(name, **arrays):
        np.savez(tmp_path / f"{name}.npz", **arrays)
        return tmp_path / f"{name}.npz"

    fit.save(SimpleNamespace(dir=tmp_path, save_arrays=save_arrays))
    back = BodyFit.load(tmp_path / "fit.npz")
    assert np.array_equal(back.observed, fit.observed)


def test_export_valid_file_marks_unobserved_joints_not_valid(anny, lower_fit, tmp_path):
    from body.joints import regressor
    from fitting.marker_graph import fit_points_observed, observed_points
    from formats.release import read_valid, write_valid
    from formats.skeletons import JOINTS3D_25

    fit, _ = lower_fit
    # what stages/export.py writes for the person (a marker fit: no keypoints_observed)
    jv = fit_points_observed(anny, fit)[None]
    assert fit.keypoints_observed is None
    assert np.array_equal(jv[0], observed_points(anny, regressor(anny, "joints3d_25"),
                                                 fit.joints_observed()))
    valid = fit.valid[None]
    reason = np.where(valid, "fitted", "too_few_markers")
    p = write_valid(tmp_path / "valid" / "a.json", valid, reason, fit.frames, jv & valid[..., None])
    v = read_valid(p)
    assert v["joints_valid"].shape == (1, 30, 25)
    k = {n: i for i, n in enumerate(JOINTS3D_25)}
    ok = v["joints_valid"][0]
    for n in ("pelvis", "l_hip", "r_knee", "l_ankle", "r_toe_end"):
        assert ok[fit.valid, k[n]].all(), n
    for n in ("head", "neck_nose", "l_wrist", "r_elbow", "l_shoulder", "r_thumb"):
        assert not ok[:, k[n]].any(), n
    assert not ok[~fit.valid].any()
    # a joint valid in a frame that is not is refused, naming the field
    bad = np.ones((1, 30, 25), bool)
    with pytest.raises(InputError, match="joints_valid"):
        write_valid(tmp_path / "b.json", valid, reason, fit.frames, bad)


def test_observed_without_markers_on_a_segment_is_false(anny):
    """observed_joints on a synthetic visibility: only the left-shank markers seen."""
    from body.lbs import rest_state
    from fitting import skinned
    from fitting.marker_graph import (
        OBSERVED_WEIGHT,
        body_joints,
        marker_coeffs,
        observed_joints,
        template_placement,
    )

    pl = template_placement(anny, "plug-in-gait")
    rest = rest_state(anny, np.zeros(1))
    skel = skinned.fit_skeleton(anny, body_joints(anny))
    sup = skinned.points_support(marker_coeffs(anny, rest, skel, pl), OBSERVED_WEIGHT)
    vis = np.zeros((2, len(pl.names)), bool)
    vis[0] = True
    vis[1, [pl.names.index(n) for n in ("LTIB", "LANK")]] = True
    obs = observed_joints(anny, skel, sup, vis)
    J = {n: i for i, n in enumerate(anny.joint_names)}
    assert obs[0, [J["head"], J["wrist.L"], J["foot.R"], J["lowerleg01.L"]]].all()
    assert not obs[0, J["finger2-1.L"]]  # fingers held at pose 0 without hand keypoints
    assert obs[1, J["lowerleg01.L"]] and obs[1, J["lowerleg02.L"]]  # twist bone rides along
    assert not obs[1, [J["head"], J["wrist.L"], J["upperleg01.R"], J["foot.R"]]].any()
