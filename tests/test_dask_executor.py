"""The Dask executor (issue #19) on a LocalCluster of 2 worker processes, with the fake domain
of ``tests/dask_registry.py``: the same artifacts as the serial run, per-subject nodes computed
once, failure isolation and its table, a rerun doing only what is missing, a worker killed
mid-stage, stage resources reaching the workers, the SLURM job script and the cluster YAML."""
from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import dask_registry as R
import numpy as np
import pytest

from pipeline import cli
from pipeline.cluster import (
    ClusterConfigError,
    config_from_dict,
    job_script,
    load_cluster_config,
    make_client,
)
from pipeline.executors import DaskExecutor, EngineSpec, SerialExecutor
from pipeline.store import Store

REPO = Path(__file__).resolve().parents[1]
REG = str(REPO / "tests" / "dask_registry.py")
WORKER_GB = 2.0
pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")


@pytest.fixture(scope="module")
def dask_client():
    cfg = config_from_dict({"kind": "local", "workers": 2, "cores": 2, "memory": f"{WORKER_GB:g}GiB",
                            "dashboard_address": ":0"}, "test")
    client, cluster, link = make_client(cfg)
    client.wait_for_workers(2, timeout=60)
    yield client
    client.close()
    cluster.close()


def _engine(recipe: Path, outputs: Path, executor, log: list[str], force=()):
    spec = EngineSpec(registry=REG, recipe=str(recipe), outputs=str(outputs), force=tuple(force))
    eng = cli.build_engine(spec, log=log.append)
    eng.executor = executor
    return eng


def _run(recipe, outputs, executor, force=()):
    log: list[str] = []
    eng = _engine(recipe, outputs, executor, log, force)
    plan = eng.plan("release")
    return eng, plan, eng.run(plan, force=force), log


def _starts(folder: Path) -> list[tuple[str, str]]:
    return [(s, u) for what, s, u, _ in R.counts(folder) if what == "start"]


def _no_tmp(root: Path) -> list[Path]:
    return [p for p in root.rglob(".tmp-*")] + [p for p in root.rglob(".trash-*")]


def test_same_artifacts_as_serial_and_per_subject_nodes_run_once(tmp_path, dask_client):
    stages = {"detect": {"pool": True}}  # a process pool inside a worker: needs daemon False
    rs = R.write_recipe(tmp_path / "serial", n_seq=4, stages=stages)
    rd = R.write_recipe(tmp_path / "dask", n_seq=4, stages=stages)
    eng_s, plan_s, rep_s, _ = _run(rs, tmp_path / "out_s", SerialExecutor())
    eng_d, plan_d, rep_d, log = _run(rd, tmp_path / "out_d", DaskExecutor(dask_client))
    assert not rep_s.failed and not rep_d.failed, log
    assert {n.id: n.key for n in plan_s.nodes} == {n.id: n.key for n in plan_d.nodes}
    assert len(plan_d.nodes) == 2 + 4 + 4 + 1
    assert all(o.status == "computed" for o in rep_d.outcomes.values())
    for n in plan_d.nodes:
        ms, md = (e.store.entry(n.unit, n.stage.name) for e in (eng_s, eng_d))
        assert ms.state == md.state == "complete"
        assert ms.manifest["key"] == md.manifest["key"] == n.key
        assert eng_d.store.verify(n.unit, n.stage.name, md.manifest) == ""
        a_s, a_d = (e.store.open(n.unit, n.stage.name, m.manifest)
                    for e, m in ((eng_s, ms), (eng_d, md)))
        name = {"shape": "shape", "detect": "detections", "fit": "fit"}.get(n.stage.name)
        if name is None:
            assert a_s.json("summary") == a_d.json("summary")
            continue
        xs, xd = a_s.arrays(name), a_d.arrays(name)
        assert sorted(xs) == sorted(xd)
        for k in xs:
            np.testing.assert_array_equal(xs[k], xd[k])
    starts = _starts(tmp_path / "dask")
    assert sorted(starts) == sorted(n.id for n in plan_d.nodes)  # each node once, shapes too
    assert starts.count(("shape", "a")) == 1 and starts.count(("shape", "b")) == 1
    workers = set(dask_client.run(os.getpid).values())
    assert {pid for *_, pid in R.counts(tmp_path / "dask")} <= workers  # ran on the workers
    for n in plan_d.nodes:  # one log line per node, as in a serial run
        assert sum(f" {n.stage.name:<12} {n.unit:<16} miss" in ln for ln in log) == 1, log
    # a rerun is all hits
    _, _, rep2, _ = _run(rd, tmp_path / "out_d", DaskExecutor(dask_client))
    assert {o.status for o in rep2.outcomes.values()} == {"hit"}
    assert len(_starts(tmp_path / "dask")) == len(starts)


