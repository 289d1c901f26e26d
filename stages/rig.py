"""Stage ``rig`` (per sequence, when the recipe says ``sequences.<id>.refine_rig: true``): the
camera rig refined from the person (issue #28: a lab's calibration off by several to tens of
pixels limits every fit and the held-out view).

A bundle adjustment of the cameras' extrinsics (and, when asked, focal length and principal
point) against the people's confident 2D detections in all views, the 3D points unknown,
with a prior towards the given calibration (``calib.rig_refine``). The gauge (a similarity of
the world) is fixed by mapping the refined camera centres onto the given ones (least-squares
similarity: the centres' centroid, scale and overall orientation stay the calibration's), so
the world frame and the ground plane stay where the recipe put them.

Honest held-out figure: the refinement sees only the frames of the even-numbered blocks of
``block`` video frames (frames ``0..block-1``, ``2 block..3 block-1``, ...); the ``heldout``
stage scores only the other frames (it reads ``refine.npz``'s ``frames``).

Every stage that uses the cameras reads this rig when the stage ran
(``stages.common.capture_cameras``): partner fit, held-out view, QA, export. Writes

- ``rig.npz``: ``artifacts.capture.CameraRig``, the refined cameras (recipe order);
- ``refine.npz``: ``frames`` (the video frames the refinement used), ``before_px`` /
  ``after_px`` (C, N) each used observation's reprojection error against its point
  triangulated (DLT, all views) with the given / refined rig, ``points`` (N, 3);
- ``report.json``: per camera how far it moved (centre mm, rotation degrees, focal %,
  principal point px), the observations used and their median / p90 / RMS px before and after
  on the refinement frames; the gauge; the options;
- ``rig.png``: that table as a figure.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from calib.rig_refine import PersonRefineOptions
from pipeline.spec import Stage, StageContext
from stages import common


@dataclass(frozen=True)
class Options(PersonRefineOptions):
    """block: frames per block; the refinement uses the even-numbered blocks of video frames,
    the held-out view scores the odd-numbered ones. min_gain: the check (see :func:`compute`)
    must improve by at least this share, else the rig stays as calibrated. min_conf: detections
    at or above this confidence are used. keypoints: ``"all"`` KP65 keypoints or ``"body"``
    (face and body, no hands). The rest are ``calib.rig_refine.PersonRefineOptions``' (the
    prior's sigmas, whether focal length / principal point are refined, the robust loss), with
    up to 6000 points here."""

    block: int = 10
    min_gain: float = 0.05
    min_conf: float = 0.6
    keypoints: Literal["all", "body"] = "all"
    max_points: int = 6000

    def __post_init__(self):
        if not (isinstance(self.block, int) and self.block >= 1):
            raise ValueError(f"block: must be an integer >= 1, got {self.block!r}")
        if not 0 <= self.min_gain < 1:
            raise ValueError(f"min_gain: must be in [0, 1), got {self.min_gain}")
        if not 0 <= self.min_conf <= 1:
            raise ValueError(f"min_conf: must be in [0, 1], got {self.min_conf}")
        if self.keypoints not in ("all", "body"):
            raise ValueError(f"keypoints: must be 'all' or 'body', got {self.keypoints!r}")
        super().__post_init__()  # its own checks, naming the field

    def refine_options(self) -> PersonRefineOptions:
        names = {f.name for f in fields(PersonRefineOptions)}
        return PersonRefineOptions(**{k: getattr(self, k) for k in names})


def refinement_frames(frames: np.ndarray, block: int) -> np.ndarray:
    """Which of the video ``frames`` the refinement may use: those in even-numbered blocks of
    ``block`` frames (bool, same shape)."""
    return (np.asarray(frames, np.int64) // int(block)) % 2 == 0


def observations(kp: np.ndarray, frames: np.ndarray, o: Options, use=None) -> np.ndarray:
    """``(C, N, 2)`` pixels of every person's keypoint at every refinement frame (or the frames
    where ``use``, a subset of them; NaN where the detection's confidence is below
    ``min_conf``): ``kp (C, F, persons, 65, 3)``."""
    kp = np.asarray(kp, float)
    ref = refinement_frames(frames, o.block)
    use = ref if use is None else (ref & np.asarray(use, bool))
    K = np.arange(23) if o.keypoints == "body" else np.arange(kp.shape[3])
    sub = kp[:, use][:, :, :, K]
    uv = np.where(sub[..., 2:3] >= o.min_conf, sub[..., :2], np.nan)
    return uv.reshape(kp.shape[0], -1, 2)


def leave_one_out_px(cams, kp: np.ndarray, min_conf: float) -> float:
    """Median px of every detection ``kp (C, F, persons, 65, 3)`` against its keypoint
    triangulated (DLT) from the other views and projected into its view (the held-out view's
    baseline), NaN when nothing is measured."""
    from fitting.heldout import pixel_errors, triangulated

    kp = np.asarray(kp, float)
    errs = []
    for h in range(len(cams)):
        oth = [i for i in range(len(cams)) if i != h]
        for p in range(kp.shape[2]):
            X = triangulated([cams[i] for i in oth], kp[oth][:, :, p], min_conf)
            e = pixel_errors(cams[h], X, kp[h, :, p], min_conf)
            errs.append(e[np.isfinite(e)])
    e = np.concatenate(errs) if errs else np.zeros(0)
    return float(np.median(e)) if len(e) else float("nan")


def compute(cams, keypoints, o: Options, log=lambda _m: None):
    """The refinement of ``cams`` (``calib.Camera`` s, recipe order) from ``keypoints``
    (``Keypoints2D``, same cameras), on the refinement frames only.

    First a check, inside the refinement frames: the rig refined on half of their blocks
    must bring the leave-one-camera-out triangulation error (the held-out baseline) on the
    other half down by ``min_gain`` against the given rig; if not (detections whose errors a
    rig cannot explain, e.g. a calibration already exact), the rig stays as calibrated
    (``applied`` false). Then the refinement on all of them.

    Returns ``(calib.rig_refine.PersonRefinement, frames used, report)``; the refinement's
    cameras are the given ones when not applied. ValueError when the refinement frames hold
    too few detections."""
    from calib.rig_refine import refine_from_points

    frames = np.asarray(keypoints.frames, np.int64)
    ref = refinement_frames(frames, o.block)
    used_frames = frames[ref]
    if not len(used_frames):
        raise ValueError(f"block: no refinement frame (frames {frames.min()}..{frames.max()}, "
                         f"block {o.block})")
    # the check: fit on the blocks 0, 4, 8, ... (x block), measure on 2, 6, 10, ...
    half = (frames // o.block) % 4 == 0
    chk = ref & ~half
    check = {"fit_frames": int((ref & half).sum()), "check_frames": int(chk.sum())}
    applied = True
    if check["fit_frames"] and check["check_frames"]:
        log("rig refinement: the check (half of the refinement frames)")
        r_half = refine_from_points(cams, observations(keypoints.kp, frames, o, use=half),
                                    o.refine_options())
        kp_chk = np.asarray(keypoints.kp, float)[:, chk]
        given_px = leave_one_out_px(cams, kp_chk, o.min_conf)
        refined_px = leave_one_out_px(list(r_half.cameras), kp_chk, o.min_conf)
        applied = bool(refined_px <= (1 - o.min_gain) * given_px)
        check.update({"given_px": round(given_px, 2), "refined_px": round(refined_px, 2),
                      "min_gain": o.min_gain, "passed": applied})
        log(f"rig refinement check: leave-one-camera-out median {given_px:.2f} px as "
            f"calibrated, {refined_px:.2f} px refined on the other half: "
            f"{'applied' if applied else 'NOT applied (the rig stays as calibrated)'}")
    else:
        check.update({"passed": None, "why": "too few blocks for a check"})
    uv = observations(keypoints.kp, frames, o)
    r = refine_from_points(cams, uv, o.refine_options(), log=log)
    solved = {c.name: {"moved_mm": round(float(r.moved_mm[i]), 1),
                       "rotated_deg": round(float(r.rotated_deg[i]), 3)} for i, c in enumerate(cams)}
    if not applied:  # the rig stays as calibrated (the report keeps what the solve found)
        z = np.zeros(len(cams))
        r = dataclasses.replace(r, cameras=tuple(cams), moved_mm=z, rotated_deg=z, focal_rel=z,
                                principal_px=z, after_px=r.before_px)

    def stats(e):
        e = e[np.isfinite(e)]
        return {"median_px": round(float(np.median(e)), 2),
                "p90_px": round(float(np.percentile(e, 90)), 2),
                "rms_px": round(float(np.sqrt(np.mean(e ** 2))), 2)}

    per = {}
    for i, c in enumerate(cams):
        per[c.name] = {"moved_mm": round(float(r.moved_mm[i]), 1),
                       "rotated_deg": round(float(r.rotated_deg[i]), 3),
                       "focal_change_pct": round(100 * float(r.focal_rel[i]), 3),
                       "principal_moved_px": round(float(r.principal_px[i]), 2),
                       "observations": int(r.used[i].sum()),
                       "before": stats(r.before_px[i]), "after": stats(r.after_px[i])}
    rep = {"applied": applied, "check": check, "solved": solved,
           "cameras": per, "all": {"before": stats(r.before_px), "after": stats(r.after_px)},
           "frames_used": [int(f) for f in used_frames], "block": o.block,
           "scored_by_heldout": "the frames of odd-numbered blocks (not used here)",
           "gauge": r.gauge, "points": int(np.isfinite(r.points[:, 0]).sum()),
           "solver": {"cost_before": round(r.cost_before, 1), "cost_after": round(r.cost_after, 1),
                      "nfev": r.nfev, "status": r.status},
           "errors_measured_as": "each used detection against its keypoint triangulated (DLT) "
                                 "from all views with the given / refined rig, on the "
                                 "refinement frames",
           "options": {f.name: getattr(o, f.name) for f in fields(o)}}
    return r, used_frames, rep


def rig_plot(path, rep: dict, title: str) -> None:
    """Per camera: median (bar) and p90 (tick) px before and after on the refinement frames,
    and how far the camera moved (mm, degrees) written under it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = list(rep["cameras"])
    x = np.arange(len(cams))
    fig, ax = plt.subplots(figsize=(1.8 * len(cams) + 2, 3.4))
    for k, (who, colour) in enumerate((("before", "tab:gray"), ("after", "tab:blue"))):
        med = [rep["cameras"][c][who]["median_px"] for c in cams]
        p90 = [rep["cameras"][c][who]["p90_px"] for c in cams]
        ax.bar(x + (k - 0.5) * 0.38, med, 0.38, color=colour,
               label="given calibration" if who == "before" else "refined from the person")
        ax.scatter(x + (k - 0.5) * 0.38, p90, marker="_", s=200, color="k")
    ax.set_xticks(x, [f"{c}\n{rep['cameras'][c]['moved_mm']:.0f} mm, "
                      f"{rep['cameras'][c]['rotated_deg']:.2f} deg" for c in cams], fontsize=8)
    ax.set_ylabel("px on the refinement frames\n(bar median, tick p90)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def given_rig(ctx):
    """The rig as the calibration files gave it: ``([calib.Camera], [file names])`` from the
    ``capture`` stage (or, on a markerless sequence, the ``keypoints`` stage)."""
    from artifacts.capture import CameraRig

    for stage in ("capture", "keypoints"):
        art = ctx.inputs.get(stage)
        if art is not None and not isinstance(art, dict) and (
                common.artifact_folder(art) / "rig.npz").exists():
            rig = CameraRig.load(art)
            return rig.cameras(list(ctx.recipe.cameras)), [str(s) for s in rig.source]
    return None


def run(ctx: StageContext) -> None:
    from artifacts.capture import CameraRig
    from artifacts.keypoints import Keypoints2D
    from formats.errors import InputError

    o: Options = ctx.params or Options()
    got = given_rig(ctx)
    if got is None:
        raise InputError(ctx.recipe_path or "<recipe>", f"sequences.{ctx.unit}.refine_rig",
                         "the sequence has no calibrated cameras to refine")
    cams, sources = got
    keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    order = [keypoints.camera(c.name) for c in cams]
    keypoints = dataclasses.replace(keypoints, kp=keypoints.kp[order],
                                    cameras=keypoints.cameras[order])
    try:
        r, used_frames, rep = compute(cams, keypoints, o, log=lambda s: ctx.log(f"{ctx.unit}: {s}"))
    except ValueError as e:
        raise InputError(ctx.recipe_path or "<recipe>", f"stages.rig ({ctx.unit})", str(e)) from None
    CameraRig.from_cameras(r.cameras, sources).save(ctx.out)
    ctx.out.save_arrays("refine", frames=np.asarray(used_frames, np.int64),
                        before_px=r.before_px, after_px=r.after_px, points=r.points)
    ck = rep["check"]
    rig_plot(ctx.out.path("rig.png"), rep,
             f"{ctx.unit}: rig refined from the person ({len(used_frames)} frames)"
             if rep["applied"] else
             f"{ctx.unit}: rig NOT refined (check: {ck.get('given_px')} px as calibrated, "
             f"{ck.get('refined_px')} px refined; gain < {o.min_gain:.0%})")
    rep.update({"sequence": ctx.unit, "plot": "rig.png"})
    ctx.out.save_json("report", rep)
    for c, v in rep["cameras"].items():
        ctx.log(f"{ctx.unit}: {c} moved {v['moved_mm']} mm, {v['rotated_deg']} deg; median "
                f"{v['before']['median_px']} -> {v['after']['median_px']} px")


STAGE = Stage(name="rig", func=run, per="sequence", upstream=("capture", "keypoints"),
              params=Options, version="1", reads=("cameras",),
              doc="the camera rig refined from the person's detections (bundle adjustment with "
                  "a prior to the given calibration; sequences with refine_rig)")
