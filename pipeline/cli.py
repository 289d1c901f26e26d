"""Command line: ``python -m pipeline sequence|release|status|demo``.

::

    python -m pipeline sequence "s02/Grab 4" --recipe recipes/demo.yaml [--until marker_fit]
    python -m pipeline release  --recipe recipes/demo.yaml [--force shape_fit]
    python -m pipeline status   --recipe recipes/demo.yaml
    python -m pipeline demo     [--recipe recipes/demo.yaml]
    python -m pipeline release  --recipe ... [--executor dask] [--cluster recipes/cluster/slurm.yaml]
                                [--scheduler tcp://host:8786] [--workers N]
    python -m pipeline cluster-script --cluster recipes/cluster/slurm.yaml

Executors (``--executor``): ``serial`` (in this process; default for ``sequence`` and
``demo``) or ``dask`` (default for ``release``; ``$PIPELINE_EXECUTOR`` changes the default):
a ``LocalCluster`` of ``os.cpu_count()`` single-threaded workers unless ``--cluster`` (a
YAML of :mod:`pipeline.cluster`: local, SLURM, PBS) or ``--scheduler ADDRESS`` (join a
running cluster) says otherwise; ``--workers N`` overrides the worker count. The dashboard
address is printed; at the end a table lists the failed nodes (stage, unit, last line of the
error) and the file holding their full tracebacks. A run without ``--force`` whose every node
is already cached (a rerun) is checked in this process instead: no cluster is started for it.

``--registry`` names the domain package (default ``stages``; a module name or a path to a
``.py`` file) whose ``registry()`` returns a :class:`pipeline.spec.Registry`.
``--outputs`` (default ``$PIPELINE_OUTPUTS`` or ``outputs``) is the artifact store root.

Exit codes: 0 done (planned-but-unimplemented stages are reported, not failures), 1 a stage
failed on a bug (its traceback is logged), 2 bad command, recipe, registry or input file. Every
problem of the recipe is reported in one run, one line each, before anything runs: the schema's
(every field), missing files, unknown stages and stage options, bad option values, the
registry's checks (videos); ``status`` too. A stage that raises bad data while it runs (an
exception with ``input_error = True``: ``formats.errors.InputError``) fails its node with that
one line (``path: field [frame N]: what is wrong``), no traceback, no artifact; the run ends
with exit code 2 when no stage failed on a bug.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.util
import os
import sys
from pathlib import Path

from pipeline.engine import Engine, RunReport, stderr_log
from pipeline.executors import EngineSpec
from pipeline.plan import PlanError
from pipeline.spec import Registry
from pipeline.store import StoreError

DEFAULT_RECIPE = "recipes/demo.yaml"


class CliError(Exception):
    """Stops the command with exit code 2 and a one-paragraph message."""


def load_registry(spec: str) -> Registry:
    """Import a registry module by name (``stages``) or by path (``tests/toy_registry.py``)
    and call its ``registry()``."""
    try:
        if spec.endswith(".py") or os.sep in spec:
            path = Path(spec).resolve()
            if not path.is_file():
                raise CliError(f"--registry {spec}: no such file")
            name = f"_registry_{path.stem}"
            mod_spec = importlib.util.spec_from_file_location(name, path)
            mod = importlib.util.module_from_spec(mod_spec)
            sys.modules[name] = mod  # dataclasses and inspect need the module registered
            mod_spec.loader.exec_module(mod)
        else:
            mod = importlib.import_module(spec)
    except ModuleNotFoundError as e:
        raise CliError(f"--registry {spec}: can't import it ({e})") from None
    fn = getattr(mod, "registry", None)
    if not callable(fn):
        raise CliError(f"--registry {spec}: module has no registry() function")
    reg = fn()
    if not isinstance(reg, Registry):
        raise CliError(f"--registry {spec}: registry() returned {type(reg).__name__}, not Registry")
    return reg


def parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--recipe", default=DEFAULT_RECIPE, help="recipe YAML (default %(default)s)")
    common.add_argument("--registry", default="stages",
                        help="module (or .py path) whose registry() lists the stages")
    common.add_argument("--outputs", default=os.environ.get("PIPELINE_OUTPUTS", "outputs"),
                        help="artifact store root (default $PIPELINE_OUTPUTS or outputs)")
    run = argparse.ArgumentParser(add_help=False)
    run.add_argument("--force", action="append", default=[], metavar="STAGE",
                     help="recompute STAGE (and what depends on it) even if cached; repeatable; 'all'")
    run.add_argument("--until", metavar="STAGE", help="run only STAGE and what it needs")
    run.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE",
                     dest="overrides",
                     help="override a stage option of the recipe for this run (VALUE in YAML, "
                     "e.g. marker_fit.loo=all); it enters that stage's key like the recipe's "
                     "own options; repeatable")
    run.add_argument("--executor", choices=("serial", "dask"), default=None,
                     help="serial (this process) or dask (one task per stage and unit); "
                     "default: dask for release, serial otherwise ($PIPELINE_EXECUTOR)")
    run.add_argument("--cluster", metavar="YAML",
                     help="Dask cluster configuration (kind local|slurm|pbs|scheduler); "
                     "implies --executor dask")
    run.add_argument("--scheduler", metavar="ADDRESS",
                     help="join a running Dask scheduler (tcp://host:8786); implies --executor dask")
    run.add_argument("--workers", type=int, metavar="N",
                     help="number of Dask workers (default: the configuration's, or one per core)")

    p = argparse.ArgumentParser(prog="python -m pipeline", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("sequence", parents=[common, run], help="run the stages of sequences")
    s.add_argument("sequences", nargs="+", metavar="GROUP/ACTION")
    sub.add_parser("release", parents=[common, run], help="run every stage of every unit")
    sub.add_parser("demo", parents=[common, run],
                   help="prepare the demo data if needed, run every sequence, say where to look")
    st = sub.add_parser("status", parents=[common],
                        help="list each stage of each unit as cached / stale / missing")
    st.add_argument("--until", metavar="STAGE", help="only STAGE and what it needs")
    cs = sub.add_parser("cluster-script",
                        help="print the batch job script a SLURM/PBS cluster configuration submits")
    cs.add_argument("--cluster", required=True, metavar="YAML")
    cs.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="scheduler address written into the script (default a placeholder)")
    return p


def main(argv: list[str] | None = None, log=stderr_log) -> int:
    from pipeline.cluster import ClusterConfigError

    args = parser().parse_args(argv)
    try:
        return _main(args, log)
    except (CliError, PlanError, StoreError, ClusterConfigError) as e:
        log(f"error: {e}")
        return 2


def overrides(items: list[str]) -> dict[str, dict]:
    """``["stage.key=value", ...]`` -> ``{stage: {key: value}}`` (values parsed as YAML)."""
    import yaml

    out: dict[str, dict] = {}
    for it in items:
        head, eq, value = it.partition("=")
        stage, dot, key = head.partition(".")
        if not (eq and dot and stage and key):
            raise CliError(f"--set {it}: expected STAGE.KEY=VALUE")
        try:
            out.setdefault(stage, {})[key] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            raise CliError(f"--set {it}: VALUE is not YAML: {e}") from None
    return out


def _registry_name(spec: str) -> str:
    """The ``--registry`` value as a worker in another folder can use it (paths made absolute)."""
    if spec.endswith(".py") or os.sep in spec:
        return str(Path(spec).resolve())
    return spec


def engine_spec(args) -> EngineSpec:
    """The picklable description of the engine of ``args`` (what Dask workers rebuild)."""
    seqs = getattr(args, "sequences", None)
    return EngineSpec(
        registry=_registry_name(args.registry), recipe=str(Path(args.recipe).resolve()),
        outputs=str(Path(args.outputs).resolve()),
        overrides=tuple(getattr(args, "overrides", []) or []), command=args.command,
        sequences=tuple(seqs) if seqs is not None else None,
        until=getattr(args, "until", None), force=tuple(getattr(args, "force", []) or []))


def build_engine(spec: EngineSpec, log=stderr_log, prepare: bool = False,
                 gather: bool = False) -> Engine:
    """The engine of ``spec``: its registry (with the ``--set`` overrides), its recipe loaded
    (after ``Registry.prepare`` when ``prepare``). CliError for a bad registry or recipe.

    gather : a recipe that loads with problems but whose loader hands back the part it could
        check (the error's ``recipe`` attribute; ``problems`` its lines) gives an engine of that
        partial recipe with ``engine.recipe_problems`` set (``Engine.check`` reports them with
        the later checks' problems, so all come out in one run; nothing may run). Without
        ``gather``, or with no partial recipe: CliError with the problems."""
    reg = load_registry(spec.registry)
    extra = overrides(list(spec.overrides))
    if extra:
        names = {s.name for s in reg.stages}
        for stage in extra:
            if stage not in names:
                raise CliError(f"--set {stage}...: no such stage (known: {', '.join(names)})")
        base = reg.stage_params
        reg = dataclasses.replace(reg, stage_params=lambda r, st: {**base(r, st),
                                                                   **extra.get(st, {})})
    recipe_path = Path(spec.recipe)
    if prepare and reg.prepare is not None:
        try:
            reg.prepare(recipe_path)
        except Exception as e:  # noqa: BLE001 - reported as one line, exit code 2
            raise CliError(f"preparing {recipe_path}: {e}") from None
    if not recipe_path.is_file():
        raise CliError(f"{recipe_path}: recipe not found")
    problems: list[str] = []
    try:
        recipe = reg.load_recipe(recipe_path)
    except (ValueError, OSError) as e:  # RecipeError / InputError are ValueErrors
        partial = getattr(e, "recipe", None)
        if not gather or partial is None:
            raise CliError(str(e)) from None
        recipe = partial
        problems = [str(p) for p in (getattr(e, "problems", None) or str(e).splitlines())]
    eng = Engine(reg, recipe, recipe_path, Path(spec.outputs), log=log, spec=spec)
    if problems:
        from pipeline.hashing import FileHasher

        eng.recipe_problems = problems
        eng.hasher = FileHasher()  # nothing will run: write nothing under outputs/ either
    return eng


def _load(args, log, prepare: bool):
    spec = engine_spec(args)
    # messages name the recipe as given; the workers get the absolute path
    eng = build_engine(dataclasses.replace(spec, recipe=args.recipe, outputs=args.outputs),
                       log=log, prepare=prepare, gather=True)
    eng.spec = spec
    return eng


def _main(args, log) -> int:
    if args.command == "cluster-script":
        from pipeline.cluster import PLACEHOLDER_SCHEDULER, job_script, load_cluster_config

        print(job_script(load_cluster_config(args.cluster), args.scheduler or PLACEHOLDER_SCHEDULER))
        return 0
    if args.command == "status":
        eng = _load(args, log, prepare=False)
        plan = eng.plan("status", until=args.until)
        if eng.recipe_problems:  # a partial recipe: its table would mislead
            _stop(eng.check(plan), "no status until they are fixed")
        rows = eng.status(plan)
        w = max([len(r.unit) for r in rows] + [4])
        print(f"{eng.store.root}  ({args.recipe})")
        print(f"{'stage':<12} {'unit':<{w}} state")
        for r in rows:
            print(f"{r.stage:<12} {r.unit:<{w}} {r.state}" + (f"  ({r.detail})" if r.detail else ""))
        counts: dict[str, int] = {}
        for r in rows:
            counts[r.state] = counts.get(r.state, 0) + 1
        print(", ".join(f"{v} {k}" for k, v in counts.items()))
        _stop(eng.check(plan), "they must be fixed before a run")
        return 0

    eng = _load(args, log, prepare=True)
    if args.command == "sequence":
        seqs = args.sequences
        if eng.recipe_problems:  # a sequence with problems may be left out of the partial
            known = set(eng.registry.units(eng.recipe, "sequence"))  # recipe: check the rest
            seqs = [q for q in seqs if q in known]
            if not seqs:
                _stop(eng.recipe_problems, "nothing was run")
        plan = eng.plan("sequence", sequences=seqs, until=args.until)
    elif args.command == "release":
        plan = eng.plan("release", until=args.until)
    else:
        plan = eng.plan("demo", until=args.until)
    _stop(eng.check(plan), "nothing was run")
    kind = executor_kind(args)
    if kind == "dask" and not args.force and all_cached(eng, plan):
        # a rerun with nothing to compute: starting a cluster (~20 s) would only check hits
        log("dask: every stage is cached; checked here without starting a cluster")
        kind = "serial"
    if kind == "dask":
        report = _run_dask(eng, plan, args, log)
    else:
        report = eng.run(plan, force=args.force)
    log(f"{args.command}: {report.summary()}")
    if report.failed:
        from datetime import datetime

        tb = None
        if report.bugs:  # bad input alone has no traceback to keep
            tb = report.write_failures(eng.store.root / ".failures"
                                       / f"{datetime.now():%Y%m%d-%H%M%S}-{os.getpid()}.txt")
        log(report.failure_table(tb))
    if args.command == "demo":
        print(where_to_look(eng, report))
    return report.exit_code()


def _stop(problems: list[str], what: str) -> None:
    """CliError (exit code 2) listing ``problems`` one per line, if there are any."""
    if problems:
        raise CliError(f"{len(problems)} problem(s) in the recipe or its inputs; {what}:\n"
                       + "\n".join(problems))


def all_cached(eng: Engine, plan) -> bool:
    """True when a run of ``plan`` would compute nothing: every node has a complete artifact
    of its current key (``status``: cached) or can't run at all (a stage not implemented yet,
    or one waiting for it)."""
    rows = eng.status(plan)
    idle = [r.state == "not implemented" or (r.state == "missing" and r.detail.startswith("can't run"))
            for r in rows]
    return any(r.state == "cached" for r in rows) and all(
        r.state == "cached" or i for r, i in zip(rows, idle, strict=True))


def executor_kind(args) -> str:
    """``serial`` or ``dask``: ``--executor``, implied by ``--cluster``/``--scheduler``/
    ``--workers``, else ``$PIPELINE_EXECUTOR``, else dask for ``release`` and serial for the rest."""
    if args.executor:
        if args.executor == "serial" and (args.cluster or args.scheduler):
            raise CliError("--executor serial: --cluster and --scheduler need --executor dask")
        return args.executor
    if args.cluster or args.scheduler or args.workers:
        return "dask"
    env = os.environ.get("PIPELINE_EXECUTOR", "")
    if env:
        if env not in ("serial", "dask"):
            raise CliError(f"$PIPELINE_EXECUTOR={env!r}: expected serial or dask")
        return env
    return "dask" if args.command == "release" else "serial"


def _run_dask(eng: Engine, plan, args, log) -> RunReport:
    """Run ``plan`` on the Dask cluster of ``args`` (started here, closed at the end)."""
    from pipeline.cluster import (
        config_from_dict,
        load_cluster_config,
        make_client,
        worker_resources,
    )
    from pipeline.executors import DaskExecutor

    if args.cluster and args.scheduler:
        raise CliError("--cluster and --scheduler: give one of them")
    if args.workers is not None and args.workers < 1:
        raise CliError(f"--workers {args.workers}: expected at least 1")
    if args.scheduler:
        config = config_from_dict({"kind": "scheduler", "address": args.scheduler}, "--scheduler")
    elif args.cluster:
        config = load_cluster_config(args.cluster)
    else:
        config = config_from_dict({"kind": "local"}, "the default LocalCluster")
    n = args.workers or config.n_workers()
    what = {"local": f"LocalCluster of {n} worker(s)", "scheduler": f"scheduler {config.address}",
            "slurm": f"SLURM cluster ({n} worker(s))", "pbs": f"PBS cluster ({n} worker(s))"}
    log(f"dask: starting {what[config.kind]}")
    client, cluster, dashboard = make_client(config, workers=args.workers)
    try:
        log(f"dask: dashboard {dashboard}" + ("" if importlib.util.find_spec("bokeh") else
                                             " (served once bokeh is installed)"))
        res = None if config.kind == "scheduler" else worker_resources(
            config, n if config.kind == "local" else None)
        eng.executor = DaskExecutor(client, progress=True, worker_resources=res, log=log)
        return eng.run(plan, force=args.force)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def where_to_look(eng: Engine, report: RunReport) -> str:
    """What the demo produced, where, and plainly what it could not do."""
    lines = [f"Artifacts: {eng.store.root}/<unit>/<stage>/ (each with a manifest.json)"]
    done: dict[str, list[str]] = {}
    for (stage, unit), o in report.outcomes.items():
        if o.ok:
            done.setdefault(stage, []).append(unit)
    for stage, units in done.items():
        for u in units:
            lines.append(f"  {eng.store.dir(u, stage)}")
    if not done:
        lines.append("  (none: no stage of this run is implemented yet)")
    planned = report.planned_stages()
    if planned:
        lines.append("Not implemented yet, so not run: " + ", ".join(planned) + ".")
    skipped = sorted({s for (s, _), o in report.outcomes.items() if o.status == "skipped"})
    if skipped:
        lines.append("Skipped because an upstream stage is missing or failed: "
                     + ", ".join(skipped) + ".")
    failed = sorted({f"{s} [{u}]" for (s, u), o in report.outcomes.items() if o.status == "failed"})
    if failed:
        lines.append("FAILED: " + ", ".join(failed) + " (errors above).")
    return "\n".join(lines)
