"""A toy domain for testing and benchmarking the engine (no bodies, no cameras).

Recipe (YAML)::

    session: toy
    counter: counts.txt              # every stage appends "start|end <stage> <unit>" lines here
    subjects: {a: a.txt, b: b.txt}   # one number per line
    sequences:
      g/x: {markers_on: a, partner: b, file: x.txt}
    stages:
      scale: {factor: 2.0}
      detect: {sleep_s: 0.0}          # also offset, fail, pool_workers (see DetectOptions)

DAG: ``scale`` (per subject, raw: the subject file) and ``detect`` (per sequence, raw: the
sequence file) feed ``fit`` (per sequence), then ``report`` (per sequence), then ``summary``
(per session, reads every sequence's report). ``polish`` (per sequence, after ``report``) is
declared but not implemented, and ``publish`` (after ``polish``) is implemented but can never
run, to exercise the "not implemented" and "skipped" paths.

Use it as ``python -m pipeline ... --registry tests/toy_registry.py``.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.procs import process_pool
from pipeline.spec import Registry, Stage, StageContext


@dataclass(frozen=True)
class ToyRecipe:
    session: str
    counter: Path
    subjects: dict
    sequences: dict
    stages: dict
    source: Path


def load_recipe(path: Path) -> ToyRecipe:
    path = Path(path)
    raw = yaml.safe_load(path.read_text())
    base = path.resolve().parent
    for k in ("session", "counter", "subjects", "sequences"):
        if k not in raw:
            raise ValueError(f"{path}: {k}: missing")
    subjects = {s: base / f for s, f in raw["subjects"].items()}
    seqs = {}
    for q, spec in raw["sequences"].items():
        for role in ("markers_on", "partner"):
            if spec[role] not in subjects:
                raise ValueError(f"{path}: sequences.{q}.{role}: unknown subject {spec[role]!r}")
        seqs[q] = {**spec, "file": base / spec["file"]}
    return ToyRecipe(raw["session"], base / raw["counter"], subjects, seqs,
                     raw.get("stages") or {}, path)


def _count(ctx: StageContext, what: str) -> None:
    # O_APPEND writes of one short line are atomic between processes.
    counter = Path(ctx.recipe_path).resolve().parent / ctx.recipe.counter
    fd = os.open(counter, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, f"{what} {ctx.stage} {ctx.unit}\n".encode())
    finally:
        os.close(fd)


def _numbers(p: Path) -> np.ndarray:
    return np.array([float(x) for x in p.read_text().split()], dtype=np.float64)


@dataclass(frozen=True)
class ScaleOptions:
    factor: float = 1.0


def run_scale(ctx: StageContext) -> None:
    _count(ctx, "start")
    ctx.out.save_arrays("scaled", values=_numbers(ctx.raw["values"]) * ctx.params.factor)
    _count(ctx, "end")


@dataclass(frozen=True)
class DetectOptions:
    sleep_s: float = 0.0
    offset: float = 0.0
    fail: bool = False
    pool_workers: int = 0  # > 0: that many worker processes (pipeline.procs) sleep along


def _sleep(ctx: StageContext) -> None:
    for _ in ctx.progress(range(10), total=10, desc="frames"):
        time.sleep(ctx.params.sleep_s / 10)


def run_detect(ctx: StageContext) -> None:
    _count(ctx, "start")
    # Write a partial output first, so a kill during the sleep leaves a half-built folder.
    ctx.out.save_json("partial", {"half": True})
    vals = _numbers(ctx.raw["values"])
    n = ctx.params.pool_workers
    if n > 0:
        with process_pool(n) as pool:
            [f.result() for f in [pool.submit(os.getpid) for _ in range(n)]]  # workers are up
            busy = [pool.submit(time.sleep, ctx.params.sleep_s) for _ in range(n)]
            _count(ctx, "pool")
            _sleep(ctx)
            [f.result() for f in busy]
    else:
        _sleep(ctx)
    if ctx.params.fail:
        raise RuntimeError("detect: asked to fail")
    ctx.out.save_arrays("detections", values=vals + ctx.params.offset)
    _count(ctx, "end")


@dataclass(frozen=True)
class FitOptions:
    weight: float = 1.0
    peek: bool = False  # read a recipe field the stage does not declare (an UndeclaredRead)


def run_fit(ctx: StageContext) -> None:
    _count(ctx, "start")
    scales = ctx.inputs["scale"]  # {subject: Artifact}, markers_on first
    det = ctx.inputs["detect"].arrays("detections")["values"]
    if ctx.params.peek:
        ctx.recipe.sequence.file  # noqa: B018 - not declared: raises UndeclaredRead
    total = det.sum() * ctx.params.weight * ctx.recipe.sequence.gain + sum(a.arrays("scaled")["values"].sum()
                                                  for a in scales.values())
    ctx.out.save_arrays("fit", total=np.array([total]), order=np.array(list(scales)))
    _count(ctx, "end")


def run_report(ctx: StageContext) -> None:
    _count(ctx, "start")
    fit = ctx.inputs["fit"].arrays("fit")
    ctx.out.save_json("report", {"total": float(fit["total"][0]), "unit": ctx.unit})
    _count(ctx, "end")


def run_summary(ctx: StageContext) -> None:
    _count(ctx, "start")
    reports = ctx.inputs["report"]  # {sequence: Artifact}
    ctx.out.save_json("summary", {u: a.json("report")["total"] for u, a in reports.items()})
    _count(ctx, "end")


def run_publish(ctx: StageContext) -> None:  # never reached: polish is not implemented
    _count(ctx, "start")


C = ("counter",)  # every toy stage appends to the counter file
STAGES = (
    Stage("scale", run_scale, per="subject", params=ScaleOptions,
          raw_inputs=lambda r, u: {"values": r.subjects[u]}, reads=C),
    Stage("detect", run_detect, per="sequence", params=DetectOptions,
          raw_inputs=lambda r, u: {"values": r.sequences[u]["file"]}, reads=C),
    Stage("fit", run_fit, per="sequence", upstream=("scale", "detect"), params=FitOptions,
          reads=C + ("sequence.gain",)),
    Stage("report", run_report, per="sequence", upstream=("fit",), reads=C),
    Stage("summary", run_summary, per="session", upstream=("report",), reads=C),
    Stage("polish", None, per="sequence", upstream=("report",), implemented=False),
    Stage("publish", run_publish, per="sequence", upstream=("polish",), reads=C),
)


def recipe_view(r: ToyRecipe, unit: str, name: str):
    """``counter`` (the counter file's path) and ``sequence.gain`` (a per-sequence number,
    default 1) are the toy recipe's fields a stage may declare."""
    if name == "counter":  # relative to the recipe's folder: keys must not depend on where it lives
        return os.path.relpath(r.counter, r.source.resolve().parent)
    if name == "sequence.gain":
        return float(r.sequences[unit].get("gain", 1.0))
    if name == "sequence.file":
        return str(r.sequences[unit]["file"])
    raise KeyError(name)


