"""The ``convert`` stage: registration, per-frame fit, the smplx peer check, the cache."""
from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest


@pytest.fixture(scope="module")
def anny():
    from body import load_model

    return load_model("anny")


@pytest.fixture(scope="module")
def target_path():
    from stages.convert import _standin

    return _standin()[0]


@pytest.fixture(scope="module")
def target(target_path):
    from body import load_model

    return load_model("smplx", target_path)


def _writer(d: Path):
    from pipeline.store import Writer

    d.mkdir(parents=True, exist_ok=True)
    return Writer(d)


def _art(d: Path):
    from pipeline.store import StoredArtifact

    return StoredArtifact(Path(d), "k", "u", "s", {})


def _anny_fit(model, rng, frames, d: Path, valid=None):
    """A smooth hand-made Anny motion: small poses on the fitted joints, drifting."""
    from artifacts import BodyFit
    from body.rotations import rodrigues

    F, J = len(frames), model.num_joints
    base = np.zeros((J, 3))
    fj = np.asarray(model.fit_joints[1:])
    base[fj] = rng.normal(0, 0.15, (len(fj), 3))
    drift = np.zeros((J, 3))
    drift[fj] = rng.normal(0, 0.03, (len(fj), 3))
    pose = base[None] + np.arange(F)[:, None, None] * drift[None]
    go = rodrigues(np.array([[0.0, 0.2 + 0.05 * i, 0.0] for i in range(F)]))
    valid = np.ones(F, bool) if valid is None else np.asarray(valid, bool)
    fit = BodyFit(body_pose=pose, global_orient=go,
                  transl=np.array([[0.1 * i, 0.0, 0.9] for i in range(F)]),
                  betas=np.zeros(model.num_betas), frames=np.asarray(frames, np.int64),
                  valid=valid, invalid_reason=np.where(valid, 0, 1).astype(np.int8))
    w = _writer(d)
    fit.save(w)
    return _art(d)


@pytest.fixture(scope="module")
def converted(tmp_path_factory, anny, target_path, monkeypatch_module):
    """The stage run on a wearer (4 frames, frame 2 not valid) and a partner (3 of them)."""
    from pipeline.spec import RecipeView, StageContext
    from stages import convert as C

    tmp = tmp_path_factory.mktemp("conv")
    monkeypatch_module.setattr(C, "CACHE_DIR", tmp / "cache")
    rng = np.random.default_rng(0)
    wear = _anny_fit(anny, rng, [0, 1, 2, 3], tmp / "mf", valid=[True, True, False, True])
    part = _anny_fit(anny, rng, [1, 2, 3, 5], tmp / "pf")
    tree = {"body_model": {"kind": "anny"}, "sequence": {"markers_on": "s1", "partner": "s2"}}
    raw = {"body_model": Path(anny.source), "target": target_path}
    ctx = StageContext(stage="convert", unit="g/A 1", recipe=RecipeView(tree, "convert"),
                       params=C.Options(), inputs={"marker_fit": wear,
                                                                "partner_fit": part},
                       raw=raw, out=_writer(tmp / "out"),
                       progress=lambda it, total=None, desc="": it, log=lambda s: None)
    C.run(ctx)
    return tmp / "out"


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_stage_artifact_layout_and_valid(converted):
    import json

    z = np.load(converted / "smplx.npz")
    assert z["frames"].tolist() == [1, 2, 3]  # the wearer's frames the partner also has
    P, F = 2, 3
    assert z["body_pose"].shape == (P, F, 21, 3, 3)
    assert z["left_hand_pose"].shape == (P, F, 15, 3, 3) == z["right_hand_pose"].shape
    assert z["global_orient"].shape == (P, F, 3, 3) and z["jaw_pose"].shape == (P, F, 3, 3)
    assert z["betas"].shape == (P, 10) and z["expression"].shape == (P, 10)
    assert z["valid"].tolist() == [[True, False, True], [True, True, True]]
    assert np.isfinite(z["v2s_mm"]).all()
    assert z["subjects"].tolist() == ["s1", "s2"]
    c = np.load(converted / "correspondence.npz")
    assert c["tgt_vert_bary"].shape[1] == 3
    assert np.allclose(c["tgt_vert_bary"].sum(1), 1)
    rep = json.loads((converted / "report.json").read_text())
    assert rep["target"]["kind"] == "smplx" and len(rep["per_person"]) == 2
    assert rep["fps_per_core"] > 0


def test_v2s_on_anny_motion_below_8mm(converted):
    z = np.load(converted / "smplx.npz")
    assert np.median(z["v2s_mm"]) < 8.0, z["v2s_mm"]


