"""A fake domain for the Dask executor tests (tiny numpy work, sleeps, failures, a pool).

Recipe (YAML)::

    session: dtoy
    counter: counts.txt            # every stage appends "start|end <stage> <unit> <pid>" lines
    subjects: {a: a.txt, b: b.txt}
    sequences:
      g/x: {markers_on: a, partner: b, file: x.txt, sleep_s: 0.0, fail: false}
    stages: {detect: {pool: true}}

DAG: ``shape`` (per subject) and ``detect`` (per sequence; ``cores=2``; writes a partial file
first, sleeps ``sequence.sleep_s``, fails when ``sequence.fail``, optionally computes in a
``pipeline.procs.process_pool`` of ``ctx.cores`` workers) feed ``fit`` (per sequence, both
subjects' shapes), then ``summary`` (per session; asks ``memory_gb=64``, more than any test
worker has). ``detect`` and ``fit`` write ``granted.json``: ``ctx.cores`` and the resource
restrictions of the Dask task that ran them (``{}`` outside a worker).

Use it as ``--registry tests/dask_registry.py``.
"""
from __future__ import annotations

import operator
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.procs import process_pool
from pipeline.spec import Registry, Stage, StageContext


@dataclass(frozen=True)
class Recipe:
    session: str
    counter: Path
    subjects: dict
    sequences: dict
    stages: dict
    source: Path


def load_recipe(path: Path) -> Recipe:
    path = Path(path)
    raw = yaml.safe_load(path.read_text())
    base = path.resolve().parent
    subjects = {s: base / f for s, f in raw["subjects"].items()}
    seqs = {q: {**spec, "file": base / spec["file"]} for q, spec in raw["sequences"].items()}
    return Recipe(raw["session"], base / raw["counter"], subjects, seqs,
                  raw.get("stages") or {}, path)