def test_stage_cores_reach_the_worker_as_resources(tmp_path, dask_client):
    r = R.write_recipe(tmp_path / "r", n_seq=1)
    eng, plan, rep, log = _run(r, tmp_path / "out", DaskExecutor(dask_client))
    assert not rep.failed, log
    det = eng.store.open("g/s0", "detect", eng.store.entry("g/s0", "detect").manifest)
    fit = eng.store.open("g/s0", "fit", eng.store.entry("g/s0", "fit").manifest)
    assert det.json("granted") == {"cores": 2, "resources": {"cores": 2.0, "memory_gb": 1.0}}
    assert fit.json("granted") == {"cores": 1, "resources": {"cores": 1.0, "memory_gb": WORKER_GB}}
    # summary asks 64 GB, more than any worker: granted the largest worker's, with a warning
    assert any("stage summary asks memory_gb=64" in ln and f"it gets {WORKER_GB:g}" in ln
               for ln in log), log
    # serially the stage gets cores 0 (the whole machine) and no Dask resources
    eng_s, _, rep_s, _ = _run(R.write_recipe(tmp_path / "s", n_seq=1), tmp_path / "out_s",
                              SerialExecutor())
    d = eng_s.store.open("g/s0", "detect", eng_s.store.entry("g/s0", "detect").manifest)
    assert d.json("granted") == {"cores": 0, "resources": {}}


def test_a_failing_sequence_does_not_stop_the_others_and_a_rerun_does_only_what_is_missing(
        tmp_path, dask_client):
    folder = tmp_path / "r"
    r = R.write_recipe(folder, n_seq=4, sequences={"g/s1": {"fail": True}})
    out = tmp_path / "out"
    addr = dask_client.scheduler.address
    argv = ["release", "--recipe", str(r), "--registry", REG, "--outputs", str(out),
            "--scheduler", addr]
    log: list[str] = []
    assert cli.main(argv, log=log.append) == 1
    text = "\n".join(log)
    assert "dask: dashboard" in text
    store = Store(out / "dtoy")
    for q in ("g/s0", "g/s2", "g/s3"):
        for st in ("detect", "fit"):
            assert store.entry(q, st).state == "complete", (q, st, text)
    assert store.entry("g/s1", "detect").state == "absent"
    assert store.entry("g/s1", "fit").state == "absent"
    assert store.entry("session", "summary").state == "absent"
    assert "2 skipped" in text and "1 FAILED" in text
    table = text[text.index("1 FAILED:"):]
    row = next(ln for ln in table.splitlines() if "g/s1" in ln)
    assert row.split()[:2] == ["detect", "g/s1"]
    assert row.rstrip().endswith("RuntimeError: detect: sequence g/s1 asked to fail")
    tb = Path(table.split("full tracebacks: ")[1].split()[0])
    assert tb.is_file() and "Traceback" in tb.read_text() and "detect [g/s1]" in tb.read_text()
    assert not _no_tmp(out)
    done = len(_starts(folder))

    # the same rerun: only the failed node runs again (and fails), nothing else starts
    assert cli.main(argv, log=[].append) == 1
    again = _starts(folder)[done:]
    assert again == [("detect", "g/s1")], again

    # fixed: only the sequence that failed and the session summary are computed
    R.write_recipe(folder, n_seq=4)
    log2: list[str] = []
    assert cli.main(argv, log=log2.append) == 0, "\n".join(log2)
    fixed = _starts(folder)[done + 1:]
    assert sorted(fixed) == [("detect", "g/s1"), ("fit", "g/s1"), ("summary", "session")], fixed
    assert "3 computed, 8 cached" in "\n".join(log2)


LEASE_TTL_S = 2.0  # short, so that a killed owner's lease expires within the test


