"""The ``qa`` stage on the studio bench session, clean and with faults put in on purpose.

Clean: the engine up to ``qa_index`` on the bench recipe (``recipes/bench.yaml`` with the
partner_fit case's options, into that case's store: the fits are reused when cached). Every
frame the qa stage flags there is a false alarm by construction (the studio's capture is
clean), up to what the fits really got wrong (the Hug partner is marked not valid by
partner_fit and so flagged).

Faults, each planted where a lab meets it:

- ``marker_swap``: a burst of ``SWAP_SAMPLES`` C3D samples (0.3 s) in which the wearer's
  ``SWAP`` markers (left and right knee) trade places, written into a copy of the capture
  (``formats.c3d.write_c3d``), through the engine (``marker_fit`` fits it, ``qa`` judges it);
- ``sync_offset``: one camera's video delayed by ``SYNC_FRAMES`` frames (its first frames
  repeated), a copy of the video, through the engine (keypoints are detected on it);
- ``limb_rotation``: ``LIMB_FRAMES`` consecutive fit frames of the partner fit with the right
  upper arm turned by ``LIMB_DEG`` degrees about its local x axis, planted into the
  ``partner_fit`` result given to ``qa.metrics`` (an artifact cannot be edited in the store:
  its manifest's hashes would make the engine rebuild it).

Keys: ``qa.flag_recall`` (planted faults flagged by a reason of their kind, in their frames,
that the clean run does not flag there; goal 1.0), ``qa.frame_recall`` (the faults' frames
flagged), ``qa.flag_rate_clean`` (flagged frames over all frames of the clean session; goal
<= 2 %), ``qa.flag_rate_clean_valid`` (the same without the frames a fit itself marks not
valid), ``qa.false_flag_rate`` (flagged frames among those whose fits are right by the studio's
truth: every H36M-17 joint of both people within ``DEFECT_MM`` and both valid),
``qa.defect_recall`` (flagged frames among those with a joint farther than ``DEFECT_MM``: the
clean session's own fit defects), ``qa.defect_frames_all`` (frames with a joint of either
person farther than ``DEFECT_MM``, published or not), ``qa.defect_frames_clean`` (issue #27: among
the person-frames the release would publish as valid, the share with a joint farther than
``DEFECT_MM``: the export's own rules, :func:`published`; goal <= 1 %) with its count
``qa.defect_person_frames_published``, ``qa.defect_frames_clean_joints`` (the same, but a
person-frame counts only when a joint the export publishes as ground truth in it, its
``joints_valid``, is farther than ``DEFECT_MM``: a joint it marks not observed is not
published as truth) and ``qa.published_fraction`` (person-frames published over
all), ``qa.withheld_{right,wrong}_{wearer,partner}`` (person-frames not published whose fit was
right, or wrong, by the truth), ``qa.s_per_frame`` (wall seconds of
the whole qa stage per frame over the clean session, from the engine's manifests: metrics,
plot, overlays, video, scene, report; goal <= 0.1, issue #29), ``qa.cpu_s_per_frame`` (its CPU
seconds, worker processes included), ``qa.metrics_s_per_frame`` (the metrics alone, wall) and
``qa.engine_wall_s_per_frame`` (the whole engine run of the clean session up to ``qa_index``:
planning, cache checks and the index page too).
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

from bench.cases import partner_fit as P

AFTER = ("partner_fit",)  # reuses that case's store of fits: runs after it (bench.run_order)
GOALS = {"qa.flag_recall": (">=", 1.0), "qa.flag_rate_clean": ("<=", 0.02),
         "qa.s_per_frame": ("<=", 0.1), "qa.defect_frames_clean": ("<=", 0.01)}
LIMITS = {
    "qa.flag_recall": (
        "the sync_offset fault when it is missed: it is planted on one view (58860488 of Kick), "
        "and on session 32's studio draw that view's detections do not follow the motion (its "
        "mean cost 17.7-18.2 px at every shift from -3 to 0 frames, 18.1-18.5 px in the clean "
        "run, where the views that do follow it go 8 -> 11 px two frames away): no test can tell "
        "a 2-frame delay there. Session 31's draw of the same view had a clear minimum at -2 "
        "(z 3.1) and was caught. Before session 32 the check then read 0 (in sync); now it says "
        "the view is not measurable and why (faults.json sync_offset.not_measurable, the QA "
        "report's camera table), which is not a detection: the miss stays counted."),
    "qa.flag_rate_clean": (
        "the clean session's fits, not false alarms: by the studio's truth 61 of the 160 bench "
        "frames have a joint more than 10 cm off (qa.defect_frames_all: the Hug partner on all "
        "20, Posing, Push, Handshake), and the flags fall on them (qa.defect_recall); among the "
        "frames whose joints are right, the few flagged (qa.false_flag_rate) are all "
        "wearer.marker_max_mm on the Handshake/HoldingHands wearer's finger marker, fitted 50-100 "
        "mm off: a marker the fit really misses. The goal assumes a session whose fits are right."),
    "qa.defect_frames_clean": (
        "the partner's arms: in session 21's run 23 published partner frames (of 109), in "
        "session 22's 27 and in session 23's 26, had a wrist or elbow 10-40 cm off the truth, "
        "every one observed by confident detections (the per-joint mask calls it seen). In "
        "session 22's run Posing's left elbow, 0.25-0.4 m off (partner_fit.mpjpe_mm_posing), "
        "was most of them; session 23 took Posing from 48.8 to 32.1 mm but the count moved "
        "by one only. Session 24's store run, before the QA: 25 valid partner frames 10+ cm "
        "off (Grab 6, Kick 5, Posing 5, Hug 3, Handshake, HoldingHands and Push 2 each; "
        "min_valid_views took 6 frames seen by two views out, all wrong); the worst joint "
        "of 20 of them is seen by three or four views, so no view-count rule separates them "
        "(a data-only 3D uncertainty of the fitted keypoints did not either: above 50 mm it "
        "withholds 11 wrong frames and 18 right ones). In those frames a view's detector "
        "puts the wrist 100-180 px from the truth at "
        "confidence 0.97 and the fit sits between the views' answers, or two views agree on the "
        "same wrong point. No 2D figure separates them from the right frames (measured on this "
        "session: the largest residual of a confident detection (conf >= 0.9) above 100 px "
        "catches 4 of the 23 and withholds 6 of 86 right frames; above 60 px at conf >= 0.5, 14 "
        "of 23 against 40 of 86): the fit, not the QA, has to get them right."),
    "qa.s_per_frame": (
        "per 20-frame bench sequence ~3.5 s of stage wall and ~5.9 CPU-s (session 31's bench): "
        "the metrics ~1.8 s, of which ~1 s waits for the per-frame geometry (each person's "
        "self-penetration and the pair's interpenetration, winding numbers and nearest points "
        "on the 2,000-vertex proxies and the full meshes: ~70 ms a frame of one core, shared "
        "by a worker process and this one; Hug ~3 s), then the overlays and the video ~1.1 s "
        "(raster_people ~0.5 s for 27 frame-scales x 4 views, PNG writing 0.2 s) while the "
        "scene (~0.5 s, a thread of this process) and the plot (0.65 s alone, 0.8-1.2 s beside "
        "the overlays: 13 matplotlib panels) share the two cores. The stage is CPU-bound on 2 "
        "cores: 0.1 s a frame needs ~2 s a sequence, i.e. less than 4 CPU-s. Since session 32 "
        "the body model is read once per process (0.4 s a stage before) and the worker "
        "imports matplotlib only for the plot. Left to try: the pair's geometry on the proxy "
        "points near the other body only, the scene out of this process's GIL, a cheaper "
        "plot"),
}

SWAP_SEQUENCE, SWAP = "s01/Push 1", ("LKNE", "RKNE")
SWAP_START_S, SWAP_SAMPLES = 1.0, 30  # 0.3 s at 100 Hz
SYNC_SEQUENCE, SYNC_CAMERA, SYNC_FRAMES = "s01/Kick 1", "58860488", 2
LIMB_SEQUENCE, LIMB_JOINT, LIMB_DEG, LIMB_FRAMES = "s01/Grab 1", "upperarm01.R", 45.0, 3
FAULT_SESSION = "studio_bench_qa_faults"


def _engine(recipe: Path, outputs: Path, until: str, work: Path, name: str) -> float:
    from bench.cases._engine import run_engine

    t0 = time.perf_counter()
    run_engine(["release", "--recipe", str(recipe), "--outputs", str(outputs), "--until", until,
                "--executor", "serial"], name, log_file=work / f"{name}.log")
    return time.perf_counter() - t0


def swap_capture(src: Path, dst: Path, names: tuple[str, str], start_s: float, n: int) -> dict:
    """A copy of the C3D with ``names`` swapped over ``n`` samples from ``start_s`` seconds."""
    from formats.c3d import read_c3d, write_c3d

    mk = read_c3d(src)
    i, j = (list(mk.names).index(x) for x in names)
    a = int(round(start_s * mk.rate_hz))
    xyz = np.array(mk.xyz)
    xyz[a:a + n, [i, j]] = xyz[a:a + n, [j, i]]
    import dataclasses

    write_c3d(dst, dataclasses.replace(mk, xyz=xyz))
    return {"first_sample": a, "samples": n, "rate_hz": float(mk.rate_hz),
            "first_frame": int(mk.first_frame)}


def delay_video(src: Path, dst: Path, frames: int) -> None:
    """A copy of the video ``frames`` frames late: frame f shows what frame f - frames showed
    (the first frame repeated at the start), same length and rate."""
    from formats.video import VideoReader, video_info, write_mp4

    info = video_info(src)
    with VideoReader(src) as r:
        imgs = [r[i] for i in range(info.n_frames)]
    write_mp4(dst, [imgs[max(0, i - frames)] for i in range(info.n_frames)], info.fps)


def fault_recipe(base: dict, work: Path) -> tuple[Path, dict]:
    """The faults session's recipe (the sequences whose raw inputs are planted, in
    ``work/planted``: the swap's and the sync offset's; the limb rotation is planted into the
    clean session's fit, :func:`limb_fault`, and needs no engine run) and where the faults are."""
    rec = json.loads(json.dumps(base))
    rec["session"] = FAULT_SESSION
    keep = {SWAP_SEQUENCE, SYNC_SEQUENCE}
    rec["sequences"] = {k: v for k, v in rec["sequences"].items() if k in keep}
    planted = work / "planted"
    planted.mkdir(parents=True, exist_ok=True)
    seq = rec["sequences"][SWAP_SEQUENCE]
    dst = planted / "swap.c3d"
    swap = swap_capture(Path(seq["c3d"]), dst, SWAP, SWAP_START_S, SWAP_SAMPLES)
    seq["c3d"] = str(dst)
    seq = rec["sequences"][SYNC_SEQUENCE]
    dst = planted / f"sync_{SYNC_CAMERA}.mp4"
    if not dst.exists():
        delay_video(Path(seq["videos"][SYNC_CAMERA]), dst, SYNC_FRAMES)
    seq["videos"][SYNC_CAMERA] = str(dst)
    path = work / "faults.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    return path, {"swap": swap}


