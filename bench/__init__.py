"""Benchmark harness (``python -m bench [CASE ...]``, ``make bench``).

A case is a module ``bench/cases/<name>.py`` (files starting with ``_`` are helpers, not
cases) with::

    def run(work: pathlib.Path) -> dict[str, float]   # flat keys, e.g. "marker_fit.mpjpe_mm"
    GOALS = {"marker_fit.mpjpe_mm": ("<=", 5.0)}      # optional
    LIMITS = {"marker_fit.mpjpe_mm": "what limits it"} # optional: shown under a FAIL
    def report(results: dict) -> str                  # optional: a markdown section
    SECTION_PREFIXES = ("marker_fit.table.",)         # optional: keys shown only there
    AFTER = ("partner_fit",)                           # optional: cases run before this one

Cases run in name order, except that a case runs after the cases its ``AFTER`` names (a
literal tuple, read from the source without importing it) when they run too: a case that
reuses another's work (the partner_fit case's store of fits) comes after the case that makes
it, so each case's wall time is its own work, not the other's, each with its own work folder ``bench/work/<name>/`` (created, not
wiped: a case decides what to reuse). A case that raises is recorded as failed
(``"<name>.error"`` in the results) and the others still run. Results are merged into
``bench/results.json`` (flat ``{key: value}``; keys of cases not run this time are kept, and a
case that ran drops the keys of its own (``<case>.``) it no longer produces, e.g. a class
without valid frames),
``bench/measured.json`` records for every key the commit and the code it was measured on
(``{key: {"commit", "code", "date"}}``; ``code`` is a hash of the project's source files, so
a figure measured before a code change is known as such), and ``bench/RESULTS.md`` is
rewritten: one table row per key (value, goal, verdict, commit), then for every goal missed
what limits it (the case's ``LIMITS``), the cases' own sections (``report(results)``, e.g. an
ablation table), then the machine (CPU model, cores, Python, numpy), the date and the command. A row measured on other code than the one
rendering the table says so in place of pass/FAIL: an old figure never passes a goal.
``python -m bench --table`` re-renders the table against the code as it is now.

Time budget: every case that ran adds its own wall time as ``<case>.case_wall_s``; the
"Time budget" section lists them (slowest first, with their commit) and their sum against the
45 minutes ``make bench`` may take; a run of every case writes ``bench.total_s`` (goal <=
2700 s; the sum of the cases' wall times, failed ones included) and ``bench.cases_failed``
(goal 0: a total with a failed case in it is not the benchmark's time). A run of every case in
which none failed starts the results afresh: keys it did not
produce (a removed case, a renamed key) are dropped, so every row carries this run's commit.
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import os
import platform
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
# Files that are results, not code: measuring them must not change the code version.
NOT_CODE = ("bench/results.json", "bench/measured.json", "bench/RESULTS.md")
CODE_SUFFIXES = (".py", ".yaml", ".yml", ".toml", ".txt", ".sh", ".cfg", ".json")
# ``<case>.case_wall_s``: wall seconds of the case's last run (``make bench`` adds them up in
# the time-budget section; ``bench.total_s`` is written by a run of every case).
CASE_WALL = "case_wall_s"
TOTAL_KEY = "bench.total_s"
FAILED_KEY = "bench.cases_failed"
TOTAL_GOAL_S = 45 * 60  # the whole ``make bench`` on 2 cores from a fresh clone (issue #29)
#: What limits ``bench.total_s`` (shown under its FAIL; the time budget section has the cases'
#: own walls)
TOTAL_LIMIT = (
    "what a fresh clone pays once and the fits' own speed. Once: the four studio sessions "
    "generated (a clone of the same studio code copies them from the studio cache instead: "
    "bench.cases._studio_data) and every CasADi graph compiled (tens of seconds each, kept in "
    "assets/cache/casadi). Then the partner fit (partner_fit.fps_per_core, far below its goal: "
    "its cost is in every case that fits a partner: partner_fit, pipeline, qa, real_video) and "
    "the detector (keypoints). Cases whose units are independent run them two at once (the "
    "bench sequences, the real captures, the demo's stages, the keypoints clips); the speed "
    "of the machine moves the sum too: the same code's serial marker fit of pyCGM's capture "
    "ran at 225 frames per CPU-second on session 36's machine and 135 on session 37's.")
OPS = {"<=": lambda v, g: v <= g, "<": lambda v, g: v < g, ">=": lambda v, g: v >= g,
       ">": lambda v, g: v > g, "==": lambda v, g: v == g}


@dataclass
class CaseResult:
    name: str
    values: dict[str, float] = field(default_factory=dict)
    goals: dict[str, tuple[str, float]] = field(default_factory=dict)
    seconds: float = 0.0
    error: str = ""


def discover(cases_dir: Path = BENCH / "cases") -> list[Path]:
    """The case modules, sorted by name."""
    return sorted(p for p in cases_dir.glob("*.py") if not p.name.startswith("_"))


def case_after(path: Path) -> tuple[str, ...]:
    """The case's ``AFTER`` (a literal tuple of case names at module level), without importing
    it; () when it has none."""
    import ast

    for node in ast.parse(path.read_text(), str(path)).body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name) and node.targets[0].id == "AFTER"):
            return tuple(str(x) for x in ast.literal_eval(node.value))
    return ()


def run_order(paths: list[Path]) -> list[Path]:
    """``paths`` in name order, each case after the cases of its ``AFTER`` that are among
    them (a cycle is broken in name order once no other case can run)."""
    todo = sorted(paths, key=lambda p: p.stem)
    names = {p.stem for p in todo}
    after = {p.stem: [a for a in case_after(p) if a in names and a != p.stem] for p in todo}
    done: list[Path] = []
    placed: set[str] = set()
    while todo:
        ready = [p for p in todo if all(a in placed for a in after[p.stem])] or todo[:1]
        done.append(ready[0])
        placed.add(ready[0].stem)
        todo.remove(ready[0])
    return done


def load_case(path: Path) -> ModuleType:
    name = f"bench_case_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def check_goals(goals: dict) -> dict[str, tuple[str, float]]:
    out = {}
    for k, g in goals.items():
        if not (isinstance(g, (tuple, list)) and len(g) == 2 and g[0] in OPS):
            raise ValueError(f"GOALS[{k!r}] = {g!r}: expected (op, number), op in {list(OPS)}")
        out[k] = (g[0], float(g[1]))
    return out


def run_case(path: Path, work_root: Path) -> CaseResult:
    """Import and run one case; never raises (a failure is recorded in ``error``)."""
    res = CaseResult(path.stem)
    t0 = time.perf_counter()
    try:
        mod = load_case(path)
        res.goals = check_goals(getattr(mod, "GOALS", {}))
        work = work_root / path.stem
        work.mkdir(parents=True, exist_ok=True)
        values = mod.run(work)
        if not isinstance(values, dict):
            raise TypeError(f"run() returned {type(values).__name__}, expected dict[str, float]")
        for k, v in values.items():
            if not isinstance(k, str) or isinstance(v, bool):
                raise TypeError(f"run() returned {k!r}: {v!r}; expected str: float")
            res.values[k] = float(v)
    except Exception:  # noqa: BLE001 - recorded, the other cases still run
        res.error = traceback.format_exc()
    res.seconds = time.perf_counter() - t0
    if not res.error:  # the time budget: each case's own wall time is one of its figures
        res.values[f"{path.stem}.{CASE_WALL}"] = round(res.seconds, 1)
    return res


def machine_info() -> dict[str, str]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import numpy

        np_version = numpy.__version__
    except ImportError:
        np_version = "-"
    return {"cpu": cpu, "cores": str(os.cpu_count()), "python": platform.python_version(),
            "numpy": np_version, "platform": platform.platform(),
            "date": datetime.now().isoformat(timespec="seconds")}


def _git(*args: str, repo: Path = REPO) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def code_files(repo: Path = REPO) -> list[str]:
    """The project's source files as git sees them (tracked, and untracked ones it does not
    ignore), without the bench's result files, prose and data."""
    names = _git("ls-files", "-co", "--exclude-standard", repo=repo).splitlines()
    return sorted(n for n in names if n.endswith(CODE_SUFFIXES) or n == "Makefile"
                  if n not in NOT_CODE and not n.startswith(("bench/work/", "outputs/", "data/")))