def test_peer_smplx_build_layer_reproduces_surface(converted, target, target_path):
    """The parameters written, through smplx.build_layer(model_type='smplx'), give the surface
    the stage converted to (our LBS on the same parameters) to 1e-5 m."""
    torch = pytest.importorskip("torch")
    smplx = pytest.importorskip("smplx")
    from body import forward
    from body.rotations import rotmat_to_rotvec
    from body.smplfamily import smplx_betas

    z = dict(np.load(converted / "smplx.npz"))
    P, F = z["valid"].shape
    layer = smplx.build_layer(str(target_path), model_type="smplx", num_betas=10,
                              num_expression_coeffs=10, dtype=torch.float64)
    keys = ("global_orient", "body_pose", "left_hand_pose", "right_hand_pose", "jaw_pose",
            "leye_pose", "reye_pose")
    for p in range(P):
        args = {k: torch.as_tensor(z[k][p]) for k in keys}
        with torch.no_grad():
            ref = layer(betas=torch.as_tensor(np.repeat(z["betas"][p][None], F, 0)),
                        expression=torch.as_tensor(np.repeat(z["expression"][p][None], F, 0)),
                        transl=torch.as_tensor(z["transl"][p]), **args).vertices.numpy()
        full = np.concatenate([np.zeros((F, 1, 3, 3)) + np.eye(3), z["body_pose"][p],
                               z["jaw_pose"][p][:, None], z["leye_pose"][p][:, None],
                               z["reye_pose"][p][:, None], z["left_hand_pose"][p],
                               z["right_hand_pose"][p]], 1)
        ours = forward(target, smplx_betas(target, z["betas"][p][None], z["expression"][p][None]),
                       rotmat_to_rotvec(full), z["global_orient"][p], z["transl"][p]).vertices
        assert np.abs(ours - ref).max() < 1e-5


def test_recovers_known_smplx_pose(target, tmp_path):
    """The target posed with known parameters is the source (target -> target): the fit gives
    back its surface (0.26 mm mean vertex error), betas and pose (0.005 rad median)."""
    from body import forward
    from body.rotations import rodrigues
    from fitting.convert import convert_motion, register

    rng = np.random.default_rng(4)
    F, J = 3, target.num_joints
    pose = np.zeros((F, J, 3))
    pose[:, 1:22] = rng.normal(0, 0.25, (1, 21, 3))
    pose[:, 25:] = rng.normal(0, 0.15, (1, 30, 3))
    pose[:, 1:22] += np.arange(F)[:, None, None] * 0.05
    betas = np.zeros(target.num_betas)
    betas[:10] = rng.normal(0, 0.8, 10)
    go = rodrigues(np.array([[0.1, 0.5 + 0.1 * i, 0.0] for i in range(F)]))
    tr = np.array([[0.2, 0.1 * i, 1.0] for i in range(F)])
    corr = register(target, target)
    res = convert_motion(target, target, corr, betas, pose, go, tr)
    assert np.median(res.v2s_mean_mm) < 0.3, res.v2s_mean_mm
    truth = forward(target, betas, pose, go, tr).vertices
    b = np.zeros(target.num_betas)
    b[:10] = res.betas
    got = forward(target, b, res.body_pose, res.global_orient, res.transl).vertices
    err = np.linalg.norm(got - truth, axis=-1)
    assert err.mean() < 5e-4 and err.max() < 2e-3, (err.mean(), err.max())
    assert np.abs(res.betas - betas[:10]).max() < 0.1
    # the body's and the fingers' rotations come back
    for sl in (slice(1, 22), slice(25, 55)):
        Rt, Rg = rodrigues(pose[:, sl]), rodrigues(res.body_pose[:, sl])
        ang = np.arccos(np.clip((np.einsum("fjab,fjab->fj", Rt, Rg) - 1) / 2, -1, 1))
        assert np.median(ang) < 0.01 and ang.max() < 0.1, (np.median(ang), ang.max())


def test_correspondence_cache_reused_and_keyed(anny, target, target_path, tmp_path):
    from fitting.convert import cached_correspondence, correspondence_key

    src = Path(anny.source)
    c1, k1, fresh1 = cached_correspondence(anny, target, src, target_path, tmp_path / "c",
                                           log=lambda s: None)
    c2, k2, fresh2 = cached_correspondence(anny, target, src, target_path, tmp_path / "c",
                                           log=lambda s: None)
    assert fresh1 and not fresh2 and k1 == k2
    assert (tmp_path / "c" / f"{k1}.npz").exists()
    assert np.array_equal(c1.tgt_vert_face, c2.tgt_vert_face)
    copy = tmp_path / "SMPLX_NEUTRAL.npz"
    shutil.copy(target_path, copy)
    assert correspondence_key(src, copy) == k1  # the content, not the path
    with open(copy, "ab") as fh:
        fh.write(b"\0")
    assert correspondence_key(src, copy) != k1


def test_bad_target_path_names_the_option(tmp_path):
    from formats.errors import InputError
    from stages.convert import raw_inputs

    rec = SimpleNamespace(stages={"convert": {"target": "models/nope.npz"}},
                          source=tmp_path / "recipe.yaml",
                          body_model=SimpleNamespace(kind="anny", path=None))
    with pytest.raises(InputError) as e:
        raw_inputs(rec, "g/A 1")
    assert "stages.convert.target" in str(e.value) and "nope.npz" in str(e.value)


