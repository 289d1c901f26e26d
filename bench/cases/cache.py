"""Cache: wall time of re-running an unchanged sequence whose stages are all cached.

``cache.rerun_s``: ``python -m pipeline sequence g/x`` on the toy registry
(``tests/toy_registry.py``: 5 stages over 2 subjects and 1 sequence), end to end in a
subprocess (interpreter start, imports, recipe, hashing the raw files, checking 5
manifests), median of 5 reruns after one computing run.

``cache.rerun_inproc_s``: the same rerun inside a warm process (recipe, planning, checks),
median of 5.

``cache.rerun_demo_s``: ``python -m pipeline sequence <first sequence>`` on
``recipes/demo.yaml`` with the real stages, when the demo recipe and its data exist (the
first run computes what is not cached yet in ``outputs/``, as ``make demo`` would). Omitted
otherwise.

``cache.make_demo_s``: ``make demo`` end to end (the setup check, ``pipeline demo``, the
release and ``evaluate.session``) in a subprocess when ``python -m pipeline status`` says every
stage of the demo is cached, median of 3 (goal <= 5 s). Omitted otherwise (a fresh clone would
compute the whole demo first: ~15 minutes of both cores).
"""
from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TOY = REPO / "tests" / "toy_registry.py"
AFTER = ("pipeline",)  # that case computes the demo sequence both rerun: runs after it
GOALS = {
    "cache.rerun_s": ("<=", 2.0),
    "cache.rerun_inproc_s": ("<=", 2.0),
    "cache.rerun_demo_s": ("<=", 2.0),
    "cache.make_demo_s": ("<=", 5.0),
}
MAKE_REPEATS = 3
REPEATS = 5


def _cli(args: list[str]) -> tuple[float, subprocess.CompletedProcess]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pipeline", *args], env=env, cwd=REPO,
                          capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"pipeline {' '.join(args)} exited {done.returncode}:\n{done.stderr}")
    return dt, done


def _all_cached(done: subprocess.CompletedProcess) -> bool:
    last = [ln for ln in done.stderr.splitlines() if ln.startswith("sequence: ")]
    return bool(last) and last[-1].startswith("sequence: 0 computed")


def _rerun_median(args: list[str]) -> float:
    _cli(args)  # computes whatever is not cached yet
    times = []
    for _ in range(REPEATS):
        dt, done = _cli(args)
        if not _all_cached(done):
            raise RuntimeError(f"rerun of {' '.join(args)} was not all cached:\n{done.stderr}")
        times.append(dt)
    return statistics.median(times)


def _toy(work: Path) -> dict[str, float]:
    sys.path.insert(0, str(TOY.parent))
    try:
        import toy_registry
    finally:
        sys.path.remove(str(TOY.parent))
    folder = work / "toy"
    shutil.rmtree(folder, ignore_errors=True)
    recipe = toy_registry.write_toy(folder, n_seq=1)
    args = ["sequence", "g/x", "--recipe", str(recipe), "--registry", str(TOY),
            "--outputs", str(folder / "outputs")]
    out = {"cache.rerun_s": _rerun_median(args)}

    from pipeline.engine import Engine

    reg = toy_registry.registry()
    times = []
    for _ in range(REPEATS + 1):  # the first one warms the imports up and is dropped
        t0 = time.perf_counter()
        eng = Engine(reg, reg.load_recipe(recipe), recipe, folder / "outputs", log=lambda _msg: None)
        rep = eng.run(eng.plan("sequence", ["g/x"]))
        times.append(time.perf_counter() - t0)
        if rep.count("computed") or rep.count("failed"):
            raise RuntimeError(f"in-process rerun was not all cached: {rep.summary()}")
    out["cache.rerun_inproc_s"] = statistics.median(times[1:])
    return out


def _demo() -> dict[str, float]:
    from recipes import load_recipe, missing_files

    demo = REPO / "recipes" / "demo.yaml"
    if not demo.is_file():
        print("[bench] cache: recipes/demo.yaml does not exist yet: cache.rerun_demo_s skipped",
              file=sys.stderr)
        return {}
    recipe = load_recipe(demo, check_files=False)
    if missing_files(recipe):
        print("[bench] cache: the demo data is missing (run `make demo` first): "
              "cache.rerun_demo_s skipped", file=sys.stderr)
        return {}
    seq = next(iter(recipe.sequences))
    out = {"cache.rerun_demo_s": _rerun_median(["sequence", seq, "--recipe", str(demo)])}
    out.update(_make_demo(demo))
    return out


def demo_all_cached(demo: Path) -> bool:
    """Whether ``python -m pipeline status`` would list every stage of the demo as cached."""
    from pipeline.cli import _load, parser

    eng = _load(parser().parse_args(["status", "--recipe", str(demo)]), lambda _m: None,
                prepare=False)
    rows = eng.status(eng.plan("status"))
    return bool(rows) and all(r.state == "cached" for r in rows)


def _make_demo(demo: Path) -> dict[str, float]:
    if not demo_all_cached(demo):
        print("[bench] cache: the demo is not all cached (run `make demo` first): "
              "cache.make_demo_s skipped", file=sys.stderr)
        return {}
    times = []
    for _ in range(MAKE_REPEATS):
        t0 = time.perf_counter()
        done = subprocess.run(["make", "demo"], cwd=REPO, capture_output=True, text=True)
        times.append(time.perf_counter() - t0)
        if done.returncode != 0:
            raise RuntimeError(f"make demo exited {done.returncode}:\n{done.stderr[-2000:]}")
        if "demo: 0 computed" not in done.stderr:
            raise RuntimeError("make demo computed something on a cached demo:\n"
                               + done.stderr[-2000:])
    return {"cache.make_demo_s": statistics.median(times)}


def run(work: Path) -> dict[str, float]:
    return {**_toy(work), **_demo()}
