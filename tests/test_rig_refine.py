"""The rig refined from the person (``calib.rig_refine``, stage ``rig``): a synthetic rig whose
given extrinsics are perturbed is recovered from 2D observations of moving unknown points, the
gauge stays the given calibration's; the refinement uses only its own frames and the held-out
view scores only the others; bad options and recipes fail naming the field."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from calib import Camera, look_at, project
from calib.rig_refine import PersonRefineOptions, refine_from_points, rodrigues, umeyama

rng_seed = 3


def _rig() -> list[Camera]:
    """Four cameras 4 m around the volume's centre, 1.5 m up, looking at it."""
    cams = []
    for i, a in enumerate(np.radians([20, 110, 200, 290])):
        eye = np.array([4 * np.cos(a), 4 * np.sin(a), 1.5 + 0.2 * i])
        cams.append(look_at(f"c{i}", eye, np.array([0, 0, 1.0]), f=(1200.0, 1200.0),
                            c=(640.0, 480.0), width=1280, height=960, k=(-0.05, 0.01, 0.0)))
    return cams


def _perturbed(cams, rng) -> list[Camera]:
    """Each camera's rotation turned by ~0.8 deg and its centre moved by ~25 mm."""
    out = []
    for c in cams:
        w = rng.normal(size=3)
        w *= np.radians(0.8) / np.linalg.norm(w)
        d = rng.normal(size=3)
        d *= 0.025 / np.linalg.norm(d)
        out.append(Camera(c.name, c.f, c.c, c.k, c.p, rodrigues(w) @ c.R, c.T + d,
                          c.width, c.height, c.model))
    return out


def _moving_points(rng, frames=30, k=20):
    """(frames * k, 3): a cloud of k points (a person-sized box) walking across the volume."""
    body = rng.uniform([-0.25, -0.15, 0.0], [0.25, 0.15, 1.8], size=(k, 3))
    path = np.linspace([-1.0, -0.5, 0.0], [1.0, 0.6, 0.0], frames)
    return (path[:, None] + body[None]).reshape(-1, 3)


def _observe(cams, X, rng, noise_px=0.5):
    uv = np.stack([project(c, X) for c in cams]) + rng.normal(scale=noise_px, size=(len(cams), len(X), 2))
    uv[rng.random(uv.shape[:2]) < 0.1] = np.nan  # some detections missing
    return uv


def _align(cams, ref):
    """``cams`` moved by the similarity that maps their centres onto ``ref``'s."""
    from calib.rig_refine import apply_similarity

    s, Q, t = umeyama(np.array([c.T for c in cams]), np.array([c.T for c in ref]))
    return apply_similarity(cams, np.zeros((1, 3)), s, Q, t)[0]


def _angle(A, B):
    from calib.rig_refine import rotation_angle_deg

    return rotation_angle_deg(A, B)


def test_refinement_recovers_perturbed_extrinsics_and_keeps_the_gauge():
    rng = np.random.default_rng(rng_seed)
    truth = _rig()
    given = _perturbed(truth, rng)
    X = _moving_points(rng)
    uv = _observe(truth, X, rng)
    r = refine_from_points(given, uv, PersonRefineOptions(sigma_rotation_deg=2.0,
                                                          sigma_position_mm=60.0))
    # before: the perturbation is visible (several px); after: the noise (0.5 px)
    assert np.nanmedian(r.before_px) > 4.0
    assert np.nanmedian(r.after_px) < 0.8
    # recovered up to the gauge: aligned to the truth by a similarity, within 5 mm / 0.1 deg
    # (the given rig is 25 mm / 0.8 deg off)
    al = _align(list(r.cameras), truth)
    for a, t, g in zip(al, truth, given, strict=True):
        assert np.linalg.norm(a.T - t.T) < 0.005, (a.name, a.T - t.T)
        assert _angle(a.R, t.R) < 0.1
        assert np.linalg.norm(g.T - t.T) > 0.02 and _angle(g.R, t.R) > 0.7  # it had moved
    # the gauge: the refined centres have the given centres' centroid, scale and orientation
    C0, C1 = np.array([c.T for c in given]), np.array([c.T for c in r.cameras])
    np.testing.assert_allclose(C1.mean(0), C0.mean(0), atol=1e-9)
    s, Q, t = umeyama(C1, C0)
    assert abs(s - 1) < 1e-9 and np.allclose(Q, np.eye(3), atol=1e-9) and np.linalg.norm(t) < 1e-9
    # the report: how far each camera moved, ~ the perturbation
    assert np.all((r.moved_mm > 5) & (r.moved_mm < 80)) and np.all(r.rotated_deg < 2)


def test_prior_holds_a_camera_its_detections_do_not_move():
    """With a very tight prior the cameras stay put (the prior is to the given calibration)."""
    rng = np.random.default_rng(rng_seed + 1)
    truth = _rig()
    given = _perturbed(truth, rng)
    uv = _observe(truth, _moving_points(rng), rng)
    r = refine_from_points(given, uv, PersonRefineOptions(sigma_rotation_deg=1e-4,
                                                          sigma_position_mm=1e-3))
    assert np.all(r.moved_mm < 0.1) and np.all(r.rotated_deg < 1e-3)


def _keypoints(cams, rng, frames):
    """A Keypoints2D-like (kp (C, F, 2, 65, 3), frames) of one person (slot 0) whose 65
    keypoints move across the volume, seen exactly by ``cams``."""
    F = len(frames)
    X = _moving_points(rng, frames=F, k=65).reshape(F, 65, 3)
    kp = np.zeros((len(cams), F, 2, 65, 3))
    for i, c in enumerate(cams):
        kp[i, :, 0, :, :2] = project(c, X)
        kp[i, :, 0, :, 2] = 0.9
    return SimpleNamespace(kp=kp, frames=np.asarray(frames, np.int64))


