"""``python -m studio.inspect GT_NPZ [--frame F] [--out PNG]``: where a studio sequence's two
true bodies go through each other, as a picture.

Reads a sequence's ground truth (``<session>/gt/<group>/<action>.npz``), finds the frame with
the deepest true interpenetration (``geometry.interpenetration``; or takes ``--frame``),
prints the body parts involved (the dominant bone of the deepest vertices of each body and of
the surface they are in) and writes a close-up of the four sides of the deepest point
(default ``<npz stem>_f<frame>_inspect.png`` beside the npz). The tool for working on a
scenario: the close-up is what shows which limb crosses which.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Inspection:
    """frame: the inspected video frame; depth_m: its deepest interpenetration (0 if none);
    point: (3,) world point inspected (the deepest vertex, or the middle of the two bodies);
    parts: [(inside body, its part, the other's part, depth m)], deepest first; png: the picture."""

    frame: int
    depth_m: float
    point: np.ndarray
    parts: list
    png: Path


def parts_inside(inside: list[tuple], faces: np.ndarray, bone_names: list[str],
                 dominant: np.ndarray, top: int = 6, min_m: float = 0.002) -> list:
    """The body parts that are inside each other, from :func:`geometry.inside_points`:
    over the inside vertices deeper than ``min_m``, (body, its part, the part of the other whose
    surface is nearest, depth m), the deepest per pair of parts, ``top`` deepest overall."""
    pairs: Counter = Counter()
    for a, (ins, d, fi) in enumerate(inside):
        for k in np.flatnonzero(d > min_m):
            key = (a, bone_names[dominant[ins[k]]], bone_names[dominant[faces[fi[k], 0]]])
            pairs[key] = max(pairs[key], float(d[k]))
    return [(*k, v) for k, v in pairs.most_common(top)]


def inspect(gt_npz: str | Path, frame: int | None = None, out: str | Path | None = None,
            model_name: str = "anny") -> Inspection:
    from body import load_model
    from drawing.render import PersonMesh
    from drawing.sheet import close_up, write_png
    from formats.errors import InputError
    from geometry import deepest_inside, inside_points, interpenetration_per_frame

    path = Path(gt_npz)
    if not path.is_file():
        raise InputError(path, "file", "no such ground-truth file")
    with np.load(path) as z:
        if "vertices" not in z or "faces" not in z:
            raise InputError(path, "vertices", "not a studio ground truth (needs 'vertices' and "
                             "'faces')")
        Vs, faces = np.asarray(z["vertices"], float), np.asarray(z["faces"])
    F = Vs.shape[1]
    if frame is None:
        frame = int(np.argmax(interpenetration_per_frame(Vs[0], Vs[1], faces)))
    elif not 0 <= frame < F:
        raise InputError(path, "vertices", f"out of range (0..{F - 1})", frame)
    model = load_model(model_name)
    if model.num_vertices != Vs.shape[2]:
        raise InputError(path, "vertices", f"{Vs.shape[2]} vertices per body, the {model_name} "
                         f"model has {model.num_vertices}")
    V = [Vs[0, frame], Vs[1, frame]]
    inside = inside_points(V[0], V[1], faces)
    depth, body, vid = deepest_inside(inside)
    point = V[body][vid] if body >= 0 else 0.5 * (V[0].mean(0) + V[1].mean(0))
    dominant = np.asarray(model.weights.argmax(axis=1)).ravel()
    parts = parts_inside(inside, faces, list(model.joint_names), dominant)
    colors = [np.tile(np.array([[230, 80, 50]], np.uint8), (len(V[0]), 1)),
              np.tile(np.array([[50, 100, 230]], np.uint8), (len(V[1]), 1))]
    title = f"{path.stem} frame {frame}: {1000 * depth:.1f} mm (person 0 red, 1 blue)"
    png = Path(out) if out else path.with_name(f"{path.stem.replace(' ', '_')}_f{frame}_inspect.png")
    write_png(png, close_up([PersonMesh(V[k], faces, colors[k]) for k in range(2)], point, title))
    return Inspection(frame, depth, point, parts, png)


def main(argv: list[str] | None = None) -> int:
    from formats.errors import InputError

    ap = argparse.ArgumentParser(prog="python -m studio.inspect", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("gt_npz", help="a sequence's ground truth, <session>/gt/<group>/<action>.npz")
    ap.add_argument("--frame", type=int, default=None, help="video frame (default: the deepest)")
    ap.add_argument("--out", default=None, help="PNG to write")
    a = ap.parse_args(argv)
    try:
        res = inspect(a.gt_npz, a.frame, a.out)
    except InputError as e:
        print(f"python -m studio.inspect: {e}", file=sys.stderr)
        return 2
    print(f"frame {res.frame}: deepest interpenetration {1000 * res.depth_m:.1f} mm at "
          f"{np.round(res.point, 3).tolist()}")
    for body, mine, theirs, d in res.parts:
        print(f"  person {body} {mine} inside person {1 - body} {theirs}: {1000 * d:.1f} mm")
    print(res.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
