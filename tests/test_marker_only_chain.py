"""A marker-only recipe through the whole marker chain with the engine: shape_fit (shape and
placement from the markers) -> marker_fit (every sample, from the C3D's first frame) ->
marker_loo (leave-one-out), on a capture with a ghost point and a label swap. The ghost and
the swap are removed before placement frames are chosen and before the fit, every report is
strict JSON, and the leave-one-out figures are there."""
from __future__ import annotations

import json

import numpy as np
import yaml


def _strict(text: str):
    def bad(c):
        raise ValueError(f"not JSON: {c}")
    return json.loads(text, parse_constant=bad)


def test_marker_only_chain_cleans_fits_and_reports_leave_one_out(tmp_path, anny):
    from artifacts import BodyFit
    from bench import fitting_synth as S
    from fitting import shape, skinned
    from formats.c3d import Markers, write_c3d
    from pipeline.cli import main

    rng = np.random.default_rng(7)
    F, rate, first = 90, 100.0, 50
    betas = S.subject_betas(anny, rng)[:40]
    tpl, _ = S.template(anny)
    pl = S.slide(anny, tpl, rng)
    skel = skinned.fit_skeleton(anny, shape.body_joints(anny))
    X = S.motion(skel, F, rate, rng)
    truth = S.posed(anny, betas, skel, X)
    xyz = S.true_markers(anny, truth.vertices, pl) + rng.normal(0, 0.0006, (F, 39, 3))
    names = list(pl.names)
    g = names.index("LKNE")
    xyz[40:43, g] += [5.0, 0.0, 0.0]  # a ghost 5 m off for 3 samples
    i, j = names.index("LELB"), names.index("LFRM")
    xyz[60:70, [i, j]] = xyz[60:70, [j, i]]  # a 10-sample label swap
    write_c3d(tmp_path / "walk.c3d", Markers(pl.names, xyz, rate, first, "Sub"))
    recipe = {"session": "lab", "subjects": {"s1": {"label_prefix": "Sub"}},
              "sequences": {"s1/Walk 1": {"markers_on": "s1", "c3d": "walk.c3d"}}}
    p = tmp_path / "r.yaml"
    p.write_text(yaml.safe_dump(recipe, sort_keys=False))
    logs: list[str] = []
    rc = main(["sequence", "s1/Walk 1", "--recipe", str(p), "--outputs", str(tmp_path / "out"),
               "--set", "marker_loo.markers=[LKNE, RELB, T10]", "--set", "marker_loo.stride=3"],
              log=logs.append)
    assert rc == 0, "\n".join(logs[-20:])
    root = tmp_path / "out" / "lab"
    for js in root.rglob("*.json"):  # every report and manifest is strict JSON
        _strict(js.read_text())
    sf = _strict((root / "s1" / "shape_fit" / "report.json").read_text())
    assert sf["shape_source"] == "markers"
    cleaned = sf["cleaned"]["s1/Walk 1"]  # by the capture stage, before placement frames
    assert cleaned["removed_samples"] >= 3 and cleaned["repaired_by_code"]["unswapped"] == 20
    from artifacts.capture import Markers as Captured

    cap = Captured.load(root / "s1" / "Walk 1" / "capture")  # the one reading of walk.c3d
    assert cap.markers_repaired_as("unswapped") == {"LELB", "LFRM"}
    assert cap.repaired[60:70][:, [i, j]].all() and not cap.observed[40:43, g].any()
    assert sf["placement_slide_mm"]["LKNE"] < 30.0  # the 5 m ghost did not drag it
    assert sf["placement_residual_mm"]["median"] < 5.0
    mf_dir = root / "s1" / "Walk 1" / "marker_fit"
    mf = _strict((mf_dir / "report.json").read_text())
    fit = BodyFit.load(mf_dir)
    np.testing.assert_array_equal(fit.frames, first + np.arange(F))
    assert mf["fit_rate_hz"] == rate and fit.valid.all()
    assert not fit.visible[40:43, g].any()  # the ghost never reached the fit
    assert sum(v for k, v in mf["capture_repaired"].items() if k != "unswapped") >= 3
    assert np.nanmax(fit.marker_residual_m[60:70][:, [i, j]]) < 0.02  # un-swapped, not fitted
    assert any("repaired by the capture stage" in w for w in mf["warnings"])
    assert mf["residual_mm"]["p90"] < 15.0, mf["residual_mm"]
    assert (mf_dir / "marker_residuals.png").is_file()
    lo_dir = root / "s1" / "Walk 1" / "marker_loo"
    lo = _strict((lo_dir / "report.json").read_text())
    assert set(lo["per_marker"]) == {"LKNE", "RELB", "T10"}
    assert all(0 < m["median_mm"] < 60 for m in lo["per_marker"].values()), lo["per_marker"]
    arr = np.load(lo_dir / "loo.npz")
    assert arr["error_mm"].shape == (len(arr["frames"]), 3) and len(arr["frames"]) == F // 3
    k = list(arr["marker_names"]).index("LKNE")  # held out; its 5 m ghost neither scores it
    assert np.nanmax(arr["error_mm"][:, k]) < 500.0  # nor drags the refits (cleaned first)
    assert (lo_dir / "loo.png").is_file()