def test_bench_case_reads_convert_artifacts(converted, tmp_path):
    from bench.cases.convert import collect

    d = tmp_path / "sess" / "g" / "A 1" / "convert"
    shutil.copytree(converted, d)
    out = collect(tmp_path)
    z = np.load(converted / "smplx.npz")
    assert out["convert.frames"] == z["v2s_mm"].size
    assert out["convert.v2s_mm"] == pytest.approx(float(np.median(z["v2s_mm"])))
    assert out["convert.fps_per_core"] > 0 and out["convert.v2s_p95_mm"] >= out["convert.v2s_mm"]
    with pytest.raises(RuntimeError):
        collect(tmp_path / "empty")


def test_a_sudden_turn_converts_like_a_smooth_frame(target):
    """A sudden half-turn and a new arm pose between two frames (a fast motion over a stride):
    every frame starts from its own source joints, not from the previous frame, so the frames
    after the jump stay on the surface too."""
    from body.rotations import rodrigues
    from fitting.convert import convert_motion, register

    rng = np.random.default_rng(5)
    F, J = 4, target.num_joints
    pose = np.zeros((F, J, 3))
    pose[:, 1:22] = rng.normal(0, 0.15, (1, 21, 3))
    pose[2:, 16:22] += rng.normal(0, 0.9, (1, 6, 3))  # both arms jump
    go = rodrigues(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 2.8],
                             [0.0, 0.0, 2.85]]))
    tr = np.array([[0.0, 0.0, 1.0], [0.0, 0.02, 1.0], [0.3, 0.2, 1.0], [0.3, 0.22, 1.0]])
    corr = register(target, target)
    res = convert_motion(target, target, corr, np.zeros(target.num_betas), pose, go, tr,
                         iters=3)
    assert np.nanmax(res.v2s_mean_mm) < 1.0, res.v2s_mean_mm
    assert abs(res.v2s_mean_mm[2] - res.v2s_mean_mm[0]) < 0.5, res.v2s_mean_mm


def test_surface_distance_matches_libigl_away_from_contact(anny, target_path, target):
    """The v2s walk (distance near each vertex's correspondence) is an upper bound of libigl's
    distance to the whole surface, equal to it for most points up to 6 mm off the surface,
    and 0.14 mm above it on average (points in a fold are nearer another part of the body)."""
    import igl

    from body import forward
    from body.rotations import rodrigues
    from fitting.convert import closest_on_mesh, surface_distance

    rng = np.random.default_rng(3)
    pose = np.zeros((1, anny.num_joints, 3))
    pose[0, np.asarray(anny.fit_joints[1:])] = rng.normal(0, 0.1, (len(anny.fit_joints) - 1, 3))
    V = forward(anny, np.zeros(anny.num_betas), pose, rodrigues(np.array([[0, 0, 0.4]])),
                np.zeros((1, 3))).vertices[0]
    F = np.asarray(anny.faces, np.int64)
    TT = igl.triangle_triangle_adjacency(F)[0]
    face0 = rng.integers(0, len(F), 3000)
    bary = rng.dirichlet(np.ones(3), 3000)
    on = np.einsum("nk,nkx->nx", bary, V[F[face0]])
    # points 0-6 mm off the surface along the facet normal, started one facet away
    n = np.cross(V[F[face0, 1]] - V[F[face0, 0]], V[F[face0, 2]] - V[F[face0, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = on + rng.uniform(0, 6e-3, (3000, 1)) * n
    start = TT[face0, 0]
    start = np.where(start >= 0, start, face0)
    walk = surface_distance(pts, start, V, F, TT)
    exact = closest_on_mesh(pts, V, F)[0]
    assert (walk >= exact - 1e-9).all()
    close = np.abs(walk - exact) < 1e-6
    assert close.mean() > 0.85, close.mean()
    assert (walk - exact).mean() < 2e-4


def test_shape_blocks_match_their_einsum_and_cross_product_form():
    """The betas' normal-equation blocks of the subject's rest fit
    (``fitting.convert.shape_blocks``, matrix products) equal their definition written with
    ``np.einsum`` and ``np.cross`` (the form the fit used before), on random inputs of the
    rig's shapes, a rotation per joint and sparse per-joint parts."""
    from body.rotations import rodrigues
    from fitting.convert import shape_blocks

    rng = np.random.default_rng(3)
    K, N, Q = 10, 57, 7
    G0 = rodrigues(rng.normal(size=(Q, 3)))
    dc = rng.normal(size=(K, N, Q, 3))
    p = rng.normal(size=(N, Q, 3)) * (rng.random((N, Q, 1)) < 0.3)
    ws, r0 = rng.random(N), rng.normal(size=(N, 3))
    B = np.einsum("qab,knqb->nak", G0, dc)
    want = (np.einsum("nak,nal->kl", B, B),
            np.cross(p[:, :, :, None], B[:, None, :, :], axis=2).sum(0),
            np.einsum("n,nak->ak", ws, B), np.einsum("nak,na->k", B, r0))
    got = shape_blocks(G0, dc, p, ws, r0)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-10)
