"""The engine: run a plan against the artifact store, or report its status.

One log line per node::

    14:02:11  marker_fit   s02/Grab 4    miss   12.31 s
    14:02:11  shape_fit    s02           hit     0.00 s

A node is a cache *hit* when a complete artifact with the same key is on disk. Otherwise the
engine takes the artifact's lock, looks again (another process may have just built it: then
it is a hit too), and builds it into a temporary folder that is renamed into place.
"""
from __future__ import annotations

import contextlib
import dataclasses
import platform
import socket
import sys
import threading
import time
import traceback
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from threadpoolctl import threadpool_limits

from pipeline.executors import EngineSpec, Executor, Outcome, SerialExecutor
from pipeline.hashing import FileHasher
from pipeline.lease import LeaseLost
from pipeline.plan import (
    ImportMemo,
    Node,
    NodeId,
    Plan,
    PlanError,
    build_plan,
    check_registry,
)
from pipeline.procs import Interrupted, end_children, signals_raise
from pipeline.spec import RecipeView, Registry, StageContext
from pipeline.store import CorruptArtifactError, Store

BLAS_THREADS = 1  # threads of numpy's BLAS/LAPACK inside a stage (see Engine._build)


def _cpu_seconds() -> float:
    """CPU seconds of this process (every thread) and of its finished child processes (a
    stage's worker pool): a stage's ``timings.cpu_s`` is the difference across its run. On a
    Dask worker that runs several tasks in threads at once it also counts the others'."""
    import resource

    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def stderr_log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def is_input_error(exc: BaseException) -> bool:
    """Bad data, not a bug: ``exc``'s class says ``input_error = True`` (the convention
    ``formats.errors.InputError`` follows without importing the engine; its message names file,
    field and frame). Raised inside a stage it fails the node with that one line, no traceback,
    and the CLI exits with 2 instead of 1."""
    return getattr(exc, "input_error", False) is True


def drop_repeats(problems: list[str]) -> list[str]:
    """``problems`` without repeats, and without the later ones that name a path an earlier one
    reported as ``file not found: <path>`` (the recipe says it first; the planned raw inputs and
    the registry's checks of the same file would only say it again)."""
    gone = [p.split("file not found: ", 1)[1].strip() for p in problems if "file not found: " in p]
    out: list[str] = []
    for p in dict.fromkeys(problems):
        if "file not found: " not in p and any(g and g in p for g in gone):
            continue
        out.append(p)
    return out


def make_progress(label: str, enabled: bool = True) -> Callable[..., Any]:
    """``progress(iterable, total=None, desc="")``: a tqdm bar on stderr, disabled (a plain
    pass-through) when stderr is not a terminal or ``enabled`` is False (a Dask worker: its
    stderr is not the user's, the executor shows one bar over the tasks instead)."""

    def progress(iterable: Iterable | None = None, total: int | None = None, desc: str = "", **kw):
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=f"{label} {desc}".strip(), leave=False,
                    disable=not (enabled and sys.stderr.isatty()), file=sys.stderr, **kw)

    return progress


def package_versions() -> dict[str, str]:
    """``{import name: __version__}`` of the non-standard-library top-level modules imported
    right now, plus ``python`` (what the stage could have used; reading ``__version__`` is
    instant where scanning the installed distributions' metadata takes ~0.2 s)."""
    out: dict[str, str] = {"python": platform.python_version()}
    for name, mod in list(sys.modules.items()):
        if "." in name or name.startswith("_") or name in sys.stdlib_module_names:
            continue
        with warnings.catch_warnings():  # some packages deprecate __version__ (click, markupsafe)
            warnings.simplefilter("ignore")
            v = getattr(mod, "__version__", None)
        if isinstance(v, str):
            out[name] = v
    return dict(sorted(out.items()))


def host_info() -> dict[str, Any]:
    import os

    return {"hostname": socket.gethostname(), "platform": platform.platform(),
            "machine": platform.machine(), "cpus": os.cpu_count(), "pid": os.getpid()}