def code_version(repo: Path = REPO) -> str:
    """A 12-hex hash of the contents of :func:`code_files` as they are on disk now (a dirty
    tree is hashed as it is; committing it does not change the hash)."""
    h = hashlib.sha256()
    for n in code_files(repo):
        p = repo / n
        if p.is_file():
            h.update(n.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def commit_label(repo: Path = REPO) -> str:
    """``<short HEAD>``, with ``+changes`` when source files differ from it."""
    head = _git("rev-parse", "--short=10", "HEAD", repo=repo) or "no-git"
    dirty = _git("status", "--porcelain", "--", ".", *[f":!{n}" for n in NOT_CODE],
                 ":!*.md", ":!bench/work", repo=repo)
    return head + ("+changes" if dirty else "")


def verdict(value: float, goal: tuple[str, float] | None) -> str:
    if goal is None:
        return ""
    if math.isnan(value):
        return "FAIL"
    return "pass" if OPS[goal[0]](value, goal[1]) else "FAIL"


def merge(results_file: Path, cases: list[CaseResult], full: bool = False) -> dict:
    """Update the flat results with this run's values and errors. ``full``: this run was of
    every case and none failed, so every key it did not produce (a case removed or renamed, a
    key of another prefix a case no longer writes) is dropped: all rows are of this run."""
    try:
        old = json.loads(results_file.read_text()) if results_file.exists() else {}
    except ValueError:
        old = {}
    if full and not any(c.error for c in cases):
        old = {}
    for c in cases:
        old.pop(f"{c.name}.error", None)
        if not c.error:  # a case that ran drops its own keys it no longer produces
            for k in [k for k in old if k.startswith(f"{c.name}.") and k not in c.values]:
                del old[k]
        old.update(c.values)
        if c.error:
            old[f"{c.name}.error"] = c.error.strip().splitlines()[-1]
    return dict(sorted(old.items()))


def all_goals(paths: list[Path], ran: list[CaseResult]) -> dict[str, tuple[str, float]]:
    goals: dict[str, tuple[str, float]] = {TOTAL_KEY: ("<=", float(TOTAL_GOAL_S)),
                                           FAILED_KEY: ("==", 0.0)}
    done = {c.name for c in ran}
    for p in paths:  # goals of cases not run this time, for keys kept from earlier runs
        if p.stem in done:
            continue
        try:
            goals.update(check_goals(getattr(load_case(p), "GOALS", {})))
        except Exception:  # noqa: BLE001 - an unimportable case just has no goals shown
            pass
    for c in ran:
        goals.update(c.goals)
    return goals


def case_extras(paths: list[Path]) -> tuple[dict[str, str], list, tuple[str, ...]]:
    """Every case's ``LIMITS`` (merged), its ``report`` function (in name order) and the key
    prefixes its section shows instead of the main table (``SECTION_PREFIXES``)."""
    limits: dict[str, str] = {TOTAL_KEY: TOTAL_LIMIT}
    reports = []
    prefixes: list[str] = []
    for p in paths:
        try:
            mod = load_case(p)
        except Exception:  # noqa: BLE001 - an unimportable case just has no extras
            continue
        limits.update(getattr(mod, "LIMITS", {}) or {})
        if callable(getattr(mod, "report", None)):
            reports.append(mod.report)
        prefixes += list(getattr(mod, "SECTION_PREFIXES", ()) or ())
    return limits, reports, tuple(prefixes)


def merge_measured(measured_file: Path, cases: list[CaseResult], commit: str, code: str) -> dict:
    """``{key: {"commit", "code", "date"}}`` updated with this run's keys."""
    try:
        old = json.loads(measured_file.read_text()) if measured_file.exists() else {}
    except ValueError:
        old = {}
    date = datetime.now().isoformat(timespec="seconds")
    for c in cases:
        for k in c.values:
            old[k] = {"commit": commit, "code": code, "date": date}
    return dict(sorted(old.items()))


def render_markdown(results: dict, goals: dict, ran: list[CaseResult], machine: dict,
                    command: str, measured: dict | None = None, code: str | None = None,
                    limits: dict[str, str] | None = None, reports=(),
                    section_prefixes: tuple[str, ...] = ()) -> str:
    """The table. ``measured``/``code``: where each key was measured and the code version
    rendering now; a row whose code differs (or is unknown) gets no pass/FAIL verdict.
    ``limits``: per key what limits it, listed for every FAIL; ``reports``: functions
    ``results -> markdown`` appended as sections; keys starting with one of
    ``section_prefixes`` are left out of the main table (a section shows them)."""
    now = {k for c in ran for k in c.values}
    measured = measured or {}
    lines = ["# Benchmark results", "",
             f"Written by `{command}`. Regenerate with `make bench`. A verdict is given only to "
             f"figures measured on the code of this table (code {code or '?'}); a figure from "
             "older code says so instead.", "",
             "| key | value | goal | pass/fail | measured at |", "|---|---|---|---|---|"]
    for k, v in results.items():
        if k.endswith(".error") or (section_prefixes and k.startswith(section_prefixes)):
            continue
        g = goals.get(k)
        goal_s = f"{g[0]} {g[1]:g}" if g else ""
        note = "" if k in now else " (earlier run)"
        m = measured.get(k) or {}
        current = code is None or m.get("code") == code
        ver = verdict(v, g) if current else ("not re-measured on this code" if g else "")
        at = m.get("commit", "unknown") + ("" if current else " (older code)")
        lines.append(f"| `{k}` | {v:.4g}{note} | {goal_s} | {ver} | {at} |")
    failed = [k for k, v in results.items() if not k.endswith(".error") and k in goals
              and (code is None or (measured.get(k) or {}).get("code") == code)
              and verdict(v, goals[k]) == "FAIL"]
    if failed:
        lines += ["", "## Goals missed: what limits them", ""]
        lines += [f"- `{k}` = {results[k]:.4g} (goal {goals[k][0]} {goals[k][1]:g}): FAIL. "
                  + ((limits or {}).get(k) or "not analysed yet.") for k in failed]
    for rep in reports:
        try:
            sec = rep(results)
        except Exception as e:  # noqa: BLE001 - a broken section must not lose the table
            sec = f"(section failed: {type(e).__name__}: {e})"
        if sec:
            lines += ["", sec.rstrip()]
    errs = {k: v for k, v in results.items() if k.endswith(".error")}
    if errs:
        lines += ["", "## Failed cases", ""]
        lines += [f"- `{k[:-6]}`: {v}" for k, v in errs.items()]
    lines += ["", "## This run", "", "| case | seconds | status |", "|---|---|---|"]
    lines += [f"| {c.name} | {c.seconds:.1f} | {'FAILED' if c.error else 'ok'} |" for c in ran]
    lines += time_budget(results, measured)
    lines += ["", "## Machine", ""]
    lines += [f"- {k}: {v}" for k, v in machine.items()]
    lines += [f"- command: `{command}`", ""]
    return "\n".join(lines)


def time_budget(results: dict, measured: dict | None = None) -> list[str]:
    """The markdown lines of the time-budget section: every case's last wall time
    (``<case>.case_wall_s``, with the commit it was measured at) and their sum against
    ``TOTAL_GOAL_S``."""
    walls = {k[: -len(CASE_WALL) - 1]: v for k, v in results.items()
             if k.endswith("." + CASE_WALL)}
    if not walls:
        return []
    measured = measured or {}
    total = sum(walls.values())
    lines = ["", "## Time budget", "",
             f"Wall seconds of each case's last run (`<case>.{CASE_WALL}`; a case that reuses "
             "another's cached work, e.g. generated data or fits, is cheaper after it). Sum "
             f"{total:.0f} s = {total / 60:.1f} min against the {TOTAL_GOAL_S / 60:.0f} min of "
             "`make bench`" + (f"; the last full run took {results[TOTAL_KEY]:.0f} s"
                               if TOTAL_KEY in results else "") + ".", "",
             "| case | seconds | share | measured at |", "|---|---|---|---|"]
    for name, v in sorted(walls.items(), key=lambda kv: -kv[1]):
        at = (measured.get(f"{name}.{CASE_WALL}") or {}).get("commit", "unknown")
        lines.append(f"| {name} | {v:.0f} | {100 * v / max(total, 1e-9):.0f} % | {at} |")
    return lines


def main(argv: list[str] | None = None, bench_dir: Path = BENCH) -> int:
    """Run the chosen cases (all when ``argv`` is empty) of ``bench_dir/cases``; write
    ``bench_dir/results.json`` and ``bench_dir/RESULTS.md``. Exit code 1 if a case failed."""
    argv = sys.argv[1:] if argv is None else argv
    paths = discover(bench_dir / "cases")
    code = code_version()
    if argv == ["--table"]:  # re-render the table against the code as it is now
        results = json.loads((bench_dir / "results.json").read_text())
        mf = bench_dir / "measured.json"
        measured = json.loads(mf.read_text()) if mf.exists() else {}
        md = render_markdown(results, all_goals(paths, []), [], machine_info(),
                             "python -m bench --table", measured, code, *case_extras(paths))
        (bench_dir / "RESULTS.md").write_text(md)
        print(f"[bench] wrote {bench_dir / 'RESULTS.md'} (code {code})", file=sys.stderr)
        return 0
    if argv:
        unknown = set(argv) - {p.stem for p in paths}
        if unknown:
            print(f"bench: no such case(s): {sorted(unknown)} (known: {[p.stem for p in paths]})",
                  file=sys.stderr)
            return 2
        chosen = run_order([p for p in paths if p.stem in argv])
    else:
        chosen = run_order(paths)
    work_root = bench_dir / "work"
    ran = []
    for p in chosen:
        print(f"[bench] {p.stem} ...", file=sys.stderr, flush=True)
        r = run_case(p, work_root)
        ran.append(r)
        if r.error:
            print(f"[bench] {p.stem} FAILED after {r.seconds:.1f} s:\n{r.error}", file=sys.stderr)
        else:
            for k, v in r.values.items():
                g = r.goals.get(k)
                print(f"[bench]   {k} = {v:.4g}" + (f"  (goal {g[0]} {g[1]:g}: {verdict(v, g)})"
                                                   if g else ""), file=sys.stderr)
    full = not argv
    if full:  # the whole benchmark's own figures (with a failed case: saying so)
        total = round(sum(r.seconds for r in ran), 1)
        failed = sum(bool(r.error) for r in ran)
        ran.append(CaseResult("bench", {TOTAL_KEY: total, FAILED_KEY: float(failed)},
                              seconds=total))
    results = merge(bench_dir / "results.json", ran, full=full)
    (bench_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    measured = merge_measured(bench_dir / "measured.json", ran, commit_label(), code)
    (bench_dir / "measured.json").write_text(json.dumps(measured, indent=1) + "\n")
    command = "python -m bench" + "".join(f" {a}" for a in argv)
    md = render_markdown(results, all_goals(paths, ran), ran, machine_info(), command,
                         measured, code, *case_extras(paths))
    (bench_dir / "RESULTS.md").write_text(md)
    print(f"[bench] wrote {bench_dir / 'results.json'} and {bench_dir / 'RESULTS.md'}",
          file=sys.stderr)
    return 1 if any(r.error for r in ran) else 0
