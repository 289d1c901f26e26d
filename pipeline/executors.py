"""How the nodes of a plan get run.

An executor receives the plan's nodes in DAG order and a ``run_node(node, done)`` callable,
where ``done`` maps the ids of finished nodes to their :class:`Outcome`; it must call
``run_node`` for a node only after all of ``node.upstream_ids()`` are in ``done``.
``run_node`` does the cache check, the locking and the atomic write itself, so it is safe to
call from several processes or machines that share the ``outputs`` folder. When SIGTERM or
SIGINT interrupts a stage, ``run_node`` raises :class:`pipeline.procs.Interrupted` (a
``SystemExit``) after cleaning up: an executor lets it through (no further node starts).
Signal handlers can only be set in the main thread, so an executor running nodes in other
threads gets no such cleanup for them; one running them in child processes should start
those with :func:`pipeline.procs.die_with_parent`.

Two executors:

- :class:`SerialExecutor`: one node after the other, in this process.
- :class:`DaskExecutor`: one ``dask.distributed`` task per (stage, unit) node, submitted with
  its upstream nodes' futures as dependencies, so a per-subject node is computed once and
  shared by every sequence that reads it. ``run_node`` itself can't travel (it closes over the
  engine, its registry and recipe), so the executor ships a picklable :class:`EngineSpec`
  (``run_node.spec``, set by the engine when it was built from one) and each worker process
  rebuilds the same engine and plan from it once (:func:`run_task`, cached per process) and
  runs the node exactly as the serial executor does: same cache check, key, lock and atomic
  write, so the artifacts are the same. A node whose task raises or whose worker dies too
  often (``distributed.scheduler.allowed-failures``) is ``failed``, its descendants
  ``skipped``; the other nodes go on.
"""
from __future__ import annotations

import os
import socket
import sys
import threading
import time
import traceback
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping, Protocol

if TYPE_CHECKING:
    from pipeline.plan import Node, NodeId

STATUSES = ("hit", "computed", "failed", "skipped", "planned")


@dataclass(frozen=True)
class Outcome:
    """What happened to one node. ``status``: ``hit`` (cached artifact reused), ``computed``,
    ``failed`` (``detail`` holds the traceback), ``skipped`` (an upstream is unavailable),
    ``planned`` (the stage is not implemented). ``seconds``: wall time spent on the node.
    ``input_error``: a ``failed`` node whose stage raised bad data (an exception with
    ``input_error = True``, see :func:`pipeline.engine.is_input_error`): ``detail`` is then
    its one-line message, not a traceback."""

    status: str
    seconds: float = 0.0
    detail: str = ""
    input_error: bool = False

    @property
    def ok(self) -> bool:
        return self.status in ("hit", "computed")


RunNode = Callable[["Node", Mapping["NodeId", Outcome]], Outcome]


class Executor(Protocol):
    def run(self, nodes: list["Node"], run_node: RunNode) -> dict["NodeId", Outcome]: ...


class SerialExecutor:
    """Runs the nodes one after the other in the given (topological) order."""

    def run(self, nodes: list["Node"], run_node: RunNode) -> dict["NodeId", Outcome]:
        done: dict = {}
        for n in nodes:
            done[n.id] = run_node(n, done)
        return done


# -- Dask ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EngineSpec:
    """What a worker process needs to rebuild the engine and the plan (picklable, hashable).

    registry : module name (``stages``) or absolute path of a ``.py`` registry file.
    recipe, outputs : absolute paths (a worker may run in another folder or on another host
        that mounts the same filesystem).
    overrides : the ``--set STAGE.KEY=VALUE`` items.
    command, sequences, until : the plan (``Engine.plan`` arguments).
    force : the ``--force`` stage names (the worker recomputes the same forced nodes).
    """

    registry: str
    recipe: str
    outputs: str
    overrides: tuple[str, ...] = ()
    command: str = "release"
    sequences: tuple[str, ...] | None = None
    until: str | None = None
    force: tuple[str, ...] = ()


@dataclass(frozen=True)
class TaskResult:
    """What a Dask task returns: the node's outcome, the engine's log lines for it (shown by
    the client as the task completes) and where it ran."""

    node_id: tuple[str, str]
    outcome: Outcome
    lines: tuple[str, ...] = ()
    host: str = ""
    pid: int = 0


class _ThreadLog:
    """The engine's ``log`` on a worker: lines go to the list of the task running in this
    thread (they travel back with its :class:`TaskResult`), else to stderr."""

    def __init__(self):
        self.local = threading.local()

    def __call__(self, msg: str) -> None:
        sink = getattr(self.local, "lines", None)
        if sink is None:
            print(msg, file=sys.stderr, flush=True)
        else:
            sink.append(msg)


# The engines of this worker process, by spec: the registry, recipe and plan are built once
# per process, not once per task (a cache, not state: rebuilt identically when lost; the
# last WORKER_CACHE specs are kept).
WORKER_CACHE = 4
_WORKER_ENGINES: dict[EngineSpec, tuple[Any, Any, set, _ThreadLog]] = {}
_WORKER_LOCK = threading.Lock()