def _count(ctx: StageContext, what: str) -> None:
    counter = Path(ctx.recipe_path).resolve().parent / ctx.recipe.counter
    fd = os.open(counter, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:  # one short O_APPEND write: atomic between processes
        os.write(fd, f"{what} {ctx.stage} {ctx.unit} {os.getpid()}\n".encode())
    finally:
        os.close(fd)


def _numbers(p: Path) -> np.ndarray:
    return np.array([float(x) for x in p.read_text().split()], dtype=np.float64)


def _granted(ctx: StageContext) -> None:
    restrictions: dict = {}
    try:
        from distributed import get_worker

        w = get_worker()
        ts = w.state.tasks.get(w.get_current_task())
        restrictions = dict(getattr(ts, "resource_restrictions", None) or {})
    except (ImportError, ValueError):
        pass
    ctx.out.save_json("granted", {"cores": ctx.cores, "resources": restrictions})


def run_shape(ctx: StageContext) -> None:
    _count(ctx, "start")
    v = _numbers(ctx.raw["values"])
    m = np.outer(v, v) + np.eye(len(v))
    ctx.out.save_arrays("shape", values=v * 2.0, eig=np.linalg.eigvalsh(m))
    _count(ctx, "end")


@dataclass(frozen=True)
class DetectOptions:
    pool: bool = False  # compute in a process pool of ctx.cores workers (needs non-daemonic)


def run_detect(ctx: StageContext) -> None:
    _count(ctx, "start")
    ctx.out.save_json("partial", {"half": True})  # a kill in the sleep leaves a half-built folder
    vals = _numbers(ctx.raw["values"])
    steps = 20
    for _ in range(steps):
        time.sleep(float(ctx.recipe.sequence.sleep_s) / steps)
    if ctx.recipe.sequence.fail:
        raise RuntimeError(f"detect: sequence {ctx.unit} asked to fail")
    if ctx.params.pool:
        with process_pool(max(ctx.cores, 1)) as pool:
            # a builtin: the spawned children can't import a registry loaded by path
            sq = np.array(list(pool.map(operator.mul, vals.tolist(), vals.tolist())))
    else:
        sq = vals * vals
    ctx.out.save_arrays("detections", values=vals, squares=sq,
                        noise=np.random.default_rng(int(vals.sum())).normal(size=8))
    _granted(ctx)
    _count(ctx, "end")


def run_fit(ctx: StageContext) -> None:
    _count(ctx, "start")
    det = ctx.inputs["detect"].arrays("detections")
    shapes = ctx.inputs["shape"]
    total = det["squares"].sum() + det["noise"].sum() + sum(
        a.arrays("shape")["eig"].sum() for a in shapes.values())
    ctx.out.save_arrays("fit", total=np.array([total]), order=np.array(list(shapes)))
    _granted(ctx)
    _count(ctx, "end")


def run_summary(ctx: StageContext) -> None:
    _count(ctx, "start")
    fits = ctx.inputs["fit"]
    ctx.out.save_json("summary", {u: float(a.arrays("fit")["total"][0]) for u, a in fits.items()})
    _count(ctx, "end")


C = ("counter",)
STAGES = (
    Stage("shape", run_shape, per="subject", raw_inputs=lambda r, u: {"values": r.subjects[u]},
          reads=C),
    Stage("detect", run_detect, per="sequence", params=DetectOptions,
          raw_inputs=lambda r, u: {"values": r.sequences[u]["file"]},
          reads=C + ("sequence.sleep_s", "sequence.fail"), cores=2, memory_gb=1.0),
    Stage("fit", run_fit, per="sequence", upstream=("shape", "detect"), reads=C),
    Stage("summary", run_summary, per="session", upstream=("fit",), reads=C, memory_gb=64.0),
)


def recipe_view(r: Recipe, unit: str, name: str):
    if name == "counter":
        return os.path.relpath(r.counter, r.source.resolve().parent)
    if name == "sequence.sleep_s":
        return float(r.sequences[unit].get("sleep_s", 0.0))
    if name == "sequence.fail":
        return bool(r.sequences[unit].get("fail", False))
    raise KeyError(name)


def units(r: Recipe, per: str) -> list[str]:
    return {"subject": list(r.subjects), "sequence": list(r.sequences), "session": ["session"]}[per]


def upstream_units(r: Recipe, stage: str, unit: str, upstream: str) -> list[str]:
    if stage == "fit" and upstream == "shape":
        return [r.sequences[unit]["markers_on"], r.sequences[unit]["partner"]]
    if stage == "summary":
        return units(r, "sequence")
    raise ValueError(f"dtoy: {stage} can't read {upstream}")


def registry() -> Registry:
    return Registry(stages=STAGES, load_recipe=load_recipe, session_name=lambda r: r.session,
                    units=units, upstream_units=upstream_units,
                    stage_params=lambda r, s: r.stages.get(s, {}), recipe_view=recipe_view)


def write_recipe(folder: Path, n_seq: int = 4, stages: dict | None = None,
                 sequences: dict | None = None) -> Path:
    """A recipe with ``n_seq`` sequences over subjects a and b, its raw files in ``folder``.
    ``sequences``: extra fields per sequence id (``{"g/s1": {"fail": True}}``)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "a.txt").write_text("1 2 3\n")
    (folder / "b.txt").write_text("10 20 30\n")
    seqs = {}
    for i in range(n_seq):
        q = f"g/s{i}"
        (folder / f"s{i}.txt").write_text(f"{i + 1} {i + 2} {2 * i + 5}\n")
        seqs[q] = {"markers_on": "a" if i % 2 == 0 else "b", "partner": "b" if i % 2 == 0 else "a",
                   "file": f"s{i}.txt", **((sequences or {}).get(q, {}))}
    recipe = {"session": "dtoy", "counter": "counts.txt", "subjects": {"a": "a.txt", "b": "b.txt"},
              "sequences": seqs, "stages": stages or {}}
    p = folder / "recipe.yaml"
    p.write_text(yaml.safe_dump(recipe, sort_keys=False))
    return p


def counts(folder: Path) -> list[tuple[str, str, str, int]]:
    """The counter lines: ``(start|end, stage, unit, pid)``."""
    f = folder / "counts.txt"
    if not f.is_file():
        return []
    out = []
    for ln in f.read_text().splitlines():
        what, stage, rest = ln.split(" ", 2)
        unit, pid = rest.rsplit(" ", 1)
        out.append((what, stage, unit, int(pid)))
    return out
