"""Public recorded Vicon captures (``recipes/real.yaml``; the files stay in ``../shared/real``,
see SOURCES.md there), each run as a marker-only sequence through the engine: shape_fit
(shape and marker placement from the markers) -> marker_fit (every sample at the capture's own
rate) -> marker_loo (leave-one-out). No ground truth exists: the honest figures are the
residual of the fitted markers and, above all, the leave-one-out error of a marker the fit
did not see.

Keys, per capture ``<tag>`` (``pycgm_movement``, ``ktk_serve``, ``ktk2_derrick``,
``ktk2_viktor``, ``cmu_walk``, ``opensim_jogging``):
- ``real.<tag>.residual_median_mm`` / ``residual_p90_mm`` / ``residual_max_mm``: marker
  residuals over all marker-frames of the valid frames;
- ``real.<tag>.loo_median_mm`` / ``loo_p90_mm``: each marker predicted by a fit without it;
- ``real.<tag>.fps_per_cpu_s``: marker_fit frames per CPU-second;
- ``real.<tag>.frames_valid_share``: valid frames / C3D samples (all frames: goal 1);
- ``real.<tag>.warnings``: how many warnings the marker_fit report gives;
- ``real.<tag>.cleaned_runs`` / ``cleaned_samples`` / ``cleaned_frames`` /
  ``unswapped_samples``: what the capture cleaning (``fitting.marker_clean.clean_markers``,
  the capture stage report's ``cleaning``) repaired: runs removed or un-swapped, marker
  samples removed, capture frames touched by any run, samples un-swapped;
  ``real.<tag>.repaired_frames`` / ``repaired_samples``: the capture stage's own counts of
  frames and marker samples it repaired.
- ``real.<tag>.loo_fps_per_cpu_s``: the capture's frames per CPU-second of its leave-one-out;
  ``marker_loo.fps_per_core``: the same over all six captures (frames / CPU-s summed).

The six captures run in one engine run on the Dask executor, ``WORKERS`` at once (one per
core; each capture's stages are single-threaded, and their CPU figures count each stage's own
process: one after the other before session 37, ~2x the wall).

Leave-one-out runs on every ``LOO_STRIDE``-th frame (``stages.marker_loo.stride``, the
stage's default 2). A coarser stride is not adequate here: each refit tracks the capture
across the stride's step, and on the fast serves it then converges worse, not just on fewer
frames. Measured at stride 10 (``python -m bench real`` at 9bb59c8, 20.4 min wall on a
loaded machine against 32 min at stride 2 before the leave-one-out speed-up): pycgm 6.88 /
29.5 mm (stride 2: 6.855 / 30.9), cmu 7.69 / 27.1 (7.75 / 27.5), jogging 9.92 / 35.0 (9.83 /
36.6), ktk 11.6 / 48.7 (11.7 / 44.6), Viktor 11.0 / 42.9 (11.2 / 42.7), but Derrick 20.1 /
64.1 (18.5 / 46.4); marker_loo.fps_per_core 38 frames per CPU-s at stride 10.

And the C3D format suite (the same capture by DEC, PC and SGI processors, int and real):
``real.c3d_suite_files_read`` (of 6) and ``real.c3d_suite_max_diff_mm`` (largest coordinate
difference from ``pc_real``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "real.yaml"
TAGS = {"pycgm/Movement 1": "pycgm_movement", "ktk/Tennis Serve 1": "ktk_serve",
        "ktk2/Derrick Serve 1": "ktk2_derrick", "ktk2/Viktor Serve 1": "ktk2_viktor",
        "cmu/Walk 05": "cmu_walk", "opensim/Jogging 1": "opensim_jogging"}
WORKERS = 2  # captures fitted at once (the engine's Dask executor), one per core
LOO_STRIDE = 2  # leave-one-out on every 2nd capture frame, the stage's default (see the docstring)
GOALS = {"marker_loo.fps_per_core": (">=", 50.0)}
LIMITS = {"marker_loo.fps_per_core": (
    "every held-out marker of a frame is refitted together (batched LM steps, fitting/loo.py), "
    "each refit started from its own previous frame moved as the full fit moved; about 1 "
    "CPU-s per call builds the compiled graph. Starting the refits from the full fit's pose "
    "was measured and rejected: that pose saw the held-out marker (pyCGM LANK 39 -> 19 mm), "
    "so the figure would flatter the fit. A refit stops below a relative cost decrease of "
    "REFIT_FTOL = 3e-4 (1e-6 before: half the speed, medians within 0.02 mm; a looser 1e-3 "
    "drifts the figure towards the full fit's: fitting/loo.py, _Refits). The fast serves (ktk, "
    "ktk2) are the slowest: their refits move most between strided frames")}
for _t in TAGS.values():
    GOALS.update({f"real.{_t}.residual_median_mm": ("<=", 2.5),
                  f"real.{_t}.residual_p90_mm": ("<=", 6.0),
                  f"real.{_t}.residual_max_mm": ("<=", 15.0),
                  f"real.{_t}.loo_median_mm": ("<=", 9.0),
                  f"real.{_t}.loo_p90_mm": ("<=", 25.0),
                  f"real.{_t}.fps_per_cpu_s": (">=", 100.0),
                  f"real.{_t}.frames_valid_share": ("==", 1.0)})
GOALS["real.c3d_suite_files_read"] = ("==", 6.0)
_SERVE = ("the trunk in the tennis serves: STRN, CLAV and T10 fit to ~5 mm in the placement "
          "frames but reach 40-60 mm together at the same instant of every serve, a pose or "
          "skinning limit, not placement: Plug-in Gait's trunk markers skin mostly to spine02 / "
          "spine04, which the fit keeps rigid (freeing them cut the serve's p90 8.3 -> 7.6 mm "
          "but raised the leave-one-out figures, pycgm 7.3 -> 8.4 mm: tried, reverted)")
_LOO = ("leave-one-out mixes the placement's error with how well the other markers fix the "
        "pose: without LSHO/RSHO or LUPA/RUPA the upper arm's roll, without a toe or heel marker "
        "the foot, is barely determined (per-marker figures in marker_loo/report.json); the "
        "throwaway prototype's 9.3 mm figure was on the pycgm capture, which passes")
for _t in ("ktk_serve", "ktk2_derrick", "ktk2_viktor"):
    LIMITS[f"real.{_t}.residual_median_mm"] = _SERVE
    LIMITS[f"real.{_t}.residual_p90_mm"] = _SERVE
for _t in TAGS.values():
    LIMITS[f"real.{_t}.loo_median_mm"] = _LOO
for _k in ("residual_median_mm", "residual_p90_mm"):
    LIMITS[f"real.cmu_walk.{_k}"] = (
        "the CMU set's template (body.markers.cmu41) was placed by rays on Anny without a real "
        "CMU subject to check it against: C7-T10 is 23 cm in the data against 35 cm on the "
        "template, and the waist markers sit elsewhere; the placement slides them but not all "
        "the way within its 200 mm cap and segment rule")
    LIMITS[f"real.opensim_jogging.{_k}"] = "as the other captures: the trunk and the knees."
_SERVE_MAX = (
    "the serve's arm overhead (session 25, ktk and ktk2 Derrick, the marker fit of a911da2): "
    "LSHO 230-248 mm off at the same instant of both files (capture frames 366-367) and RELB "
    "161-166 mm (frame 195); the raw trajectories are smooth there (no ghost or swap: the "
    "cleaning is right to leave them), but the acromion marker slides with the scapula, LSHO "
    "coming 80 mm nearer LELB and 87 mm nearer C7, which the rig's clavicle and shoulder "
    "cannot follow, so the fit holds LSHO or LUPA off in turn; 327 of ktk's 1,092 frames have "
    "a marker > 50 mm off. Tried: re-tracking every run of outlier frames backwards from the "
    "frame after it (max 230 -> 223 mm, frames > 50 mm 327 -> 321) and a graduated re-solve "
    "of those frames from the warm start (-> 203 mm, 315 frames): not kept")
for _t in ("ktk_serve", "ktk2_derrick", "ktk2_viktor"):
    LIMITS[f"real.{_t}.residual_max_mm"] = _SERVE_MAX
LIMITS["real.cmu_walk.residual_max_mm"] = (
    "RSHO 53 mm at frame 172, LFWT 38, LFRM 36, LKNE 32 (session 25); LKNE and RUPA are more "
    "than 15 mm off in 220 and 214 of the 1,854 frames: the thigh's and upper arm's soft "
    "tissue, and the CMU template's placement (the median's reason)")


def _recipe(work: Path) -> Path:
    """recipes/real.yaml with absolute paths (the bench runs from its own work folder)."""
    import yaml

    rec = yaml.safe_load(RECIPE.read_text())

    def absolute(p):
        q = (RECIPE.parent / p).resolve()
        if not q.exists():
            raise FileNotFoundError(f"{RECIPE}: {p}: not found ({q}); the real captures live in "
                                    "../shared/real beside the checkout")
        return str(q)

    for s in rec["subjects"].values():
        for t in s.get("static", []):
            t["c3d"] = absolute(t["c3d"])
    for q in rec["sequences"].values():
        q["c3d"] = absolute(q["c3d"])
    stages = rec.setdefault("stages", {}) or {}
    stages["marker_loo"] = {**(stages.get("marker_loo") or {}), "stride": LOO_STRIDE}
    rec["stages"] = stages
    path = work / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path


def _suite() -> dict[str, float]:
    from formats.c3d import read_c3d
    from formats.errors import InputError

    folder = (RECIPE.parent / "../../shared/real/c3d_format_suite").resolve()
    ref = read_c3d(folder / "pc_real.c3d")
    read, diff = 0, 0.0
    for f in sorted(folder.glob("*.c3d")):
        try:
            m = read_c3d(f)
        except InputError as e:
            print(f"[bench real] {f.name}: {e}", flush=True)
            continue
        read += 1
        both = np.isfinite(m.xyz) & np.isfinite(ref.xyz)
        if m.names != ref.names or m.xyz.shape != ref.xyz.shape:
            raise RuntimeError(f"{f.name}: other labels or shape than pc_real.c3d")
        diff = max(diff, float(np.max(np.abs(m.xyz[both] - ref.xyz[both]))) * 1000)
    return {"real.c3d_suite_files_read": float(read), "real.c3d_suite_max_diff_mm": diff}


def cleaning_counts(cleaned: dict | None) -> dict[str, float]:
    """What the capture cleaning repaired, from its report (``CleanReport.to_json``): runs,
    removed samples, frames touched by a run (union of their sample ranges), un-swapped
    samples."""
    cleaned = cleaned or {}
    runs = cleaned.get("runs") or []
    touched: set[int] = set()
    for r in runs:
        touched.update(range(int(r["first_sample"]), int(r["last_sample"]) + 1))
    return {"cleaned_runs": float(len(runs)),
            "cleaned_samples": float(cleaned.get("removed_samples") or 0),
            "cleaned_frames": float(len(touched)),
            "unswapped_samples": float(sum((cleaned.get("unswapped") or {}).values()))}


def run(work: Path) -> dict[str, float]:
    from artifacts import BodyFit
    from bench.cases._engine import run_engine
    from recipes import load_recipe

    path = _recipe(work)
    recipe = load_recipe(path)
    out: dict[str, float] = {}
    loo_frames, loo_cpu = 0, 0.0
    # every capture in one engine run, two at once (one per core): a capture that fails is
    # recorded below, the others still run (the engine's other nodes go on)
    rc = run_engine(["sequence", *TAGS, "--recipe", str(path), "--outputs", str(work / "outputs"),
                     "--until", "marker_loo", "--executor", "dask", "--workers", str(WORKERS)],
                    "the real captures", log_file=work / "engine.log", echo=8, check=False)
    bad = [ln for ln in (work / "engine.log").read_text().splitlines()
           if " FAILED" in ln or " skipped" in ln] if rc else []
    for sid, tag in TAGS.items():
        g, a = sid.split("/")
        base = work / "outputs" / recipe.session / g / a
        if any(sid in ln for ln in bad) or not all(
                (base / st / "manifest.json").is_file() for st in ("marker_fit", "marker_loo")):
            out[f"real.{tag}.error"] = 1.0  # recorded, not raised (engine.log says why)
            continue
        rep = json.loads((base / "marker_fit" / "report.json").read_text())
        fit = BodyFit.load(base / "marker_fit")
        mm = fit.marker_residual_m[fit.valid] * 1000
        out[f"real.{tag}.residual_median_mm"] = float(np.nanmedian(mm))
        out[f"real.{tag}.residual_p90_mm"] = float(np.nanpercentile(mm, 90))
        out[f"real.{tag}.residual_max_mm"] = float(np.nanmax(mm))
        cap = base / "capture" / "report.json"  # the capture stage cleans the capture once
        cr = json.loads(cap.read_text()) if cap.is_file() else {}
        out.update({f"real.{tag}.{k}": v for k, v in
                    cleaning_counts(cr.get("cleaning") or rep.get("cleaned")).items()})
        if "repaired_frames" in cr:
            out[f"real.{tag}.repaired_frames"] = float(cr["repaired_frames"])
            out[f"real.{tag}.repaired_samples"] = float(cr["repaired_samples"])
        out[f"real.{tag}.fps_per_cpu_s"] = float(rep["fps_per_cpu_s"])
        out[f"real.{tag}.frames_valid_share"] = float(fit.valid.mean())
        out[f"real.{tag}.warnings"] = float(len(rep["warnings"]))
        loo = base / "marker_loo" / "report.json"
        if loo.is_file():
            lr = json.loads(loo.read_text())
            out[f"real.{tag}.loo_median_mm"] = float(lr["overall"]["median_mm"])
            out[f"real.{tag}.loo_p90_mm"] = float(lr["overall"]["p90_mm"])
            n = int(np.count_nonzero(fit.valid))  # the frames leave-one-out covers
            out[f"real.{tag}.loo_fps_per_cpu_s"] = n / max(float(lr["cpu_s"]), 1e-9)
            loo_frames += n
            loo_cpu += float(lr["cpu_s"])
    if loo_cpu > 0:
        out["marker_loo.fps_per_core"] = loo_frames / loo_cpu
    out.update(_suite())
    return out
