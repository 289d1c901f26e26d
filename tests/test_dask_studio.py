"""The real stages on a LocalCluster of 2 workers: a release of 4 small studio sequences (the
small session's two, each also under a second take name) up to ``marker_fit`` gives the same
artifact keys and the same arrays as the serial run, the per-subject shape fits are computed
once, and the workers ran the tasks (not the client)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from bench.cases.partner_fit import absolute_paths

pytestmark = pytest.mark.slow


def _recipe(small_session: Path, tmp: Path) -> Path:
    root = small_session.parent
    rec = absolute_paths(yaml.safe_load(small_session.read_text()), root)
    seqs = {}
    for sid, seq in rec["sequences"].items():
        group, action = sid.split("/", 1)
        seqs[sid] = seq
        seqs[f"{group}/{action.rsplit(' ', 1)[0]} 9"] = seq  # a second take of the same files
    rec["sequences"] = seqs
    rec["stages"] = {"keypoints": {"stride": 6}}
    path = tmp / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path


def _artifacts(root: Path) -> dict[str, dict]:
    import json

    out = {}
    for m in sorted(root.rglob("manifest.json")):
        if "/.tmp-" in str(m):
            continue
        out[str(m.parent.relative_to(root))] = json.loads(m.read_text())
    return out


def test_release_on_two_workers_equals_the_serial_run(small_session, tmp_path):
    from pipeline.cli import main

    recipe = _recipe(Path(small_session), tmp_path)
    logs: dict[str, list[str]] = {"serial": [], "dask": []}
    for name, extra in (("dask", ["--executor", "dask", "--workers", "2"]),
                        ("serial", ["--executor", "serial"])):
        rc = main(["release", "--recipe", str(recipe), "--outputs", str(tmp_path / name),
                   "--until", "marker_fit", *extra], log=logs[name].append)
        assert rc == 0, "\n".join(logs[name][-30:])
    a, b = _artifacts(tmp_path / "serial"), _artifacts(tmp_path / "dask")
    assert set(a) == set(b) and len([k for k in a if k.endswith("marker_fit")]) == 4, sorted(a)
    for k in a:
        assert a[k]["key"] == b[k]["key"], k
        for f in a[k].get("sha256", {}):
            if f.endswith(".npz"):
                za, zb = np.load(tmp_path / "serial" / k / f), np.load(tmp_path / "dask" / k / f)
                for arr in za.files:
                    np.testing.assert_array_equal(za[arr], zb[arr], err_msg=f"{k}/{f}:{arr}")
    # the two per-subject shape fits ran once each, on the workers
    dask_log = "\n".join(logs["dask"])
    assert sum(" shape_fit " in line and " miss " in line for line in logs["dask"]) == 2, dask_log
    assert "dashboard" in dask_log.lower(), dask_log
    assert not list((tmp_path / "dask").rglob(".tmp-*"))
