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


def test_fast_refits_match_refitting_the_sequence_per_marker(anny, capture):
    """The default path (every held marker of a frame solved together, each started from its
    own previous frame moved by the full fit's motion) gives the per-marker errors of calling
    ``fit_markers`` once per held marker (``reference=True``) once the reference has settled,
    a misplaced marker (a large held-out error) included: the same frames scored and, from
    the 10th fitted frame on, every error within 0.05 mm (measured: 0.015 mm at most with
    ``REFIT_FTOL`` 3e-4, 0.005 mm with 1e-6). Before,
    the reference is still in its start-up transient (its refit's first frame is searched from
    the initial pose: LTHI 35-37 mm worse in the first two frames, settling over ~8 frames),
    and the default path is not worse there."""
    betas, tpl, m = capture
    clock = mocap.VideoClock(FPS)
    for pl in (_moved(anny, tpl, WRONG, 0.03)[0], tpl):
        sf = to_shape_fit(betas, pl, "given", "given")
        ref = leave_one_out(anny, sf, tpl, m, clock, np.arange(F), held=HELD, stride=2,
                            reference=True)
        new = leave_one_out(anny, sf, tpl, m, clock, np.arange(F), held=HELD, stride=2)
        a, b = ref["error_mm"], new["error_mm"]
        assert np.array_equal(np.isnan(a), np.isnan(b)) and a.shape == (F // 2, len(HELD))
        assert np.nanmax(np.abs(a[10:] - b[10:])) < 0.05, np.abs(a - b)
        assert np.nanmean(b[:10]) <= np.nanmean(a[:10])
        assert new["fps_per_cpu_s"] == pytest.approx(F / new["cpu_s"])
    wrong = _moved(anny, tpl, WRONG, 0.03)[0]
    r = leave_one_out(anny, to_shape_fit(betas, wrong, "given", "given"), tpl, m, clock,
                      np.arange(F), held=[WRONG], stride=2)
    assert r["per_marker"][WRONG]["median_mm"] > 20


def test_batched_refits_take_the_steps_of_lm_solve(anny, capture):
    """``_batched_lm`` solves each held marker's frame problem as ``fitting.lm.solve`` does
    with the same start, options and terms (robust L_3d without the marker, L_theta, L_s
    toward its own previous pose): the same solution to 1e-9, for refits with and without a
    previous frame and with starts of their own or at the full fit."""
    from fitting import lm, terms
    from fitting.loo import LAMBDA_INIT, REFIT_FTOL, _batched_lm, _Refits
    from fitting.marker_fit import DEFAULT_WEIGHTS, MarkerFitOptions

    betas, tpl, m = capture
    sf = to_shape_fit(betas, tpl, "given", "given")
    obs, vis = mocap.video_observations(m, np.arange(F), mocap.VideoClock(FPS))
    R = _Refits(anny, sf, tpl, obs, vis, MarkerFitOptions(), "synth")
    S = R.solver
    f, held = 10, np.array([tpl.names.index(n) for n in HELD])
    v = vis[f].astype(float)
    x_full = S.solve(np.zeros(R.skel.n), obs[f], v, first=True).x
    rng = np.random.default_rng(3)
    K = len(held)
    vk = np.repeat(v[None], K, axis=0)
    vk[np.arange(K), held] = 0.0
    x_prev = x_full + 0.02 * rng.standard_normal((K, len(x_full)))
    has_prev = np.arange(K) % 2 == 0
    x0 = np.repeat(x_full[None], K, axis=0)
    x0[1::2] += 0.03 * rng.standard_normal((len(x0[1::2]), len(x_full)))  # own starts
    got = _batched_lm(S, x_full, x0, obs[f], v, vk, x_prev, has_prev)
    for b in range(K):
        quad = S.quad_prior
        if has_prev[b]:
            quad = quad + terms.quadratic_L_s(len(x_full), np.arange(len(x_full)), x_prev[b],
                                              DEFAULT_WEIGHTS["L_s"])
        S.graph.set_observations(S.p, obs[f], vk[b])
        want = lm.solve(S.graph.fun, S.p, x0[b], row_scale=S.row_scale,
                        groups=S.groups(vk[b], None), quad=quad, box=S.box,
                        opts=lm.LMOptions(max_iters=10 if has_prev[b] else 60,
                                          ftol=REFIT_FTOL, lambda_init=LAMBDA_INIT))
        assert np.max(np.abs(got[b] - want.x)) < 1e-9, (b, np.max(np.abs(got[b] - want.x)))
        assert np.max(np.abs(got[b] - x_full)) > 1e-6  # each problem moved: not a no-op


def test_a_refit_start_moves_with_the_full_fit_across_a_rewrapped_rotation():
    """A refit's start is its previous pose moved as the full fit moved: the full fit's own
    previous pose goes to its new one exactly, and a root turning from 3.13 rad about z to
    3.15 rad (re-wrapped to -3.13) moves a nearby pose by 0.02 rad, not by the 2 pi a sum of
    rotation vectors would add."""
    from body.rotations import rodrigues
    from fitting.loo import _moved_by

    rng = np.random.default_rng(0)
    n = 3 * 22 + 3
    a = 0.5 * rng.standard_normal(n)
    b = a + 0.05 * rng.standard_normal(n)
    assert np.allclose(_moved_by(a[None], a, b)[0], b, atol=1e-12)
    a[:3], b[:3] = [0, 0, 3.13], [0, 0, 3.15 - 2 * np.pi]
    x = a + 0.01 * rng.standard_normal(n)
    y = _moved_by(x[None], a, b)[0]
    turn = rodrigues(y[:3]) @ rodrigues(x[:3]).T  # the root's turn, world frame
    assert np.allclose(turn, rodrigues(np.array([0, 0, 0.02])), atol=1e-9)
    assert np.allclose(y[3:6], x[3:6] + b[3:6] - a[3:6])


def test_refit_rows_rewrap_as_the_marker_fit_does():
    """The refits' poses are re-wrapped row by row exactly as ``fitting.marker_fit.rewrap``
    re-wraps one pose (every rotation vector to an angle <= pi)."""
    from fitting.loo import _rewrap_rows
    from fitting.marker_fit import rewrap

    X = 3.0 * np.random.default_rng(1).standard_normal((20, 3 * 22 + 3))
    Y = _rewrap_rows(X)
    assert np.array_equal(Y, np.stack([rewrap(x) for x in X]))
    assert not np.array_equal(Y, X)  # some rotations were past pi


def test_the_graph_is_built_once_per_thread_and_reused_with_the_same_numbers(anny, capture,
                                                                             monkeypatch):
    """A second call with the same subject and options in the same thread reuses the compiled
    graph (no MarkerGraph built) and gives the held-out errors of the first bit for bit; a
    call in another thread builds its own (a graph's buffers are not shared between threads);
    another compile mode is another graph."""
    import threading

    from fitting import loo
    from fitting import marker_graph as MG
    from fitting.marker_fit import MarkerFitOptions

    built = []

    class Counting(MG.MarkerGraph):
        def __init__(self, *a, **k):
            built.append(threading.get_ident())
            super().__init__(*a, **k)

    monkeypatch.setattr(MG, "MarkerGraph", Counting)
    monkeypatch.setattr(loo, "_GRAPHS", threading.local())
    betas, tpl, m = capture
    sf = to_shape_fit(betas, tpl, "given", "given")

    six = MarkerFitOptions(max_frames=6)

    def call(opts=six):
        return leave_one_out(anny, sf, tpl, m, mocap.VideoClock(FPS), np.arange(F),
                             held=HELD[:2], opts=opts, stride=1)

    a = call()
    assert len(built) == 1
    b = call()
    assert len(built) == 1
    np.testing.assert_array_equal(a["error_mm"], b["error_mm"])
    out = {}
    t = threading.Thread(target=lambda: out.update(r=call()))
    t.start()
    t.join()
    assert len(built) == 2 and built[1] != built[0]
    np.testing.assert_array_equal(out["r"]["error_mm"], a["error_mm"])
    c = call(MarkerFitOptions(max_frames=6, compile="interpreted"))
    assert len(built) == 3
    np.testing.assert_allclose(c["error_mm"], a["error_mm"], rtol=0, atol=1e-6)
