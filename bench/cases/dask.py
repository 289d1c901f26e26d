"""The Dask executor (issue #19): speed-up of 2 workers over 1 on the fits, and the executor's
overhead per task.

``dask.speedup_2w``: the bench session's (``bench/work/partner_fit/recipe.yaml``, see
``bench/cases/partner_fit.py``) eight sequences (all), the wearer's fit only: ``marker_fit``
forced (``--force marker_fit --until marker_fit``), its upstreams (``shape_fit``,
``keypoints``: the detections) cached, hard-linked from the partner_fit case's store into
``bench/work/dask/outputs``. At 88224db the case forced the partner fit too, with its second
detection pass, on four sequences: 1059 s of the bench's 88 minutes (``dask.fits_1w_s`` 682 s)
for a scheduling figure. Measured in session 17 on one machine, an hour apart: these eight
~9 s tasks 1.45 and 1.68 (``dask.task_slowdown_2w`` 1.35, 1.16), both fits on four sequences
with the partner's second pass off 1.65 (slowdown 1.14, 490 s case); the 1.95 at 88224db had
a slowdown of 0.97. The tasks' slowdown beside each other is the machine's, not the
executor's (``dask.busy_fraction_2w`` 0.94-0.98 in all three), so the cheapest case measures
it. Wall time of the run on a ``LocalCluster`` of 1 worker, then of 2
(one thread each, one BLAS thread each: ``OMP_NUM_THREADS=1`` ...); each cluster is started and
its workers have imported the domain packages before the clock starts (``dask.cluster_start_s``
is that start-up, once per run, not per sequence). ``dask.fits_1w_s``, ``dask.fits_2w_s``: the
two wall times; ``dask.same_fits``: 1 when both runs wrote the same fit arrays (and keys);
``dask.busy_fraction_2w``: the tasks' summed wall time over 2 x the run's (how well the two
workers were kept busy: what the executor controls); ``dask.task_slowdown_2w``: the tasks'
summed time with 2 workers over that with 1 (the machine: two fits at once run slower than
one, more so when other processes share the cores).

``dask.overhead_s_per_task``: ``N_NOOP`` + 1 nodes of a stage that writes one tiny JSON
(``bench/cases/_dask_noop.py``), all computed into a fresh store: (wall time on a 1-worker
LocalCluster - wall time of the serial executor) / nodes; ``dask.overhead_hits_s_per_task``:
the same with every node a cache hit (a rerun). ``dask.loadavg_1m``: the machine's load when
the case started (other processes share its 2 cores and bend the speed-up).
"""
from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

from bench.cases import partner_fit as P

SEQUENCES = None  # every sequence of the bench session: eight tasks (six: 1.81, the last
# task's length deciding it)
FITS = ("marker_fit",)  # forced and timed
CACHED = ("shape_fit", "keypoints")  # hard-linked from the partner_fit case's store
N_NOOP = 200
NOOP = Path(__file__).resolve().parent / "_dask_noop.py"
AFTER = ("partner_fit",)  # reuses that case's store of fits: runs after it (bench.run_order)
GOALS = {"dask.speedup_2w": (">=", 1.8), "dask.overhead_s_per_task": ("<=", 0.05)}
LIMITS = {
    "dask.speedup_2w": (
        "the machine, not the scheduling: the workers are busy ~95% of the run "
        "(dask.busy_fraction_2w), but each fit runs ~25% slower when two run at once "
        "(dask.task_slowdown_2w; the two vCPUs were shared with other jobs, dask.loadavg_1m); "
        "and eight tasks of unequal length (8-12 s) leave one worker idle at the end. The "
        "figure moves between runs of the same code on this machine (1.45, 1.68 and 2.09 in "
        "session 17): read one run's value against dask.task_slowdown_2w, not alone."),
    "dask.overhead_s_per_task": (
        "a task's round trip client -> scheduler -> worker -> client, plus the worker-side "
        "lock, manifest and fsync that the serial run pays too."),
}


def _link(src: Path, dst: Path, stages: tuple[str, ...]) -> None:
    """Hard-link the cached artifacts of ``stages`` under ``src`` into ``dst``."""
    for m in sorted(src.rglob("manifest.json")):
        art = m.parent
        if art.name in stages:
            target = dst / art.relative_to(src)
            if not target.exists():
                shutil.copytree(art, target, copy_function=os.link)


def _cluster(n: int):
    from pipeline.cluster import config_from_dict, make_client

    t0 = time.perf_counter()
    cfg = config_from_dict({"kind": "local", "workers": n, "cores": 1, "dashboard_address": ":0"},
                           "bench")
    client, cluster, _ = make_client(cfg)
    client.wait_for_workers(n, timeout=120)
    return client, cluster, time.perf_counter() - t0


