"""Stage ``shape_fit`` (per subject): body shape from the scan, marker placement from captures.

Thin adapter around ``fitting.shape.fit_shape``: reads the subject's scan (PLY/OBJ mesh or
point cloud, ``formats.scan``) and the C3D of every sequence in which the subject wears
markers (``formats.c3d``), and writes

- ``shape.npz``: an ``artifacts.ShapeFit`` (``betas (S,)``; the marker placement
  ``marker_names (M,)``, ``marker_face (M,)``, ``marker_bary (M, 3)``, ``marker_offset (M,)``
  metres; ``shape_source``, ``placement_source``);
- ``report.json``: where the shape comes from (``scan``, ``markers`` or ``mean``), scan
  distances and marker residuals in mm, the frames used.

A subject without a scan gets a marker-based shape (MoSh++ stage I) and the report says so;
a subject with neither (an unmarked partner without scan) keeps the mean shape, also reported.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fitting.shape import ShapeFitOptions as Options
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind", "subject.markerset")


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    subj = recipe.subjects[unit]
    out: dict[str, Path] = {"body_model": common.body_model_file(recipe)}
    if subj.scan is not None:
        out["scan"] = Path(subj.scan)
    out.update(common.markerset_file(subj))
    for sid in recipe.sequences_of(unit):
        seq = recipe.sequences[sid]
        if seq.markers_on == unit:
            out[f"c3d:{sid}"] = Path(seq.c3d)
    return out


def read_captures(raw: dict[str, Path], names) -> tuple[list[np.ndarray], list[str]]:
    """Markers ``names`` of every capture in ``raw`` (keys ``c3d:<sequence>``, in key order):
    a list of (F_i, M, 3) arrays, metres with NaN gaps, and the sequence ids."""
    from formats.c3d import read_c3d

    chunks, used = [], []
    for key, path in sorted(raw.items()):
        if key.startswith("c3d:"):
            chunks.append(read_c3d(path, markers=list(names), allow_missing=True).xyz)
            used.append(key[4:])
    return chunks, used


def run(ctx: StageContext) -> None:
    from fitting.shape import fit_shape
    from formats.scan import read_scan

    o: Options = ctx.params or Options()
    model = common.load_body(ctx)
    template = common.marker_template(ctx, ctx.recipe.subject.markerset, model)
    scan = read_scan(ctx.raw["scan"]) if "scan" in ctx.raw else None
    captures, seqs = read_captures(ctx.raw, template.names)
    shape, report = fit_shape(model, template, scan, captures, o, np.random.default_rng(o.seed),
                              log=lambda s: ctx.log(f"{ctx.unit}: {s}"))
    shape.save(ctx.out)
    ctx.out.save_json("report", {"subject": ctx.unit, "marker_sequences": seqs, **report})


STAGE = Stage(name="shape_fit", func=run, per="subject", upstream=(), params=Options,
              raw_inputs=raw_inputs, reads=READS, version="1",
              doc="body shape (scan or markers) and marker placement per subject")
