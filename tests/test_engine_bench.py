"""The bench harness: discovery, per-case work folders, failures recorded without stopping
the others, flat results merged across runs, the Markdown table with goals and machine."""
from __future__ import annotations

import json
from pathlib import Path

import bench

OK = '''
GOALS = {"ok.speed_s": ("<=", 1.0), "ok.acc_mm": (">=", 10.0)}
LIMITS = {"ok.acc_mm": "the toy detector is blind", "ok.speed_s": "never shown: it passes"}
SECTION_PREFIXES = ("ok.table.",)
def report(results):
    return "## Toy section\\n\\nacc is " + str(results["ok.acc_mm"]) + ", t=" + str(results["ok.table.t"])
def run(work):
    (work / "touched").write_text("x")
    return {"ok.speed_s": 0.5, "ok.acc_mm": 3.0, "ok.table.t": 42.0}
'''
BAD = '''
def run(work):
    raise RuntimeError("boom in case")
'''
LATER = '''
def run(work):
    return {"later.n": 7}
'''


def make(tmp_path: Path) -> Path:
    cases = tmp_path / "cases"
    cases.mkdir()
    (cases / "a_ok.py").write_text(OK)
    (cases / "b_bad.py").write_text(BAD)
    (cases / "c_later.py").write_text(LATER)
    (cases / "_helper.py").write_text("raise SystemExit('helpers are not cases')\n")
    return tmp_path


def test_harness_records_failures_merges_and_renders(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code-one")
    monkeypatch.setattr(bench, "commit_label", lambda repo=None: "abc123")
    d = make(tmp_path)
    assert [p.stem for p in bench.discover(d / "cases")] == ["a_ok", "b_bad", "c_later"]
    assert bench.main([], bench_dir=d) == 1  # one case failed
    res = json.loads((d / "results.json").read_text())
    assert res["ok.speed_s"] == 0.5 and res["later.n"] == 7.0  # the case after the failure ran
    assert res["b_bad.error"] == "RuntimeError: boom in case"
    assert (d / "work" / "a_ok" / "touched").exists()
    md = (d / "RESULTS.md").read_text()
    assert "| `ok.speed_s` | 0.5 | <= 1 | pass | abc123 |" in md
    assert "| `ok.acc_mm` | 3 | >= 10 | FAIL | abc123 |" in md
    meas = json.loads((d / "measured.json").read_text())
    assert meas["ok.speed_s"]["commit"] == "abc123" and meas["ok.speed_s"]["code"] == "code-one"
    assert "- `b_bad`: RuntimeError: boom in case" in md
    # a missed goal says what limits it; a passed one is not listed; the case's own section
    assert "- `ok.acc_mm` = 3 (goal >= 10): FAIL. the toy detector is blind" in md
    assert "never shown" not in md
    assert "## Toy section\n\nacc is 3.0, t=42.0" in md
    assert "`ok.table.t`" not in md  # shown in its section only
    for word in ("- cpu: ", "- cores: ", "- python: ", "- numpy: ", "- date: ",
                 "- command: `python -m bench`"):
        assert word in md

    # a second run of one case keeps the other keys and clears that case's old error
    (d / "cases" / "b_bad.py").write_text('def run(work):\n    return {"bad.fixed": 1}\n')
    assert bench.main(["b_bad"], bench_dir=d) == 0
    res = json.loads((d / "results.json").read_text())
    assert "b_bad.error" not in res and res["bad.fixed"] == 1.0 and res["ok.speed_s"] == 0.5
    md = (d / "RESULTS.md").read_text()
    assert "| `ok.speed_s` | 0.5 (earlier run) | <= 1 | pass | abc123 |" in md  # same code

    assert "command: `python -m bench b_bad`" in md
    # a case that runs again drops its own keys it no longer produces, not the others'
    (d / "cases" / "c_later.py").write_text('def run(work):\n    return {"c_later.m": 1}\n')
    res = json.loads((d / "results.json").read_text())
    res["c_later.stale"] = 5.0
    (d / "results.json").write_text(json.dumps(res))
    assert bench.main(["c_later"], bench_dir=d) == 0
    res = json.loads((d / "results.json").read_text())
    assert "c_later.stale" not in res and res["c_later.m"] == 1.0 and res["later.n"] == 7.0
    assert bench.main(["nope"], bench_dir=d) == 2


def test_bad_return_values_are_failures(tmp_path):
    cases = tmp_path / "cases"
    cases.mkdir()
    (cases / "x.py").write_text('def run(work):\n    return {"x.flag": True}\n')
    (cases / "y.py").write_text('def run(work):\n    return [1]\n')
    (cases / "z.py").write_text('GOALS = {"z.v": ("~", 1)}\ndef run(work):\n    return {}\n')
    assert bench.main([], bench_dir=tmp_path) == 1
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res) == {"x.error", "y.error", "z.error", "bench.total_s", "bench.cases_failed"}
    assert res["bench.cases_failed"] == 3.0


