"""``python -m annotate.agreement FILE FILE [...]``: how well annotators agree (the paper's
Table 1), from several annotators' ``interaction_contact_signature.json`` of the same sequences.

For every action the files share and every pair of files (annotators), at 75, 37, 17 and 9
regions (``body.regions.GROUPING``: our nested map; a file's region ids must be those of our
75-region map, as the annotation page and the studio write them):

- segmentation IoU: the regions each person touches with (the two sides of the region pairs),
  pooled over both people: (|A0 & B0| + |A1 & B1|) / (|A0 | B0| + |A1 | B1|);
- signature IoU: the region pairs (person 0's region, person 1's region): |A & B| / |A | B|;
- interval IoU (not in the paper's table): the frames of the two contact intervals.

The table is the mean over actions and annotator pairs (an action both annotators left without
any pair is not counted). ``--json FILE`` writes it with the per-action, per-pair figures.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from formats.errors import InputError

LEVELS = (75, 37, 17, 9)


def _iou(a: set, b: set) -> float | None:
    u = len(a | b)
    return None if u == 0 else len(a & b) / u


def segmentation_iou(pa: np.ndarray, pb: np.ndarray) -> float | None:
    """(R, 2) region pairs of two annotators -> IoU of the regions in contact, both people."""
    inter = union = 0
    for p in range(2):
        a, b = set(pa[:, p].tolist()), set(pb[:, p].tolist())
        inter += len(a & b)
        union += len(a | b)
    return None if union == 0 else inter / union


def signature_iou(pa: np.ndarray, pb: np.ndarray) -> float | None:
    """(R, 2) region pairs of two annotators -> IoU of the sets of region pairs."""
    return _iou({tuple(r) for r in pa.tolist()}, {tuple(r) for r in pb.tolist()})


def interval_iou(a: tuple[int, int], b: tuple[int, int]) -> float:
    inter = max(0, min(a[1], b[1]) - max(a[0], b[0]) + 1)
    return inter / (max(a[1], b[1]) - min(a[0], b[0]) + 1)


def coarse(pairs: np.ndarray, n: int) -> np.ndarray:
    from body.regions import GROUPING

    return GROUPING[n][pairs] if len(pairs) else pairs


def _read(path: Path, family: str) -> tuple[str, dict]:
    from formats.chi3d import read_contact_signatures

    sigs = read_contact_signatures(path)
    raw = json.loads(path.read_text())
    names = {(raw.get(a) or {}).get("annotation", {}).get("annotator") for a in sigs}
    names.discard(None)
    names.discard("")
    who = sorted(names)[0] if len(names) == 1 else str(path)
    out = {}
    for action, s in sigs.items():
        r = np.asarray(s.regions(family), np.int64).reshape(-1, 2)
        if len(r) and r.max() >= 75:
            raise InputError(path, f"{action}.{family}_signature.region_id",
                             f"region id {int(r.max())}: not our 75-region map (0..74)", s.fr_id)
        start = s.fr_id if s.start_fr is None else s.start_fr
        end = s.fr_id if s.end_fr is None else s.end_fr
        out[action] = (r, (int(start), int(end)))
    return who, out


def agreement(files: list[Path], family: str = "anny", actions: list[str] | None = None) -> dict:
    """The table (module doc) of ``files`` (at least two)."""
    if len(files) < 2:
        raise ValueError("agreement needs at least two annotators' files")
    read = [_read(Path(f), family) for f in files]
    names = [w for w, _ in read]
    if len(set(names)) < len(names):
        names = [str(f) for f in files]
    common = set.intersection(*(set(d) for _, d in read))
    if actions:
        missing = [a for a in actions if a not in common]
        if missing:
            raise InputError(files[0], missing[0], "action not in every file")
        common = set(actions)
    if not common:
        raise InputError(files[0], "<actions>", "the files share no action")
    rows = []
    for action in sorted(common):
        for (i, (_, da)), (j, (_, db)) in itertools.combinations(enumerate(read), 2):
            (pa, ia), (pb, ib) = da[action], db[action]
            row = {"action": action, "annotators": [names[i], names[j]],
                   "interval_iou": interval_iou(ia, ib)}
            for n in LEVELS:
                ca, cb = coarse(pa, n), coarse(pb, n)
                row[f"segmentation_iou_{n}"] = segmentation_iou(ca, cb)
                row[f"signature_iou_{n}"] = signature_iou(ca, cb)
            rows.append(row)

    def mean(key):
        v = [r[key] for r in rows if r[key] is not None]
        return None if not v else float(np.mean(v))

    table = {n: {"segmentation_iou": mean(f"segmentation_iou_{n}"),
                 "signature_iou": mean(f"signature_iou_{n}")} for n in LEVELS}
    return {"files": [str(f) for f in files], "annotators": names, "family": family,
            "actions": sorted(common), "pairs_compared": len(rows),
            "table": {str(n): v for n, v in table.items()},
            "interval_iou": mean("interval_iou"), "rows": rows}


def markdown(res: dict) -> str:
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    lines = [f"Annotator agreement: {len(res['annotators'])} annotators "
             f"({', '.join(res['annotators'])}), {len(res['actions'])} actions, "
             f"{res['pairs_compared']} comparisons", "",
             "| regions | segmentation IoU | signature IoU |", "|---|---|---|"]
    for n in LEVELS:
        t = res["table"][str(n)]
        lines.append(f"| {n} | {f(t['segmentation_iou'])} | {f(t['signature_iou'])} |")
    lines += ["", f"contact interval IoU (frames): {f(res['interval_iou'])}"]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m annotate.agreement", description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="one interaction_contact_signature.json per annotator")
    ap.add_argument("--action", action="append", help="only these actions (repeatable)")
    ap.add_argument("--family", default="anny", choices=("anny", "smplx", "ghum"))
    ap.add_argument("--json", type=Path, help="also write the table and per-action rows here")
    a = ap.parse_args(argv)
    try:
        res = agreement(a.files, a.family, a.action)
    except (InputError, ValueError) as e:
        print(f"annotate.agreement: {e}", file=sys.stderr)
        return 2
    print(markdown(res))
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