@dataclass
class RunReport:
    plan: Plan
    outcomes: dict[NodeId, Outcome]

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes.values())

    @property
    def failed(self) -> bool:
        return self.count("failed") > 0

    @property
    def bugs(self) -> int:
        """Failed nodes that are not bad input (their detail is a traceback)."""
        return sum(o.status == "failed" and not o.input_error for o in self.outcomes.values())

    def exit_code(self) -> int:
        """0 nothing failed, 1 a stage failed on a bug, 2 only on bad input files."""
        return 1 if self.bugs else 2 if self.failed else 0

    def failures(self) -> list[tuple[str, str, str]]:
        """``(stage, unit, last line of the error)`` of every failed node, in plan order."""
        out = []
        for (s, u), o in self.outcomes.items():
            if o.status == "failed":
                lines = [ln for ln in o.detail.strip().splitlines() if ln.strip()]
                out.append((s, u, lines[-1].strip() if lines else "(no message)"))
        return out

    def write_failures(self, path: Path) -> Path:
        """Write every failed node's full error (traceback) to ``path``; returns it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        parts = []
        for (s, u), o in self.outcomes.items():
            if o.status == "failed":
                parts.append(f"=== {s} [{u}] ({o.seconds:.2f} s)\n{o.detail.rstrip()}\n")
        path.write_text("\n".join(parts))
        return path

    def failure_table(self, traceback_file: Path | None = None) -> str:
        """The failures as a table: stage, unit, the last line of the error; then where the
        full tracebacks are. "" when nothing failed."""
        rows = self.failures()
        if not rows:
            return ""
        ws = max(len(r[0]) for r in rows + [("stage", "", "")])
        wu = max(len(r[1]) for r in rows + [("", "unit", "")])
        lines = [f"{len(rows)} FAILED:", f"  {'stage':<{ws}}  {'unit':<{wu}}  error",
                 *(f"  {s:<{ws}}  {u:<{wu}}  {e}" for s, u, e in rows)]
        if traceback_file is not None and self.bugs:
            lines.append(f"  full tracebacks: {traceback_file}")
        return "\n".join(lines)

    def planned_stages(self) -> list[str]:
        seen: dict[str, None] = {}
        for (s, _), o in self.outcomes.items():
            if o.status == "planned":
                seen[s] = None
        return list(seen)

    def summary(self) -> str:
        parts = [f"{self.count('computed')} computed", f"{self.count('hit')} cached"]
        if self.count("failed"):
            parts.append(f"{self.count('failed')} FAILED")
        if self.count("skipped"):
            parts.append(f"{self.count('skipped')} skipped (an upstream is unavailable)")
        planned = self.planned_stages()
        if planned:
            parts.append(f"{self.count('planned')} not implemented yet ({', '.join(planned)})")
        return ", ".join(parts)


@dataclass(frozen=True)
class StatusRow:
    stage: str
    unit: str
    state: str  # cached | stale | missing | not implemented | error
    detail: str = ""


class _UpstreamCorrupt(Exception):
    """Raised out of ``_build`` when the stage failed on an unreadable upstream file."""

    def __init__(self, err: CorruptArtifactError, manifest: dict | None, detail: str):
        super().__init__(str(err))
        self.err, self.manifest, self.detail = err, manifest, detail


def _corrupt_cause(exc: BaseException) -> CorruptArtifactError | None:
    """The CorruptArtifactError ``exc`` is or was raised from (a stage may wrap it)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, CorruptArtifactError):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _manifest_of(inputs: Mapping[str, Any], err: CorruptArtifactError) -> dict | None:
    """The manifest of the artifact (err.stage, err.unit) among a stage's inputs."""
    v = inputs.get(err.stage)
    arts = v.values() if isinstance(v, dict) else [v]
    return next((a.manifest for a in arts if getattr(a, "unit", None) == err.unit), None)


