"""Recipes: a valid one loads with paths resolved; bad ones raise RecipeError naming the
recipe file and the field; the stages registry interprets a recipe for the engine."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from recipes import RecipeError, input_files, load_recipe, missing_files

CAMS = ["c1", "c2"]


def good(folder: Path) -> dict:
    """A valid recipe dict whose files exist under ``folder`` (relative paths)."""
    (folder / "data").mkdir(parents=True, exist_ok=True)
    for name in ["scan_a.ply", "Grab 1.c3d", "c1.mp4", "c2.mp4", "c1.json", "c2.json",
                 "contact.json", "marks.json"]:
        (folder / "data" / name).write_text("x")
    return {
        "session": "demo",
        "cameras": CAMS,
        "subjects": {"a": {"scan": "data/scan_a.ply", "markerset": "data/marks.json"},
                     "b": {"sex": "female"}},
        "sequences": {"s01/Grab 1": {
            "markers_on": "a", "partner": "b", "c3d": "data/Grab 1.c3d",
            "videos": {c: f"data/{c}.mp4" for c in CAMS},
            "calibration": {c: f"data/{c}.json" for c in CAMS},
            "contact": "data/contact.json", "text": "a grabs b", "fps": 50}},
        "stages": {"marker_fit": {"iters": 3}},
    }


def write(folder: Path, recipe: dict, name: str = "r.yaml") -> Path:
    p = folder / name
    p.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return p


def test_valid_recipe_loads_with_paths_resolved_against_its_folder(tmp_path):
    p = write(tmp_path, good(tmp_path))
    s = load_recipe(p)
    seq = s.sequence("s01/Grab 1")
    assert seq.c3d == (tmp_path / "data" / "Grab 1.c3d").resolve()
    assert seq.videos["c2"] == (tmp_path / "data" / "c2.mp4").resolve()
    assert s.subjects["a"].scan == (tmp_path / "data" / "scan_a.ply").resolve()
    assert s.subjects["a"].markerset == str((tmp_path / "data" / "marks.json").resolve())
    assert s.subjects["b"].markerset == "plug-in-gait" and s.subjects["b"].scan is None
    assert s.stages == {"marker_fit": {"iters": 3}}
    assert s.source == p
    assert s.sequences_of("b") == ["s01/Grab 1"]
    fields = [f for f, _ in input_files(s)]
    assert "sequences.s01/Grab 1.videos.c1" in fields and "subjects.a.markerset" in fields


def test_recipe_loaded_from_another_working_directory(tmp_path, monkeypatch):
    p = write(tmp_path, good(tmp_path))
    monkeypatch.chdir("/")
    assert load_recipe(p).sequence("s01/Grab 1").c3d.is_file()


def bad(tmp_path: Path, edit) -> str:
    r = good(tmp_path)
    edit(r)
    p = write(tmp_path, r, "bad.yaml")
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    msg = str(e.value)
    assert msg.startswith(str(p) + ": "), msg  # names the file
    return msg


def seq(r: dict) -> dict:
    return r["sequences"]["s01/Grab 1"]


def test_missing_field(tmp_path):
    msg = bad(tmp_path, lambda r: seq(r).pop("c3d"))
    assert "sequences.s01/Grab 1.c3d: missing required field" in msg
    msg = bad(tmp_path, lambda r: r.pop("cameras"))  # optional (marker-only), not with videos
    assert "videos: cameras ['c1', 'c2'] do not match cameras []" in msg


def test_wrong_type(tmp_path):
    msg = bad(tmp_path, lambda r: seq(r).update(fps="fast"))
    assert "sequences.s01/Grab 1.fps:" in msg and "got 'fast'" in msg
    msg = bad(tmp_path, lambda r: r["subjects"]["b"].update(sex="other"))
    assert "subjects.b.sex:" in msg and "got 'other'" in msg


def test_unknown_key(tmp_path):
    msg = bad(tmp_path, lambda r: r.update(camras=["c1"]))
    assert ": camras: unknown key" in msg
    msg = bad(tmp_path, lambda r: seq(r).update(vidoes={}))
    assert "sequences.s01/Grab 1.vidoes: unknown key" in msg


def test_unknown_subject(tmp_path):
    msg = bad(tmp_path, lambda r: seq(r).update(partner="zed"))
    assert "sequences.s01/Grab 1.partner: unknown subject 'zed'" in msg
    msg = bad(tmp_path, lambda r: seq(r).update(partner="a"))
    assert "sequences.s01/Grab 1.partner: the same subject as markers_on" in msg


def test_missing_file_names_field_and_path(tmp_path):
    msg = bad(tmp_path, lambda r: seq(r)["videos"].update(c2="data/nope.mp4"))
    assert "sequences.s01/Grab 1.videos.c2: file not found: " in msg
    assert msg.endswith(str((tmp_path / "data" / "nope.mp4").resolve()))
    r = good(tmp_path)
    seq(r)["videos"]["c2"] = "data/nope.mp4"
    s = load_recipe(write(tmp_path, r), check_files=False)  # layout checks only
    assert [f for f, _ in missing_files(s)] == ["sequences.s01/Grab 1.videos.c2"]


def test_camera_mismatch_bad_ids_and_keypoints_without_format(tmp_path):
    msg = bad(tmp_path, lambda r: seq(r)["calibration"].pop("c2"))
    assert "sequences.s01/Grab 1.calibration: cameras ['c1'] do not match" in msg
    msg = bad(tmp_path, lambda r: r["sequences"].update({"noslash": r["sequences"]["s01/Grab 1"]}))
    assert "sequences.noslash: sequence id 'noslash'" in msg and "'<group>/<action>'" in msg
    msg = bad(tmp_path, lambda r: r.update(session="../up"))
    assert "session:" in msg
    msg = bad(tmp_path, lambda r: seq(r).update(keypoints={"c1": "data"}))
    assert "sequences.s01/Grab 1.keypoints_format: required" in msg


def test_not_yaml_or_not_a_mapping(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("session: [unclosed")
    with pytest.raises(RecipeError, match="x.yaml: not valid YAML"):
        load_recipe(p)
    p.write_text("- a\n- b\n")
    with pytest.raises(RecipeError, match="x.yaml: expected a mapping"):
        load_recipe(p)
    with pytest.raises(RecipeError, match="nothing.yaml: recipe not found"):
        load_recipe(tmp_path / "nothing.yaml")


# -- the stages registry interpreting a recipe -----------------------------------------------

def test_registry_units_upstream_units_and_params(tmp_path):
    import stages

    r = good(tmp_path)
    r["sequences"]["s01/Hug 2"] = {**seq(r), "markers_on": "b", "partner": "a"}
    reg = stages.registry()
    s = reg.load_recipe(write(tmp_path, r))
    assert [st.name for st in reg.stages] == [p[0] for p in stages.PLANNED]
    assert reg.session_name(s) == "demo"
    assert reg.units(s, "subject") == ["a", "b"]
    assert reg.units(s, "sequence") == ["s01/Grab 1", "s01/Hug 2"]
    assert reg.units(s, "session") == ["session"]
    assert reg.upstream_units(s, "marker_fit", "s01/Hug 2", "shape_fit") == ["b", "a"]
    assert reg.upstream_units(s, "marker_fit", "s01/Hug 2", "keypoints") == ["s01/Hug 2"]
    assert reg.stage_params(s, "marker_fit") == {"iters": 3}
    assert reg.stage_params(s, "keypoints") == {}


def test_registry_rejects_unknown_stage_section(tmp_path):
    import stages

    r = good(tmp_path)
    r["stages"]["marker_fitt"] = {}
    with pytest.raises(RecipeError, match=r"r.yaml: stages.marker_fitt: unknown stage"):
        stages.registry().load_recipe(write(tmp_path, r))


def test_registry_placeholders_match_the_architecture_table():
    import stages

    reg = stages.registry()
    for (name, per, upstream, _), st in zip(stages.PLANNED, reg.stages, strict=True):
        assert st.name == name and st.per == per
        if not st.implemented:
            assert st.upstream == upstream and st.func is None
    stages.prepare(Path("some/other.yaml"))  # not the demo recipe: nothing to do


FAKE_STUDIO = '''
import sys
import os
from pathlib import Path
assert sys.argv[1:] == ["--recipe-preset", "demo"], sys.argv
Path("recipes").mkdir(exist_ok=True)
Path("calls.txt").open("a").write("called\\n")
Path("data").mkdir(exist_ok=True)
Path("data/made.c3d").write_text("x")
Path("recipes/demo.yaml").write_text(Path("template.yaml").read_text())
'''


def test_prepare_runs_the_studio_only_when_demo_data_is_missing(tmp_path):
    import stages

    repo = tmp_path / "repo"
    (repo / "studio").mkdir(parents=True)
    (repo / "studio" / "__init__.py").write_text("")
    (repo / "studio" / "__main__.py").write_text(FAKE_STUDIO)
    tpl = {"session": "d", "cameras": ["c1"], "subjects": {"a": {}, "b": {}},
           "sequences": {"g/x": {"markers_on": "a", "partner": "b", "c3d": "../data/made.c3d",
                                 "videos": {"c1": "../data/made.c3d"},
                                 "calibration": {"c1": "../data/made.c3d"}}}}
    (repo / "template.yaml").write_text(yaml.safe_dump(tpl))
    demo = repo / "recipes" / "demo.yaml"
    stages.prepare(tmp_path / "other.yaml", demo_recipe=demo, repo=repo)
    assert not (repo / "calls.txt").exists()  # not the demo recipe: nothing happens
    stages.prepare(demo, demo_recipe=demo, repo=repo)
    assert (repo / "calls.txt").read_text() == "called\n"
    assert load_recipe(demo).sequence("g/x").c3d.is_file()
    stages.prepare(demo, demo_recipe=demo, repo=repo)  # complete now: not called again
    assert (repo / "calls.txt").read_text() == "called\n"
    (repo / "data" / "made.c3d").unlink()
    stages.prepare(demo, demo_recipe=demo, repo=repo)  # a file went missing: regenerated
    assert (repo / "calls.txt").read_text() == "called\ncalled\n"


# -- every problem at once, names that fit the file system ----------------------------------------

def test_every_problem_at_once_with_the_checkable_rest(tmp_path):
    r = good(tmp_path)
    seq(r)["fps"] = "fast"
    seq(r)["contact"] = "data/gone.json"  # a missing file of the same sequence
    r["subjects"]["b"]["sex"] = "other"
    r["sequences"]["s01/Hug 2"] = {**seq(r), "fps": 25, "markers_on": "zed"}
    r["camras"] = []
    p = write(tmp_path, r)
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    probs = e.value.problems
    assert str(e.value).splitlines() == probs
    assert all(x.startswith(f"{p}: ") for x in probs), probs
    for want in ("sequences.s01/Grab 1.fps:", "subjects.b.sex:", "camras: unknown key",
                 "sequences.s01/Hug 2.markers_on: unknown subject 'zed'",
                 "sequences.s01/Grab 1.contact: file not found:",
                 "sequences.s01/Hug 2.contact: file not found:"):
        assert sum(f"{p}: {want}" in x for x in probs) == 1, (want, probs)
    assert len(probs) == 6, probs
    part = e.value.recipe  # what the engine can still check: the bad values at their defaults
    assert list(part.sequences) == ["s01/Grab 1"]  # Hug 2 names no known subject: left out
    assert part.sequence("s01/Grab 1").fps is None and part.subjects["b"].sex == "unknown"
    assert part.sequence("s01/Grab 1").c3d.is_file() and part.source == p


def test_schema_errors_do_not_repeat_as_reference_errors(tmp_path):
    r = good(tmp_path)
    r["cameras"] = ["c1", "c1"]  # repeated: dropped, so every camera check would fail too
    seq(r)["markers_on"] = 7
    with pytest.raises(RecipeError) as e:
        load_recipe(write(tmp_path, r))
    probs = e.value.problems
    assert len(probs) == 2 and "cameras: Value error, camera ids repeat" in probs[0] + probs[1]
    assert any("sequences.s01/Grab 1.markers_on: Input should be a valid string" in x
               for x in probs), probs
    r = good(tmp_path)
    r["subjects"]["b"] = "not a mapping"  # kept with its defaults: no 'unknown subject b'
    with pytest.raises(RecipeError) as e:
        load_recipe(write(tmp_path, r))
    assert len(e.value.problems) == 1 and "subjects.b:" in e.value.problems[0]
    assert list(e.value.recipe.sequences) == ["s01/Grab 1"]


def test_names_too_long_for_the_file_system(tmp_path):
    from recipes.schema import NAME_RESERVE, name_max

    limit = name_max(tmp_path)
    assert limit == os.pathconf(tmp_path, "PC_NAME_MAX")
    fits = "a" * (limit - NAME_RESERVE)
    r = good(tmp_path)
    r["subjects"][fits] = {}
    r["sequences"][f"s01/{fits}"] = {**seq(r), "markers_on": fits}
    assert load_recipe(write(tmp_path, r)).sequence(f"s01/{fits}")  # exactly at the limit
    long = fits + "é"  # bytes count, not characters
    r = good(tmp_path)
    r["session"] = "s" * (limit + 1)
    r["subjects"][long] = {}
    r["sequences"][f"{long}/Grab 1"] = dict(seq(r))
    r["sequences"][f"s01/{long}"] = {**seq(r), "markers_on": long}
    p = write(tmp_path, r)
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    probs = e.value.problems
    assert [x.split(": name too long")[0] for x in probs] == [
        f"{p}: session", f"{p}: subjects.{long}", f"{p}: sequences.{long}/Grab 1",
        f"{p}: sequences.s01/{long}"], probs
    assert all(f"{limit} per file name (NAME_MAX)" in x for x in probs)
    assert list(e.value.recipe.sequences) == ["s01/Grab 1"]  # the rest is still checked
    with pytest.raises(RecipeError, match=r"sequences.s01/Grab 1: name too long: action"):
        load_recipe(write(tmp_path, good(tmp_path)), max_name=NAME_RESERVE + 5)
