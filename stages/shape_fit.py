"""Stage ``shape_fit`` (per subject): body shape from the scan, marker placement from captures.

Reads the subject's scan (PLY/OBJ mesh or point cloud) and the C3D of every sequence in which
the subject wears markers. Writes

- ``shape.npz``: ``betas (S,)``; the marker placement ``marker_names (M,)``, ``marker_face
  (M,)``, ``marker_bary (M, 3)``, ``marker_offset (M,)`` metres (fitting/shape.py Placement);
- ``report.json``: where the shape comes from (``scan``, ``markers`` or ``mean``), scan
  distances and marker residuals in mm, the frames used.

A subject without a scan gets a marker-based shape (MoSh++ stage I: shape, placement and
poses of a few well-spread frames fitted jointly) and the report says so; a subject with
neither (an unmarked partner without scan) keeps the mean shape, also reported.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from formats.errors import InputError
from pipeline.spec import Stage, StageContext


@dataclass(frozen=True)
class Options:
    """num_betas: shape coefficients fitted to a scan; marker_num_betas: without a scan;
    scan_iters, scan_points: scan fit iterations and points per iteration; frames: well-spread
    capture frames used to place the markers; rounds: placement alternations; slide_sd_mm /
    offset_sd_mm: how far a marker may move from the template (prior spread); compile: how the
    residual function runs; seed: sampling of scan points and frames."""

    num_betas: int = 404  # all of anny's (fitting.shape.ScanFitOptions)
    marker_num_betas: int = 20
    scan_iters: int = 40
    scan_points: int = 4000
    frames: int = 8
    rounds: int = 4
    slide_sd_mm: float = 20.0
    offset_sd_mm: float = 5.0
    compile: Literal["auto", "compiled", "interpreted"] = "auto"
    seed: int = 0


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    subj = recipe.subjects[unit]
    out: dict[str, Path] = {}
    if subj.scan is not None:
        out["scan"] = Path(subj.scan)
    if subj.markerset.endswith(".json"):
        out["markerset"] = Path(subj.markerset)
    for sid in recipe.sequences_of(unit):
        seq = recipe.sequences[sid]
        if seq.markers_on == unit:
            out[f"c3d:{sid}"] = Path(seq.c3d)
    return out


def load_scan(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Scan points (N, 3) metres and normals (N, 3) or None. Meshes give their vertices (and
    vertex normals). Raises InputError when missing, unreadable or empty."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "scan", "file not found")
    try:
        obj = trimesh.load(str(path), process=False)
    except Exception as e:  # trimesh raises many types on bad files
        raise InputError(path, "scan", f"unreadable: {e}") from None
    if isinstance(obj, trimesh.Scene):
        geoms = list(obj.geometry.values())
        obj = trimesh.util.concatenate(geoms) if geoms else None
    pts = None if obj is None else np.asarray(getattr(obj, "vertices", np.zeros((0, 3))), float)
    if pts is None or len(pts) == 0:
        raise InputError(path, "scan", "no points (empty scan)")
    if not np.all(np.isfinite(pts)):
        raise InputError(path, "scan", "non-finite coordinates")
    normals = None
    if isinstance(obj, trimesh.Trimesh) and len(obj.faces):
        normals = np.asarray(obj.vertex_normals, float)
    else:
        # PLY point clouds: trimesh keeps the raw vertex properties (dict in ASCII files, a
        # structured array in binary ones)
        data = getattr(obj, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
        names = () if data is None else (data.dtype.names if hasattr(data, "dtype") else tuple(data))
        if names and all(k in names for k in ("nx", "ny", "nz")):
            normals = np.stack([np.asarray(data[k], float).reshape(-1) for k in ("nx", "ny", "nz")], 1)
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            if len(normals) != len(pts):
                normals = None
    if len(pts) < 100:
        raise InputError(path, "scan", f"only {len(pts)} points: not a body scan")
    return pts, normals


def load_captures(ctx: StageContext, names) -> tuple[np.ndarray, list[str]]:
    """Markers of every capture of this subject, (F_total, M, 3) metres with NaN gaps."""
    from formats.c3d import read_c3d

    chunks, used = [], []
    for key, path in sorted(ctx.raw.items()):
        if not key.startswith("c3d:"):
            continue
        m = read_c3d(path, markers=list(names), allow_missing=True)
        chunks.append(m.xyz)
        used.append(key[4:])
    if not chunks:
        return np.zeros((0, len(names), 3)), used
    return np.concatenate(chunks), used


def run(ctx: StageContext) -> None:
    from body import load_model
    from body.lbs import rest_state
    from fitting import compiled, marker_fit, priors, shape
    from fitting.marker_graph import GraphSpec, MarkerGraph
    from stages.marker_fit import load_body, template_placement

    o: Options = ctx.params or Options()
    rng = np.random.default_rng(o.seed)
    model = load_body(ctx.recipe, load_model)
    subj = ctx.recipe.subjects[ctx.unit]
    template = template_placement(model, subj.markerset)
    obs_all, seqs = load_captures(ctx, template.names)
    report: dict = {"subject": ctx.unit, "body_model": model.name, "marker_sequences": seqs,
                    "num_markers": len(template.names)}

    betas = np.zeros(o.num_betas)
    if "scan" in ctx.raw:
        pts, normals = load_scan(ctx.raw["scan"])
        ctx.log(f"{ctx.unit}: fitting {o.num_betas} shape coefficients to {len(pts)} scan points")
        sf = shape.fit_scan(model, pts, normals, rng,
                            shape.ScanFitOptions(num_betas=o.num_betas, iters=o.scan_iters,
                                                 n_points=o.scan_points), log=ctx.log)
        betas = sf.betas
        d = sf.scan_to_model_mm
        report.update(shape_source="scan", scan_points=int(len(pts)),
                      scan_to_model_mm={"median": float(np.median(d)),
                                        "p90": float(np.percentile(d, 90)),
                                        "mean": float(np.mean(d))},
                      scan_iterations=sf.iterations)
    elif len(obs_all):
        report["shape_source"] = "markers"
        report["note"] = ("no scan: the shape is fitted to the markers of a few well-spread "
                          "frames (MoSh++ stage I), less accurate than a scan fit")
        betas = np.zeros(o.marker_num_betas)
    else:
        report["shape_source"] = "mean"
        report["note"] = "no scan and no marker capture: mean shape"

    placement = template
    if len(obs_all):
        vis = np.all(np.isfinite(obs_all), axis=2)
        idx = shape.spread_frames(vis, obs_all, o.frames)
        obs = obs_all[idx]
        skel = shape.skinned.fit_skeleton(model, shape.body_joints(model))
        graph = MarkerGraph(GraphSpec(skel.topology, shape.marker_support(model, skel, template)),
                            compiled.CompileOptions(mode=o.compile), log=ctx.log)
        prior = priors.default_prior(skel.names[1:])

        def make_solver(_rest, skel_, u, Hm):
            return marker_fit.FrameSolver(graph, skel_, u, Hm, prior,
                                          marker_fit.MarkerFitOptions())

        popts = shape.PlacementOptions(rounds=o.rounds, slide_sd_m=o.slide_sd_mm / 1000,
                                       offset_sd_m=o.offset_sd_mm / 1000,
                                       num_betas=o.marker_num_betas)
        pf = shape.refine_placement(model, betas, template, obs, vis[idx].astype(float),
                                    make_solver, popts,
                                    fit_betas=report["shape_source"] == "markers", log=ctx.log)
        placement, betas = pf.placement, pf.betas
        per = np.nanmedian(pf.residual_mm, axis=0)
        rest0 = rest_state(model, betas)
        moved = np.linalg.norm(
            shape.marker_rest_points(rest0.vertices[0], np.asarray(model.faces), placement)
            - shape.marker_rest_points(rest0.vertices[0], np.asarray(model.faces), template),
            axis=1) * 1000
        report.update(
            placement_frames=[int(i) for i in idx],
            placement_residual_mm={"median": float(np.nanmedian(pf.residual_mm)),
                                   "p90": float(np.nanpercentile(pf.residual_mm, 90)),
                                   "per_marker_median": {n: float(v) for n, v in
                                                         zip(template.names, per, strict=True)}},
            placement_moved_mm={"median": float(np.median(moved)), "max": float(np.max(moved))})
    else:
        report["placement"] = "template (no capture to refine it)"
    report["num_betas"] = int(len(betas))
    ctx.out.save_arrays("shape", betas=np.asarray(betas, float),
                        marker_names=np.array(placement.names),
                        marker_face=np.asarray(placement.face, np.int64),
                        marker_bary=np.asarray(placement.bary, float),
                        marker_offset=np.asarray(placement.offset, float))
    ctx.out.save_json("report", report)


STAGE = Stage(name="shape_fit", func=run, per="subject", upstream=(), params=Options,
              raw_inputs=raw_inputs, version="1",
              doc="body shape (scan or markers) and marker placement per subject")
