"""The engine on the toy registry, in process: order, cache hits, invalidation, status,
--force, --until, corrupt entries, failures, bad parameters, missing inputs."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import toy_registry
import yaml

from pipeline.engine import Engine
from pipeline.plan import PlanError

ALL_NODES = {("scale", "a"), ("scale", "b"), ("detect", "g/x"), ("detect", "g/y"),
             ("fit", "g/x"), ("fit", "g/y"), ("report", "g/x"), ("report", "g/y"),
             ("summary", "session")}


class Toy:
    """A toy session in a temporary folder, run in process."""

    def __init__(self, folder: Path, stages: dict | None = None, n_seq: int = 2):
        self.recipe = toy_registry.write_toy(folder, stages, n_seq)
        self.folder = folder
        self.outputs = folder / "outputs"
        self.logs: list[str] = []

    def engine(self) -> Engine:
        reg = toy_registry.registry()
        return Engine(reg, reg.load_recipe(self.recipe), self.recipe, self.outputs,
                      log=self.logs.append)

    def run(self, command="release", sequences=None, force=(), until=None):
        """Run; return the set of (stage, unit) computed by *this* run, and the report."""
        before = len(self.ends())
        eng = self.engine()
        rep = eng.run(eng.plan(command, sequences, until), force)
        return set(self.ends()[before:]), rep

    def ends(self) -> list[tuple[str, str]]:
        p = self.folder / "counts.txt"
        if not p.exists():
            return []
        return [tuple(line.split(" ", 2)[1:]) for line in p.read_text().splitlines()
                if line.startswith("end ")]

    def set_param(self, stage: str, **kw) -> None:
        r = yaml.safe_load(self.recipe.read_text())
        r["stages"].setdefault(stage, {}).update(kw)
        self.recipe.write_text(yaml.safe_dump(r))

    def status(self) -> dict[tuple[str, str], str]:
        eng = self.engine()
        return {(r.stage, r.unit): r.state for r in eng.status(eng.plan("status"))}

    def art(self, stage: str, unit: str) -> Path:
        return self.outputs / "toy" / unit / stage


@pytest.fixture
def toy(tmp_path) -> Toy:
    return Toy(tmp_path)


def test_runs_every_node_once_in_dag_order(toy):
    computed, rep = toy.run()
    assert computed == ALL_NODES
    ends = toy.ends()
    lines = (toy.folder / "counts.txt").read_text().splitlines()
    # every node starts after all of its upstream nodes ended
    pos_end = {n: lines.index(f"end {n[0]} {n[1]}") for n in ends}
    for n in rep.plan.nodes:
        if n.id in ALL_NODES:
            start = lines.index(f"start {n.stage.name} {n.unit}")
            for u in n.upstream_ids():
                assert pos_end[u] < start, (u, n.id)
    assert rep.outcomes[("polish", "g/x")].status == "planned"
    assert rep.outcomes[("publish", "g/x")].status == "skipped"
    assert "polish" in rep.outcomes[("publish", "g/x")].detail
    # one log line per node, with hit/miss and a time
    node_lines = [ln for ln in toy.logs if ln[8:10] == "  "]
    assert len(node_lines) == len(rep.plan.nodes)
    assert sum(" miss " in ln and ln.endswith(" s") for ln in node_lines) == len(ALL_NODES)
    # the fit read both subjects, markers_on first
    fit = np.load(toy.art("fit", "g/y") / "fit.npz")
    assert list(fit["order"]) == ["b", "a"]
    assert fit["total"][0] == pytest.approx((2 + 3) + (1 + 2 + 3) + (10 + 20))


def test_manifest_records_key_inputs_parameters_timings_packages_host(toy):
    _, rep = toy.run(sequences=["g/x"], command="sequence")
    m = json.loads((toy.art("fit", "g/x") / "manifest.json").read_text())
    node = rep.plan.by_id[("fit", "g/x")]
    assert m["key"] == node.key
    assert m["inputs"]["upstream"]["scale"] == {
        "a": rep.plan.by_id[("scale", "a")].key, "b": rep.plan.by_id[("scale", "b")].key}
    assert m["parameters"] == {"weight": 1.0, "peek": False}
    assert m["timings"]["seconds"] >= 0 and "started" in m["timings"]
    assert m["packages"]["numpy"] == np.__version__
    assert m["host"]["cpus"] == os.cpu_count()
    assert m["files"] == {"fit.npz": (toy.art("fit", "g/x") / "fit.npz").stat().st_size}
    md = json.loads((toy.art("detect", "g/x") / "manifest.json").read_text())
    assert md["inputs"]["raw"]["values"]["path"].endswith("x.txt")


def test_second_run_is_all_hits_and_touches_nothing(toy):
    toy.run()
    mtimes = {p: p.stat().st_mtime_ns for p in toy.outputs.rglob("manifest.json")}
    toy.logs.clear()
    computed, rep = toy.run()
    assert computed == set()
    assert {nid for nid, o in rep.outcomes.items() if o.status == "hit"} == ALL_NODES
    assert {p: p.stat().st_mtime_ns for p in toy.outputs.rglob("manifest.json")} == mtimes
    assert sum(" hit " in ln for ln in toy.logs) == len(ALL_NODES)


def test_parameter_change_recomputes_that_stage_and_its_descendants_only(toy):
    toy.run()
    toy.set_param("fit", weight=2.0)
    assert toy.status()[("fit", "g/x")] == "stale"
    assert toy.status()[("detect", "g/x")] == "cached"
    computed, _ = toy.run()
    assert computed == {("fit", "g/x"), ("fit", "g/y"), ("report", "g/x"), ("report", "g/y"),
                        ("summary", "session")}
    rep = json.loads((toy.art("report", "g/x") / "report.json").read_text())
    assert rep["total"] == pytest.approx(2 * (1 + 2) + (1 + 2 + 3) + (10 + 20))


def test_sequence_command_only_touches_that_sequence(toy):
    toy.run()
    toy.set_param("detect", offset=1.0)
    computed, _ = toy.run("sequence", ["g/x"])
    assert computed == {("detect", "g/x"), ("fit", "g/x"), ("report", "g/x")}
    st = toy.status()
    assert st[("detect", "g/y")] == "stale" and st[("report", "g/y")] == "stale"
    assert st[("summary", "session")] == "stale"
    assert st[("scale", "a")] == "cached"


def test_input_file_change_recomputes_its_readers_and_descendants_only(toy):
    toy.run()
    (toy.folder / "a.txt").write_text("1 2 4\n")  # subject a is in both sequences
    computed, _ = toy.run()
    assert computed == {("scale", "a"), ("fit", "g/x"), ("fit", "g/y"), ("report", "g/x"),
                        ("report", "g/y"), ("summary", "session")}
    (toy.folder / "y.txt").write_text("7 7\n")
    computed, _ = toy.run()
    assert computed == {("detect", "g/y"), ("fit", "g/y"), ("report", "g/y"),
                        ("summary", "session")}


def test_touch_without_content_change_is_still_a_hit(toy):
    toy.run()
    p = toy.folder / "x.txt"
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    computed, _ = toy.run()
    assert computed == set()


def test_keys_do_not_depend_on_where_the_session_lives(toy, tmp_path):
    eng = toy.engine()
    keys = {n.id: n.key for n in eng.plan("release").nodes}
    other = tmp_path / "elsewhere"
    shutil.copytree(toy.folder, other, ignore=shutil.ignore_patterns("outputs"))
    toy2 = Toy.__new__(Toy)
    toy2.recipe, toy2.folder, toy2.outputs, toy2.logs = other / "toy.yaml", other, other / "o", []
    assert {n.id: n.key for n in toy2.engine().plan("release").nodes} == keys
    assert len(set(keys.values())) == len(keys)  # and every node has its own key


def test_status_lists_cached_stale_missing_and_not_implemented(toy):
    st = toy.status()
    assert {s for (stage, _), s in st.items() if stage != "polish"} == {"missing"}
    assert st[("polish", "g/x")] == "not implemented"
    toy.run("sequence", ["g/x"], until="fit")
    st = toy.status()
    assert st[("fit", "g/x")] == "cached" and st[("report", "g/x")] == "missing"
    assert st[("fit", "g/y")] == "missing"


def test_until_runs_only_the_stage_and_what_it_needs(toy):
    computed, rep = toy.run("sequence", ["g/x"], until="fit")
    assert computed == {("scale", "a"), ("scale", "b"), ("detect", "g/x"), ("fit", "g/x")}
    assert set(rep.outcomes) == computed
    with pytest.raises(PlanError, match="--until nope: no such stage"):
        toy.run("sequence", ["g/x"], until="nope")
    with pytest.raises(PlanError, match="summary: that stage is not part of this run"):
        toy.run("sequence", ["g/x"], until="summary")


def test_force_recomputes_the_stage_and_its_descendants(toy):
    toy.run()
    computed, _ = toy.run("sequence", ["g/x"], force=["detect"])
    assert computed == {("detect", "g/x"), ("fit", "g/x"), ("report", "g/x")}
    computed, _ = toy.run("release", force=["scale"])
    assert computed == ALL_NODES - {("detect", "g/x"), ("detect", "g/y")}
    with pytest.raises(PlanError, match="--force nope: no such stage"):
        toy.run(force=["nope"])


@pytest.mark.parametrize("damage", ["manifest", "file", "size"])
def test_corrupt_entry_is_reported_deleted_and_recomputed(toy, damage):
    toy.run()
    d = toy.art("detect", "g/x")
    if damage == "manifest":
        (d / "manifest.json").write_text("{not json")
    elif damage == "file":
        (d / "detections.npz").unlink()
    else:
        with open(d / "detections.npz", "ab") as f:
            f.write(b"junk")
    assert toy.status()[("detect", "g/x")] == "missing"
    toy.logs.clear()
    computed, _ = toy.run()
    assert computed == {("detect", "g/x")}  # same key: descendants stay valid
    assert any("WARNING" in ln and "corrupt" in ln for ln in toy.logs)
    assert toy.status()[("detect", "g/x")] == "cached"


def test_failing_stage_leaves_nothing_and_skips_its_descendants(toy):
    toy.set_param("detect", fail=True)
    computed, rep = toy.run()
    assert rep.failed
    assert computed == {("scale", "a"), ("scale", "b")}
    assert rep.outcomes[("detect", "g/x")].status == "failed"
    assert "asked to fail" in rep.outcomes[("detect", "g/x")].detail
    assert rep.outcomes[("fit", "g/x")].status == "skipped"
    assert not toy.art("detect", "g/x").exists()
    assert not list((toy.outputs / "toy" / "g" / "x").glob(".tmp-*"))


def test_bad_parameters_name_the_recipe_stage_and_field(toy):
    toy.set_param("fit", wieght=2.0)
    with pytest.raises(PlanError, match=r"toy.yaml: stages.fit.wieght: unknown parameter"):
        toy.run()
    toy.set_param("fit", wieght=None)
    r = yaml.safe_load(toy.recipe.read_text())
    r["stages"]["fit"] = {"weight": "heavy"}
    toy.recipe.write_text(yaml.safe_dump(r))
    with pytest.raises(PlanError, match=r"toy.yaml: stages.fit.weight: .*number.*got 'heavy'"):
        toy.run()
    r["stages"]["fit"] = {}
    r["stages"]["report"] = {"x": 1}
    toy.recipe.write_text(yaml.safe_dump(r))
    with pytest.raises(PlanError, match=r"stages.report: stage report takes no parameters"):
        toy.run()


def test_missing_raw_input_is_an_error_naming_the_file_and_stage(toy):
    (toy.folder / "y.txt").unlink()
    with pytest.raises(PlanError, match=r"y.txt: not found \(raw input 'values' of stage detect, unit g/y\)"):
        toy.run()
    st = toy.status()  # status still works for the rest
    assert st[("detect", "g/y")] == "error" and st[("fit", "g/y")] == "error"
    assert st[("detect", "g/x")] == "missing"
    computed, _ = toy.run("sequence", ["g/x"])  # an unaffected sequence still runs
    assert ("detect", "g/x") in computed


def test_artifact_arrays_are_read_only(toy):
    toy.run("sequence", ["g/x"], until="detect")
    eng = toy.engine()
    e = eng.store.entry("g/x", "detect")
    arr = eng.store.open("g/x", "detect", e.manifest).arrays("detections")["values"]
    with pytest.raises(ValueError):
        arr[0] = 5.0


def test_progress_bar_is_silent_when_stderr_is_not_a_terminal(capfd):
    from pipeline.engine import make_progress

    bar = make_progress("fit [g/x]")
    assert list(bar(range(5), total=5, desc="frames")) == [0, 1, 2, 3, 4]
    assert bar(range(5)).disable  # stderr is captured here, not a tty
    assert capfd.readouterr().err == ""


def test_reports_are_strict_json(tmp_path):
    """A missing value (NaN) is written as null, never as a bare NaN that strict parsers reject."""
    import json as _json

    import numpy as np

    from pipeline.store import Writer

    w = Writer(tmp_path)
    w.save_json("report", {"median": float("nan"), "per": {"a": np.float64(np.inf), "b": 2.5},
                           "arr": np.array([1.0, np.nan]), "n": np.int64(3)})

    def reject(c):
        raise ValueError(f"non-standard constant {c}")

    got = _json.loads((tmp_path / "report.json").read_text(), parse_constant=reject)
    assert got == {"median": None, "per": {"a": None, "b": 2.5}, "arr": [1.0, None], "n": 3}