def _timed(spec, executor) -> tuple[float, object, list[str]]:
    from pipeline.cli import build_engine

    logs: list[str] = []
    eng = build_engine(spec, log=logs.append)
    eng.executor = executor
    plan = eng.plan(spec.command, sequences=list(spec.sequences) if spec.sequences else None,
                    until=spec.until)
    t0 = time.perf_counter()
    rep = eng.run(plan, force=spec.force)
    wall = time.perf_counter() - t0
    if rep.failed:
        raise RuntimeError("engine failed:\n" + "\n".join(logs[-40:]))
    return wall, (eng, rep), logs


def _fits(eng, rep) -> dict:
    import numpy as np

    out = {}
    for (stage, unit), o in rep.outcomes.items():
        if stage in FITS:
            assert o.status == "computed", (stage, unit, o)
            e = eng.store.entry(unit, stage)
            a = eng.store.open(unit, stage, e.manifest).arrays("fit")
            out[(stage, unit)] = (e.manifest["key"], {k: np.array(v) for k, v in a.items()})
    return out


def _same(a: dict, b: dict) -> bool:
    import numpy as np

    return a.keys() == b.keys() and all(
        a[k][0] == b[k][0] and a[k][1].keys() == b[k][1].keys()
        and all(np.array_equal(a[k][1][n], b[k][1][n], equal_nan=a[k][1][n].dtype.kind in "fc")
                for n in a[k][1])
        for k in a)


def speedup(work: Path) -> dict[str, float]:
    from pipeline.executors import DaskExecutor, EngineSpec

    src_work = work.parent / "partner_fit"
    recipe = src_work / "recipe.yaml"
    if not recipe.is_file():
        src_work.mkdir(parents=True, exist_ok=True)
        recipe = P.bench_recipe(src_work, P.stride())
    outputs = work / "outputs"
    _link(src_work / "outputs", outputs, CACHED)
    base = dict(registry="stages", recipe=str(recipe.resolve()), outputs=str(outputs.resolve()),
                command="sequence", sequences=SEQUENCES)
    walls, fits, start, busy = {}, {}, [], {}
    for n in (1, 2):
        client, cluster, t_start = _cluster(n)
        start.append(t_start)
        try:
            client.run(exec, "import stages, fitting.marker_fit, fitting.partner_fit")
            # the detections (and shapes) cached before the clock starts; hits when linked
            _timed(EngineSpec(**base, until="keypoints"), DaskExecutor(client, progress=False))
            wall, (eng, rep), logs = _timed(
                EngineSpec(**base, until="marker_fit", force=FITS),
                DaskExecutor(client, progress=False))
            (work / f"fits_{n}w.log").write_text("\n".join(logs))
            walls[n], fits[n] = wall, _fits(eng, rep)
            busy[n] = sum(o.seconds for o in rep.outcomes.values())
        finally:
            client.close()
            cluster.close()
    return {"dask.speedup_2w": walls[1] / walls[2], "dask.fits_1w_s": walls[1],
            "dask.fits_2w_s": walls[2], "dask.cluster_start_s": max(start),
            "dask.same_fits": float(_same(fits[1], fits[2])),
            "dask.busy_fraction_2w": busy[2] / (2 * walls[2]),
            "dask.task_slowdown_2w": busy[2] / busy[1]}


def overhead(work: Path) -> dict[str, float]:
    from pipeline.executors import DaskExecutor, EngineSpec, SerialExecutor

    recipe = work / "noop.yaml"
    recipe.write_text(f"session: noop\nn: {N_NOOP}\n")
    walls: dict[str, float] = {}
    client, cluster, _ = _cluster(1)
    try:
        client.run(exec, "import pipeline.cli, pipeline.engine")
        for name, make in (("serial", SerialExecutor), ("dask", lambda: DaskExecutor(
                client, progress=False))):
            out = work / f"noop_{name}"
            shutil.rmtree(out, ignore_errors=True)
            spec = EngineSpec(registry=str(NOOP), recipe=str(recipe), outputs=str(out))
            walls[name], (_, rep), _ = _timed(spec, make())
            assert rep.count("computed") == N_NOOP + 1, rep.summary()
            walls[f"{name}_hits"], (_, rep), _ = _timed(spec, make())
            assert rep.count("hit") == N_NOOP + 1, rep.summary()
    finally:
        client.close()
        cluster.close()
    n = N_NOOP + 1
    return {"dask.overhead_s_per_task": (walls["dask"] - walls["serial"]) / n,
            "dask.overhead_hits_s_per_task": (walls["dask_hits"] - walls["serial_hits"]) / n,
            "dask.noop_serial_s_per_task": walls["serial"] / n}


def run(work: Path) -> dict[str, float]:
    out = {"dask.loadavg_1m": os.getloadavg()[0]}
    out.update(overhead(work))
    out.update(speedup(work))
    return out