def units(r: ToyRecipe, per: str) -> list[str]:
    return {"subject": list(r.subjects), "sequence": list(r.sequences), "session": ["session"]}[per]


def upstream_units(r: ToyRecipe, stage: str, unit: str, upstream: str) -> list[str]:
    per = {s.name: s.per for s in STAGES}
    if per[stage] == "sequence" and per[upstream] == "subject":
        return [r.sequences[unit]["markers_on"], r.sequences[unit]["partner"]]
    if per[stage] == "session":
        return units(r, per[upstream])
    raise ValueError(f"toy: {stage} can't read {upstream}")


def registry() -> Registry:
    return Registry(
        stages=STAGES, load_recipe=load_recipe, session_name=lambda r: r.session,
        units=units, upstream_units=upstream_units,
        stage_params=lambda r, s: r.stages.get(s, {}), recipe_view=recipe_view,
    )


def write_toy(folder: Path, stages: dict | None = None, n_seq: int = 2) -> Path:
    """Write a toy recipe with its raw files into ``folder``; return the recipe path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "a.txt").write_text("1 2 3\n")
    (folder / "b.txt").write_text("10 20\n")
    seqs = {}
    for i, name in enumerate(["x", "y", "z", "w"][:n_seq]):
        (folder / f"{name}.txt").write_text(f"{i + 1} {i + 2}\n")
        seqs[f"g/{name}"] = {"markers_on": "a" if i % 2 == 0 else "b",
                             "partner": "b" if i % 2 == 0 else "a", "file": f"{name}.txt"}
    recipe = {"session": "toy", "counter": "counts.txt", "subjects": {"a": "a.txt", "b": "b.txt"},
              "sequences": seqs, "stages": stages or {}}
    p = folder / "toy.yaml"
    p.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return p
