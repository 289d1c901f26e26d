"""Implausible input is caught on entry, through the engine, not fitted: a capture in metres
labelled mm (a person 1.8 mm tall) and a scan in mm read as metres (1.8 km) stop their stage
with an error naming the file and the unit the data seem to be in, and leave no artifact that
looks complete."""
from __future__ import annotations

import numpy as np
import yaml


def _capture(model, rng, F=12):
    from bench import fitting_synth as S
    from fitting import shape, skinned

    betas = S.subject_betas(model, rng)[:40]
    tpl, _ = S.template(model)
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    X = S.motion(skel, F, 100.0, rng)
    truth = S.posed(model, betas, skel, X)
    return tpl, S.true_markers(model, truth.vertices, tpl), truth


def _run(tmp, recipe: dict):
    from pipeline.cli import main

    p = tmp / "r.yaml"
    p.write_text(yaml.safe_dump(recipe, sort_keys=False))
    logs: list[str] = []
    rc = main(["sequence", *recipe["sequences"], "--recipe", str(p), "--outputs",
               str(tmp / "out")], log=logs.append)
    return rc, "\n".join(logs)


def _complete_artifacts(out):
    return [m.parent for m in out.rglob("manifest.json")]


def test_capture_in_metres_labelled_mm_is_an_error_not_a_fit(tmp_path, anny):
    from formats.c3d import Markers, write_c3d

    tpl, xyz, _ = _capture(anny, np.random.default_rng(0))
    # write_c3d writes mm: dividing by 1000 leaves metre values under a "mm" label
    write_c3d(tmp_path / "walk.c3d", Markers(tpl.names, xyz / 1000.0, 100.0, 0))
    rc, log = _run(tmp_path, {"session": "lab", "subjects": {"s1": {}},
                              "sequences": {"s1/Walk 1": {"markers_on": "s1",
                                                          "c3d": "walk.c3d"}}})
    assert rc == 2  # bad data: one line, no traceback
    assert "walk.c3d" in log and "POINT:UNITS" in log and "look like metres" in log, log
    assert "mm tall" in log, log
    assert _complete_artifacts(tmp_path / "out") == []


def test_scan_in_mm_is_an_error_not_a_fit(tmp_path, anny):
    from formats.c3d import Markers, write_c3d
    from studio.scan import write_ply

    tpl, xyz, truth = _capture(anny, np.random.default_rng(1))
    write_c3d(tmp_path / "walk.c3d", Markers(tpl.names, xyz, 100.0, 0))
    v = truth.vertices[0]
    write_ply(tmp_path / "scan.ply", v * 1000.0, np.zeros_like(v) + [0, 0, 1.0])  # mm
    rc, log = _run(tmp_path, {"session": "lab", "subjects": {"s1": {"scan": "scan.ply"}},
                              "sequences": {"s1/Walk 1": {"markers_on": "s1",
                                                          "c3d": "walk.c3d"}}})
    assert rc == 2  # bad data: one line, no traceback
    assert "scan.ply" in log and "look like millimetres" in log and "km" in log, log
    # the capture (a good C3D) may be complete; nothing made from the scan, or after it, is
    assert [p.name for p in _complete_artifacts(tmp_path / "out")] in ([], ["capture"])
