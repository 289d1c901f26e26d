"""Synthetic data for the fitting bench cases (helper, not a case).

A subject drawn like the studio's (anny phenotypes and a few body sliders -> exact betas), the
built-in Plug-in Gait marker set, each marker slid a few millimetres from its
template as a lab places them, a smooth motion of the fitted body joints, and markers as an
optical system records them (posed surface point + offset along the posed face normal,
1 mm noise, occlusion gaps).
"""
from __future__ import annotations

import numpy as np

from body.lbs import forward, rest_state
from body.rotations import rodrigues
from fitting import shape, skinned
from fitting.marker_graph import template_placement
from geometry import face_normals

MARKER_NOISE_SD_M = 0.001 / 3 ** 0.5  # ~1 mm 3D RMS
SLIDE_SD_M, OFFSET_SD_M = 0.004, 0.001


def subject_betas(model, rng) -> np.ndarray:
    from body.anny import betas_from_anny

    ph = np.array([rng.uniform(0, 1), rng.uniform(0.45, 0.6), rng.uniform(0.35, 0.7),
                   rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.8), rng.uniform(0.35, 0.65)])
    L = len(model.extras["local_change_labels"])
    lc = np.zeros(L)
    pick = rng.choice(L, size=6, replace=False)
    lc[pick] = rng.uniform(-0.5, 0.5, 6)
    return betas_from_anny(model, ph, lc)


def template(model) -> tuple[shape.Placement, str]:
    """The built-in Plug-in Gait template placement on ``model`` and its name."""
    return template_placement(model, "plug-in-gait"), "plug-in-gait"


def slide(model, pl: shape.Placement, rng) -> shape.Placement:
    """The template moved on the surface (tangential SLIDE_SD_M) and off it (OFFSET_SD_M)."""
    rest = rest_state(model, np.zeros(1)).vertices[0]
    faces = np.asarray(model.faces)
    p = shape.marker_rest_points(rest, faces, pl)
    n = face_normals(rest, faces[pl.face])
    t = rng.normal(0, SLIDE_SD_M, p.shape)
    t -= np.einsum("md,md->m", t, n)[:, None] * n
    f, b, _ = shape.project_to_surface(rest, faces, p - pl.offset[:, None] * n + t)
    return shape.Placement(pl.names, f, b, pl.offset + rng.normal(0, OFFSET_SD_M, len(pl.face)))


def motion(skel, F: int, fps: float, rng) -> np.ndarray:
    """(F, n) smooth motion: each fitted joint swings around a random posture (<= ~40 deg),
    the body turns and walks."""
    t = np.arange(F)[:, None] / fps
    n = skel.n
    base = rng.normal(0, 0.25, n)
    amp = rng.normal(0, 0.35, n)
    w = rng.uniform(0.5, 2.0, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    X = base + amp * np.sin(2 * np.pi * w * t / 2 + ph)
    X[:, :3] = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]) + t * np.array([0.0, 0.0, 0.4])
    X[:, 3:6] = np.array([0.0, 0.0, 0.0]) + t * np.array([0.5, 0.2, 0.0])
    return X


def posed(model, betas, skel, X, rest=None):
    F = len(X)
    pose = np.zeros((F, model.num_joints, 3))
    pose[:, skel.joints[1:]] = X[:, 6:].reshape(F, -1, 3)
    return forward(model, betas, pose, rodrigues(X[:, :3]), X[:, 3:6], rest=rest)


def true_markers(model, vertices: np.ndarray, pl: shape.Placement) -> np.ndarray:
    """(F, M, 3): posed surface point + offset along the posed face normal."""
    faces = np.asarray(model.faces)
    tri = vertices[:, faces[pl.face]]  # (F, M, 3, 3)
    nrm = face_normals(vertices, faces[pl.face])
    return np.einsum("mk,fmkd->fmd", pl.bary, tri) + pl.offset[None, :, None] * nrm


def observe(markers: np.ndarray, rng, gap_fraction=0.3) -> tuple[np.ndarray, np.ndarray]:
    F, M, _ = markers.shape
    obs = markers + rng.normal(0, MARKER_NOISE_SD_M, markers.shape)
    vis = np.ones((F, M), bool)
    for m in rng.choice(M, int(gap_fraction * M), replace=False):
        L = int(rng.integers(5, max(6, F // 4)))
        s = int(rng.integers(0, max(1, F - L)))
        vis[s:s + L, m] = False
    obs[~vis] = np.nan
    return obs, vis


__all__ = ["subject_betas", "template", "slide", "motion", "posed", "true_markers", "observe",
           "skinned"]


def studio_session():
    """(recipe, data folder) of the first studio preset whose data exist (bench, then demo),
    or None. The data are never generated here (``make bench`` would take the rendering time
    of a whole session); ``python -m studio --preset bench`` makes them."""
    from pathlib import Path

    from recipes import RecipeError, load_recipe

    repo = Path(__file__).resolve().parents[1]
    for name in ("bench", "demo"):
        path = repo / "recipes" / f"{name}.yaml"
        if not path.is_file():
            continue
        try:
            r = load_recipe(path)
        except RecipeError:
            continue  # data not generated
        first = next(iter(r.sequences.values()))
        gt = Path(first.c3d).parents[2] / "gt"
        if gt.is_dir():
            return r, gt
    return None