def test_refinement_frames_and_scored_frames_are_disjoint_and_scored_frames_unused():
    from stages.heldout import scored_frames
    from stages.rig import Options, compute, refinement_frames

    rng = np.random.default_rng(rng_seed + 2)
    truth = _rig()
    given = _perturbed(truth, rng)
    frames = np.arange(3, 63)  # video frames 3..62
    kp = _keypoints(truth, rng, frames)
    o = Options(block=10, sigma_rotation_deg=2.0, sigma_position_mm=60.0)
    r1, used, rep = compute(given, kp, o)
    np.testing.assert_array_equal(used, [f for f in frames if (f // 10) % 2 == 0])
    assert rep["frames_used"] == used.tolist()
    # the held-out view scores none of them
    idx = scored_frames(frames, 2, None, exclude=used)
    assert len(idx) and not np.isin(frames[idx], used).any()
    assert np.all((frames[idx] // 10) % 2 == 1)
    assert len(scored_frames(frames, 2)) > len(idx)  # without the rig every stride frame
    # detections of the scored frames (odd blocks) wrecked: the refinement does not change
    bad = SimpleNamespace(kp=kp.kp.copy(), frames=kp.frames)
    odd = ~refinement_frames(frames, 10)
    bad.kp[1, odd, 0, :, :2] += 150.0
    r2, used2, _ = compute(given, bad, o)
    np.testing.assert_array_equal(used2, used)
    for a, b in zip(r1.cameras, r2.cameras, strict=True):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.T, b.T, atol=1e-12)
    # and the refined rig is the true one up to the gauge
    for a, t in zip(_align(list(r1.cameras), truth), truth, strict=True):
        assert np.linalg.norm(a.T - t.T) < 0.005 and _angle(a.R, t.R) < 0.1
    assert rep["applied"] and rep["check"]["refined_px"] < 0.5 * rep["check"]["given_px"]


def test_an_exact_rig_whose_check_does_not_improve_stays_as_calibrated():
    """Detections of an exact rig with noise: refined on half of the refinement frames, the
    other half's leave-one-camera-out error does not drop by min_gain: the rig is kept."""
    from stages.rig import Options, compute

    rng = np.random.default_rng(rng_seed + 4)
    truth = _rig()
    frames = np.arange(0, 80)
    kp = _keypoints(truth, rng, frames)
    kp.kp[..., :2] += rng.normal(scale=3.0, size=kp.kp[..., :2].shape)
    r, _, rep = compute(truth, kp, Options(block=10))
    assert rep["applied"] is False and rep["check"]["passed"] is False
    assert rep["check"]["refined_px"] > 0.95 * rep["check"]["given_px"]
    for a, t in zip(r.cameras, truth, strict=True):
        assert a is t
    assert all(v["moved_mm"] == 0 for v in rep["cameras"].values())


@pytest.mark.parametrize("raw, field", [
    ({"block": 0}, "block"),
    ({"sigma_rotation_deg": -1.0}, "sigma_rotation_deg"),
    ({"keypoints": "feet"}, "keypoints"),
    ({"loss": "l3"}, "loss"),
    ({"min_views": 1}, "min_views"),
    ({"blocks": 10}, "blocks"),
])
def test_bad_rig_option_names_the_field(raw, field):
    from pipeline.plan import PlanError, validate_params
    from stages.rig import STAGE

    with pytest.raises(PlanError) as e:
        validate_params(STAGE, raw, "r.yaml: stages.rig")
    assert "stages.rig" in str(e.value) and field in str(e.value)


def _recipe(tmp_path, **seq):
    (tmp_path / "d").mkdir()
    for n in ("c1.mp4", "c2.mp4", "c1.json", "c2.json"):
        (tmp_path / "d" / n).write_text("x")
    s = {"people": ["a"], "videos": {c: f"d/{c}.mp4" for c in ("c1", "c2")},
         "calibration": {c: f"d/{c}.json" for c in ("c1", "c2")}, **seq}
    r = {"session": "t", "cameras": ["c1", "c2"], "subjects": {"a": {"sex": "female"}},
         "sequences": {"s01/Walk 1": {k: v for k, v in s.items() if v is not None}}}
    p = tmp_path / "r.yaml"
    p.write_text(yaml.safe_dump(r))
    return p


def test_recipe_refine_rig_turns_the_stage_on_and_bad_values_name_the_field(tmp_path):
    from recipes import RecipeError, load_recipe
    from stages import applies

    for d in ("on", "off", "bad", "novid"):
        (tmp_path / d).mkdir()
    on = load_recipe(_recipe(tmp_path / "on", refine_rig=True))
    assert on.sequences["s01/Walk 1"].refine_rig and applies(on, "rig", "s01/Walk 1")
    off = load_recipe(_recipe(tmp_path / "off"))
    assert not applies(off, "rig", "s01/Walk 1")
    with pytest.raises(RecipeError) as e:
        load_recipe(_recipe(tmp_path / "bad", refine_rig="sometimes"))
    assert "refine_rig" in str(e.value) and "s01/Walk 1" in str(e.value)
    with pytest.raises(RecipeError) as e:
        load_recipe(_recipe(tmp_path / "novid", refine_rig=True, videos=None, calibration=None))
    assert "sequences.s01/Walk 1.refine_rig" in str(e.value)
