"""``python -m studio --out DIR --seed N [--frames N] [--scenarios hug,handshake] [--preset demo|bench|markers] [--realistic-markers]``

``--preset markers``: the marker-only session (no cameras, videos, scans or partner).
``--realistic-markers``: a two-person session whose marker capture is realistic
(``studio.mocap.capture``). ``--realistic``: the whole realistic studio (``studio.lab``: lab
room, bystander, clean plates, camera look, calibration error, a camera out of sync, realistic
markers; the demo and bench presets' default); ``--kind``: none of it (exact, for tests).

``python -m studio --recipe-preset demo``: generate the data of ``recipes/demo.yaml`` if any
file is missing (``studio.ensure_generated``; what ``make demo`` runs).
"""
from __future__ import annotations

import argparse
import sys

from studio import plan as PL


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studio", description=__doc__)
    ap.add_argument("--out", default=None, help="session folder to write (created)")
    ap.add_argument("--recipe-preset", choices=sorted(PL.PRESETS), default=None,
                    help="make sure the data of recipes/<preset>.yaml exist (generate if missing)")
    ap.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, or 3)")
    ap.add_argument("--frames", type=int, default=None, help="video frames per sequence (50 fps)")
    ap.add_argument("--scenarios", default=None,
                    help=f"comma-separated, from: {', '.join(PL.SCENARIOS)}")
    ap.add_argument("--preset", choices=sorted(PL.PRESETS), default=None)
    ap.add_argument("--realistic-markers", action="store_true",
                    help="two-person sessions: realistic marker placement and capture")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--realistic", action="store_true", default=None,
                   help="the realistic studio (default of the demo and bench presets)")
    g.add_argument("--kind", action="store_true", help="the kind studio: nothing realistic")
    ap.add_argument("--write-recipe", default=None, metavar="PATH",
                    help="with --preset: only write the preset's committed recipe to PATH (paths "
                         "relative to it, pointing into --out); generate nothing")
    a = ap.parse_args(argv)
    if a.recipe_preset:
        from pathlib import Path

        from studio import ensure_generated

        print(ensure_generated(Path(__file__).resolve().parents[1] / "recipes" / f"{a.recipe_preset}.yaml"))
        return 0
    if not a.out:
        ap.error("--out is required")
    if a.write_recipe:
        if not a.preset:
            print("python -m studio: --write-recipe needs --preset", file=sys.stderr)
            return 2
        from pathlib import Path

        from studio import preset_recipe
        from studio.session import write_recipe

        path = Path(a.write_recipe)
        header = (f"# Studio preset {a.preset!r}: its data ({a.out}, git-ignored) are generated on "
                  f"demand by studio.ensure_generated.\n# Regenerate this file with: python -m studio "
                  f"--preset {a.preset} --out {a.out} --write-recipe {path}")
        write_recipe(path, preset_recipe(a.preset, path.resolve().parent, Path(a.out)), header)
        print(path)
        return 0
    try:
        scen = PL.parse_scenarios(a.scenarios) if a.scenarios else None
        seed = a.seed if a.seed is not None else (PL.PRESETS[a.preset].seed if a.preset else 3)
        realism = False if a.kind else (True if a.realistic else None)
        plan = PL.make_plan(seed, a.frames, scen, a.preset, realism=realism)
        if a.realistic_markers:
            if not isinstance(plan, PL.SessionPlan):
                raise ValueError("--realistic-markers: the markers preset is always realistic")
            import dataclasses

            plan = dataclasses.replace(plan, marker_realism=True)
    except ValueError as e:
        print(f"python -m studio: {e}", file=sys.stderr)
        return 2
    from studio.session import generate

    recipe = generate(a.out, plan)
    print(recipe)
    return 0


if __name__ == "__main__":
    sys.exit(main())
