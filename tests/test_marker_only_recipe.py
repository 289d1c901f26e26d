"""Marker-only sessions: a recipe with only a C3D per sequence (and optionally a subject's
static trials) loads, plans exactly the marker stages, and the bad variants name the field."""
from __future__ import annotations

import pytest
import yaml

from recipes import RecipeError, load_recipe


def _write(tmp, raw):
    for name in ("walk.c3d", "static.c3d", "v.mp4", "cal.json"):
        (tmp / name).write_text(name)
    p = tmp / "r.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def _raw():
    return {"session": "lab",
            "subjects": {"s1": {"markerset": "plug-in-gait", "label_prefix": "Derrick",
                                "static": [{"c3d": "static.c3d", "frames": [10, 200]}]}},
            "sequences": {"s1/Walk 1": {"markers_on": "s1", "c3d": "walk.c3d"}}}


def test_marker_only_recipe_loads_and_plans_only_the_marker_stages(tmp_path):
    import stages
    from pipeline.plan import build_plan, targets_for

    p = _write(tmp_path, _raw())
    r = load_recipe(p)
    seq = r.sequences["s1/Walk 1"]
    assert r.cameras == [] and seq.partner is None and seq.fps is None and not seq.has_video
    assert r.subjects["s1"].static[0].frames == (10, 200)
    assert r.subjects["s1"].static[0].c3d == (tmp_path / "static.c3d").resolve()
    reg = stages.registry()
    for cmd in ("sequence", "release"):
        ids = {n.id for n in build_plan(reg, r, p, targets_for(reg, r, cmd)).nodes
               if n.stage.implemented}
        want = {("capture", "s1/Walk 1"), ("shape_fit", "s1"), ("marker_fit", "s1/Walk 1"),
                ("marker_loo", "s1/Walk 1"),
                ("convert", "s1/Walk 1"), ("export", "s1/Walk 1"), ("qa", "s1/Walk 1")}  # the wearer alone, P = 1
        if cmd == "release":
            want |= {("release", "session"), ("qa_index", "session")}  # no evaluate: no truth
        assert ids == want, (cmd, ids)
    plan = build_plan(reg, r, p, targets_for(reg, r, "sequence"))
    mf = plan.by_id[("marker_fit", "s1/Walk 1")]
    assert "keypoints" not in mf.upstream and mf.upstream["shape_fit"] == ["s1"]
    sf = plan.by_id[("shape_fit", "s1")]
    # the static trial is read by shape_fit itself; the movement capture comes cleaned from
    # the sequence's capture stage, the only reader of its C3D
    assert "static:0" in sf.raw and not any(k.startswith("c3d") for k in sf.raw)
    assert sf.upstream["capture"] == ["s1/Walk 1"]
    assert [k for n in plan.nodes for k in n.raw if k == "c3d"] == ["c3d"]
    assert stages.recipe_view(r, "s1", "subject.static_frames") == [[10, 200]]
    assert stages.recipe_view(r, "s1/Walk 1", "wearer.label_prefix") == "Derrick"


@pytest.mark.parametrize("edit, message", [
    (lambda r: r["sequences"]["s1/Walk 1"].update(partner="s1"), "partner: the same subject"),
    (lambda r: (r["subjects"].update(s2={}), r["sequences"]["s1/Walk 1"].update(partner="s2")),
     "partner: the partner is fitted to the videos, and this sequence has none"),
    (lambda r: r["subjects"]["s1"]["static"][0].update(frames=[200, 10]),
     "subjects.s1.static.0.frames"),
    (lambda r: r["subjects"]["s1"]["static"][0].update(c3d="nope.c3d"),
     "subjects.s1.static[0].c3d: file not found"),
    (lambda r: r["sequences"]["s1/Walk 1"].update(videos={"c1": "v.mp4"}),
     "sequences.s1/Walk 1.videos: cameras ['c1'] do not match cameras []"),
    (lambda r: (r.update(cameras=["c1"]),
                r["sequences"]["s1/Walk 1"].update(videos={"c1": "v.mp4"})),
     "sequences.s1/Walk 1.calibration: cameras [] do not match cameras ['c1']"),
])
def test_bad_marker_only_recipes_name_the_field(tmp_path, edit, message):
    raw = _raw()
    edit(raw)
    with pytest.raises(RecipeError, match=None) as e:
        load_recipe(_write(tmp_path, raw))
    assert message in str(e.value), str(e.value)


