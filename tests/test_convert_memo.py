"""The convert stage's per-process memos (stages.convert._RIGS / _MODELS,
fitting.convert._source_rest, the v2s rig's coefficients per betas): a sequence converted after
others in the same process gives exactly what it gives in a fresh process."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _fit(model, rng, frames, d: Path, betas):
    from artifacts import BodyFit
    from body.rotations import rodrigues
    from pipeline.store import StoredArtifact, Writer

    F, J = len(frames), model.num_joints
    pose = np.zeros((F, J, 3))
    fj = np.asarray(model.fit_joints[1:])
    pose[:, fj] = rng.normal(0, 0.15, (len(fj), 3))[None] + \
        np.arange(F)[:, None, None] * rng.normal(0, 0.03, (len(fj), 3))[None]
    b = np.zeros(model.num_betas)
    b[:len(betas)] = betas
    fit = BodyFit(body_pose=pose, global_orient=rodrigues(np.array([[0.0, 0.3 * i, 0.0]
                                                                    for i in range(F)])),
                  transl=np.array([[0.1 * i, 0.0, 0.9] for i in range(F)]), betas=b,
                  frames=np.asarray(frames, np.int64), valid=np.ones(F, bool),
                  invalid_reason=np.zeros(F, np.int8))
    d.mkdir(parents=True, exist_ok=True)
    fit.save(Writer(d))
    return StoredArtifact(d, "k", "u", "s", {})


def test_a_sequence_after_others_in_one_process_converts_as_in_a_fresh_one(tmp_path,
                                                                          monkeypatch):
    from body import load_model
    from fitting import convert as FC
    from pipeline.spec import RecipeView, StageContext
    from pipeline.store import Writer
    from stages import convert as C

    anny = load_model("anny")
    monkeypatch.setattr(C, "CACHE_DIR", tmp_path / "cache")
    rng = np.random.default_rng(3)
    seqs = {}
    for name, (bw, bp) in {"one": ([0.8, -0.5], [-0.6, 0.4, 0.3]),
                           "two": ([-0.4, 0.9, -0.2], [0.5])}.items():
        seqs[name] = (_fit(anny, rng, [0, 1, 2], tmp_path / name / "mf", bw),
                      _fit(anny, rng, [0, 1, 2], tmp_path / name / "pf", bp))

    def run(name, out):
        tree = {"body_model": {"kind": "anny"}, "sequence": {"markers_on": "a", "partner": "b"}}
        wear, part = seqs[name]
        ctx = StageContext(stage="convert", unit=f"g/{name}", recipe=RecipeView(tree, "convert"),
                           params=C.Options(), inputs={"marker_fit": wear, "partner_fit": part},
                           raw={"body_model": Path(anny.source),
                                "target": C._standin()[0]},
                           out=Writer(out), progress=lambda it, total=None, desc="": it,
                           log=lambda s: None)
        out.mkdir(parents=True)
        C.run(ctx)
        with np.load(out / "smplx.npz") as z:
            return {k: z[k] for k in z.files}

    def fresh():
        C._RIGS.clear()
        C._MODELS.clear()
        FC._REST_MEMO.clear()

    fresh()
    alone = run("one", tmp_path / "out_alone")  # the first conversion of a fresh process
    fresh()
    run("two", tmp_path / "out_two")  # other subjects: the shared rigs carry their betas
    after = run("one", tmp_path / "out_after")
    assert len(C._RIGS) == 1 and len(FC._REST_MEMO) == 4  # the memos were used
    assert alone.keys() == after.keys()
    for k in alone:
        if alone[k].dtype.kind in "fc":
            np.testing.assert_array_equal(alone[k], after[k], err_msg=k)
    assert not np.allclose(alone["betas"][0], alone["betas"][1])  # two different subjects


def test_v2s_rig_coefficients_memo_follows_the_betas():
    from body import load_model
    from body.rotations import rodrigues
    from fitting.convert import GlobalRig, v2s_vertices
    from stages.convert import _standin

    target = load_model("smplx", _standin()[0])
    verts = v2s_vertices(target)[:200]
    rig = GlobalRig(target, verts, 10, shape=False)  # betas -> coefficients recomputed, memoised
    G = rodrigues(np.random.default_rng(0).normal(0, 0.2, (2, rig.Q, 3)))
    t0 = np.zeros((2, 3))
    b1, b2 = np.linspace(-1, 1, 10), np.linspace(1, -0.5, 10)
    out = []
    for b in (b1, b2, b1):
        rig.set_betas(b)
        out.append(rig.positions(G, t0, rig.correctives(G)))
    ref = GlobalRig(target, verts, 10, shape=False)
    ref.set_betas(b1)
    np.testing.assert_array_equal(out[2], ref.positions(G, t0, ref.correctives(G)))
    np.testing.assert_array_equal(out[0], out[2])
    assert np.abs(out[1] - out[0]).max() > 1e-3  # other betas move the points
