"""convert accuracy and speed on the studio bench session's fits (the partner_fit case's store).

Runs ``python -m pipeline release --recipe bench/work/partner_fit/recipe.yaml --outputs
bench/work/partner_fit/outputs --until convert`` (a subprocess, like the engine runs of the
other cases; the fits of the partner_fit case are reused when cached, so only convert is
computed), then reads every sequence's convert artifact (``artifacts.ConversionReport`` and
``artifacts.SMPLXFit``). The conversion itself takes ~10 s of the case (320 person-frames,
~0.3 s per sequence of loading); the rest is the store's fits: when they are not cached for
this code (a partner-fit change), the engine computes them first (the 584 s this case once
took: 42 stage runs of which 8 were convert). ``AFTER``: in a run of every case the partner_fit
case has made the store current, so only convert is computed here.

Keys: ``convert.v2s_mm``: median over all person-frames of the per-frame mean distance of the
target vertices to the fitted Anny surface (mm; smplx's transfer_model reaches 5.0 mm);
``convert.v2s_p95_mm``: median over person-frames of the per-frame 95th percentile;
``convert.v2s_max_mm``: the largest vertex distance seen; ``convert.fps_per_core``: converted
person-frames per CPU-second of the conversion (registration excluded, it is cached per model
pair); ``convert.frames``: person-frames converted.

Peer: ``smplfitter`` (PyPI, pinned in requirements-test.txt; its PyTorch backend on one CPU
thread when torch is there, else its numpy one), fitted on the same person-frames: the same
target points (the source surface at every target vertex's correspondence), its
``BodyFitter.fit`` with 3 iterations, betas shared over each person's frames. It loads the
target file as ``SMPLX_NEUTRAL.npz`` from a folder of its own with an all-zero kid template
(kid fitting off). ``convert.peer_smplfitter_fps_per_core``: person-frames per CPU-second of its
fit alone (no source skinning, no scoring); ``convert.peer_smplfitter_v2s_mm`` / ``_p95_mm`` /
``_max_mm``: the same statistics as ours, by the same distance
(``fitting.convert.surface_distance``).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
AFTER = ("partner_fit",)  # reuses that case's store of fits: runs after it (bench.run_order)
GOALS = {
    "convert.v2s_mm": ("<=", 5.0),
    "convert.fps_per_core": (">=", 100.0),
}
LIMITS = {
    "convert.fps_per_core": "per person-frame (bench store, 20-frame sequences, loaded 2-core "
                            "machine, one BLAS thread): ~4 ms of batched LM (613 target points, "
                            "2 iterations: the dense (points, 3 x 53) float32 Gram product, a "
                            "(162, 162) solve and 3 evaluations of the parts), ~3 ms the v2s "
                            "facet walk over 2,000 scored vertices (~140k point-triangle tests "
                            "per 20 frames), ~2 ms skinning the Anny source (13,718 vertices), "
                            "~0.7 ms posing the scored vertices; the rigs (~0.2 s) once per "
                            "process and model pair, a subject's rest state once per process",
}


def collect(outputs: Path) -> dict[str, float]:
    """The figures of every ``convert`` artifact under ``outputs``."""
    from artifacts import ConversionReport, SMPLXFit

    mean, p95, mx, cpu, n = [], [], [], 0.0, 0
    for d in sorted(p.parent for p in Path(outputs).rglob("convert/smplx.npz")):
        r, z = ConversionReport.load(d), SMPLXFit.load(d)
        mean.append(np.ravel(z.v2s_mm))
        p95.append(np.ravel(z.v2s_p95_mm))
        mx.append(np.ravel(z.v2s_max_mm))
        cpu += r.cpu_s
        n += int(np.isfinite(z.v2s_mm).sum())
    if not n:
        raise RuntimeError(f"no convert artifact under {outputs}")
    cat = np.concatenate
    return {"convert.v2s_mm": float(np.nanmedian(cat(mean))),
            "convert.v2s_p95_mm": float(np.nanmedian(cat(p95))),
            "convert.v2s_max_mm": float(np.nanmax(cat(mx))),
            "convert.fps_per_core": float(n / max(cpu, 1e-9)), "convert.frames": float(n)}


def run(work: Path) -> dict[str, float]:
    store = work.parent / "partner_fit"
    recipe, outputs = store / "recipe.yaml", store / "outputs"
    if not recipe.exists():  # the partner_fit case writes it (and fills the store)
        from bench.cases import partner_fit as P

        store.mkdir(parents=True, exist_ok=True)
        recipe = P.bench_recipe(store, P.stride())
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "pipeline", "release", "--recipe", str(recipe), "--outputs",
           str(outputs), "--until", "convert", "--executor", "serial"]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    work.mkdir(parents=True, exist_ok=True)
    (work / "engine.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError("engine failed:\n" + "\n".join((proc.stdout + proc.stderr)
                                                          .splitlines()[-30:]))
    out = collect(outputs)
    try:
        out.update(peer(outputs, work / "smplfitter"))
    except ImportError as e:  # the peer not installed: our figures still count
        print(f"[bench] convert: smplfitter peer skipped ({e})", file=sys.stderr)
    return out


def _smplfitter_fitter(target_file: Path, n_vertices: int, tmp: Path):
    """(BodyModel, BodyFitter, torch module or None) of smplfitter on ``target_file``."""
    tmp.mkdir(parents=True, exist_ok=True)
    link = tmp / "SMPLX_NEUTRAL.npz"
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(Path(target_file).resolve())
    np.save(tmp / "kid_template.npy", np.zeros((n_vertices, 3)))  # the "no kid" placeholder
    try:
        import smplfitter.pt as sf
        import torch

        torch.set_num_threads(1)
    except ImportError:
        torch = None
        import smplfitter.np as sf
    bm = sf.BodyModel("smplx", "neutral", model_root=str(tmp), num_betas=10)
    return bm, sf.BodyFitter(bm), torch


def peer(outputs: Path, tmp: Path) -> dict[str, float]:
    """smplfitter's figures on the person-frames of every ``convert`` artifact under
    ``outputs`` (the fits it converted: ``marker_fit``/``partner_fit`` next to it)."""
    import igl

    from artifacts import BodyFit, ConversionReport, SMPLXFit
    from body import forward, load_model
    from fitting.convert import Correspondence, surface_distance

    source = load_model("anny")
    Fs = np.asarray(source.faces, np.int64)
    TT = igl.triangle_triangle_adjacency(Fs)[0]
    fitter, stats, cpu, n = None, [], 0.0, 0
    for d in sorted(p.parent for p in Path(outputs).rglob("convert/smplx.npz")):
        rep, z = ConversionReport.load(d), SMPLXFit.load(d)
        corr = Correspondence.load(d / "correspondence.npz")
        if fitter is None:
            target = load_model("smplx", rep.target.path)
            bm, fitter, torch = _smplfitter_fitter(Path(rep.target.path), target.num_vertices,
                                                   tmp)
        frames = np.asarray(z.frames)
        for name in ("marker_fit", "partner_fit")[:len(z.subjects)]:
            fit = BodyFit.load(d.parent / name)
            ix = np.searchsorted(np.asarray(fit.frames), frames)
            Vs = forward(source, fit.betas, fit.body_pose[ix], fit.global_orient[ix],
                         fit.transl[ix]).vertices
            tg = corr.target_points(Vs)
            t0 = time.process_time()
            if torch is not None:
                res = fitter.fit(torch.as_tensor(tg, dtype=torch.float32), num_iter=3,
                                 share_beta=True, requested_keys=("pose_rotvecs", "shape_betas"))
            else:
                res = fitter.fit(tg, num_iter=3, share_beta=True,
                                 requested_keys=("pose_rotvecs", "shape_betas"))
            cpu += time.process_time() - t0
            Vt = bm(pose_rotvecs=res["pose_rotvecs"], shape_betas=res["shape_betas"],
                    trans=res["trans"])["vertices"]
            Vt = np.asarray(Vt.numpy() if torch is not None else Vt, float)
            for f in range(len(frames)):
                dist = surface_distance(Vt[f], corr.tgt_vert_face, Vs[f], Fs, TT) * 1e3
                stats.append((dist.mean(), np.percentile(dist, 95), dist.max()))
            n += len(frames)
    if not n:
        raise RuntimeError(f"no convert artifact under {outputs}")
    a = np.array(stats)
    return {"convert.peer_smplfitter_fps_per_core": float(n / max(cpu, 1e-9)),
            "convert.peer_smplfitter_v2s_mm": float(np.median(a[:, 0])),
            "convert.peer_smplfitter_v2s_p95_mm": float(np.median(a[:, 1])),
            "convert.peer_smplfitter_v2s_max_mm": float(a[:, 2].max())}
