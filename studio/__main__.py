"""``python -m studio --out DIR --seed N [--frames N] [--scenarios hug,handshake] [--preset demo|bench]``"""
from __future__ import annotations

import argparse
import sys

from studio import plan as PL


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studio", description=__doc__)
    ap.add_argument("--out", required=True, help="session folder to write (created)")
    ap.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, or 3)")
    ap.add_argument("--frames", type=int, default=None, help="video frames per sequence (50 fps)")
    ap.add_argument("--scenarios", default=None,
                    help=f"comma-separated, from: {', '.join(PL.SCENARIOS)}")
    ap.add_argument("--preset", choices=sorted(PL.PRESETS), default=None)
    a = ap.parse_args(argv)
    try:
        scen = PL.parse_scenarios(a.scenarios) if a.scenarios else None
        seed = a.seed if a.seed is not None else (PL.PRESETS[a.preset].seed if a.preset else 3)
        plan = PL.make_plan(seed, a.frames, scen, a.preset)
    except ValueError as e:
        print(f"python -m studio: {e}", file=sys.stderr)
        return 2
    from studio.session import generate

    recipe = generate(a.out, plan)
    print(recipe)
    return 0


if __name__ == "__main__":
    sys.exit(main())
