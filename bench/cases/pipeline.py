"""The CPU a two-person sequence costs end to end, per 1,000 video frames, from the stage
timings the engine records (``timings.cpu_s`` in each artifact's manifest: the stage's
process and worker-pool CPU seconds).

Data: the first sequence of ``recipes/demo.yaml`` (two people, four views, markers on one;
the demo's stages at their defaults; the data generated through the bench's studio cache,
``bench.cases._studio_data.ensure``, so that a fresh clone of the same studio code copies them
instead of rendering them again), run with ``python -m pipeline sequence`` into
``outputs/`` as ``make demo`` does (what is cached for this code is reused: its manifests hold
the timings of the run that computed it, on the same stage code), on the Dask executor with
two workers: the stages that do not wait for each other (the two subjects' shape fits, the
keypoints, the marker fit, the silhouettes) run side by side, one per core; each stage's CPU
is its own process's (and its pool's), whoever runs beside it.

Keys:

- ``pipeline.cpu_s_per_1000_frames``: the sequence's per-sequence stages (capture,
  keypoints, marker_fit, marker_loo, partner_fit, convert, qa, export) summed, divided by the
  sequence's video frames, times 1,000 (goal <= 900 s: 15 CPU-minutes);
- ``pipeline.cpu_s.<stage>``: each stage's CPU seconds on this sequence, and
  ``pipeline.share.<stage>`` its share of the sum (the RESULTS.md section names the largest);
- ``pipeline.fixed_cpu_s``: the per-subject stages (shape_fit of both people: paid once per
  subject, not per frame), not in the per-frame figure;
- ``pipeline.frames``: the sequence's video frames; ``pipeline.wall_only_stages``: stages
  whose artifact predates ``timings.cpu_s`` and count their wall seconds instead (0 when
  every figure is CPU).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "demo.yaml"
GOALS = {"pipeline.cpu_s_per_1000_frames": ("<=", 900.0)}
LIMITS = {"pipeline.cpu_s_per_1000_frames": (
    "two stages carry ~80 % of it (pipeline.share.*): the partner fit (~55 %, ~1.5 CPU-s a "
    "frame: two fitting passes whose residuals are numpy, ~15 evaluations of ~5 ms per frame "
    "solve, and a second mediapipe pass over the frames the first left short; "
    "partner_fit.fps_per_core) and the keypoints (~26 %, ~0.7 CPU-s a four-view frame: "
    "mediapipe's pose and hand calls, keypoints.fps_per_core_clip). 900 needs both about 3x "
    "cheaper: compiled residuals for the partner fit (as the marker fit's CasADi graph) and "
    "the second detection pass only where the first needs it; the other stages together (qa "
    "~10 %, marker_fit ~5 %, export, convert, capture) are ~500 CPU-s per 1,000 frames. The "
    "demo recipe runs no leave-one-out (marker_loo: not in the sum). Session 34: 2084 -> "
    "3168, the partner fit 121 -> 220 CPU-s on the demo sequence (share 0.58 -> 0.69): its "
    "final fit runs the forward pass twice where a view's keypoint is left out as that "
    "view's bias (reliability_px).")}
PER_SEQUENCE = ("capture", "keypoints", "marker_fit", "marker_loo", "partner_fit", "convert",
                "qa", "export")
PER_SUBJECT = ("shape_fit",)
SECTION_PREFIXES = ("pipeline.cpu_s.", "pipeline.share.")


def _cpu(manifest: Path) -> tuple[float, bool]:
    """(CPU seconds of the stage's run, whether they are CPU and not wall seconds)."""
    t = json.loads(manifest.read_text())["timings"]
    if "cpu_s" in t:
        return float(t["cpu_s"]), True
    return float(t["seconds"]), False


def run(work: Path) -> dict[str, float]:
    from bench.cases._engine import run_engine
    from bench.cases._studio_data import ensure
    from formats.video import video_info
    from recipes import load_recipe

    ensure(RECIPE)  # the demo's data as this studio code makes them (cached outside the checkout)
    run_engine(["sequence", "--recipe", str(RECIPE), "--until", "export",
                next(iter(load_recipe(RECIPE, check_files=False).sequences)),
                "--executor", "dask", "--workers", "2"], "the demo sequence",
               log_file=work / "engine.log", tail=20)
    recipe = load_recipe(RECIPE)
    seq_id, seq = next(iter(recipe.sequences.items()))
    root = REPO / "outputs" / recipe.session
    frames = video_info(seq.videos[recipe.cameras[0]]).n_frames
    out: dict[str, float] = {"pipeline.frames": float(frames)}
    total, wall_only = 0.0, 0
    for stage in PER_SEQUENCE:
        m = root / seq_id / stage / "manifest.json"
        if not m.is_file():
            continue
        c, is_cpu = _cpu(m)
        wall_only += not is_cpu
        out[f"pipeline.cpu_s.{stage}"] = c
        total += c
    for stage in PER_SEQUENCE:
        if f"pipeline.cpu_s.{stage}" in out:
            out[f"pipeline.share.{stage}"] = out[f"pipeline.cpu_s.{stage}"] / max(total, 1e-9)
    fixed = 0.0
    for stage in PER_SUBJECT:
        for subj in {seq.markers_on, seq.partner} - {None}:
            m = root / subj / stage / "manifest.json"
            if m.is_file():
                c, is_cpu = _cpu(m)
                fixed += c
                wall_only += not is_cpu
    out["pipeline.fixed_cpu_s"] = fixed
    out["pipeline.wall_only_stages"] = float(wall_only)
    out["pipeline.cpu_s_per_1000_frames"] = total / frames * 1000.0
    print(f"[bench pipeline] {seq_id}: {frames} frames, {total:.0f} CPU-s over "
          f"{len(PER_SEQUENCE)} stages", file=sys.stderr)
    return out


def report(results: dict) -> str:
    """Which stage dominates the per-frame cost."""
    shares = {k.rsplit(".", 1)[1]: v for k, v in results.items() if k.startswith("pipeline.share.")}
    if not shares:
        return ""
    per = results.get("pipeline.cpu_s_per_1000_frames", float("nan"))
    rows = sorted(shares.items(), key=lambda kv: -kv[1])
    frames = results.get("pipeline.frames", float("nan"))
    lines = ["### Where a two-person sequence's CPU goes (`python -m bench pipeline`)", "",
             f"{per:.0f} CPU-s per 1,000 frames (goal 900); the largest stage is "
             f"**{rows[0][0]}** ({100 * rows[0][1]:.0f} %).", "",
             "| stage | CPU-s on the sequence | per 1,000 frames | share |", "|---|---|---|---|"]
    for st, sh in rows:
        c = results.get(f"pipeline.cpu_s.{st}", float("nan"))
        lines.append(f"| {st} | {c:.1f} | {c / frames * 1000:.0f} | {100 * sh:.0f} % |")
    return "\n".join(lines)
