"""Command line: ``python -m pipeline sequence|release|status|demo``.

::

    python -m pipeline sequence "s02/Grab 4" --recipe recipes/demo.yaml [--until marker_fit]
    python -m pipeline release  --recipe recipes/demo.yaml [--force shape_fit]
    python -m pipeline status   --recipe recipes/demo.yaml
    python -m pipeline demo     [--recipe recipes/demo.yaml]

``--registry`` names the domain package (default ``stages``; a module name or a path to a
``.py`` file) whose ``registry()`` returns a :class:`pipeline.spec.Registry`.
``--outputs`` (default ``$PIPELINE_OUTPUTS`` or ``outputs``) is the artifact store root.

Exit codes: 0 done (planned-but-unimplemented stages are reported, not failures), 1 a stage
failed, 2 bad command, recipe, registry or input file.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
from pathlib import Path

from pipeline.engine import Engine, RunReport, stderr_log
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
    return p


def main(argv: list[str] | None = None, log=stderr_log) -> int:
    args = parser().parse_args(argv)
    try:
        return _main(args, log)
    except (CliError, PlanError, StoreError) as e:
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


def _load(args, log, prepare: bool):
    reg = load_registry(args.registry)
    extra = overrides(getattr(args, "overrides", []) or [])
    if extra:
        import dataclasses

        names = {s.name for s in reg.stages}
        for stage in extra:
            if stage not in names:
                raise CliError(f"--set {stage}...: no such stage (known: {', '.join(names)})")
        base = reg.stage_params
        reg = dataclasses.replace(reg, stage_params=lambda r, st: {**base(r, st),
                                                                   **extra.get(st, {})})
    recipe_path = Path(args.recipe)
    if prepare and reg.prepare is not None:
        try:
            reg.prepare(recipe_path)
        except Exception as e:  # noqa: BLE001 - reported as one line, exit code 2
            raise CliError(f"preparing {recipe_path}: {e}") from None
    if not recipe_path.is_file():
        raise CliError(f"{recipe_path}: recipe not found")
    try:
        recipe = reg.load_recipe(recipe_path)
    except (ValueError, OSError) as e:  # RecipeError / InputError are ValueErrors
        raise CliError(str(e)) from None
    return Engine(reg, recipe, recipe_path, Path(args.outputs), log=log)


def _main(args, log) -> int:
    if args.command == "status":
        eng = _load(args, log, prepare=False)
        plan = eng.plan("status", until=args.until)
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
        return 0

    eng = _load(args, log, prepare=True)
    if args.command == "sequence":
        plan = eng.plan("sequence", sequences=args.sequences, until=args.until)
    elif args.command == "release":
        plan = eng.plan("release", until=args.until)
    else:
        plan = eng.plan("demo", until=args.until)
    problems = eng.check(plan)
    if problems:
        raise CliError(f"{len(problems)} problem(s) in the recipe or its inputs; nothing was run:\n"
                       + "\n".join(problems))
    report = eng.run(plan, force=args.force)
    log(f"{args.command}: {report.summary()}")
    if args.command == "demo":
        print(where_to_look(eng, report))
    return 1 if report.failed else 0


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
        lines.append("FAILED: " + ", ".join(failed) + " (tracebacks above).")
    return "\n".join(lines)