def test_a_figure_from_older_code_gets_no_verdict(tmp_path, monkeypatch):
    d = make(tmp_path)
    monkeypatch.setattr(bench, "commit_label", lambda repo=None: "old111")
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code-old")
    bench.main(["a_ok"], bench_dir=d)
    monkeypatch.setattr(bench, "commit_label", lambda repo=None: "new222")
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code-new")
    assert bench.main(["c_later"], bench_dir=d) == 0
    md = (d / "RESULTS.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| `ok.speed_s`"))
    assert "pass" not in row and "FAIL" not in row
    assert "not re-measured on this code" in row and "old111 (older code)" in row
    assert "| `later.n` | 7 |  |  | new222 |" in md
    # re-rendering against the old code gives the verdict back
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code-old")
    assert bench.main(["--table"], bench_dir=d) == 0
    row = next(line for line in (d / "RESULTS.md").read_text().splitlines()
               if line.startswith("| `ok.speed_s`"))
    assert "| pass | old111 |" in row


def test_code_version_follows_source_files_not_results(tmp_path):
    import subprocess

    repo = tmp_path / "r"
    (repo / "bench").mkdir(parents=True)
    (repo / "a.py").write_text("x = 1\n")
    (repo / "bench" / "results.json").write_text("{}")
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    v1 = bench.code_version(repo)
    (repo / "bench" / "results.json").write_text('{"k": 1}')
    (repo / "notes.md").write_text("prose")
    assert bench.code_version(repo) == v1
    (repo / "a.py").write_text("x = 2\n")
    assert bench.code_version(repo) != v1


def test_case_wall_times_budget_and_a_full_run_refreshes_every_row(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code-one")
    monkeypatch.setattr(bench, "commit_label", lambda repo=None: "run1")
    cases = tmp_path / "cases"
    cases.mkdir()
    (cases / "fast.py").write_text('def run(work):\n    return {"fast.v": 1}\n')
    (cases / "slow.py").write_text('import time\ndef run(work):\n    time.sleep(0.3)\n'
                                   '    return {"slow.v": 2}\n')
    # a key no case writes any more (a renamed prefix), from an older run
    (tmp_path / "results.json").write_text(json.dumps({"gone.v": 5.0, "fast.v": 0.0}))
    assert bench.main(["fast"], bench_dir=tmp_path) == 0  # one case: the old key stays
    res = json.loads((tmp_path / "results.json").read_text())
    assert "gone.v" in res and "bench.total_s" not in res and res["fast.case_wall_s"] < 0.3
    assert bench.main([], bench_dir=tmp_path) == 0  # every case, none failed
    res = json.loads((tmp_path / "results.json").read_text())
    assert "gone.v" not in res
    assert res["slow.case_wall_s"] >= 0.3
    assert res["bench.total_s"] >= res["slow.case_wall_s"]
    md = (tmp_path / "RESULTS.md").read_text()
    assert "(earlier run)" not in md
    rows = [ln for ln in md.split("## Goals")[0].splitlines() if ln.startswith("| `")]
    assert rows and all(ln.endswith("| run1 |") for ln in rows)
    assert "| `bench.total_s` |" in md and "<= 2700 | pass |" in md
    budget = md.split("## Time budget")[1]
    assert budget.index("| slow |") < budget.index("| fast |")  # slowest first
    # a full run with a failed case keeps the earlier keys (nothing is dropped)
    (cases / "fast.py").write_text('def run(work):\n    raise ValueError("x")\n')
    assert bench.main([], bench_dir=tmp_path) == 1
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["fast.v"] == 1.0 and "fast.error" in res
