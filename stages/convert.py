"""Stage ``convert`` (per sequence): the fitted bodies as SMPL-family parameters, frame by frame.

Thin adapter around ``fitting.convert``: the target model file is the option ``target`` (a
path; relative to the recipe file's folder), else ``$SMPLX_MODEL_PATH``, else the SMPL-X-schema
stand-in (``body.smplx_standin``); its content is a raw input (part of the key). The surface
correspondence source <-> target is registered once per model pair and cached under
``assets/cache/correspondence/<key>.npz`` (key: both model files' sha256 and the registration
code), then copied into the artifact; next to it ``<key>.rest.npz``, the target fitted on the
source template at rest (``fitting.convert.cached_rest``), every subject's starting point, and
``<key>.subject-<hash>.npz``, the target at each subject's rest posture (its betas; once per
subject, ``fitting.convert.cached_subject_rest``).
Conversion: ``fitting.convert.convert_motion`` (batched LM on global joint rotations). Person 0 is the marker wearer (marker_fit), person 1 the
partner (partner_fit) when the sequence has one; frames are marker_fit's frames that
partner_fit also has. Frames flagged not valid in a source fit stay not valid (still
converted). Writes

- ``smplx.npz`` (``artifacts.SMPLXFit``): ``transl (P,F,3)``, ``global_orient (P,F,3,3)``,
  ``body_pose (P,F,21,3,3)``, ``left_hand_pose``/``right_hand_pose (P,F,15,3,3)``,
  ``jaw_pose``, ``leye_pose``, ``reye_pose (P,F,3,3)``, ``betas (P,10)``, ``expression
  (P,10)``, ``frames (F,)``, ``valid (P,F)``, ``v2s_mm (P,F)`` (per frame mean over the target
  vertices of the distance to the source surface), ``v2s_median_mm``/``v2s_p95_mm``/
  ``v2s_max_mm (P,F)``, ``subjects (P,)``;
- ``correspondence.npz`` (``artifacts.SurfaceCorrespondence``, the arrays of
  ``fitting.convert.Correspondence``);
- ``report.json`` (``artifacts.ConversionReport``): ``target`` {path, sha256, kind,
  n_vertices, standin, description}, ``per_person`` [{subject, v2s_median_mm (median over frames of v2s_mm), v2s_p95_mm (median
  over frames of the per-frame 95th percentile), v2s_max_mm, frames}], ``fps_per_core``,
  ``cpu_s`` (conversion: the rig, every person's rest fit, frames and v2s; registration and the
template rest fit excluded), ``registration_cpu_s``, ``warnings``.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.spec import Stage, StageContext
from stages import common

REPO = Path(__file__).resolve().parents[1]
CACHE_DIR = REPO / "assets" / "cache" / "correspondence"
WARN_V2S_MM = 10.0  # a person converted worse than this (median over frames): say so
NUM_BETAS = 10

READS = ("body_model.kind", "sequence.markers_on", "sequence.partner")
# The per-model-pair precomputations of a process: {(correspondence key, thread): (fit rig,
# v2s rig, the source's facet adjacency)}. They depend on the two model files alone (the key
# hashes both); every use sets the rigs' betas first, and a thread has its own (an executor
# running two sequences in two threads of one process must not share the rigs' betas). A run of many sequences in one process (the
# serial executor, a Dask worker) builds them once, as the registration is made once; the
# first sequence's conversion pays for them (counted in its cpu_s).
_RIGS: dict[str, tuple] = {}
_MODELS: dict[tuple, object] = {}  # {(kind, file, size, mtime_ns): BodyModel} of this process


def _model(kind: str, path: Path, load_model):
    """``load_model(kind, path)``, loaded once per process while the file is unchanged (same
    size and modification time; its content is part of this stage's key): the source and the
    target are the same for every sequence, and reading the target takes ~0.7 s."""
    st = path.stat()
    key = (kind, str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _MODELS:
        if len(_MODELS) >= 4:
            _MODELS.clear()
        _MODELS[key] = load_model(kind, path)
    return _MODELS[key]


@dataclass(frozen=True)
class Options:
    """target : SMPL-family model file (.npz/.pkl; relative to the recipe's folder), empty:
    ``$SMPLX_MODEL_PATH`` or the stand-in; iters : LM iterations per frame (each frame starts
    from its source joints' rotations; betas are fitted once per subject at its rest posture)."""

    target: str = ""
    iters: int = 2

    def __post_init__(self):
        if self.iters < 1:
            raise ValueError(f"iters: must be >= 1, got {self.iters}")


def _standin() -> tuple[Path, bool]:
    """The stand-in target (built on demand), else the Anny-mesh SMPL-X asset. The builders
    are imported by name: their source is no part of this stage's key (the file's content,
    a raw input, is), and a test-asset builder stays out of every stage's source hash."""
    import importlib

    try:
        mod = importlib.import_module("body.smplx_standin")
        return Path(mod.standin_path()), True
    except ImportError:  # the stand-in builder not there: the Anny-mesh asset
        mod = importlib.import_module("body.smplx_from_anny")
        return Path(mod.smplx_from_anny_path()), True


def target_file(recipe) -> tuple[Path, bool]:
    """(the target model file, whether it is the stand-in). InputError naming
    ``stages.convert.target`` when the option names no readable file."""
    from formats.errors import InputError

    opt = (recipe.stages.get("convert") or {}).get("target") if recipe.stages else None
    src = getattr(recipe, "source", None)
    if opt:
        p = Path(os.path.expanduser(str(opt)))
        if not p.is_absolute() and src is not None:
            p = Path(src).resolve().parent / p
        if p.is_dir():
            for n in ("SMPLX_NEUTRAL.npz", "SMPLX_NEUTRAL.pkl"):
                if (p / n).is_file():
                    p = p / n
                    break
        if not p.is_file():
            raise InputError(src or "recipe", "stages.convert.target",
                             f"target model file not found: {p}")
        return p, False
    env = os.environ.get("SMPLX_MODEL_PATH")
    if env:
        p = Path(env)
        if p.is_dir():
            p = p / "SMPLX_NEUTRAL.npz"
        if not p.is_file():
            raise InputError(src or "recipe", "stages.convert.target",
                             f"$SMPLX_MODEL_PATH names no model file: {p}")
        return p, False
    return _standin()


def raw_inputs(recipe, unit: str) -> dict[str, Path]:  # noqa: ARG001 (the Stage protocol)
    target = target_file(recipe)[0]  # first: a bad option is the error to report
    return {"body_model": common.body_model_file(recipe), "target": target}


def _frames(wearer, partner):
    fr = np.asarray(wearer.frames)
    if partner is None:
        return fr, [np.arange(len(fr))]
    pf = np.asarray(partner.frames)
    keep = np.isin(fr, pf)
    fr = fr[keep]
    pos = {int(f): i for i, f in enumerate(pf)}
    return fr, [np.flatnonzero(keep), np.array([pos[int(f)] for f in fr], dtype=np.int64)]


def run(ctx: StageContext) -> None:
    import igl

    from artifacts import BodyFit, ConversionReport, SMPLXFit, SurfaceCorrespondence
    from artifacts.smplx_fit import PersonConversion, TargetInfo
    from body import load_model
    from fitting.convert import (
        GlobalRig,
        cached_correspondence,
        cached_rest,
        cached_subject_rest,
        convert_motion,
        file_sha256,
        smplx_arrays,
        subsample_vertices,
        v2s_vertices,
    )
    from formats.errors import InputError

    o: Options = ctx.params or Options()
    source = _model(ctx.recipe.body_model.kind, Path(ctx.raw["body_model"]), load_model)
    tfile = Path(ctx.raw["target"])
    if tfile.suffix not in (".npz", ".pkl"):
        raise InputError(tfile, "stages.convert.target", "expected a .npz or .pkl model file")
    target = _model("smplx", tfile, load_model)
    standin = tfile.resolve().parent.name in ("smplx_standin", "smplx_from_anny")
    t0 = time.process_time()
    corr, key, fresh = cached_correspondence(source, target, ctx.raw["body_model"], tfile,
                                             CACHE_DIR, log=ctx.log)
    rest = cached_rest(source, target, corr, key, CACHE_DIR)
    reg_cpu = time.process_time() - t0
    SurfaceCorrespondence.of(corr).save(ctx.out)

    people = common.fitted_people(ctx)  # the wearer's marker_fit (markerless: partner_fit's)
    wearer = BodyFit.load(people[0][0])
    partner = BodyFit.load(people[1][0]) if len(people) > 1 else None
    frames, idx = _frames(wearer, partner)
    fits = [wearer] + ([partner] if partner is not None else [])
    seq = ctx.recipe.sequence
    subjects = [seq.markers_on] + ([seq.partner] if partner is not None else [])
    P, F = len(fits), len(frames)
    if F == 0:
        raise InputError("partner_fit/fit.npz", "frames",
                         "no frame of marker_fit is also in partner_fit: nothing to convert")
    t1 = time.process_time()
    mine = (key, threading.get_ident())  # a rig holds the betas it was last set to: one per thread
    rigs = _RIGS.get(mine)  # built once per model pair and thread in this process (see _RIGS)
    if rigs is None:
        rigs = (GlobalRig(target, subsample_vertices(target), NUM_BETAS),
                GlobalRig(target, v2s_vertices(target), NUM_BETAS, shape=False),
                igl.triangle_triangle_adjacency(np.asarray(source.faces, np.int64))[0])
        if len(_RIGS) >= 4:
            _RIGS.clear()
        _RIGS[mine] = rigs
    rig, eval_rig, adjacency = rigs
    setup_cpu = time.process_time() - t1  # the rigs and the source's facet adjacency
    K = rig.K
    arrays = {"transl": np.zeros((P, F, 3)), "global_orient": np.zeros((P, F, 3, 3)),
              "betas": np.zeros((P, NUM_BETAS)), "expression": np.zeros((P, 10)),
              "valid": np.zeros((P, F), bool)}
    v2s = {k: np.full((P, F), np.nan) for k in ("v2s_mm", "v2s_median_mm", "v2s_p95_mm",
                                                 "v2s_max_mm")}
    poses = []
    per_person, warnings, cpu = [], [], setup_cpu
    for p, (fit, ix) in enumerate(zip(fits, idx, strict=True)):
        t1 = time.process_time()
        subj, _ = cached_subject_rest(source, corr, rig, fit.betas, rest, key, CACHE_DIR)
        cpu += time.process_time() - t1  # the subject's betas at rest (cached per subject)
        res = convert_motion(source, target, corr, fit.betas, fit.body_pose[ix],
                             fit.global_orient[ix], fit.transl[ix], iters=o.iters,
                             progress=ctx.progress, rig=rig, rest=rest, adjacency=adjacency,
                             eval_rig=eval_rig, subject=subj)
        cpu += res.cpu_s
        arrays["transl"][p], arrays["global_orient"][p] = res.transl, res.global_orient
        arrays["betas"][p, :K] = res.betas
        arrays["valid"][p] = np.asarray(fit.valid)[ix]
        poses.append(res.body_pose)
        v2s["v2s_mm"][p], v2s["v2s_median_mm"][p] = res.v2s_mean_mm, res.v2s_median_mm
        v2s["v2s_p95_mm"][p], v2s["v2s_max_mm"][p] = res.v2s_p95_mm, res.v2s_max_mm
        med = float(np.nanmedian(res.v2s_mean_mm))
        per_person.append(PersonConversion(
            subjects[p], med, float(np.nanmedian(res.v2s_p95_mm)), float(np.nanmax(res.v2s_max_mm)),
            F, int(res.restarts)))
        ctx.log(f"{ctx.unit}: {subjects[p]} -> {target.name}: v2s {med:.1f} mm (median), "
                f"{F} frames, {F / max(res.cpu_s, 1e-9):.1f} frames/s")
        if med > WARN_V2S_MM:
            warnings.append(f"{subjects[p]}: converted surface {med:.1f} mm from the fitted "
                            f"one (median over frames), above {WARN_V2S_MM:g} mm")
    for w in warnings:
        ctx.log(f"{ctx.unit}: WARNING {w}")
    parts = {}
    for p in range(P):
        for k, v in smplx_arrays(target, poses[p]).items():
            parts.setdefault(k, []).append(v)
    arrays.update({k: np.stack(v) for k, v in parts.items()})
    SMPLXFit(**arrays, **v2s, frames=np.asarray(frames, np.int64),
             subjects=np.array(subjects)).save(ctx.out)
    ConversionReport(
        sequence=ctx.unit,
        target=TargetInfo(path=str(tfile), sha256=file_sha256(tfile), kind=target.name,
                          n_vertices=int(target.num_vertices), standin=bool(standin),
                          description=("SMPL-X-schema stand-in built from Anny (not the "
                                       "licensed SMPL-X)" if standin
                                       else f"{target.name} model file")),
        correspondence_key=key, registered_now=bool(fresh), per_person=tuple(per_person),
        fps_per_core=float(P * F / max(cpu, 1e-9)), cpu_s=float(cpu),
        registration_cpu_s=float(reg_cpu) if fresh else 0.0,
        warnings=tuple(warnings)).save(ctx.out)


STAGE = Stage(name="convert", func=run, per="sequence", upstream=("marker_fit", "partner_fit"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="2",
              doc="SMPL-X parameters of both people (surface-correspondence fit)")