def test_a_labs_own_labels_and_prefix_read_as_the_marker_set(tmp_path):
    """``label_prefix`` picks one subject of a two-subject file; ``marker_labels`` maps a
    marker to the lab's label (LFRM written as LFRA): the markers come back under the marker
    set's names, the other subject's never."""
    import numpy as np

    from fitting.capture import read_capture
    from formats.c3d import Markers, write_c3d

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 2, 3)), rng.normal(size=(5, 2, 3)) + 10
    p = tmp_path / "two.c3d"
    write_c3d(p, Markers(("Ann:LFHD", "Ann:LFRA", "Bob:LFHD", "Bob:LFRA"),
                         np.concatenate([a, b], axis=1), 100.0))
    m, labels, scale = read_capture(p, ("LFHD", "LFRM"), "Ann", {"LFRM": "LFRA"})
    assert m.names == ("LFHD", "LFRM")
    assert labels == ["Ann:LFHD", "Ann:LFRA"] and scale == 1e-3  # what the file called them
    np.testing.assert_allclose(m.xyz, a, atol=1e-6)
    m, _, _ = read_capture(p, ("LFHD", "LFRM"), "Bob", {"LFRM": "LFRA"})
    np.testing.assert_allclose(m.xyz, b, atol=1e-6)
    from formats.c3d import read_c3d

    assert np.isnan(read_c3d(p, ["LFHD", "LFRM"], "Ann", allow_missing=True).xyz[:, 1]).all()


def test_cli_set_overrides_a_stage_option_and_names_bad_ones(tmp_path):
    from pipeline.cli import CliError, overrides

    assert overrides(["marker_fit.max_frames=5", "marker_fit.weights={L_s: 0.5}"]) == {
        "marker_fit": {"max_frames": 5, "weights": {"L_s": 0.5}}}
    with pytest.raises(CliError, match="expected STAGE.KEY=VALUE"):
        overrides(["marker_fit=5"])


def test_shape_fit_warnings_name_the_marker():
    """A placement that left its segment, slid 160 mm, sits 33 mm off the skin or fits its
    placement frames 40 mm off is a warning naming the marker; a clean report has none."""
    from stages.shape_fit import shape_warnings

    clean = {"shape_source": "markers", "markers_off_segment": [],
             "placement_slide_mm": {"LTIB": 20.0}, "placement_offset_mm": {"LTIB": 10.0},
             "placement_residual_mm": {"per_marker_median": {"LTIB": 2.0}}}
    assert shape_warnings(clean) == []
    bad = {**clean, "markers_off_segment": ["RELB"], "placement_slide_mm": {"LTIB": 160.0},
           "placement_offset_mm": {"STRN": 33.0},
           "placement_residual_mm": {"per_marker_median": {"C7": 40.0}},
           "placement_frames": [{"capture": "s1/Walk 1", "frame": 12}]}
    w = "\n".join(shape_warnings(bad))
    for s in ("RELB", "LTIB: placed 160 mm", "STRN: 33 mm off the skin", "C7: 40 mm",
              "s1/Walk 1 sample 12"):
        assert s in w, w
    # a scan fit that leaves a body part off the scan (1 % of its points 290 mm away)
    scan = {"shape_source": "scan", "scan_to_model_mm": {"median": 1.4, "p90": 3.0, "p99": 5.4}}
    assert shape_warnings(scan) == []
    off = shape_warnings({**scan, "scan_to_model_mm": {"median": 3.3, "p90": 9.0, "p99": 289.4}})
    assert len(off) == 1 and "more than 289 mm" in off[0], off