@pytest.mark.parametrize("locks", ["flock", "lease"])
def test_a_worker_killed_mid_stage_is_retried_elsewhere_leaving_nothing_half_written(
        tmp_path, locks):
    # flock (a LocalCluster's default): the kernel drops the dead worker's lock at once; lease (SLURM/PBS,
    # pipeline/lease.py): the retry waits until the dead owner's lease expires, then takes over
    cfg = config_from_dict({"kind": "local", "workers": 2, "cores": 2, "dashboard_address": ":0",
                            "env": {"PIPELINE_LOCKS": locks,
                                    "PIPELINE_LEASE_TTL_S": str(LEASE_TTL_S)}}, "test")
    client, cluster, _ = make_client(cfg)
    try:
        client.wait_for_workers(2, timeout=60)
        _kill_mid_stage(tmp_path, client, locks)
    finally:
        client.close()
        cluster.close()


def _kill_mid_stage(tmp_path: Path, client, locks: str) -> None:
    folder = tmp_path / "r"
    r = R.write_recipe(folder, n_seq=2, sequences={"g/s0": {"sleep_s": 4.0}})
    out = tmp_path / "out"
    result: dict = {}

    def go():
        result["run"] = _run(r, out, DaskExecutor(client))

    t = threading.Thread(target=go)
    t.start()
    seq_dir = out / "dtoy" / "g" / "s0"
    t_end = time.monotonic() + 30
    while not (list(seq_dir.glob(".tmp-detect-*/partial.json")) if seq_dir.is_dir() else []):
        assert time.monotonic() < t_end, "the slow stage did not start"
        time.sleep(0.05)
    pid = next(p for what, s, u, p in R.counts(folder) if (what, s, u) == ("start", "detect", "g/s0"))
    assert pid in set(client.run(os.getpid).values())
    if locks == "lease":
        assert (seq_dir / ".detect.lease").is_file()  # the worker builds under a lease
    os.kill(pid, signal.SIGKILL)
    t.join(90)
    assert not t.is_alive()
    eng, plan, rep, log = result["run"]
    assert not rep.failed, log
    assert rep.outcomes[("detect", "g/s0")].status == "computed"
    e = eng.store.entry("g/s0", "detect")
    assert e.state == "complete" and e.manifest["key"] == plan.by_id[("detect", "g/s0")].key
    assert eng.store.verify("g/s0", "detect", e.manifest) == ""
    assert "partial.json" in e.manifest["files"] and "detections.npz" in e.manifest["files"]
    assert not _no_tmp(out)
    runs = [(w, p) for w, s, u, p in R.counts(folder) if (s, u) == ("detect", "g/s0")]
    assert [w for w, _ in runs] == ["start", "start", "end"]  # killed once, retried once
    assert runs[1][1] != pid
    assert eng.store.entry("session", "summary").state == "complete"
    waited = any("detect       g/s0" in ln and "waiting" in ln for ln in log)
    if locks == "lease":  # the retry waited for the dead owner's lease to expire
        assert waited, log
    else:
        assert not waited, log


SLURM_YAML = """\
kind: slurm
workers: 4
cores: 8
processes: 4
memory: 16GiB
walltime: "02:30:00"
queue: short-cpu
account: lab42
job_extra_directives: ["--exclusive", "--constraint=avx2"]
local_directory: /scratch/dask
env: {ANNY_CACHE_DIR: /shared/anny}
python: /shared/repo/.venv/bin/python
"""


