"""The manifest's timings carry the stage's CPU seconds next to its wall seconds (the bench's
pipeline.cpu_s_per_1000_frames adds them up): a stage that waits uses wall time, not CPU."""
from __future__ import annotations

import json

import toy_registry

from pipeline.cli import main


def test_manifest_cpu_seconds_of_a_waiting_stage(tmp_path):
    recipe = toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 3.0}}, n_seq=1)
    assert main(["sequence", "g/x", "--recipe", str(recipe), "--registry",
                 toy_registry.__file__, "--outputs", str(tmp_path / "outputs"),
                 "--executor", "serial"], log=lambda _m: None) == 0
    t = json.loads((tmp_path / "outputs" / "toy" / "g" / "x" / "detect" / "manifest.json")
                   .read_text())["timings"]
    assert t["seconds"] >= 0.3  # detect sleeps sleep_s / 10 in the stage itself
    assert 0.0 <= t["cpu_s"] < 0.5 * t["seconds"]
