"""``python -m evaluate.session --recipe R [--outputs DIR]``: after ``make release`` / ``make demo``
/ ``make evaluate``, say where a session's release folder is and print its benchmark.

Reads the engine's artifacts (``<outputs>/<session>/session/release``, ``.../qa_index`` and
``.../evaluate``): prints the release folder, its verification and the datasheet's totals, the
QA index page and its most flagged sequences, then the evaluator's
markdown table (when the recipe has a ground truth, ``stages.evaluate.truth``), and copies
``evaluation.json`` to ``<outputs>/<session>/evaluation.json``. Exit code 1 when the release (or
the evaluation a recipe asks for) is missing: the pipeline's own log says why.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path


def summary(recipe_path: Path, outputs: Path) -> tuple[int, str]:
    import yaml

    raw = yaml.safe_load(Path(recipe_path).read_text()) or {}
    session = raw.get("session")
    root = Path(outputs) / str(session)
    rel, ev = root / "session" / "release", root / "session" / "evaluate"
    lines, rc = [], 0
    if (rel / "manifest.json").is_file() and (rel / "verification.json").is_file():
        ver = json.loads((rel / "verification.json").read_text())
        sheet = json.loads((rel / "datasheet.json").read_text())
        tot = sheet.get("totals", {})
        lines += [f"Release folder: {rel}",
                  f"  {'verified' if ver.get('ok') else 'NOT verified'}: "
                  f"{ver.get('files_checked', ver.get('files', '?'))} files re-read, "
                  f"SHA-256 manifest {rel / 'MANIFEST.sha256'}",
                  f"  datasheet {rel / 'datasheet.md'}: "
                  + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in tot.items()
                              if isinstance(v, (int, float)))]
    else:
        lines.append(f"No release of session {session!r} under {root} (see the pipeline's log).")
        rc = 1
    qa = root / "session" / "qa_index"
    if (qa / "manifest.json").is_file() and (qa / "summary.json").is_file():
        q = json.loads((qa / "summary.json").read_text())
        lines += ["", f"QA report: {(qa / 'index.html').resolve()}",
                  f"  {q['flagged']} of {q['frames']} frames flagged ({100 * q['rate']:.1f} %) over "
                  f"{q['sequences']} sequences; open the index in a browser, each sequence's "
                  "report shows both meshes on the four views at the flagged frames"]
        for r in sorted(q["rows"], key=lambda r: -r["flagged"] / max(r["frames"], 1))[:5]:
            lines.append(f"  {r['sequence']}: {r['flagged']}/{r['frames']} flagged"
                         + (": " + ", ".join(f"{k} {v}" for k, v in sorted(
                             r["reasons"].items(), key=lambda kv: -kv[1])[:3]) if r["reasons"] else ""))
    wants_eval = bool(((raw.get("stages") or {}).get("evaluate") or {}).get("truth"))
    if (ev / "evaluation.json").is_file():
        shutil.copyfile(ev / "evaluation.json", root / "evaluation.json")
        lines += ["", f"CHI3D benchmark of the release against the ground truth "
                      f"({ev / 'evaluation.md'}; figures in {root / 'evaluation.json'}):", "",
                  (ev / "evaluation.md").read_text()]
    elif wants_eval:
        lines.append(f"No evaluation of session {session!r} under {root} (see the pipeline's log).")
        rc = 1
    return rc, "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m evaluate.session", description=__doc__.split("\n\n")[0])
    ap.add_argument("--recipe", type=Path, required=True)
    ap.add_argument("--outputs", type=Path, default=Path(os.environ.get("PIPELINE_OUTPUTS", "outputs")))
    a = ap.parse_args(argv)
    rc, text = summary(a.recipe, a.outputs)
    print(text)
    return rc


if __name__ == "__main__":
    sys.exit(main())
