"""fitting.loo.leave_one_out on a synthetic capture of Anny (bench/fitting_synth.py): with the
exact placement a held-out marker is predicted to the noise; a marker whose placement is
3 cm off is off by those 3 cm while the others stay small."""
from __future__ import annotations

import numpy as np
import pytest

from fitting import mocap, skinned
from fitting.loo import leave_one_out
from fitting.marker_graph import Placement, marker_rest_points, to_shape_fit
from formats.c3d import Markers
from formats.errors import InputError

F, FPS = 40, 50.0
HELD = ("LTHI", "RFHD", "CLAV", "RASI", "LANK")
WRONG = "LTHI"


@pytest.fixture(scope="module")
def capture(anny):
    from bench import fitting_synth as S
    from fitting import shape as fshape

    rng = np.random.default_rng(11)
    betas = S.subject_betas(anny, rng)
    tpl, _ = S.template(anny)
    skel = skinned.fit_skeleton(anny, fshape.body_joints(anny))
    X = S.motion(skel, F, FPS, rng)
    V = S.posed(anny, betas, skel, X).vertices
    obs, _ = S.observe(S.true_markers(anny, V, tpl), rng, gap_fraction=0.0)  # 1 mm noise
    return betas, tpl, Markers(tpl.names, obs, FPS, 0, "Synth")


def _moved(model, pl: Placement, name: str, dist: float) -> tuple[Placement, float]:
    """``pl`` with marker ``name`` slid ``dist`` along the rest surface (mean shape); returns
    the placement and how far its rest point actually moved (metres)."""
    from body.lbs import rest_state
    from fitting import shape as fshape
    from geometry import face_normals

    rest = rest_state(model, np.zeros(1)).vertices[0]
    faces = np.asarray(model.faces)
    k = pl.names.index(name)
    p = marker_rest_points(rest, faces, pl)
    n = face_normals(rest, faces[pl.face])[k]
    t = np.cross(n, [0.0, 0.0, 1.0])  # horizontal, tangent to the skin
    q = p.copy()
    q[k] += dist * t / np.linalg.norm(t) - pl.offset[k] * n
    f, b, _ = fshape.project_to_surface(rest, faces, q[[k]])
    face, bary = pl.face.copy(), pl.bary.copy()
    face[k], bary[k] = f[0], b[0]
    out = Placement(pl.names, face, bary, pl.offset.copy())
    return out, float(np.linalg.norm(marker_rest_points(rest, faces, out)[k] - p[k]))


def test_exact_placement_predicts_held_markers_to_the_noise(anny, capture):
    betas, tpl, m = capture
    r = leave_one_out(anny, to_shape_fit(betas, tpl, "given", "given"), tpl, m,
                      mocap.VideoClock(FPS), np.arange(F), held=HELD, stride=1)
    assert set(r["per_marker"]) == set(HELD)
    for name, s in r["per_marker"].items():
        assert s["frames"] == F
        assert s["median_mm"] < 5.0, (name, s)  # measured 1.5-3.2 mm (1 mm noise)
    assert r["median_mm"] < 4.0 and r["p90_mm"] < 10.0
    assert r["cpu_s"] > 0 and r["stride"] == 1 and r["fitted_frames"] == F
    # stride 2 fits every other frame, scores half of them
    r2 = leave_one_out(anny, to_shape_fit(betas, tpl, "given", "given"), tpl, m,
                       mocap.VideoClock(FPS), np.arange(F), held=HELD[:1], stride=2)
    assert r2["per_marker"][HELD[0]]["frames"] == F // 2 and r2["per_marker"][HELD[0]]["median_mm"] < 5.0


def test_a_wrong_placement_shows_in_its_own_marker_only(anny, capture):
    betas, tpl, m = capture
    wrong, moved = _moved(anny, tpl, WRONG, 0.03)
    assert 0.025 < moved < 0.035
    r = leave_one_out(anny, to_shape_fit(betas, wrong, "given", "given"), tpl, m,
                      mocap.VideoClock(FPS), np.arange(F), held=HELD, stride=1)
    s = r["per_marker"][WRONG]
    assert abs(s["median_mm"] - 1000 * moved) < 6.0, (s, moved)
    for name in HELD:
        if name != WRONG:
            # measured 1.8-4.6 mm
            assert r["per_marker"][name]["median_mm"] < 7.0, (name, r["per_marker"][name])


def test_bad_held_names_and_stride(anny, capture):
    betas, tpl, m = capture
    sf = to_shape_fit(betas, tpl, "given", "given")
    with pytest.raises(InputError, match="held"):
        leave_one_out(anny, sf, tpl, m, mocap.VideoClock(FPS), np.arange(F), held=["NOPE"])
    with pytest.raises(ValueError, match="stride"):
        leave_one_out(anny, sf, tpl, m, mocap.VideoClock(FPS), np.arange(F), stride=0)


def test_refits_run_with_the_given_marker_fit_options(anny, capture):
    """The refits use the options passed (the recipe's stages.marker_fit): ``max_frames``
    limits the frames fitted, and a pose prior weighted to pin the pose at zero makes the
    held-out markers far worse than the default options do."""
    from fitting.marker_fit import MarkerFitOptions

    betas, tpl, m = capture
    sf = to_shape_fit(betas, tpl, "given", "given")
    r = leave_one_out(anny, sf, tpl, m, mocap.VideoClock(FPS), np.arange(F), held=HELD[:2],
                      opts=MarkerFitOptions(max_frames=8), stride=1)
    assert r["fitted_frames"] == 8 and r["per_marker"][HELD[0]]["frames"] == 8
    assert r["median_mm"] < 5.0
    stiff = leave_one_out(anny, sf, tpl, m, mocap.VideoClock(FPS), np.arange(F), held=HELD[:2],
                          opts=MarkerFitOptions(max_frames=8, weights={"L_theta": 10.0}),
                          stride=1)
    assert stiff["median_mm"] > 3 * r["median_mm"], (stiff["median_mm"], r["median_mm"])


def test_refits_set_up_once_match_fit_markers_per_marker(anny, capture):
    """The default path (graph, solver and subject set up once for every held marker) gives
    the numbers of calling ``fit_markers`` once per held marker (``reference=True``), frame by
    frame, a misplaced marker (a large held-out error) included."""
    betas, tpl, m = capture
    wrong, _ = _moved(anny, tpl, WRONG, 0.03)
    sf = to_shape_fit(betas, wrong, "given", "given")
    clock = mocap.VideoClock(FPS)
    ref = leave_one_out(anny, sf, tpl, m, clock, np.arange(F), held=HELD, stride=2,
                        reference=True)
    new = leave_one_out(anny, sf, tpl, m, clock, np.arange(F), held=HELD, stride=2)
    assert np.array_equal(np.isnan(ref["error_mm"]), np.isnan(new["error_mm"]))
    assert np.nanmax(np.abs(ref["error_mm"] - new["error_mm"])) < 1e-6
    assert ref["per_marker"][WRONG]["median_mm"] > 20
    assert new["fps_per_cpu_s"] == pytest.approx(F / new["cpu_s"])
