"""Marker placement and shape from markers (fitting/placement.py, MoSh stage I) on hard
synthetic captures: a subject drawn like the studio's, the Plug-in Gait template slid 2-3 cm
per marker, skin offsets 5-25 mm, soft-tissue motion of 3 mm, 1 mm noise, gaps, a ghost
marker 5 m off for a few frames and a label swap for 10 frames."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.cases.shape_fit import v2v_mm

GHOST_MARKER, SWAP = "LKNE", ("LWRA", "RWRA")


def slid_placement(model, tpl, rng, slide_m=(0.02, 0.03), offset_m=(0.005, 0.025)):
    """The template moved tangentially by ``slide_m`` (uniform magnitude, random direction) on
    the mean body and given offsets uniform in ``offset_m``."""
    from body.lbs import rest_state
    from fitting import placement as P
    from geometry import face_normals

    rest = rest_state(model, np.zeros(1)).vertices[0]
    faces = np.asarray(model.faces)
    s0 = P.surface_points(rest, faces, tpl)
    n = face_normals(rest, faces[tpl.face])
    d = rng.normal(size=s0.shape)
    d -= np.einsum("md,md->m", d, n)[:, None] * n
    d *= (rng.uniform(*slide_m, len(d)) / np.linalg.norm(d, axis=1))[:, None]
    f, b, _ = P.project_to_surface(rest, faces, s0 + d)
    return P.Placement(tpl.names, f, b, rng.uniform(*offset_m, len(f)))


def hard_capture(model, rng, F=240, fps=60.0, ghost=(100, 106), swap=(150, 160)):
    """(obs (F, M, 3) with NaN gaps, true betas, true placement, skel, true poses)."""
    from bench import fitting_synth as S
    from body.lbs import rest_state
    from fitting import shape, skinned

    betas = S.subject_betas(model, rng)
    skel = skinned.fit_skeleton(model, shape.body_joints(model))
    tpl, _ = S.template(model)
    pl = slid_placement(model, tpl, rng)
    X = S.motion(skel, F, fps, rng)
    rest = rest_state(model, betas)
    true = S.true_markers(model, S.posed(model, betas, skel, X, rest).vertices, pl)
    t = np.arange(F)[:, None, None] / fps  # soft tissue: 3 mm smooth wobble per marker
    M = len(pl.names)
    true = true + 0.003 * np.sin(2 * np.pi * rng.uniform(0.5, 2, (1, M, 3)) * t
                                 + rng.uniform(0, 2 * np.pi, (1, M, 3)))
    obs, _ = S.observe(true, rng)
    g = pl.names.index(GHOST_MARKER)
    obs[ghost[0]:ghost[1], g] = true[ghost[0]:ghost[1], g] + [5.0, 0.0, 0.0]
    a, b = pl.names.index(SWAP[0]), pl.names.index(SWAP[1])
    obs[swap[0]:swap[1], [a, b]] = obs[swap[0]:swap[1], [b, a]]
    return obs, betas, pl, skel, X


def test_a_surface_tree_projects_as_libigls_own_query_does(anny):
    """project_to_surface (one libigl AABB tree per rest mesh, fitting.placement.surface_tree,
    built once or per call) finds the faces and closest points that libigl's one-off query
    (igl.point_mesh_squared_distance, the peer) finds, one point or many."""
    import igl

    from body.lbs import rest_state
    from fitting import placement as P

    rest = rest_state(anny, np.zeros(1)).vertices[0]
    faces = np.asarray(anny.faces)
    rng = np.random.default_rng(3)
    pts = rest[rng.integers(0, len(rest), 40)] + rng.normal(0, 0.03, (40, 3))
    tree = P.surface_tree(rest, faces)
    for q in (pts, pts[7:8]):
        _, want_f, want_c = igl.point_mesh_squared_distance(q, rest, faces)
        for t in (None, tree):
            f, bary, off = P.project_to_surface(rest, faces, q, t)
            np.testing.assert_array_equal(f, want_f)
            surf = np.einsum("mk,mkd->md", bary, rest[faces[f]])
            np.testing.assert_allclose(surf, want_c, atol=1e-9)
            assert np.all(np.abs(off) <= np.linalg.norm(q - surf, axis=1) + 1e-12)


@pytest.fixture(scope="module")
def hard_fit(anny):
    from bench import fitting_synth as S
    from fitting import shape

    rng = np.random.default_rng(0)
    obs, betas, pl, skel, _ = hard_capture(anny, rng)
    tpl, _ = S.template(anny)
    out, rep = shape.fit_shape(anny, tpl, None, [obs], shape.ShapeFitOptions(), rng,
                               names=["take"])
    return out, rep, betas, pl, tpl


def test_shape_and_placement_from_a_hard_capture(anny, hard_fit):
    """Measured (seed 0, 240 frames, ~22 s on a shared core): v2v 16.3 mm in pose 0 (the mean
    body: 18.2; ``bench.cases.shape_fit.v2v_mm``. In the template space the helper measured
    before session 28: 17.1, 20.4 before the placement update was linearised at the current
    skin point, the mean body 16.4 -- there the marker-based shape did not beat the mean: the
    size grid picks beta 0 and 1 by the placement-frame residual and the free placement
    absorbs part of the size),
    placement error 25.5 mm mean against the template's 27.1, residual median 3.4 mm, largest
    slide 60 mm (the true slides are 20-30 mm; the cap is 200 mm, held on the segment); the
    ghost frames 100-105 are not chosen, no marker leaves its segment, every offset in
    [0, 35] mm."""
    import json

    from body.lbs import rest_state
    from fitting import shape

    out, rep, betas, pl, tpl = hard_fit
    json.dumps(rep, allow_nan=False)  # every float finite
    assert rep["shape_source"] == "markers" and len(out.betas) == 30
    assert v2v_mm(anny, betas, out.betas) < 19.0
    rest = rest_state(anny, betas).vertices[0]
    faces = np.asarray(anny.faces)
    p_true = shape.marker_rest_points(rest, faces, pl)
    err = np.linalg.norm(shape.marker_rest_points(rest, faces, shape.placement_of(out)) - p_true,
                         axis=1).mean() * 1000
    err_tpl = np.linalg.norm(shape.marker_rest_points(rest, faces, tpl) - p_true, axis=1).mean()
    assert err < 26.5 and err < err_tpl * 1000, (err, err_tpl)
    frames = [f["frame"] for f in rep["placement_frames"]]
    assert {f["capture"] for f in rep["placement_frames"]} == {"take"}
    assert not any(100 <= f < 106 for f in frames), frames
    assert rep["markers_off_segment"] == []
    assert max(rep["placement_slide_mm"].values()) <= 80.0
    assert 0.0 <= min(rep["placement_offset_mm"].values())
    assert max(rep["placement_offset_mm"].values()) <= 35.0
    assert rep["placement_residual_mm"]["median"] < 5.0
    assert rep["tracking_residual_mm"]["median"] < 8.0 and rep["tracking_outlier_marker_frames"] > 0


def test_a_marker_started_on_the_wrong_segment_is_flagged(anny):
    """RELB's template put on the back (RBAK's face): the capture's elbow lies on the arm,
    two segments from the trunk, so the marker is reported and refitted from the template with
    the tight 5 cm cap, on the trunk or next to it."""
    from dataclasses import replace

    from bench import fitting_synth as S
    from fitting import shape

    rng = np.random.default_rng(2)
    obs, betas, pl, _, _ = hard_capture(anny, rng, F=120, ghost=(40, 43), swap=(60, 70))
    tpl, _ = S.template(anny)
    i, j = tpl.names.index("RELB"), tpl.names.index("RBAK")
    face, bary = tpl.face.copy(), tpl.bary.copy()
    face[i], bary[i] = face[j], bary[j]
    wrong = replace(tpl, face=face, bary=bary)
    out, rep = shape.fit_placement(anny, shape.to_shape_fit(betas[:30], wrong, "scan", "template"),
                                   [obs], shape.ShapeFitOptions(frames=8))
    assert "RELB" in rep["markers_off_segment"], rep["markers_off_segment"]
    assert rep["placement_slide_mm"]["RELB"] <= 50.5
    from fitting import placement as P
    from fitting import skinned

    skel = skinned.fit_skeleton(anny, shape.body_joints(anny))
    groups = P.segment_groups(skel)
    seg = P.marker_segments(anny, skel, shape.placement_of(out), groups)[i]
    seg0 = P.marker_segments(anny, skel, wrong, groups)[i]
    assert P.same_or_adjacent(groups[1], np.array([seg]), np.array([seg0]))[0]
    assert len(rep["markers_off_segment"]) <= 3


REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "real" / "pycgm_movement_trial.c3d"


@pytest.mark.slow
@pytest.mark.skipif(not REAL.exists(), reason="public capture ../shared/real not present")
def test_real_capture_placement(anny):
    """The first 300 frames of the public Plug-in Gait capture (pyCGM, 120 Hz): no marker
    flagged off its segment (this lab puts the tibia markers ~16 cm above the template's:
    they slide along the shank, not off it) and the placement frames fit to < 4 mm median
    (measured 2.7 mm on the whole trial with its static trial)."""
    from bench import fitting_synth as S
    from fitting import shape
    from formats.c3d import read_c3d

    tpl, _ = S.template(anny)
    m = read_c3d(REAL, markers=list(tpl.names), allow_missing=True)
    obs = np.asarray(m.xyz, float)[:300]
    _, rep = shape.fit_shape(anny, tpl, None, [obs], shape.ShapeFitOptions(),
                             np.random.default_rng(0), names=["movement"])
    assert rep["markers_off_segment"] == [], rep["markers_off_segment"]
    assert rep["placement_residual_mm"]["median"] < 4.0, rep["placement_residual_mm"]["median"]
