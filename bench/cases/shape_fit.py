"""shape_fit accuracy on synthetic subjects with exact ground truth.

A subject drawn like the studio's (bench/fitting_synth.py) is scanned with the
studio's scanner model (studio/scan.py: 60k points, 2 mm noise along the normal, holes at the
armpits and no soles, uneven density) in the neutral pose (pose 0, as the studio scans) at a random heading, and captured
with slid Plug-in Gait markers in a few well-spread frames (1 mm noise).

Keys:
- ``shape_fit.v2v_mm``: mean vertex distance between the fitted and true bodies in the neutral
  pose (pose 0, both centred on their mean vertex: :func:`v2v_mm`), scan-based shape;
- ``shape_fit.scan_to_model_mm``: median distance of the scan points to the fitted surface;
- ``shape_fit.placement_mm``: mean distance between refined and true marker positions on the
  true body's rest pose, on the realistic marker studio through the stage chain
  (``_markers_chain``: no scan, shape and placement from the markers);
  ``placement_template_mm`` the template's;
- ``shape_fit.v2v_markers_mm``: like ``v2v_mm`` for the marker-based shape of that chain
  (``v2v_mean_body_mm``: the mean body's, for scale);
- ``shape_fit.scan_fit_s``: wall time of the scan fit.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evaluate.metrics import mean_distance

GOALS = {"shape_fit.v2v_mm": ("<=", 5.0), "shape_fit.v2v_markers_mm": ("<=", 10.0)}
LIMITS = {"shape_fit.v2v_markers_mm": (
    "markers fix the body's outside where they sit, not its shape: with slides of 2-3 cm and "
    "skin offsets of 8-25 mm allowed, shape and placement trade off (a body 1 cm thicker with "
    "markers 1 cm closer fits as well), and Anny's rest posture (bind rotations) changes with "
    "the shape, which free poses absorb: even with the true placement and clean markers the "
    "joint betas and poses fit reached 13-16 mm v2v (helper measurement, "
    "tests/test_shape_markers.py, in the template space the row used before session 28; "
    "the row is now measured in pose 0, v2v_mm: 18.1 -> 14.7 mm on the same fits). The size "
    "grid over beta 0 (-3..3, refined) fixed the worst case (a 1.46 m subject fitted 15 cm "
    "too tall: 40 -> 14.5 mm).")}
SEED = 5
PLACEMENT_FRAMES = 8


def v2v_mm(model, b1, b2) -> float:
    """Mean vertex distance (mm) between the bodies of betas ``b1`` and ``b2`` in the neutral
    pose (``body.forward`` at pose 0: the body as the studio scans it and as every pose starts
    from), each centred on its mean vertex. Not the template-space rest meshes
    (``body.lbs.rest_state(...).vertices``): Anny's bind rotations, which depend on the betas,
    turn the bones of those meshes into pose 0, and on the studio's subjects the two spaces
    differ by ~13 mm for the same betas (lower legs ~17 mm), so a template-space distance
    counts a posture no posed body has (session 28: 5.4 mm in template space, 1.9 in pose 0,
    for the same scan fit)."""
    from body import forward

    J = model.num_joints
    a, b = (forward(model, np.atleast_1d(np.asarray(x, float)), np.zeros((1, J, 3)),
                    np.eye(3)[None], np.zeros((1, 3))).vertices[0] for x in (b1, b2))
    return float(mean_distance(a - a.mean(0), b - b.mean(0)) * 1000)


def run(work: Path) -> dict[str, float]:  # noqa: ARG001 - nothing written to disk
    from bench import fitting_synth as S

    studio = S.studio_session()
    if studio is not None:
        return {**_run_studio(*studio), **_markers_chain()}

    from body import load_model
    from fitting import shape, skinned
    from studio.scan import sample_scan

    rng = np.random.default_rng(SEED)
    model = load_model("anny")
    opts = shape.ShapeFitOptions(frames=PLACEMENT_FRAMES)
    betas = S.subject_betas(model, rng)
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    x = np.zeros(skel.n)  # the studio scans people in the neutral pose (pose 0)
    x[:3] = [0.0, 0.0, rng.uniform(-np.pi, np.pi)]
    v = S.posed(model, betas, skel, x[None]).vertices[0]
    v[:, 2] -= v[:, 2].min()
    armpits = S.posed(model, betas, skel, x[None]).joints[0][
        [model.joint_index("upperarm01.L"), model.joint_index("upperarm01.R")]]
    armpits[:, 2] -= S.posed(model, betas, skel, x[None]).vertices[0][:, 2].min()
    pts, nrm = sample_scan(v, np.asarray(model.faces), armpits, rng)
    t0 = time.perf_counter()
    scan_betas, rep = shape.shape_from_scan(model, pts, nrm, opts, rng)
    t_scan = time.perf_counter() - t0
    out = {"shape_fit.v2v_mm": v2v_mm(model, betas, scan_betas),
           "shape_fit.scan_to_model_mm": rep["scan_to_model_mm"]["median"],
           "shape_fit.scan_fit_s": float(t_scan)}

    out.update(_markers_chain())
    return out


def _markers_chain() -> dict[str, float]:
    """Shape and placement from markers only, on the realistic marker studio through the
    stage chain (``_markers_chain``): per subject the fitted betas against the true ones
    (v2v in pose 0, centred) and the fitted placement against the true one (both on the true
    rest body), averaged over the subjects."""
    from artifacts import ShapeFit
    from bench.cases._markers_chain import run_chain
    from body import load_model
    from body.lbs import rest_state
    from body.markers import load_json
    from fitting import shape
    from fitting.marker_graph import template_placement

    recipe, out, gt = run_chain(until="shape_fit")
    model = load_model("anny")
    faces = np.asarray(model.faces)
    v2v, v2v_mean, place, place_tpl = [], [], [], []
    tpl = template_placement(model, "plug-in-gait")
    for sid in recipe.subjects:
        sf = ShapeFit.load(out / sid / "shape_fit")
        true_betas = np.load(gt / "subjects" / f"{sid}.npz")["betas"]
        v2v.append(v2v_mm(model, true_betas, sf.betas))
        v2v_mean.append(v2v_mm(model, true_betas, np.zeros(1)))
        rest = rest_state(model, true_betas).vertices[0]
        truth = template_placement(model, load_json(gt / "subjects" / f"{sid}_markers.json",
                                                    num_faces=len(faces)))
        p_true = shape.marker_rest_points(rest, faces, truth)
        p_fit = shape.marker_rest_points(rest, faces, shape.placement_of(sf))
        place.append(np.linalg.norm(p_fit - p_true, axis=1).mean() * 1000)
        place_tpl.append(np.linalg.norm(shape.marker_rest_points(rest, faces, tpl) - p_true,
                                        axis=1).mean() * 1000)
    return {"shape_fit.v2v_markers_mm": float(np.mean(v2v)),
            "shape_fit.v2v_mean_body_mm": float(np.mean(v2v_mean)),
            "shape_fit.placement_mm": float(np.mean(place)),
            "shape_fit.placement_template_mm": float(np.mean(place_tpl))}


def _run_studio(recipe, gt: Path) -> dict[str, float]:
    """Every subject of a generated studio session: its scan fitted, v2v vs the true betas in
    the neutral pose."""
    from body import load_model
    from fitting import shape
    from formats.scan import read_scan

    model = load_model("anny")
    rng = np.random.default_rng(SEED)
    opts = shape.ShapeFitOptions(frames=PLACEMENT_FRAMES)
    v2v, dist, secs = [], [], 0.0
    for sid, subj in recipe.subjects.items():
        if subj.scan is None:
            continue
        pts, nrm = read_scan(subj.scan)
        t0 = time.perf_counter()
        betas, rep = shape.shape_from_scan(model, pts, nrm, opts, rng)
        secs += time.perf_counter() - t0
        v2v.append(v2v_mm(model, np.load(gt / "subjects" / f"{sid}.npz")["betas"], betas))
        dist.append(rep["scan_to_model_mm"]["median"])
    return {"shape_fit.v2v_mm": float(np.mean(v2v)),
            "shape_fit.scan_to_model_mm": float(np.mean(dist)),
            "shape_fit.scan_fit_s": secs / max(len(v2v), 1),
            "shape_fit.studio_subjects": float(len(v2v))}
