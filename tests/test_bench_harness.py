"""The bench harness's run order (a case's ``AFTER``) and the figures of a run of every case
when one fails (``bench.total_s`` and ``bench.cases_failed`` still written)."""
from __future__ import annotations

import json

import bench

# each case appends its name to a log in the work root, so the test sees the order they ran in
CASE = '''{after}
def run(work):
    log = work.parent / "order.txt"
    log.write_text((log.read_text() if log.exists() else "") + "{name}\\n")
    {body}
    return {{"{name}.v": 1.0}}
'''


def write(cases, name, after="", body="pass"):
    (cases / f"{name}.py").write_text(CASE.format(name=name, after=after, body=body))


def test_cases_run_after_the_cases_they_reuse_and_a_failure_still_gives_the_total(
        tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "code_version", lambda repo=None: "code")
    monkeypatch.setattr(bench, "commit_label", lambda repo=None: "run")
    cases = tmp_path / "cases"
    cases.mkdir()
    write(cases, "convert", 'AFTER = ("partner_fit",)')
    write(cases, "dask", 'AFTER = ("partner_fit", "no_such_case")')
    write(cases, "partner_fit", body='raise RuntimeError("store broke")')
    write(cases, "zeta")
    assert [p.stem for p in bench.run_order(bench.discover(cases))] == [
        "partner_fit", "convert", "dask", "zeta"]
    assert bench.main([], bench_dir=tmp_path) == 1  # a case failed: recorded, the rest ran
    order = (tmp_path / "work" / "order.txt").read_text().split()
    assert order == ["partner_fit", "convert", "dask", "zeta"]
    res = json.loads((tmp_path / "results.json").read_text())
    assert "partner_fit.error" in res and res["zeta.v"] == 1.0
    assert res["bench.cases_failed"] == 1.0 and res["bench.total_s"] >= 0.0
    md = (tmp_path / "RESULTS.md").read_text()
    assert "| `bench.cases_failed` |" in md and "FAIL" in md.split("`bench.cases_failed`")[1] \
        .splitlines()[0]
    # one case chosen: its AFTER case is not run for it
    (tmp_path / "work" / "order.txt").unlink()
    assert bench.main(["convert"], bench_dir=tmp_path) == 0
    assert (tmp_path / "work" / "order.txt").read_text().split() == ["convert"]
    # fixed: the full run has no failure, and the total covers every case
    write(cases, "partner_fit")
    assert bench.main([], bench_dir=tmp_path) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["bench.cases_failed"] == 0.0 and "partner_fit.error" not in res
    assert res["bench.total_s"] >= max(res[f"{c}.case_wall_s"] for c in
                                       ("convert", "dask", "partner_fit", "zeta"))


def test_a_cycle_of_after_is_broken_in_name_order_once_nothing_else_can_run(tmp_path):
    write(tmp_path, "a", 'AFTER = ("b",)')
    write(tmp_path, "b", 'AFTER = ("a",)')
    write(tmp_path, "c")
    assert [p.stem for p in bench.run_order(bench.discover(tmp_path))] == ["c", "a", "b"]


def test_partner_fit_ablation_rows_asked_for():
    """bench partner_fit: BENCH_PARTNER_VARIANTS picks the ablation rows; the full method and,
    beside any row, the reference row (the full method on the first detection pass) always
    run, in table order; an unknown name is an error naming it."""
    import pytest

    from bench.cases import partner_fit as P

    assert P.variants_to_run("none") == ["full"]
    assert P.variants_to_run("") == ["full"]  # the documented default: the full method alone
    assert P.variants_to_run("all") == list(P.VARIANTS)
    assert P.variants_to_run("no_temporal, no_L_G") == ["full", "first_pass", "no_L_G", "no_temporal"]
    with pytest.raises(ValueError, match="no_L_x"):
        P.variants_to_run("no_L_x")
    assert set(P.ROWS) == set(P.VARIANTS)


def test_an_engine_run_that_fails_is_raised_or_returned_with_its_log(tmp_path):
    """bench.cases._engine.run_engine: a failed run raises naming what ran (check) or returns
    its exit code (the real case records a failed capture and goes on); the log is kept."""
    import pytest

    from bench.cases._engine import run_engine

    args = ["sequence", "s/a", "--recipe", str(tmp_path / "missing.yaml"), "--outputs",
            str(tmp_path / "out")]
    log = tmp_path / "run.log"
    with pytest.raises(RuntimeError, match="the missing recipe"):
        run_engine(args, "the missing recipe", log_file=log)
    assert "missing.yaml" in log.read_text()
    log.unlink()
    rc = run_engine(args, "the missing recipe", log_file=log, check=False)
    assert rc != 0 and "missing.yaml" in log.read_text()


def test_the_qa_case_counts_only_the_published_joints_of_a_frame():
    """``bench.cases.qa.worst_errors``: a frame's worst joint over every joint, and over the
    joints the export publishes (``joints_valid``); a 15 cm error on an unpublished joint
    counts in the first only, a frame publishing no joint counts 0."""
    import numpy as np

    from bench.cases.qa import worst_errors

    true = np.zeros((3, 4, 3))
    pred = true.copy()
    pred[:, 1, 0] = 0.15  # joint 1 15 cm off in every frame
    pred[:, 2, 1] = 0.02  # joint 2 2 cm off
    pub = np.array([[True] * 4, [True, False, True, True], [False] * 4])
    worst, worst_pub = worst_errors(pred, true, np.c_[pub, np.ones((3, 2), bool)])
    assert np.allclose(worst, 150.0)
    assert np.allclose(worst_pub, [150.0, 20.0, 0.0])
    assert np.allclose(worst_errors(pred, true)[1], 150.0)