def _load_qa(outputs: Path, session: str, unit: str):
    """The sequence's ``artifacts.QAResult`` (``.metrics``: qa.npz; ``.summary``)."""
    from artifacts import QAResult

    return QAResult.load(outputs / session / unit / "qa")


def _flagged_by(qa, frames, kind) -> np.ndarray:
    """(len(frames),) whether each frame is flagged by a reason for which ``kind(reason)``."""
    return qa.metrics.flagged_by(frames, kind)


def limb_fault(recipe: Path, outputs: Path, session: str) -> dict:
    """Plant the limb rotation into the partner fit of LIMB_SEQUENCE and run the QA metrics on
    it and on the untouched fit; returns the frames and whether each is flagged (any reason)
    with and without the fault."""
    import dataclasses

    from artifacts import BodyFit
    from artifacts.keypoints import Keypoints2D
    from body import load_model
    from body.rotations import rodrigues, rotmat_to_rotvec
    from calib.io import read_chi3d_camera
    from fitting.contact_signature import load_contact
    from formats.video import video_info
    from qa.metrics import QAOptions, flag_frames, sequence_metrics
    from recipes import load_recipe

    rec = load_recipe(recipe)
    seq = rec.sequences[LIMB_SEQUENCE]
    root = outputs / session / LIMB_SEQUENCE
    model = load_model("anny")
    wearer = BodyFit.load(root / "marker_fit")
    partner = BodyFit.load(root / "partner_fit")
    kp = (Keypoints2D.load(root / "partner_fit") if Keypoints2D.exists_in(root / "partner_fit")
          else Keypoints2D.load(root / "keypoints"))
    cams = [read_chi3d_camera(seq.calibration[c], name=c) for c in rec.cameras]
    n = video_info(seq.videos[rec.cameras[0]]).n_frames
    contact = load_contact(seq.contact, LIMB_SEQUENCE.split("/", 1)[1], model, n) if seq.contact else None
    ground = (np.asarray(rec.ground_plane.normal, float), float(rec.ground_plane.offset))
    opts = QAOptions(**((yaml.safe_load(recipe.read_text()).get("stages") or {}).get("qa") or {}))
    fps = float(seq.fps)
    F = len(partner.frames)
    rows = np.arange(F // 2, F // 2 + LIMB_FRAMES)
    j = list(model.joint_names).index(LIMB_JOINT)
    pose = np.array(partner.body_pose)
    delta = rodrigues(np.array([np.deg2rad(LIMB_DEG), 0.0, 0.0]))
    pose[rows, j] = rotmat_to_rotvec(rodrigues(pose[rows, j]) @ delta)
    bad = dataclasses.replace(partner, body_pose=pose)
    out = {}
    for name, p in (("clean", partner), ("planted", bad)):
        m = sequence_metrics(model, wearer, p, kp, cams, contact, ground, fps, opts)
        fl = flag_frames(m, opts)
        fr = np.asarray(m.frames)
        idx = np.searchsorted(fr, partner.frames[rows])
        out[name] = {"flagged": np.asarray(fl.any)[idx],
                     "reasons": sorted({str(r) for i in idx for r, x in
                                        zip(fl.reasons, fl.flagged[i], strict=True) if x})}
    out["frames"] = [int(f) for f in partner.frames[rows]]
    return out


DEFECT_MM = P.DEFECT_MM  # a fit frame whose worst H36M joint is farther from the truth is a defect


def worst_errors(pred: np.ndarray, true: np.ndarray, published: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the worst joint error (mm) of ``pred`` against ``true`` (both (F, K, 3), m),
    over every joint and over the joints ``published (F, >= K) bool`` marks as ground truth
    (0 where it marks none; without ``published``: every joint)."""
    err = np.linalg.norm(pred - true, axis=-1) * 1000  # (F, K)
    pub = err if published is None else np.where(np.asarray(published, bool)[:, :err.shape[1]],
                                                  err, 0.0)
    return err.max(-1), pub.max(-1)


def truth_errors(outputs: Path, session: str, unit: str, frames: np.ndarray, model, R
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(2, F) per person (0 = the wearer, 1 = the partner) and QA frame the worst H36M-17 joint
    error (mm) of the fit against the studio's truth (``data/bench/gt``), NaN where a fit is
    missing; and the same over the joints the export publishes as ground truth in that frame
    (``joints_valid``: ``fitting.marker_graph.fit_points_observed``; 0 where it publishes
    none), both from one forward pass (:func:`worst_errors`)."""
    from artifacts import BodyFit
    from body import forward
    from fitting.marker_graph import fit_points_observed

    gt = np.load(P.REPO / "data" / "bench" / "gt" / f"{unit}.npz")
    worst = np.full((2, len(frames)), np.nan)
    worst_pub = np.full((2, len(frames)), np.nan)
    for p, stage in enumerate(("marker_fit", "partner_fit")):
        d = outputs / session / unit / stage
        if not (d / "fit.npz").exists():
            continue
        fit = BodyFit.load(d)
        rows = np.searchsorted(fit.frames, frames)
        est = forward(model, fit.betas, fit.body_pose[rows], fit.global_orient[rows], fit.transl[rows])
        pred = np.einsum("kn,fnd->fkd", R, np.concatenate([est.vertices, est.joints], 1))
        true = np.einsum("kn,fnd->fkd", R, np.concatenate(
            [gt["vertices"][p][frames].astype(float), gt["joints"][p][frames]], 1))
        worst[p], worst_pub[p] = worst_errors(pred, true, fit_points_observed(model, fit)[rows])
    return worst, worst_pub


def published(outputs: Path, session: str, unit: str, res, frames: np.ndarray, opts) -> np.ndarray:
    """(2, F) whether each person-frame would be published as valid: the fit calls it valid
    and no QA flag of a reason the export withholds for holds it back (``opts``: the recipe's
    ``stages.export.Options``; ``stages.export.qa_withheld`` and ``validity``, the export's own
    rules; the conversion's mask left out)."""
    from artifacts import BodyFit
    from stages.export import validity, withheld_by_qa

    fits = [BodyFit.load(outputs / session / unit / s) for s in ("marker_fit", "partner_fit")]
    ix = [np.searchsorted(f.frames, frames) for f in fits]
    roles = ["wearer", "partner"]
    held = withheld_by_qa(res, frames, fits, roles, opts)
    valid, _ = validity([f.valid[i] for f, i in zip(fits, ix, strict=True)],
                        [f.invalid_reason[i] for f, i in zip(fits, ix, strict=True)], None, held)
    return valid


def run(work: Path) -> dict[str, float]:
    store_work = work.parent / "partner_fit"
    store_work.mkdir(parents=True, exist_ok=True)
    base_path = P.bench_recipe(store_work, P.stride())
    base = yaml.safe_load(base_path.read_text())
    outputs = store_work / "outputs"
    clean_path = work / "clean.yaml"
    clean_path.write_text(yaml.safe_dump(base, sort_keys=False))
    # the clean session: qa of every sequence and the index (fits cached from partner_fit)
    _engine(clean_path, outputs, "partner_fit", work, "clean_fits")
    qa_dirs = list((outputs / base["session"]).glob("*/*/qa"))
    for d in qa_dirs:  # time the qa stage itself: rebuild it
        shutil.rmtree(d)
    wall = _engine(clean_path, outputs, "qa_index", work, "clean_qa")
    summary = json.loads((outputs / base["session"] / "session" / "qa_index" / "summary.json").read_text())
    from body import load_model
    from body.joints import regressor

    model = load_model("anny")
    R = regressor(model, "h36m17")
    R = R.toarray() if hasattr(R, "toarray") else np.asarray(R)
    frames = flagged = flagged_valid = frames_valid = 0
    correct = flagged_correct = defects = flagged_defects = 0
    metrics_s = stage_s = stage_cpu_s = 0.0
    person_frames = published_pf = published_bad = published_bad_joints = 0
    withheld_right, withheld_wrong = {"wearer": 0, "partner": 0}, {"wearer": 0, "partner": 0}
    from stages.export import Options as ExportOptions

    export_opts = ExportOptions(**((base.get("stages") or {}).get("export") or {}))
    per_seq = {}
    for unit in base["sequences"]:
        res = _load_qa(outputs, base["session"], unit)
        qa = res.metrics
        F = len(qa.frames)
        anyf = qa.any
        nv = np.zeros(F, bool)
        for nm in map(str, qa.names):
            if nm.endswith(".not_valid"):
                nv |= np.nan_to_num(qa.metric(nm)) > 0.5
        frames += F
        flagged += int(anyf.sum())
        frames_valid += int((~nv).sum())
        flagged_valid += int((anyf & ~nv).sum())
        metrics_s += res.summary.metrics_s
        timings = json.loads((outputs / base["session"] / unit / "qa" / "manifest.json")
                             .read_text())["timings"]
        stage_s += float(timings["seconds"])
        stage_cpu_s += float(timings["cpu_s"])
        errs, errs_pj = truth_errors(outputs, base["session"], unit, np.asarray(qa.frames),
                                     model, R)
        err = np.nanmax(errs, axis=0)
        ok = (err <= DEFECT_MM) & ~nv
        bad = err > DEFECT_MM
        pub = published(outputs, base["session"], unit, res, np.asarray(qa.frames), export_opts)
        pub_bad = pub & (errs > DEFECT_MM)
        published_bad_joints += int((pub & (errs_pj > DEFECT_MM)).sum())
        person_frames += int(np.isfinite(errs).sum())
        published_pf += int(pub.sum())
        published_bad += int(pub_bad.sum())
        for p, who in enumerate(("wearer", "partner")):
            withheld_right[who] += int((~pub[p] & (errs[p] <= DEFECT_MM)).sum())
            withheld_wrong[who] += int((~pub[p] & (errs[p] > DEFECT_MM)).sum())
        correct += int(ok.sum())
        flagged_correct += int((anyf & ok).sum())
        defects += int(bad.sum())
        flagged_defects += int((anyf & bad).sum())
        per_seq[unit] = {"frames": F, "flagged": int(anyf.sum()),
                         "reasons": dict(res.summary.per_reason),
                         "defect_frames": int(bad.sum()), "flagged_defects": int((anyf & bad).sum()),
                         "flagged_correct": int((anyf & ok).sum()),
                         "published_person_frames": int(pub.sum()),
                         "published_defects": {w: int(pub_bad[p].sum()) for p, w in
                                               enumerate(("wearer", "partner"))},
                         "worst_joint_mm": [round(float(x), 1) for x in err]}
    (work / "clean.json").write_text(json.dumps({"summary": summary, "per_sequence": per_seq}, indent=1))

    # the faults session
    fpath, where = fault_recipe(base, work)
    _engine(fpath, outputs, "qa_index", work, "faults")
    faults = {}
    # marker swap: the burst's video frames (capture sample s at s / rate - offset on the video clock)
    seq = base["sequences"][SWAP_SEQUENCE]
    sw = where["swap"]
    off = float((seq.get("mocap") or {}).get("sync_offset_s") or 0.0)
    t0 = (sw["first_frame"] + sw["first_sample"]) / sw["rate_hz"]
    t1 = (sw["first_frame"] + sw["first_sample"] + sw["samples"]) / sw["rate_hz"]
    fps = float(seq["fps"])
    qa_f = _load_qa(outputs, FAULT_SESSION, SWAP_SEQUENCE)
    qa_c = _load_qa(outputs, base["session"], SWAP_SEQUENCE)
    fr = np.asarray(qa_f.metrics.frames)
    mocap_t = fr / fps - off  # video frame f is at mocap time f / fps - sync_offset_s
    inside = fr[(mocap_t >= t0) & (mocap_t < t1)]
    kind = lambda r: r.startswith("wearer.")  # noqa: E731
    hit = _flagged_by(qa_f, inside, kind) & ~_flagged_by(qa_c, inside, kind)
    faults["marker_swap"] = {"frames": inside.tolist(), "flagged": hit.tolist()}
    # sync offset: the sequence-level estimate for that camera, and the frames it flags
    qa_f = _load_qa(outputs, FAULT_SESSION, SYNC_SEQUENCE)
    qa_c = _load_qa(outputs, base["session"], SYNC_SEQUENCE)
    est = qa_f.summary.sync_offset_frames.get(SYNC_CAMERA)
    est_clean = qa_c.summary.sync_offset_frames.get(SYNC_CAMERA)
    kind = lambda r: r.startswith("sync_offset_frames.") and r.endswith(SYNC_CAMERA)  # noqa: E731
    fr = np.asarray(qa_f.metrics.frames)
    hit = _flagged_by(qa_f, fr, kind) & ~_flagged_by(qa_c, fr, kind)
    why = [(json.loads((outputs / sess / SYNC_SEQUENCE / "qa" / "report.json").read_text())
            ["summary"].get("sync_not_measurable_why") or {}).get(SYNC_CAMERA)
           for sess in (FAULT_SESSION, base["session"])]
    faults["sync_offset"] = {"estimated_frames": est, "clean_estimate": est_clean,
                             "not_measurable": why[0], "clean_not_measurable": why[1],
                             "frames": fr.tolist(), "flagged": hit.tolist()}
    # limb rotation: planted into the partner fit handed to the metrics
    limb = limb_fault(clean_path, outputs, base["session"])
    hit = np.asarray(limb["planted"]["flagged"]) & ~np.asarray(limb["clean"]["flagged"])
    faults["limb_rotation"] = {"frames": limb["frames"], "flagged": hit.tolist(),
                               "reasons": limb["planted"]["reasons"]}
    (work / "faults.json").write_text(json.dumps(faults, indent=1, default=str))
    caught = [bool(np.any(f["flagged"])) for f in faults.values()]
    n_frames = sum(len(f["flagged"]) for f in faults.values())
    n_hit = sum(int(np.sum(f["flagged"])) for f in faults.values())
    return {
        "qa.flag_recall": float(np.mean(caught)),
        "qa.frame_recall": float(n_hit / max(n_frames, 1)),
        "qa.flag_rate_clean": float(flagged / max(frames, 1)),
        "qa.flag_rate_clean_valid": float(flagged_valid / max(frames_valid, 1)),
        "qa.false_flag_rate": float(flagged_correct / max(correct, 1)),
        "qa.defect_recall": float(flagged_defects / max(defects, 1)),
        "qa.defect_frames_clean": float(published_bad / max(published_pf, 1)),
        "qa.defect_person_frames_published": float(published_bad),
        "qa.defect_frames_clean_joints": float(published_bad_joints / max(published_pf, 1)),
        "qa.published_fraction": float(published_pf / max(person_frames, 1)),
        "qa.withheld_right_partner": float(withheld_right["partner"]),
        "qa.withheld_wrong_partner": float(withheld_wrong["partner"]),
        "qa.withheld_right_wearer": float(withheld_right["wearer"]),
        "qa.withheld_wrong_wearer": float(withheld_wrong["wearer"]),
        "qa.defect_frames_all": float(defects),
        "qa.frames_clean": float(frames),
        "qa.s_per_frame": float(stage_s / max(frames, 1)),
        "qa.cpu_s_per_frame": float(stage_cpu_s / max(frames, 1)),
        "qa.metrics_s_per_frame": float(metrics_s / max(frames, 1)),
        "qa.engine_wall_s_per_frame": float(wall / max(frames, 1)),
    }
