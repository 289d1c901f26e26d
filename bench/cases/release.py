"""``make release`` on the studio bench session, and the CHI3D benchmark of that release.

Data: ``recipes/bench.yaml`` (eight interaction classes, four views; generated on demand) with
the partner_fit case's stage options (``bench/cases/partner_fit.py``: keypoints on every
``STRIDE``-th frame), run through the engine up to ``evaluate`` into the partner_fit case's
store (``bench/work/partner_fit/outputs``: the fits that case measured are reused when cached,
so this case adds convert, export, release and evaluate). The truth is the studio's own CHI3D
layout (``data/bench/gt``, ``stages.evaluate.truth``).

Keys:

- ``release.verified``: 1 when the release stage's re-read pass found every file it wrote
  readable and the SHA-256 manifest matching (the stage fails otherwise), ``release.files``,
  ``release.mb``, ``release.frames``, ``release.frames_not_valid`` (person-frames marked not
  valid in the exported masks), ``release.s`` (wall seconds of convert + export + release +
  evaluate);
- ``evaluate.<metric>`` and ``evaluate.<metric>_contact``: the evaluator's mean over sequences
  (both people, mm) of the bench release against the studio truth, for ``mpjpe``,
  ``pa_mpjpe``, ``mpvpe``, ``pa_mpvpe``, ``transl_err``; the evaluator's markdown table is the
  RESULTS.md section of :func:`report`.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import yaml

from bench.cases import partner_fit as P

TRUTH = P.REPO / "data" / "bench" / "gt"
AFTER = ("partner_fit",)  # reuses that case's store of fits: runs after it (bench.run_order)
GOALS = {"release.verified": (">=", 1.0)}


def run(work: Path) -> dict[str, float]:
    from bench.cases._engine import run_engine

    store_work = work.parent / "partner_fit"
    store_work.mkdir(parents=True, exist_ok=True)
    base = P.bench_recipe(store_work, P.stride())  # writes the partner case's recipe too
    rec = yaml.safe_load(base.read_text())
    rec["stages"] = {**(rec.get("stages") or {}), "evaluate": {"truth": str(TRUTH)}}
    path = work / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    outputs = store_work / "outputs"
    t0 = time.perf_counter()
    run_engine(["release", "--recipe", str(path), "--outputs", str(outputs), "--until",
                "evaluate", "--executor", "serial"], "release", log_file=work / "engine.log")
    wall = time.perf_counter() - t0
    root = outputs / rec["session"] / "session"
    rel, ev = root / "release", root / "evaluate"
    from artifacts import Release

    release = Release.load(rel)
    files = [f for f in rel.rglob("*") if f.is_file()]
    out: dict[str, float] = {
        "release.verified": float(release.verified),
        "release.files": float(len(files)),
        "release.mb": float(sum(f.stat().st_size for f in files) / 1e6),
        "release.s": float(wall),
        "release.frames": float(release.sheet.totals.frames),
        "release.frames_not_valid": float(release.sheet.totals.person_frames_not_valid),
    }
    result = json.loads((ev / "evaluation.json").read_text())
    overall = result["overall"]
    for group, suffix in (("all", ""), ("contact", "_contact")):
        for metric, value in (overall.get(group) or {}).items():
            if isinstance(value, (int, float)) and value == value:
                out[f"evaluate.{metric}{suffix}"] = float(value)
    (work / "evaluation.md").write_text((ev / "evaluation.md").read_text())
    return out


def report(results: dict) -> str:  # noqa: ARG001 - the table is read from the run's file
    """The evaluator's own table of the bench release (written by the last run)."""
    md = Path(__file__).resolve().parents[1] / "work" / "release" / "evaluation.md"
    if not md.is_file():
        return ""
    return ("### The CHI3D benchmark of the bench release (`python -m bench release`; both "
            "people, against the studio truth)\n\n" + md.read_text())