class _NodeRunner:
    """``run_node(node, done)`` for the executors: the engine's cache check, lock and atomic
    write of one node. ``spec`` (an :class:`EngineSpec`, or None) lets an executor rebuild
    the same engine in another process; ``log`` is the engine's log."""

    def __init__(self, engine: "Engine", forced: set[NodeId]):
        self.engine, self.forced = engine, forced
        self.spec: EngineSpec | None = None
        self.log = engine.log

    def __call__(self, node: Node, done: Mapping[NodeId, Outcome]) -> Outcome:
        return self.engine._run_logged(node, done, node.id in self.forced)


class Engine:
    """Runs stages of ``registry`` for one recipe, storing artifacts under
    ``outputs/<session>/``.

    recipe : the object ``registry.load_recipe`` returned; ``recipe_path`` names it in errors.
    log : one-line messages (default: stderr).
    """

    def __init__(self, registry: Registry, recipe: Any, recipe_path: Path, outputs: Path,
                 executor: Executor | None = None, log: Callable[[str], None] = stderr_log,
                 spec: EngineSpec | None = None):
        check_registry(registry)
        self.registry = registry
        self.recipe = recipe
        self.recipe_path = Path(recipe_path)
        self.session = registry.session_name(recipe)
        self.store = Store(Path(outputs) / self.session)
        self.executor = executor or SerialExecutor()
        self.log = log
        self.hasher = FileHasher(self.store.root / ".filehashes.json")
        self.imports = ImportMemo(self.store.root / ".imports.json")
        self._packages: dict[str, str] | None = None
        self.stage_names = [s.name for s in registry.stages]
        # How to rebuild this engine in another process (a Dask worker); the CLI sets it.
        self.spec = spec
        # The cores a stage is granted (StageContext.cores): 0 = the whole machine (serial
        # run); a Dask worker sets it to min(Stage.cores, the worker's "cores" resource).
        self.cores_of: Callable[[Any], int] = lambda _stage: 0
        self.stage_bars = True  # per-frame bars of the stages (off on Dask workers)
        # Problems found while loading the recipe (the CLI loads a partial recipe to check the
        # rest too); check() reports them first.
        self.recipe_problems: list[str] = []

    # -- planning ---------------------------------------------------------------------------
    def plan(self, command: str, sequences: list[str] | None = None,
             until: str | None = None) -> Plan:
        """Plan for ``sequence`` (one or more sequence ids), ``demo`` (every sequence),
        ``release`` or ``status`` (every stage of every unit)."""
        from pipeline.plan import targets_for

        if sequences is not None:
            known = list(self.registry.units(self.recipe, "sequence"))
            for q in sequences:
                if q not in known:
                    raise PlanError(f"{self.recipe_path}: sequences: no sequence {q!r} "
                                    f"(known: {', '.join(known)})")
        targets = targets_for(self.registry, self.recipe, command, sequences)
        return build_plan(self.registry, self.recipe, self.recipe_path, targets, until,
                          self.hasher, self.imports)

    def check(self, plan: Plan) -> list[str]:
        """Every problem that stops ``plan`` from running, one line each, before anything
        runs: the problems of loading the recipe (``recipe_problems``), the nodes' planning
        errors (bad stage options, missing raw files, unknown recipe fields; deduplicated) and
        the registry's own checks of the recipe (``Registry.check``) for the sequences of the
        plan (:func:`drop_repeats`: a missing file is named once)."""
        errs = [n.error for n in plan.nodes if n.error]
        roots = [e for e in errs if not e.startswith("upstream ")]  # the rest follow from these
        out = list(self.recipe_problems) + list(dict.fromkeys(roots or errs))
        if self.registry.check is not None:
            seqs = sorted({n.unit for n in plan.nodes if n.stage.per == "sequence"})
            out += list(self.registry.check(self.recipe, self.recipe_path, seqs))
        return drop_repeats([ln for p in out for ln in str(p).splitlines() if ln.strip()])

    # -- running ----------------------------------------------------------------------------
    def run(self, plan: Plan, force: Iterable[str] = ()) -> RunReport:
        """Run every node of ``plan``. ``force``: stage names (or ``"all"``) to recompute even
        when cached; their descendants in the plan are recomputed too."""
        errors = [n for n in plan.nodes if n.error]
        if errors:
            raise PlanError("\n".join(dict.fromkeys(n.error for n in errors)))
        force = set(force)
        for f in force - {"all"}:
            if f not in self.stage_names:
                raise PlanError(f"--force {f}: no such stage (known: {', '.join(self.stage_names)})")
        seeds = {n.id for n in plan.nodes if "all" in force or n.stage.name in force}
        forced = plan.descendants(seeds)
        self._plan = plan  # a corrupt upstream artifact is rebuilt from its node
        runner = _NodeRunner(self, forced)
        if self.spec is not None:  # what a remote executor ships to its workers
            runner.spec = dataclasses.replace(self.spec, force=tuple(sorted(force)))
        outcomes = self.executor.run(plan.nodes, runner)
        return RunReport(plan, outcomes)

    def _run_logged(self, node: Node, done: Mapping[NodeId, Outcome], force: bool) -> Outcome:
        t0 = time.perf_counter()
        o = self._run_node(node, done, force)
        o = dataclasses.replace(o, seconds=time.perf_counter() - t0)
        word = {"hit": "hit", "computed": "miss", "failed": "FAILED", "skipped": "skipped",
                "planned": "not implemented"}[o.status]
        line = f"{datetime.now():%H:%M:%S}  {node.stage.name:<12} {node.unit:<16} {word:<6}"
        if o.ok or o.status == "failed":
            line += f" {o.seconds:7.2f} s"
        if o.status == "skipped":
            line += f" ({o.detail})"
        self.log(line)
        if o.status == "failed":
            self.log(f"error: {o.detail}" if o.input_error else o.detail.rstrip())
        return o

    def _run_node(self, node: Node, done: Mapping[NodeId, Outcome], force: bool,
                  retry: bool = True) -> Outcome:
        st = node.stage
        if not st.implemented:
            return Outcome("planned", detail="not implemented yet")
        for uid in node.upstream_ids():
            up = done.get(uid)
            if up is None or not up.ok:
                why = {None: "not run", "planned": "not implemented", "failed": "failed",
                       "skipped": "skipped"}[up.status if up else None]
                return Outcome("skipped", detail=f"needs {uid[0]} [{uid[1]}]: {why}")
        self._clean_stale(node)  # a killed run's temp folders go even when this is a hit
        if not force:
            e = self.store.entry(node.unit, st.name)
            if e.state == "complete" and e.manifest["key"] == node.key:
                return Outcome("hit")
        bad = self._check_upstream(node, done)
        if bad is not None:
            return bad

        def waiting() -> None:
            self.log(f"{datetime.now():%H:%M:%S}  {st.name:<12} {node.unit:<16} waiting "
                     "(another process holds the lock)")

        try:
            with self.store.lock(node.unit, st.name, on_wait=waiting):
                self.store.clean_leftovers(node.unit, st.name)
                e = self.store.entry(node.unit, st.name)
                if e.state == "corrupt":
                    self.log(f"WARNING: {self.store.dir(node.unit, st.name)}: corrupt artifact "
                             f"({e.problem}); deleting it and recomputing")
                    self.store.remove(node.unit, st.name)
                elif not force and e.state == "complete" and e.manifest["key"] == node.key:
                    return Outcome("hit", detail="built by another process")
                return self._build(node)
        except LeaseLost as lost:  # paused past the lease: another builder took the artifact
            self.log(f"WARNING: {st.name} [{node.unit}]: {lost}; this build is discarded")
            if not retry:
                return Outcome("failed", detail=f"lease lost twice: {lost}")
            return self._run_node(node, done, force, retry=False)  # waits for it, then a hit
        except _UpstreamCorrupt as c:  # the stage could not read an upstream file
            if not retry:
                return Outcome("failed", detail=c.detail)
            bad = self._rebuild_corrupt((c.err.stage, c.err.unit), f"{c.err.file}: {c.err.problem}",
                                        c.manifest, done)
            return bad if bad is not None else self._run_node(node, done, force, retry=False)

    def _clean_stale(self, node: Node) -> None:
        """Remove the leftovers of killed runs of this node that nobody is building."""
        gone = self.store.clean_stale_leftovers(node.unit, node.stage.name)
        if gone:
            self.log(f"          {node.stage.name} [{node.unit}]: removed what a killed run left: "
                     + ", ".join(p.name for p in gone))

    def _check_upstream(self, node: Node, done: Mapping[NodeId, Outcome]) -> Outcome | None:
        """Before building ``node``: compare each upstream artifact's files with the sha256
        of its manifest; rebuild the corrupt ones. None when all is well, else the outcome
        of ``node`` (its upstream could not be rebuilt)."""
        for s, u in node.upstream_ids():
            e = self.store.entry(u, s)
            if e.state != "complete":
                continue  # _build reports it
            problem = self.store.verify(u, s, e.manifest)
            if problem:
                bad = self._rebuild_corrupt((s, u), problem, e.manifest, done)
                if bad is not None:
                    return bad
        return None

    def _rebuild_corrupt(self, uid: NodeId, problem: str, seen: dict | None,
                         done: Mapping[NodeId, Outcome]) -> Outcome | None:
        """Warn, delete the corrupt artifact ``uid`` (if its manifest is still ``seen``: not
        replaced by another process meanwhile) and build it again from its plan node. None
        when rebuilt, else the failed outcome for the node that needed it."""
        s, u = uid
        d = self.store.dir(u, s)
        self.log(f"WARNING: {d}: corrupt artifact ({problem}); recomputing {s} [{u}]")
        up = getattr(self, "_plan", None) and self._plan.by_id.get(uid)
        if not up:
            return Outcome("failed", detail=f"upstream {s} [{u}]: {d}: corrupt artifact "
                           f"({problem}), and it is not part of this plan to rebuild it")
        with self.store.lock(u, s):
            e = self.store.entry(u, s)
            if e.state != "absent" and (seen is None or e.manifest == seen):
                self.store.remove(u, s)
        o = self._run_logged(up, done, False)
        if not o.ok:
            return Outcome("failed", detail=f"upstream {s} [{u}] was corrupt ({problem}) and "
                           f"rebuilding it {o.status}: {o.detail}")
        return None

    def _build(self, node: Node) -> Outcome:
        st = node.stage
        inputs: dict[str, Any] = {}
        upstream_keys: dict[str, dict[str, str]] = {}
        for up, units in node.upstream.items():
            arts = {}
            for u in units:
                e = self.store.entry(u, up)
                if e.state != "complete":
                    return Outcome("failed", detail=f"upstream {up} [{u}] vanished: {e.state} {e.problem}")
                if e.manifest["key"] != node.upstream_keys[up][u]:
                    return Outcome("failed", detail=f"upstream {up} [{u}] was replaced by "
                                   "another run with other inputs; run again")
                arts[u] = self.store.open(u, up, e.manifest)
            same = self.registry_per(up) == st.per
            inputs[up] = arts[node.unit] if same else arts
            upstream_keys[up] = {u: a.key for u, a in arts.items()}
        writer = self.store.begin(node.unit, st.name)
        label = f"{st.name} [{node.unit}]"
        ctx = StageContext(
            stage=st.name, unit=node.unit, recipe=RecipeView(node.recipe_view, st.name),
            params=node.params, recipe_path=self.recipe_path,
            inputs=inputs, raw=dict(node.raw), out=writer,
            progress=make_progress(label, self.stage_bars),
            log=lambda msg: self.log(f"          {label}: {msg}"),
            extras={"key": node.key, "session": self.session, "outputs": self.store.root},
            cores=int(self.cores_of(st)),
        )
        # Signal handlers can only be set in the main thread: a Dask worker runs stages in
        # its task threads, where SIGTERM is the nanny's business (no Interrupted cleanup).
        in_main = threading.current_thread() is threading.main_thread()
        started = datetime.now(timezone.utc)
        t0, c0 = time.perf_counter(), _cpu_seconds()
        try:
            # SIGTERM/SIGINT -> Interrupted (exit code 128 + signum)
            # one BLAS thread in every stage, whatever runs it: the fits' results depend on
            # the summation order (shape_fit's betas moved by 0.4 between 1 and 2 threads), and
            # an artifact's numbers must not depend on the executor or the machine's cores
            with signals_raise() if in_main else contextlib.nullcontext(), \
                    threadpool_limits(limits=BLAS_THREADS):
                st.func(ctx)
        except BaseException as exc:  # noqa: BLE001 - the temp folder must go in every case
            self.store.abort(writer)
            if isinstance(exc, Interrupted):
                end_children()
                self.log(f"{datetime.now():%H:%M:%S}  {st.name:<12} {node.unit:<16} interrupted "
                         f"by {exc.signal_name}: its temporary folder was removed; exiting with "
                         f"code {exc.code}")
            if not isinstance(exc, Exception):
                raise
            bad = _corrupt_cause(exc)
            if bad is not None and (bad.stage, bad.unit) in node.upstream_ids():
                raise _UpstreamCorrupt(bad, _manifest_of(inputs, bad), traceback.format_exc()) from exc
            if is_input_error(exc):  # bad data: its one line (file, field, frame), no traceback
                return Outcome("failed", detail="; ".join(
                    ln.strip() for ln in str(exc).splitlines() if ln.strip()), input_error=True)
            return Outcome("failed", detail=traceback.format_exc())
        seconds = time.perf_counter() - t0
        cpu_s = _cpu_seconds() - c0
        if self._packages is None:
            self._packages = package_versions()
        manifest = {
            "key": node.key,
            "version": st.version,
            "inputs": {
                "upstream": upstream_keys,
                "raw": {n: {"path": str(p), "sha256": node.raw_hashes[n]}
                        for n, p in node.raw.items()},
            },
            "parameters": node.params_canon,
            "recipe_fields": node.recipe_view,
            "timings": {"started": started.isoformat(timespec="seconds"),
                        "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                        "seconds": round(seconds, 4), "cpu_s": round(cpu_s, 4)},
            "packages": self._packages,
            "host": host_info(),
            "recipe": str(self.recipe_path.resolve()),
        }
        try:
            self.store.commit(writer, node.unit, st.name, manifest)
        except BaseException:
            self.store.abort(writer)
            raise
        return Outcome("computed")

    def registry_per(self, stage: str) -> str:
        return next(s.per for s in self.registry.stages if s.name == stage)

    # -- status -----------------------------------------------------------------------------
    def status(self, plan: Plan) -> list[StatusRow]:
        """Each node's state: ``cached`` (complete artifact, same key), ``stale`` (complete
        artifact, other key), ``missing`` (none, or a corrupt one), ``not implemented``, or
        ``error`` (its key can't be computed: missing input file, bad parameter)."""
        rows = []
        blocked: dict[NodeId, str] = {}  # node -> the unimplemented stage it waits for
        for n in plan.nodes:
            if not n.stage.implemented:
                rows.append(StatusRow(n.stage.name, n.unit, "not implemented"))
                blocked[n.id] = n.stage.name
                continue
            why = next((blocked[u] for u in n.upstream_ids() if u in blocked), None)
            if why is not None:
                blocked[n.id] = why
            if n.error:
                rows.append(StatusRow(n.stage.name, n.unit, "error", n.error))
                continue
            e = self.store.entry(n.unit, n.stage.name)
            if e.state == "complete":
                same = e.manifest["key"] == n.key
                rows.append(StatusRow(n.stage.name, n.unit, "cached" if same else "stale",
                                      "" if same else f"stored key {e.manifest['key'][:12]}, "
                                      f"now {n.key[:12]}"))
            elif e.state == "corrupt":
                rows.append(StatusRow(n.stage.name, n.unit, "missing", f"corrupt: {e.problem}"))
            else:
                rows.append(StatusRow(n.stage.name, n.unit, "missing",
                                      f"can't run: needs {why} (not implemented)" if why else ""))
        return rows

