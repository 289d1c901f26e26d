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
    (data / D.STAMP).write_text("older\n")  # made by another version of the studio's code
    D.ensure(recipe)
    assert len(calls) == 2 and (data / "g" / "mocap" / "a.c3d").read_text() == "generated 2"
    assert D._current(data, "bench")


def test_stamped_data_of_this_version_are_kept_whatever_the_studio_source_says(setup):
    recipe, data, calls = setup
    D.ensure(recipe)
    meta = json.loads((data / "gt" / "session.json").read_text())
    meta["studio_source"] = "a module the studio does not import changed"
    (data / "gt" / "session.json").write_text(json.dumps(meta))
    D.ensure(recipe)
    assert len(calls) == 1 and (data / D.STAMP).read_text().strip() == D.version_key("bench")


def _tree(root, files):
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)


def test_code_hash_follows_the_studios_imports_and_nothing_else(tmp_path):
    _tree(tmp_path, {
        "studio/__init__.py": "from .gen import make\n",
        "studio/gen.py": "import numpy as np\nfrom body.lbs import forward\n"
                         "def make():\n    from calib import camera\n    return camera\n",
        "body/__init__.py": "", "body/lbs.py": "def forward(): pass\n",
        "body/unused.py": "X = 1\n",
        "calib/__init__.py": "", "calib/camera.py": "from . import constants\n",
        "calib/constants.py": "K = 1\n", "calib/refine.py": "import calib.camera\n",
        "drawing/overlay.py": "import studio\n"})
    names = {f.relative_to(tmp_path).as_posix() for f in D.code_files(tmp_path)}
    assert names == {"studio/__init__.py", "studio/gen.py", "body/__init__.py", "body/lbs.py",
                     "calib/__init__.py", "calib/camera.py", "calib/constants.py"}
    h0 = D.code_hash(tmp_path)
    _tree(tmp_path, {"calib/refine.py": "# edited\n", "body/unused.py": "X = 2\n",
                     "drawing/overlay.py": "# edited\n"})
    assert D.code_hash(tmp_path) == h0  # files the studio does not import
    _tree(tmp_path, {"calib/constants.py": "K = 2\n"})  # imported relatively, two steps away
    h1 = D.code_hash(tmp_path)
    assert h1 != h0
    _tree(tmp_path, {"body/lbs.py": "def forward(): return 1\n"})
    assert D.code_hash(tmp_path) != h1


def test_a_killed_runs_half_made_copies_are_removed_by_the_next(setup, tmp_path):
    """A run killed while copying (SIGTERM skips its ``finally``) leaves a ``.<name>.tmp-*``
    sibling of the data or cache folder; the next run, holding the preset's lock, removes it."""
    recipe, data, calls = setup
    D.ensure(recipe)
    cached = tmp_path / "cache" / f"bench-{D.version_key('bench')}"
    left = [data.parent / ".bench.tmp-deadbeef", cached.parent / f".{cached.name}.tmp-0badf00d"]
    for d in left:
        (d / "gt").mkdir(parents=True)
    other = data.parent / ".other.tmp-12345678"  # another folder's: not ours to remove
    other.mkdir()
    D.ensure(recipe)
    assert not any(d.exists() for d in left) and other.exists()
    assert len(calls) == 1 and (data / "g" / "mocap" / "a.c3d").exists()
