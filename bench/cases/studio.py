"""Synthetic studio: does the true motion of every interaction class touch where it should and
never pass through the other body? On the motion of the ``bench`` preset's plan (seed 11, all
eight classes, 120 frames), synthesized without rendering as the generator does it
(``studio.session.verified_motion``: a draw that fails the checks is drawn again) and measured
by ``studio.contact.check_motion`` (libigl winding number and exact distances, independent of
the synthesis' own measure).

Keys:

- ``studio.max_penetration_mm``: deepest true interpenetration over all classes and frames;
  ``studio.penetration_mm.<class>``: the same per class;
- ``studio.contact_touching_min``: over all contacts, the smallest fraction of the frames a
  contact is fully held where its effector really touches the other body (gap < 5 mm);
- ``studio.first_draw_ok``: how many of the classes passed the checks at their first draw
  (the scenarios' own quality; the rest were drawn again); ``studio.draws.<class>``: draws
  made;
- ``studio.motion_s_per_frame``: CPU seconds per video frame of the delivered motion
  (synthesis and checks of every draw, rejected ones included; no rendering).

Per-class details (per-contact median gaps) go to ``bench/work/studio/classes.json``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

GOALS = {
    "studio.max_penetration_mm": ("<=", 5.0),
    "studio.contact_touching_min": (">=", 0.75),
}


def run(work: Path) -> dict[str, float]:
    from body import load_model
    from studio import plan as PL
    from studio.session import verified_motion
    from studio.subjects import make_subjects

    model = load_model("anny")
    preset = PL.PRESETS["bench"]
    plan = PL.make_plan(preset.seed, preset=preset.name)
    subjects = make_subjects(model, plan.subjects, np.random.default_rng([plan.seed, 2]))
    out, per, cpu, frames, first_ok = {}, {}, 0.0, 0, 0
    touching = []
    for seq in plan.sequences:
        t0 = time.process_time()
        _, chk, draw, _ = verified_motion(plan, seq, subjects, model)
        cpu += time.process_time() - t0
        frames += seq.frames
        first_ok += int(draw == 0 and chk.ok)
        depth_mm = float(chk.depth.max() * 1000)
        out[f"studio.penetration_mm.{seq.scenario}"] = round(depth_mm, 2)
        out[f"studio.draws.{seq.scenario}"] = draw + 1
        per[seq.seq_id] = {
            "scenario": seq.scenario, "max_penetration_mm": depth_mm, "draw": draw, "ok": chk.ok,
            "frames_over_5mm": int((chk.depth > 5e-3).sum()),
            "contacts": {k: {"held_frames": len(g), "touching": chk.touching(k),
                             "median_gap_mm": float(np.median(g) * 1000) if len(g) else None}
                         for k, g in chk.gaps.items()},
        }
        touching += [chk.touching(k) for k in chk.gaps]
        print(f"[bench studio] {seq.seq_id}: draw {draw}, {chk.summary()}", flush=True)
    work.mkdir(parents=True, exist_ok=True)
    (work / "classes.json").write_text(json.dumps(per, indent=1))
    out["studio.max_penetration_mm"] = max(v for k, v in out.items() if k.startswith("studio.penetration_mm."))
    out["studio.contact_touching_min"] = round(min(touching), 3)
    out["studio.first_draw_ok"] = first_ok
    out["studio.motion_s_per_frame"] = round(cpu / frames, 3)
    return out