def test_slurm_job_script_has_what_the_yaml_says(tmp_path, capsys):
    p = tmp_path / "slurm.yaml"
    p.write_text(SLURM_YAML)
    text = job_script(load_cluster_config(p), "tcp://head:8786")
    for want in ("#SBATCH -p short-cpu", "#SBATCH -A lab42", "#SBATCH --cpus-per-task=8",
                 "#SBATCH --mem=16G", "#SBATCH -t 02:30:00", "#SBATCH --exclusive",
                 "#SBATCH --constraint=avx2", "export PIPELINE_LOCKS=lease",
                 "export DASK_DISTRIBUTED__WORKER__DAEMON=False",
                 "export ANNY_CACHE_DIR=/shared/anny", "/shared/repo/.venv/bin/python -m",
                 "tcp://head:8786", "--nworkers 4", "--local-directory /scratch/dask",
                 "--resources cores=2,memory_gb=4"):
        assert want in text, (want, text)
    cmd = next(ln for ln in text.splitlines() if "distributed.cli.dask_worker" in ln).split()
    last = max(i for i, w in enumerate(cmd) if w == "--nthreads")
    assert cmd[last + 1] == "1"  # one thread per worker process (the last --nthreads wins)
    # the CLI prints the same script; the repo's example configurations are valid
    assert cli.main(["cluster-script", "--cluster", str(p), "--scheduler", "tcp://head:8786"]) == 0
    assert capsys.readouterr().out.strip() == text.strip()
    for name, head in (("slurm", "#SBATCH"), ("pbs", "#PBS")):
        assert head in job_script(load_cluster_config(REPO / "recipes" / "cluster" / f"{name}.yaml"))
    assert load_cluster_config(REPO / "recipes" / "cluster" / "local.yaml").kind == "local"


@pytest.mark.parametrize("text, field", [
    ("kind: sge\n", "kind"),
    ("kind: local\ncores: two\n", "cores"),
    ("kind: slurm\nmemory: lots\n", "memory"),
    ("kind: slurm\nqueu: cpu\nmemory: 8GiB\n", "queu"),
    ("kind: local\nworkers: 2\nadaptive: {minimum: 1, maximum: 4}\n", "workers"),
    ("kind: local\nadaptive: {minimum: 5, maximum: 4}\n", "adaptive"),
    ("kind: scheduler\n", "address"),
    ("kind: slurm\ncores: 8\nprocesses: 3\nmemory: 8GiB\n", "processes"),
    ("[1, 2\n", "(file)"),
])
def test_bad_cluster_yaml_names_file_and_field(tmp_path, text, field):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ClusterConfigError) as e:
        load_cluster_config(p)
    assert str(e.value).startswith(f"{p}: {field}"), str(e.value)


def test_cli_stops_on_a_bad_cluster_yaml_before_anything_runs(tmp_path):
    r = R.write_recipe(tmp_path / "r", n_seq=1)
    c = tmp_path / "c.yaml"
    c.write_text("kind: local\nworkers: 0\n")
    log: list[str] = []
    code = cli.main(["release", "--recipe", str(r), "--registry", REG, "--outputs",
                     str(tmp_path / "out"), "--cluster", str(c)], log=log.append)
    assert code == 2 and any(f"{c}: workers:" in ln for ln in log), log
    assert not list((tmp_path / "out").rglob("manifest.json"))


def test_workers_lock_with_flock_on_one_host_and_with_leases_across_hosts():
    """A LocalCluster's workers share one kernel (flock holds, a dead worker's lock goes at
    once); SLURM/PBS workers and a joined scheduler's may be on other hosts: leases."""
    from pipeline.cluster import worker_env

    def env(kind, **extra):
        d = {"kind": kind, **extra}
        if kind == "scheduler":
            d["address"] = "tcp://h:8786"
        if kind in ("slurm", "pbs"):
            d.update(memory="8GiB", cores=2, walltime="01:00:00", queue="q")
        return worker_env(config_from_dict(d, "test"))

    assert env("local")["PIPELINE_LOCKS"] == "flock"
    for kind in ("slurm", "pbs", "scheduler"):
        assert env(kind)["PIPELINE_LOCKS"] == "lease", kind
    assert env("local", env={"PIPELINE_LOCKS": "lease"})["PIPELINE_LOCKS"] == "lease"


def _worker_env(names):
    import os

    return {k: os.environ.get(k) for k in names}


def test_workers_start_without_dask_s_malloc_trim_threshold(dask_client):
    """Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 before it spawns a worker (also in our own
    process, where a LocalCluster's nannies live): glibc then maps and unmaps every array over
    128 kB afresh (the partner fit's Jacobian blocks: 2.8x the CPU). Our clusters leave it
    unset, in the workers and here; the thread limits still reach the workers."""
    import os

    got = dask_client.submit(_worker_env, ["MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS"],
                             pure=False).result()
    assert got["MALLOC_TRIM_THRESHOLD_"] is None, got
    assert got["OMP_NUM_THREADS"] == "1"
    assert os.environ.get("MALLOC_TRIM_THRESHOLD_") is None
