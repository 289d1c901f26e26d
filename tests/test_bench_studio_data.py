"""bench/cases/_studio_data.py: a preset's generated data are reused when this studio code
made them, copied from the cache outside the checkout when it holds them, regenerated (and
cached) otherwise, including when the data on disk came from other studio code."""
from __future__ import annotations

import json

import pytest
import yaml

from bench.cases import _studio_data as D


@pytest.fixture
def setup(tmp_path, monkeypatch):
    import studio
    from studio import plan as PL
    from studio.session import plan_dict, source_hash

    data = tmp_path / "data" / "bench"
    recipe = tmp_path / "recipes" / "bench.yaml"
    recipe.parent.mkdir(parents=True)
    recipe.write_text(yaml.safe_dump({"session": "studio_bench", "subjects": {"s": {
        "scan": "../data/bench/scans/s.ply"}}, "sequences": {"g/a": {
        "c3d": "../data/bench/g/mocap/a.c3d", "videos": {"1": "../data/bench/g/videos/1/a.mp4"}}}}))
    monkeypatch.setenv("MOCAP_STUDIO_CACHE", str(tmp_path / "cache"))
    calls = []

    def fake_generate(path):  # what studio.ensure_generated leaves: the files, session.json
        if (data / "g" / "mocap" / "a.c3d").exists():
            return path
        calls.append(1)
        for f in ("g/mocap/a.c3d", "g/videos/1/a.mp4", "scans/s.ply"):
            (data / f).parent.mkdir(parents=True, exist_ok=True)
            (data / f).write_text(f"generated {len(calls)}")
        (data / "gt").mkdir(exist_ok=True)
        (data / "gt" / "session.json").write_text(json.dumps({
            "plan": plan_dict(PL.make_plan(PL.PRESETS["bench"].seed, preset="bench")),
            "studio_source": source_hash()}))
        return path

    monkeypatch.setattr(studio, "ensure_generated", fake_generate)
    return recipe, data, calls


def test_generated_once_then_reused_then_copied_from_the_cache(setup, tmp_path):
    recipe, data, calls = setup
    D.ensure(recipe)
    assert len(calls) == 1
    cached = tmp_path / "cache" / f"bench-{D.version_key('bench')}"
    assert (cached / "g" / "mocap" / "a.c3d").read_text() == "generated 1"
    D.ensure(recipe)  # current data: kept
    assert len(calls) == 1
    import shutil

    shutil.rmtree(data)  # a fresh clone: copied from the cache, not generated
    D.ensure(recipe)
    assert len(calls) == 1 and (data / "g" / "mocap" / "a.c3d").read_text() == "generated 1"


def test_data_of_other_studio_code_are_regenerated(setup, tmp_path):
    recipe, data, calls = setup
    D.ensure(recipe)
    import shutil

    shutil.rmtree(tmp_path / "cache")
    meta = json.loads((data / "gt" / "session.json").read_text())
    meta["studio_source"] = "older"
    (data / "gt" / "session.json").write_text(json.dumps(meta))
    D.ensure(recipe)
    assert len(calls) == 2 and (data / "g" / "mocap" / "a.c3d").read_text() == "generated 2"
    assert D._current(data, "bench")
