"""Keypoints stage: accuracy against projected ground truth and detector speed, on the studio
bench session.

Data: ``recipes/bench.yaml`` (studio preset ``bench``: all eight interaction scenarios, two
Anny people in different clothing, four 900 x 900 views; its data in ``data/bench`` are
generated on demand by ``studio.ensure_generated`` and shared with other cases). For a quick
look, ``BENCH_KEYPOINTS_RECIPE=<recipe.yaml>`` runs the case on another studio session.

Every sequence is run through the stage's own code (``stages.keypoints.compute``, the
adapter around ``detect.sequence.detect_keypoints``: mediapipe, crops from the markers, the
partner rule, the cross-view check) on every ``STRIDE``-th video frame, with one worker
process per core. Truth: the studio's posed vertices and joints (``gt/<group>/<action>.npz``)
through ``body.joints`` KP65 regressor, projected with the calibrated cameras.

Keys:

- ``keypoints.fps_per_core``: video frames (all four views) per CPU-second of the workers;
  ``keypoints.fps_per_core_steady``: the same without ``setup_cpu_s`` (importing mediapipe
  and building its graphs, opening the videos: ~1.2 s per worker process and chunk, paid
  once per 12-frame sequence here but once per 32 frames, the import once per worker, on a
  full sequence at stride 1);
- ``keypoints.median_px`` and ``_body`` / ``_hands`` / ``_feet`` (groups of detect.metrics),
  ``_wearer`` / ``_partner``: median pixel error of detected keypoints (confidence >= 0.1)
  whose truth lies in the image; ``keypoints.p90_px``;
- ``keypoints.detected_<group>_<person>``: fraction of in-image truth keypoints detected
  (mediapipe gives no small toes: feet top out at 4/6);
- ``keypoints.identity_swaps``: frames (over all sequences) where in at least one view a
  person's body keypoints lie nearer (median) the other person's truth than its own;
  ``keypoints.identity_swap_views``: the same counted per view. A person detected with its
  left and right swapped (back views fool the detector) is not a swap but a flip:
  ``keypoints.lr_flips_wearer`` / ``_partner`` count the views (detect.metrics.lr_flips).

- ``keypoints.fps_per_core_clip``, ``keypoints.median_px_clip``: the same stage on CLIP_FRAMES
  consecutive frames (stride 1, one chunk, ``video_mode`` auto = on) of CLIP_SEQUENCE: the
  stage's default stride, where mediapipe's video mode tracks (at stride 10 people move too
  far between kept frames and the per-chunk graphs cost more than tracking saves).

Per-sequence details go to ``bench/work/keypoints/sequences.json``.
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
STRIDE = 10
CLIP_SEQUENCE = "s01/Grab 1"
CLIP_FRAMES = 32
GOALS = {
    "keypoints.identity_swaps": ("<=", 0),
    "keypoints.median_px": ("<=", 8.0),
}


def _truth_uv(recipe, sid: str, seq, frames: np.ndarray, reg) -> np.ndarray:
    """(C, F, 2, 65, 2) projected truth of both people (person 0 = the marker wearer)."""
    from body.joints import regress
    from calib import project
    from calib.io import read_chi3d_camera

    group, action = sid.split("/")
    data = Path(seq.c3d).parents[2]  # <data>/<group>/mocap/<action>.c3d
    gt = np.load(data / "gt" / group / f"{action}.npz")
    kp3 = np.stack([regress(reg, gt["vertices"][p][frames].astype(np.float64), gt["joints"][p][frames])
                    for p in (0, 1)], axis=1)
    return np.stack([project(read_chi3d_camera(seq.calibration[c], name=c), kp3)
                     for c in recipe.cameras])


def run(work: Path) -> dict[str, float]:
    from body import load_model
    from body.joints import regressor
    from detect.metrics import GROUPS, group_summary, identity_swaps, keypoint_errors, lr_flips
    from recipes import load_recipe
    from stages import view_for
    from stages.keypoints import Options, compute, raw_inputs

    recipe_path = Path(os.environ.get("BENCH_KEYPOINTS_RECIPE", REPO / "recipes" / "bench.yaml"))
    if recipe_path.resolve() == (REPO / "recipes" / "bench.yaml").resolve():
        from studio import ensure_generated

        ensure_generated(recipe_path)
    recipe = load_recipe(recipe_path)
    reg = regressor(load_model("anny"), "kp65")
    opts = Options(stride=STRIDE, workers=os.cpu_count() or 1)
    errs, swaps, frames_total, cpu, setup, per_seq = [], 0, 0, 0.0, 0.0, {}
    swap_views = 0
    flips = np.zeros(2, int)
    for sid, seq in recipe.sequences.items():
        c = compute(view_for(recipe, "keypoints", sid), raw_inputs(recipe, sid), opts, unit=sid,
                    recipe_path=recipe_path)
        res = c.keypoints
        truth = _truth_uv(recipe, sid, seq, res.frames, reg)
        inside = (truth[..., 0] >= 0) & (truth[..., 0] < 900) & (truth[..., 1] >= 0) & (truth[..., 1] < 900)
        err = keypoint_errors(res.kp, truth, inside)
        sw = identity_swaps(res.kp, truth)
        fl = lr_flips(res.kp, truth)
        flips += fl.sum(axis=(0, 1))
        errs.append((err, inside))
        swaps += int(sw.any(axis=0).sum())
        swap_views += int(sw.sum())
        frames_total += len(res.frames)
        cpu += c.report["cpu_s"]
        setup += c.report["detector_calls"].get("setup_cpu_s", 0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per_seq[sid] = {"frames": len(res.frames), "swapped_frames": int(sw.any(axis=0).sum()),
                            "lr_flipped_views": fl.sum(axis=(0, 1)).tolist(),
                            "wearer": group_summary(err[:, :, 0], inside[:, :, 0]),
                            "partner": group_summary(err[:, :, 1], inside[:, :, 1]),
                            "report": c.report}

    clip = {}
    if CLIP_SEQUENCE in recipe.sequences:
        sid, seq = CLIP_SEQUENCE, recipe.sequences[CLIP_SEQUENCE]
        o1 = Options(stride=1, start=0, stop=CLIP_FRAMES, chunk=CLIP_FRAMES, workers=1)
        c = compute(view_for(recipe, "keypoints", sid), raw_inputs(recipe, sid), o1, unit=sid,
                    recipe_path=recipe_path)
        truth = _truth_uv(recipe, sid, seq, c.keypoints.frames, reg)
        inside = (truth[..., 0] >= 0) & (truth[..., 0] < 900) & (truth[..., 1] >= 0) & (truth[..., 1] < 900)
        e1 = keypoint_errors(c.keypoints.kp, truth, inside)
        steady = c.report["cpu_s"] - c.report["detector_calls"].get("setup_cpu_s", 0.0)
        clip = {"keypoints.fps_per_core_clip": c.report["fps_per_core"],
                "keypoints.fps_per_core_clip_steady": CLIP_FRAMES / steady if steady > 0 else float("nan"),
                "keypoints.median_px_clip": float(np.median(e1[np.isfinite(e1)]))}
        per_seq["clip"] = {"sequence": sid, "frames": CLIP_FRAMES,
                           "swapped_frames": int(identity_swaps(c.keypoints.kp, truth).any(axis=0).sum()),
                           "wearer": group_summary(e1[:, :, 0], inside[:, :, 0]),
                           "partner": group_summary(e1[:, :, 1], inside[:, :, 1]),
                           "report": c.report}
    (work / "sequences.json").write_text(json.dumps(per_seq, indent=1, default=float))

    e = np.concatenate([x[0].reshape(-1, 2, 65) for x in errs])  # (C*F, 2, 65)
    ins = np.concatenate([x[1].reshape(-1, 2, 65) for x in errs])
    out = {"keypoints.fps_per_core": frames_total / cpu if cpu > 0 else float("nan"),
           "keypoints.fps_per_core_steady": frames_total / (cpu - setup) if cpu > setup else float("nan"),
           "keypoints.frames": float(frames_total),
           "keypoints.identity_swaps": float(swaps),
           "keypoints.identity_swap_views": float(swap_views),
           "keypoints.lr_flips_wearer": float(flips[0]),
           "keypoints.lr_flips_partner": float(flips[1])}
    out.update(clip)
    allv = e[np.isfinite(e)]
    out["keypoints.median_px"] = float(np.median(allv))
    out["keypoints.p90_px"] = float(np.percentile(allv, 90))
    for g, idx in GROUPS.items():
        v = e[..., idx]
        out[f"keypoints.median_px_{g}"] = float(np.median(v[np.isfinite(v)]))
    for p, who in enumerate(("wearer", "partner")):
        v = e[:, p]
        out[f"keypoints.median_px_{who}"] = float(np.median(v[np.isfinite(v)]))
        for g, idx in GROUPS.items():
            can = ins[:, p][:, idx]
            out[f"keypoints.detected_{g}_{who}"] = float(np.isfinite(e[:, p][:, idx])[can].mean())
    return out
