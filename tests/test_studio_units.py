"""Unit tests of the studio's parts (no session generated): plan and recipes, camera rig,
inverse kinematics, scans, marker noise and gaps, contact runs (the renderer's tests are in
``tests/test_drawing.py``)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from tests.conftest import REPO


# ------------------------------------------------------------------------------ plan / recipes
def test_plan_alternates_marker_wearer_and_validates():
    from recipes.schema import Session
    from studio import plan as PL

    plan = PL.make_plan(3, 40, PL.parse_scenarios("hug,handshake,kick,hug"))
    wearers = [s.markers_on for s in plan.sequences]
    assert wearers == [plan.subjects[0], plan.subjects[1], plan.subjects[0], plan.subjects[1]]
    assert [s.partner for s in plan.sequences] == [plan.subjects[1], plan.subjects[0]] * 2
    assert [s.action for s in plan.sequences] == ["Hug 1", "Handshake 1", "Kick 1", "Hug 2"]
    assert all(s.text.endswith(".") and len(s.text.split()) >= 6 for s in plan.sequences)
    s = Session.model_validate(PL.recipe_dict(plan))
    assert set(s.sequences) == {f"s01/{a}" for a in ("Hug 1", "Handshake 1", "Kick 1", "Hug 2")}
    assert s.sequences["s01/Hug 1"].mocap.sync_offset_s == pytest.approx(plan.sync_offset_s)
    with pytest.raises(ValueError, match="unknown scenario 'dance'"):
        PL.parse_scenarios("hug,dance")


def test_plan_is_deterministic_and_seeded():
    from studio import plan as PL

    a, b = PL.make_plan(5, 30, ("push", "grab")), PL.make_plan(5, 30, ("push", "grab"))
    assert a == b
    texts = {tuple(s.text for s in PL.make_plan(seed, 30, ("push", "grab", "hit")).sequences)
             for seed in range(6)}
    assert len(texts) > 1


@pytest.mark.parametrize("preset", ["demo", "bench"])
def test_committed_preset_recipes_match_the_studio(preset):
    from studio import preset_recipe

    path = REPO / "recipes" / f"{preset}.yaml"
    raw = yaml.safe_load(path.read_text())
    want = preset_recipe(preset, path.parent, REPO / "data" / preset)
    raw.pop("stages", None)
    want.pop("stages", None)
    assert raw == want, f"rewrite with: python -m studio --preset {preset} --out data/{preset} --write-recipe {path}"


def test_ensure_generated_refuses_foreign_or_stale_recipes(tmp_path):
    from recipes import RecipeError
    from studio import ensure_generated

    demo = yaml.safe_load((REPO / "recipes" / "demo.yaml").read_text())
    foreign = dict(demo, session="lab_2024")
    p = tmp_path / "foreign.yaml"
    p.write_text(yaml.safe_dump(foreign))
    with pytest.raises(RecipeError, match="not a studio preset"):
        ensure_generated(p)
    stale = dict(demo)
    stale["sequences"] = dict(demo["sequences"])
    k = next(iter(stale["sequences"]))
    stale["sequences"][k] = dict(stale["sequences"][k], text="something else")
    p2 = tmp_path / "stale.yaml"
    p2.write_text(yaml.safe_dump(stale))
    with pytest.raises(RecipeError, match="does not match"):
        ensure_generated(p2)
    assert not any(tmp_path.glob(".*tmp*"))


# ------------------------------------------------------------------------------ cameras
def test_rig_surrounds_the_capture_volume():
    from calib import project
    from studio import constants as C
    from studio.rig import make_rig

    cams = make_rig(np.random.default_rng(0))
    assert [c.name for c in cams] == list(C.CAMERA_NAMES)
    centre = np.array([0.0, 0.0, 0.9])
    az = []
    for cam in cams:
        d = np.linalg.norm(cam.T[:2])
        assert C.CAMERA_DISTANCE_M[0] <= d <= C.CAMERA_DISTANCE_M[1]
        uv = project(cam, centre)
        assert np.all(np.abs(uv - 450) < 120), (cam.name, uv)
        # a 1.9 m tall person at the centre fits in the frame
        top, foot = project(cam, np.array([0, 0, 1.9])), project(cam, np.array([0, 0, 0.0]))
        assert 0 < top[1] < foot[1] < 900
        # mild distortion: under 3 % at the image corner
        corner = np.array([[0.0, 0.0]])
        from calib.camera import undistort_pixels

        shift = np.linalg.norm(undistort_pixels(cam, corner) - corner)
        assert 2 < shift < 0.03 * 900 * 1.5
        az.append(np.arctan2(cam.T[1], cam.T[0]))
    gaps = np.diff(np.sort(np.mod(az, 2 * np.pi)))
    assert gaps.min() > np.deg2rad(60)  # spread all around


# ------------------------------------------------------------------------------ kinematics
def test_chain_fk_matches_body_forward(anny):
    from body.lbs import forward_kinematics
    from studio.kin import Person

    rng = np.random.default_rng(0)
    p = Person.make(anny, rng.normal(0, 0.5, 20))
    pose = rng.normal(0, 0.3, (3, anny.num_joints, 3))
    R = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(3)])
    R *= np.sign(np.linalg.det(R))[:, None, None]
    T = rng.normal(0, 1, (3, 3))
    chain = p.chain([anny.joint_index("wrist.L"), anny.joint_index("foot.R")])
    t, G = p.fk_chain(pose, R, T, chain)
    G2, t2, _ = forward_kinematics(anny, p.rest, pose, R, T)
    np.testing.assert_allclose(t[:, chain], t2[:, chain], atol=1e-12)
    np.testing.assert_allclose(G[:, chain], G2[:, chain], atol=1e-12)


def test_ik_puts_the_hand_on_a_target_with_a_hinged_elbow(anny):
    from studio import posture as P
    from studio.kin import Goal, Person, effector, solve_ik

    p = Person.make(anny, np.zeros(10))
    an = P.anatomy(p)
    pose = P.standing(p, an, np.random.default_rng(0))
    R, T = np.eye(3), np.array([0.0, 0.0, p.floor_z])
    wrist = p.j("wrist.R")
    h = an.hands["R"]
    start = effector(p, pose[None], R[None], T[None], wrist, h.palm_offset)[0]
    target = start + np.array([0.05, -0.35, 0.45])  # forward and up, within reach
    dofs = P.arm_dofs(p, an, "R")
    sol = solve_ik(p, pose, R, T, [Goal(wrist, tuple(h.palm_offset), tuple(target))], dofs,
                   iters=40)
    got = effector(p, sol[None], R[None], T[None], wrist, h.palm_offset)[0]
    assert np.linalg.norm(got - target) < 3e-3  # the pose prior keeps ~1 mm
    # only the arm's joints moved, and the elbow is a hinge about its axis
    moved = np.flatnonzero(np.abs(sol - pose).max(1) > 1e-9)
    assert set(moved) <= {d.joint for d in dofs}
    e = sol[p.j("lowerarm01.R")]
    axis = an.elbow_axis["R"]
    assert np.linalg.norm(e - (e @ axis) * axis) < 1e-9


def test_shifted_target_moves_its_base_by_the_offset(anny):
    from studio import posture as P
    from studio.kin import Person
    from studio.motion import Anchor, Fixed, Shifted, Track

    p = Person.make(anny, np.zeros(10))
    pose = P.standing(p, P.anatomy(p), np.random.default_rng(1))
    N = 5
    tr = Track(np.repeat(pose[None], N, 0), np.repeat(np.eye(3)[None], N, 0),
               np.tile([0.3, -0.2, p.floor_z], (N, 1)))
    rng = np.random.default_rng(2)
    shift = rng.normal(0, 0.05, (N, 3))
    idx = np.array([4, 0, 2])
    for base in (Anchor(p.j("wrist.L"), np.array([0.0, 0.02, -0.05]), np.array([1.0, 0.0, 0.0])),
                 Fixed(rng.normal(0, 1, (N, 3)), np.array([0.0, 0.0, 1.0]))):
        pts, nrm = base.world(p, tr, idx)
        got, got_n = Shifted(base, shift).world(p, tr, idx)
        np.testing.assert_allclose(got, pts + shift[idx], atol=1e-12)
        np.testing.assert_allclose(got_n, nrm, atol=1e-12)


def test_holding_hands_arm_swings_in_to_the_middle(anny):
    """The nominal hold pose: the arm swung in from the shoulder until the palm is at the middle
    between the two people (world y = 0), whichever side the partner is on."""
    from studio import posture as P
    from studio.kin import Person, effector
    from studio.motion import make_timeline
    from studio.scenarios import Cast, _swing_in, place

    people = [Person.make(anny, np.zeros(10)), Person.make(anny, np.full(10, 0.3))]
    an = [P.anatomy(q) for q in people]
    tl = make_timeline(10)
    cast = Cast(people, an, tl, np.random.default_rng(0))
    for r, (y, side, toward) in enumerate(((-0.4, "L", 1.0), (0.4, "R", -1.0))):
        base = P.standing(people[r], an[r], np.random.default_rng(r))
        tr = place(people[r], (0, y), (1, 0), cast.N, base)
        h = an[r].hands[side]
        hang = effector(people[r], base[None], tr.R[:1], tr.T[:1], h.wrist, h.palm_offset)[0]
        pose, palm = _swing_in(cast, r, tr, base, side, toward, 0.15, 0.35)
        assert abs(palm[1]) < 0.01, (r, palm)
        # only the arm moved, and the palm went toward the partner, not past the middle
        moved = {int(j) for j in np.flatnonzero(np.abs(pose - base).max(1) > 1e-9)}
        assert moved <= {people[r].j(f"upperarm01.{side}"), people[r].j(f"lowerarm01.{side}")}
        assert abs(palm[1]) < abs(hang[1])
        np.testing.assert_allclose(
            effector(people[r], pose[None], tr.R[:1], tr.T[:1], h.wrist, h.palm_offset)[0], palm,
            atol=1e-9)


def test_palm_facing_turns_only_the_forearm(anny):
    """The hold's palm orientation: a hanging arm's forearm turned (pronation / supination)
    until the palm faces the wanted direction, back or forward."""
    from studio import posture as P
    from studio.kin import FWD, Person
    from studio.motion import make_timeline
    from studio.scenarios import Cast, _palm_facing, place

    person = Person.make(anny, np.zeros(10))
    an = P.anatomy(person)
    cast = Cast([person, person], [an, an], make_timeline(10), np.random.default_rng(0))
    base = P.standing(person, an, np.random.default_rng(1))
    tr = place(person, (0, 0), (1, 0), cast.N, base)
    for side in ("L", "R"):
        h = an.hands[side]
        for want in (tr.R[0] @ FWD, -(tr.R[0] @ FWD)):
            palm_normal = lambda pose: person.fk(pose[None], tr.R[:1], tr.T[:1])[1][0, h.wrist] @ h.normal  # noqa: E731, B023
            assert palm_normal(base) @ want < 0.6  # hanging, the palm faces the thigh
            turned = _palm_facing(cast, 0, tr, base, side, want)
            assert palm_normal(turned) @ want > 0.9, (side, want)  # the forearm is not vertical
            moved = np.flatnonzero(np.abs(turned - base).max(1) > 1e-9)
            assert list(moved) == [person.j(f"lowerarm02.{side}")]


def test_holding_hands_is_led_by_the_shorter_person(anny):
    """Whoever the actor is, the shorter person's hand comes first and lies in front (the
    contact on a fixed target); built with the roles swapped, the contacts and their pole
    targets still refer to the right person."""
    from studio import posture as P
    from studio.kin import Person
    from studio.motion import Fixed, make_timeline
    from studio.scenarios import Cast, holding_hands

    people = [Person.make(anny, np.zeros(10)), Person.make(anny, np.full(10, 0.3))]
    an = [P.anatomy(q) for q in people]
    tall = [float(np.ptp(a.pose0_vertices[:, 2])) for a in an]
    assert abs(tall[0] - tall[1]) > 0.02
    short = int(np.argmin(tall))
    for order in ((0, 1), (1, 0)):
        cast = Cast([people[k] for k in order], [an[k] for k in order], make_timeline(40),
                    np.random.default_rng(0))
        scene = holding_hands(cast)
        lead = next(c for c in scene.contacts if isinstance(c.anchor, Fixed))
        assert cast.people[lead.who] is people[short]
        assert scene.movable == 1 - lead.who
        for c in scene.contacts:
            # the elbow pole is on the contact's own person, at its swung elbow
            j, _, fn, _ = c.poles[0]
            i = int(np.argmax(c.weight))
            tr = scene.nominal[c.who]
            elbow = cast.people[c.who].fk(tr.pose[i:i + 1], tr.R[i:i + 1], tr.T[i:i + 1])[0][0, j]
            assert np.linalg.norm(fn(i, scene.nominal) - elbow) < 0.1


def test_verified_motion_draws_again_until_the_checks_pass(monkeypatch, capsys):
    """A draw that goes through the other body is drawn again; when none passes, the least deep
    one is kept, with a warning."""
    from types import SimpleNamespace

    from studio import session as S
    from studio.contact import MotionCheck

    depth = {0: 0.02, 1: 0.009, 2: 0.001, 3: 0.03}
    calls = []

    def motion(plan, seq, subjects, attempt=0):  # noqa: ARG001
        calls.append(attempt)
        return SimpleNamespace(attempt=attempt, skin=lambda model: [SimpleNamespace(vertices=None)] * 2)

    monkeypatch.setattr(S, "sequence_motion", motion)
    monkeypatch.setattr(S, "check_motion", lambda model, mo, verts=None: MotionCheck(
        np.array([0.0, depth[mo.attempt]]), {"hand": np.array([0.001, 0.002, 0.003])}))
    seq = SimpleNamespace(seq_id="s01/Hug 1")
    mo, chk, attempt, _ = S.verified_motion(None, seq, None, None)
    assert (attempt, calls, chk.ok) == (2, [0, 1, 2], True)
    assert "draw 0 rejected (deepest 20.0 mm, hand touching 1.00)" in capsys.readouterr().out
    depth[2] = 0.008
    calls.clear()
    mo, chk, attempt, _ = S.verified_motion(None, seq, None, None)
    assert (attempt, calls, chk.ok) == (2, [0, 1, 2, 3], False)
    assert "WARNING s01/Hug 1: none of 4 draws" in capsys.readouterr().err


def test_motion_check_needs_depth_and_touching():
    from studio import constants as C
    from studio.contact import MotionCheck

    held = np.array([0.001, 0.002, 0.003, 0.02])
    assert MotionCheck(np.array([0.0, 0.004]), {"a": held}).ok
    assert not MotionCheck(np.array([0.0, 0.006]), {"a": held}).ok
    assert C.MIN_TOUCHING > 0.5
    assert not MotionCheck(np.array([0.0, 0.001]), {"a": np.array([0.001, 0.02, 0.03])}).ok


def test_timeline_maps_video_frames_to_mocap_samples():
    from studio.motion import make_timeline

    tl = make_timeline(30, fps=50, hz=100, sync_offset_s=-0.12)
    vs = tl.video_samples
    assert vs[0] == 12 and np.all(np.diff(vs) == 2) and vs[-1] < tl.n
    # what the pipeline assumes (fitting.mocap.frame_times): frame f at f / fps - offset
    from fitting.mocap import frame_times

    np.testing.assert_allclose(vs / 100.0, frame_times(30, 50, -0.12), atol=1e-12)
    with pytest.raises(ValueError):
        make_timeline(30, fps=50, hz=120, sync_offset_s=0.0)


# ------------------------------------------------------------------------------ scans / markers
def test_scan_has_noise_holes_and_uneven_density(tmp_path):
    import trimesh

    from studio.scan import ScanOptions, sample_scan, write_ply

    sph = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    V = sph.vertices + [0, 0, 0.3]
    holes = np.array([[0.3, 0.0, 0.3], [-0.3, 0.0, 0.3]])
    opts = ScanOptions(n_points=40000)
    pts, nrm = sample_scan(V, sph.faces, holes, np.random.default_rng(0), opts)
    r = np.linalg.norm(pts - [0, 0, 0.3], axis=1) - 0.3
    assert abs(np.std(r) - opts.noise_m) < 0.2 * opts.noise_m  # ~2 mm along the normal
    assert np.all(np.linalg.norm(pts[:, None] - holes[None], axis=2).min(1) > opts.hole_radius_m - 0.01)
    assert not np.any((pts[:, 2] < opts.sole_height_m - 0.005) & (nrm[:, 2] < -0.5))
    # uneven: point density per unit area differs a lot between directions
    d = (pts - [0, 0, 0.3]) / np.linalg.norm(pts - [0, 0, 0.3], axis=1, keepdims=True)
    counts = np.array([np.sum(d @ u > 0.95) for u in np.eye(3)[:2]] +
                      [np.sum(d @ u > 0.95) for u in [np.array([1, 1, 0]) / 2 ** 0.5]])
    assert counts.max() > 1.5 * counts.min()
    path = write_ply(tmp_path / "s.ply", pts, nrm)
    pc = trimesh.load(path)
    np.testing.assert_allclose(np.asarray(pc.vertices), pts, atol=1e-6)


def test_marker_noise_and_occlusion_gaps():
    from studio.mocap import MocapOptions, observe_markers

    true = np.random.default_rng(0).normal(0, 1, (400, 39, 3))
    opts = MocapOptions()
    obs, gap = observe_markers(true, np.random.default_rng(1), opts)
    assert np.array_equal(np.isnan(obs).any(2), gap)
    err = (obs - true)[~gap]
    assert abs(err.std() - opts.noise_sd_m) < 0.1 * opts.noise_sd_m
    affected = gap.any(0)
    assert affected.sum() == round(opts.gap_fraction * 39)
    for m in np.flatnonzero(affected):
        g = np.concatenate([[0], gap[:, m].astype(int), [0]])
        starts, ends = np.flatnonzero(np.diff(g) == 1), np.flatnonzero(np.diff(g) == -1)
        assert np.all(ends - starts >= opts.gap_len[0])
        assert not gap[:, m].all()


def test_longest_run():
    from studio.contact import longest_run

    assert longest_run(np.array([0, 1, 1, 0, 1, 1, 1, 0], bool)) == (4, 6)
    assert longest_run(np.zeros(5, bool)) == (-1, -1)
    assert longest_run(np.ones(3, bool)) == (0, 2)


def test_cli_rejects_bad_input_and_writes_preset_recipes(tmp_path, capsys):
    from studio import preset_recipe
    from studio.__main__ import main

    assert main(["--out", str(tmp_path / "x"), "--scenarios", "hug,dance"]) == 2
    assert "unknown scenario 'dance'" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--frames", "3"]) == 2
    assert not (tmp_path / "x").exists()
    path = tmp_path / "recipes" / "demo.yaml"
    path.parent.mkdir()
    assert main(["--preset", "demo", "--out", str(tmp_path / "data" / "demo"), "--write-recipe", str(path)]) == 0
    raw = yaml.safe_load(path.read_text())
    assert raw == preset_recipe("demo", path.parent, tmp_path / "data" / "demo")
    assert raw["subjects"]["s01a"]["scan"] == "../data/demo/scans/s01a.ply"


def test_ensure_generated_regenerates_data_made_from_another_plan(tmp_path, monkeypatch):
    """All files present but ``gt/session.json`` records another plan of the preset (e.g. an
    older frame count): regenerate; the current plan: keep, without generating."""
    import json

    import studio.session as S
    from studio import ensure_generated, preset_recipe, recipe_files
    from studio import plan as PL

    data = tmp_path / "data" / "demo"
    raw = preset_recipe("demo", tmp_path, data)
    recipe = tmp_path / "demo.yaml"
    recipe.write_text(yaml.safe_dump(raw))
    calls = []

    def fake_generate(out, plan):  # writes what the recipe names, and the plan it used
        calls.append(plan)
        for f in recipe_files(raw, tmp_path):
            dst = out / f.relative_to(data)
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(b"x")
        (out / "gt").mkdir(exist_ok=True)
        (out / "gt" / "session.json").write_text(json.dumps({"plan": S.plan_dict(plan),
                                                             "studio_source": S.source_hash()}))
        return out / "recipe.yaml"

    monkeypatch.setattr(S, "generate", fake_generate)
    old = PL.make_plan(PL.PRESETS["demo"].seed, frames=150, preset="demo")
    fake_generate(data, old)  # "data generated by an older preset (150 frames)"
    calls.clear()
    ensure_generated(recipe)
    assert len(calls) == 1 and calls[0].sequences[0].frames == PL.PRESETS["demo"].frames
    meta = json.loads((data / "gt" / "session.json").read_text())
    assert meta["plan"]["sequences"][0]["frames"] == PL.PRESETS["demo"].frames
    ensure_generated(recipe)  # now current: nothing generated
    assert len(calls) == 1
    assert not any((tmp_path / "data").glob(".*tmp*"))