def _worker_cores() -> int:
    """The ``cores`` resource of the Dask worker running this task (0 outside a worker)."""
    try:
        from distributed import get_worker

        w = get_worker()
    except (ImportError, ValueError):
        return 0
    res = getattr(getattr(w, "state", None), "total_resources", None) or {}
    return int(res.get("cores", 0) or 0)


def _worker_engine(spec: EngineSpec, fresh: bool = False):
    """``(engine, plan, forced node ids, log)`` of ``spec`` in this process; ``fresh``
    rebuilds them (the recipe, raw files or code changed since they were cached)."""
    with _WORKER_LOCK:
        hit = None if fresh else _WORKER_ENGINES.get(spec)
        if hit is not None:
            return hit
        from pipeline.cli import build_engine  # lazily: the CLI imports this module

        log = _ThreadLog()
        engine = build_engine(spec, log=log)
        plan = engine.plan(spec.command, sequences=list(spec.sequences) if spec.sequences
                           is not None else None, until=spec.until)
        errs = [n.error for n in plan.nodes if n.error]
        if errs:
            raise RuntimeError(f"the plan can't be built on {socket.gethostname()}: {errs[0]}")
        force = set(spec.force)
        seeds = {n.id for n in plan.nodes if "all" in force or n.stage.name in force}
        forced = plan.descendants(seeds)
        cores = _worker_cores()
        if cores > 0:
            engine.cores_of = lambda st: max(1, min(int(st.cores), cores))
        engine.stage_bars = False
        engine._plan = plan  # a corrupt upstream artifact is rebuilt from its node
        _WORKER_ENGINES.pop(spec, None)
        _WORKER_ENGINES[spec] = (engine, plan, forced, log)
        while len(_WORKER_ENGINES) > WORKER_CACHE:
            _WORKER_ENGINES.pop(next(iter(_WORKER_ENGINES)))
        return _WORKER_ENGINES[spec]


def run_task(spec: EngineSpec, node_id: tuple[str, str], key: str | None,
             *upstream: TaskResult) -> TaskResult:
    """The Dask task of one node: rebuild (once per process) the engine of ``spec``, check
    that this process planned the same ``key`` for ``node_id``, and run the node as the serial
    executor would, with the upstream outcomes as ``done``. Never raises an ``Exception``:
    a failure is the node's ``failed`` outcome (its traceback in ``detail``)."""
    node_id = tuple(node_id)
    host, pid = socket.gethostname(), os.getpid()
    lines: list[str] = []
    log = None
    t0 = time.perf_counter()
    try:
        engine, plan, forced, log = _worker_engine(spec)
        node = plan.by_id.get(node_id)
        if node is None or node.key != key:  # planned before an edit: plan again
            engine, plan, forced, log = _worker_engine(spec, fresh=True)
            node = plan.by_id.get(node_id)
        if node is None:
            raise RuntimeError(f"{node_id[0]} [{node_id[1]}] is not in the plan this worker built")
        if node.key != key:
            raise RuntimeError(f"{node_id[0]} [{node_id[1]}]: this worker ({host}) computes key "
                               f"{str(node.key)[:12]}, the client {str(key)[:12]}: the code, "
                               "recipe or raw files differ between the hosts")
        done = {u.node_id: u.outcome for u in upstream}
        log.local.lines = lines
        try:
            o = engine._run_logged(node, done, node.id in forced)
        finally:
            log.local.lines = None
    except Exception:  # noqa: BLE001 - the node fails, the graph goes on
        o = Outcome("failed", time.perf_counter() - t0, traceback.format_exc())
        lines += [f"{_now()}  {node_id[0]:<12} {node_id[1]:<16} FAILED on {host} (pid {pid})",
                  o.detail.rstrip()]
    return TaskResult(node_id, o, tuple(lines), host, pid)


def _max_resources(client, wait_s: float = 60.0) -> dict[str, float]:
    """The largest ``cores`` and ``memory_gb`` resources among the client's workers (waits for
    a first worker, e.g. a SLURM job that is still queued); ``{}`` when none declare any."""
    info = client.scheduler_info(n_workers=-1) if _accepts_n_workers(client) else \
        client.scheduler_info()
    if not info.get("workers"):
        client.wait_for_workers(1, timeout=wait_s)
        info = client.scheduler_info()
    out: dict[str, float] = {}
    for w in info.get("workers", {}).values():
        for k, v in (w.get("resources") or {}).items():
            out[k] = max(out.get(k, 0.0), float(v))
    return out


def _accepts_n_workers(client) -> bool:
    import inspect

    try:
        return "n_workers" in inspect.signature(client.scheduler_info).parameters
    except (TypeError, ValueError):
        return False


