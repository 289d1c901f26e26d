"""Body model speed: numpy forward of the full Anny mesh.

Keys:
- ``body.forward_ms``: one frame, full mesh (13,718 vertices, 104 joints), numpy, shape part
  precomputed (``rest_state`` once per subject, as the pipeline does);
- ``body.forward_batch_ms``: per frame, 100 frames in one call;
- ``body.rest_state_ms``: the shape part for 404 betas (once per subject);
- ``body.slot_graph_build_s``: building the CasADi marker graph (39 Plug-in Gait markers as
  surface points, ``fitting.marker_graph.MarkerGraph``, 52 fit joints, shape fixed,
  interpreted: the symbolic residual and Jacobian, no C compile).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

GOALS = {"body.forward_ms": ("<=", 2.0)}


def _best_ms(f, n: int) -> float:
    best = float("inf")
    for _ in range(5):
        t = time.perf_counter()
        for _ in range(n):
            f()
        best = min(best, (time.perf_counter() - t) / n * 1e3)
    return best


def run(work: Path) -> dict[str, float]:  # noqa: ARG001 (bench contract)
    from body import forward, load_model, rest_state
    from body.rotations import rodrigues
    from fitting import compiled, skinned
    from fitting.marker_graph import GraphSpec, MarkerGraph, marker_support, template_placement

    model = load_model("anny")
    rng = np.random.default_rng(0)
    betas = rng.normal(size=model.num_betas)
    rest = rest_state(model, betas)
    pose = rng.normal(0, 0.2, (1, model.num_joints, 3))
    R, T = rodrigues(rng.normal(size=(1, 3))), rng.normal(size=(1, 3))
    poses = rng.normal(0, 0.2, (100, model.num_joints, 3))
    Rs, Ts = rodrigues(rng.normal(size=(100, 3))), rng.normal(size=(100, 3))
    res = {
        "body.forward_ms": _best_ms(lambda: forward(model, None, pose, R, T, rest=rest), 50),
        "body.forward_batch_ms": _best_ms(lambda: forward(model, None, poses, Rs, Ts, rest=rest), 1) / 100,
        "body.rest_state_ms": _best_ms(lambda: rest_state(model, betas), 3),
    }
    t = time.perf_counter()
    skel = skinned.fit_skeleton(model)
    spec = GraphSpec(skel.topology, marker_support(model, skel, template_placement(model, "plug-in-gait")))
    MarkerGraph(spec, compiled.CompileOptions(mode="interpreted"))
    res["body.slot_graph_build_s"] = time.perf_counter() - t
    return res
