"""``python -m evaluate PRED GT [--json OUT] [--smplx-model PATH] [--anny-model PATH]``: score a prediction folder
against a truth folder, both in the CHI3D layout. Prints a markdown table (mm) and writes the
same figures as JSON (default ``<PRED>/evaluation.json``). Bad input: one line per problem
(file, field, frame), exit code 2."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from evaluate import constants as K
from evaluate.folders import load_pairs
from evaluate.protocol import evaluate_pairs, markdown
from formats.errors import InputError


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluate", description=__doc__.split("\n\n")[0])
    ap.add_argument("pred", type=Path, help="prediction folder (CHI3D layout)")
    ap.add_argument("gt", type=Path, help="ground-truth folder (CHI3D layout)")
    ap.add_argument("--json", type=Path, default=None, help=f"output (default <PRED>/{K.DEFAULT_JSON})")
    ap.add_argument("--smplx-model", default=None,
                    help="SMPL-X model file for smplx/<action>.json (default $SMPLX_MODEL_PATH)")
    ap.add_argument("--anny-model", default=None,
                    help="Anny model file for anny/<action>.json (default: body.load_model's)")
    a = ap.parse_args(argv)
    try:
        pairs, errors = load_pairs(a.pred, a.gt, a.smplx_model, a.anny_model)
        if errors:
            for e in errors:
                print(f"error: {e}", file=sys.stderr)
            return 2
        result = evaluate_pairs(pairs)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    result["pred"], result["gt"] = str(a.pred), str(a.gt)
    out = a.json or a.pred / K.DEFAULT_JSON
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, allow_nan=False))
    print(markdown(result))
    print(f"figures written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