class DaskExecutor:
    """Runs each (stage, unit) node as a task of a ``dask.distributed`` client.

    client : a ``distributed.Client`` (``pipeline.cluster.make_client``).
    spec : the engine to rebuild on the workers; default ``run_node.spec`` (set when the
        engine was built from an :class:`EngineSpec`, as the CLI does).
    progress : a tqdm bar over the tasks on stderr (quiet when stderr is not a terminal); the
        engine's line for each node is logged as its task completes, bar or not.
    worker_resources : the ``{"cores", "memory_gb"}`` of the largest worker; default: asked
        of the scheduler. A stage asking more than that is granted that (it would never be
        scheduled otherwise), with a warning.
    log : default ``run_node.log`` (the engine's log).
    """

    def __init__(self, client, spec: EngineSpec | None = None, progress: bool = True,
                 worker_resources: Mapping[str, float] | None = None,
                 log: Callable[[str], None] | None = None):
        self.client = client
        self.spec = spec
        self.progress = progress
        self.worker_resources = dict(worker_resources) if worker_resources else None
        self.log = log

    def _needs(self, nodes: list["Node"], log) -> dict[str, dict[str, float]]:
        caps = self.worker_resources or _max_resources(self.client)
        out, warned = {}, set()
        for n in nodes:
            st = n.stage
            if st.name in out:
                continue
            need = {"cores": float(st.cores), "memory_gb": float(st.memory_gb)}
            for k in need:
                if k in caps and need[k] > caps[k]:
                    if (st.name, k) not in warned:
                        log(f"note: stage {st.name} asks {k}={need[k]:g}, the largest "
                            f"worker has {caps[k]:g}: it gets {caps[k]:g}")
                        warned.add((st.name, k))
                    need[k] = caps[k]
            out[st.name] = {k: v for k, v in need.items() if k in caps}
        return out

    def run(self, nodes: list["Node"], run_node: RunNode) -> dict["NodeId", Outcome]:
        from distributed import as_completed

        spec = self.spec or getattr(run_node, "spec", None)
        if spec is None:
            raise ValueError("DaskExecutor: the engine has no EngineSpec to rebuild on the "
                             "workers (build it with pipeline.cli.build_engine)")
        log = self.log or getattr(run_node, "log", None) or (
            lambda m: print(m, file=sys.stderr, flush=True))
        needs = self._needs(nodes, log)
        token = uuid.uuid4().hex[:8]
        futs: dict = {}
        node_of: dict = {}
        for n in nodes:
            ups = [futs[u] for u in n.upstream_ids()]
            f = self.client.submit(run_task, spec, n.id, n.key, *ups,
                                   key=f"{n.stage.name}-{n.unit}-{token}",
                                   resources=needs[n.stage.name] or None, pure=False)
            futs[n.id] = f
            node_of[f.key] = n
        bar = _bar(len(nodes), self.progress)
        results: dict = {}
        errored: dict = {}
        try:
            for f in as_completed(list(futs.values())):
                n = node_of[f.key]
                if f.status == "finished":
                    r = f.result()
                    results[n.id] = r.outcome
                    _emit(bar, log, r.lines)
                else:
                    errored[n.id] = _dask_error(f)
                bar.update(1)
                bar.set_postfix_str(_counts(results, errored), refresh=False)
        finally:
            bar.close()
        # Tasks that raised out of run_task (a worker killed too often, an unpicklable
        # argument): failed, or skipped when an upstream node is what failed.
        for n in nodes:
            if n.id not in errored:
                continue
            bad = next((u for u in n.upstream_ids()
                        if u in results and not results[u].ok), None)
            if bad is not None:
                why = {"failed": "failed", "skipped": "skipped", "planned": "not implemented"}
                o = Outcome("skipped", detail=f"needs {bad[0]} [{bad[1]}]: "
                            f"{why.get(results[bad].status, results[bad].status)}")
                log(f"{_now()}  {n.stage.name:<12} {n.unit:<16} skipped ({o.detail})")
            else:
                o = Outcome("failed", detail=errored[n.id])
                log(f"{_now()}  {n.stage.name:<12} {n.unit:<16} FAILED (its Dask task)")
                log(o.detail.rstrip())
            results[n.id] = o
        return {n.id: results[n.id] for n in nodes}


def _now() -> str:
    return time.strftime("%H:%M:%S")


def _dask_error(f) -> str:
    try:
        exc = f.exception()
        tb = f.traceback()
    except Exception as e:  # noqa: BLE001 - cancelled, lost: say so
        return f"{type(e).__name__}: {e} (task {f.key}, status {f.status})"
    if exc is None:
        return f"task {f.key}: status {f.status}"
    text = "".join(traceback.format_exception(type(exc), exc, tb))
    if type(exc).__name__ == "KilledWorker":
        text += ("the task's worker died more often than distributed.scheduler.allowed-failures "
                 "allows (killed, or over its memory limit)\n")
    return text


def _counts(results: Mapping, errored: Mapping) -> str:
    c: dict[str, int] = {}
    for o in results.values():
        c[o.status] = c.get(o.status, 0) + 1
    if errored:
        c["error"] = len(errored)
    return ", ".join(f"{v} {k}" for k, v in sorted(c.items()))


def _bar(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc="tasks", unit="task", file=sys.stderr, leave=False,
                disable=not (enabled and sys.stderr.isatty()))


def _emit(bar, log, lines) -> None:
    if not lines:
        return
    if bar.disable:
        for ln in lines:
            log(ln)
        return
    from tqdm import tqdm

    with tqdm.external_write_mode(file=sys.stderr):
        for ln in lines:
            log(ln)
