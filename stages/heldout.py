"""Stage ``heldout`` (per markerless sequence): a view left out of the fit, the honest figure
where no truth exists (issue #28 item 3).

Each camera in turn is left out: the people are fitted again from the other views (the
partner fit's terms and options, ``stages.partner_fit``'s section of the recipe; their shapes
as ``partner_fit`` found them), on every ``stride``-th fitted frame, and their keypoints
projected into the left-out view against its own detections; beside it the plain baseline,
each keypoint triangulated from the other views (DLT) and projected the same way
(``fitting.heldout``). When the rig was refined from the person (stage ``rig``), the frames
it was refined on are not scored. Writes

- ``report.json``: per camera and over all, for the fit and the baseline, median / p90 px and
  the count per keypoint group (face, body, hands, all), on the same detections; frames per
  CPU second of the refits;
- ``heldout.npz``: per left-out camera and person the per-keypoint errors (``fit_px``,
  ``baseline_px`` (N, 65), NaN where not measured), ``camera``, ``person``, ``frame`` (N,);
- ``heldout.png``: median and p90 per camera and group, fit beside baseline.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.spec import Stage, StageContext
from stages import common


@dataclass(frozen=True)
class Options:
    """stride : every n-th fitted frame is refitted per left-out camera (the refits cost one
    partner fit per camera and person); max_frames : at most this many of them (None: all);
    min_conf : detections below this confidence are not measured (nor triangulated)."""

    stride: int = 5
    max_frames: int | None = None
    min_conf: float = 0.5

    def __post_init__(self):
        if self.stride < 1:
            raise ValueError(f"stride: must be >= 1, got {self.stride}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames: must be >= 1, got {self.max_frames}")
        if not 0 <= self.min_conf <= 1:
            raise ValueError(f"min_conf: must be in [0, 1], got {self.min_conf}")


def raw_inputs(recipe, unit: str):  # noqa: ARG001 (the Stage protocol)
    return {"body_model": common.body_model_file(recipe)}


def scored_frames(frames, stride: int, max_frames: int | None = None, exclude=()) -> np.ndarray:
    """Indices into ``frames`` (video frame indices) the held-out view scores: every
    ``stride``-th, without the video frames in ``exclude`` (those the rig was refined on:
    the figure is measured where the rig saw nothing), at most ``max_frames``."""
    frames = np.asarray(frames, np.int64)
    idx = np.arange(0, len(frames), stride)
    idx = idx[~np.isin(frames[idx], np.asarray(list(exclude), np.int64))]
    return idx[:max_frames] if max_frames else idx


def compute(model, keypoints, fits, cams, o: Options, fit_opts, ground=None, progress=None,
            log=lambda _m: None, exclude_frames=()):
    """The held-out figures of a sequence: ``keypoints`` (``Keypoints2D``, person p in slot
    p), ``fits`` (each person's ``BodyFit``, person 0 first: their shapes), ``cams`` (the
    rig), ``exclude_frames`` (video frames not scored: the rig's refinement frames). Returns
    ``(report, [fitting.heldout.HeldOut])``."""
    from fitting.heldout import held_out_view, summarise
    from stages.partner_fit import person_keypoints

    idx = scored_frames(keypoints.frames, o.stride, o.max_frames, exclude_frames)
    if not len(idx):
        raise ValueError(f"stride: no frame left to score ({keypoints.n_frames} frames, stride "
                         f"{o.stride}, {len(exclude_frames)} refinement frames excluded)")
    people_kp = [person_keypoints(keypoints, p) for p in range(len(fits))]
    betas = [np.asarray(f.betas, float) for f in fits]
    results = []
    for h, cam in enumerate(cams):
        log(f"heldout: {cam.name} left out, {len(idx)} frames x {len(fits)} person(s)")
        results += held_out_view(model, people_kp, betas, cams, h, idx, fit_opts, ground,
                                 o.min_conf, progress=progress)
    rep = summarise(results)
    rep.update({"stride": o.stride, "frames": [int(keypoints.frames[i]) for i in idx],
                "min_conf": o.min_conf, "people": len(fits),
                "excluded_refinement_frames": len(exclude_frames),
                "measured_on": "detections of the left-out view the baseline can predict "
                               "(seen in >= 2 of the other views), the same for fit and baseline"})
    return rep, results


def heldout_plot(path, rep: dict, title: str) -> None:
    """Median (bar) and p90 (tick) px per left-out camera and keypoint group, the fit beside
    the triangulation baseline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = ("body", "hands", "face")
    cams = list(rep["cameras"])
    fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 3.2), sharey=True)
    x = np.arange(len(cams))
    for ax, g in zip(axes, groups, strict=True):
        for k, (who, colour) in enumerate((("fit", "tab:blue"), ("baseline", "tab:gray"))):
            med = [rep["cameras"][c][who][g]["median_px"] or np.nan for c in cams]
            p90 = [rep["cameras"][c][who][g]["p90_px"] or np.nan for c in cams]
            ax.bar(x + (k - 0.5) * 0.38, med, 0.38, color=colour,
                   label=f"{'fit from the other views' if who == 'fit' else 'triangulation'}")
            ax.scatter(x + (k - 0.5) * 0.38, p90, marker="_", s=200, color="k")
        ax.set_xticks(x, cams, rotation=30)
        ax.set_title(g)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("px in the left-out view (bar median, tick p90)")
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run(ctx: StageContext) -> None:
    from artifacts import BodyFit
    from artifacts.keypoints import Keypoints2D
    from stages.partner_fit import Options as FitOptions

    o: Options = ctx.params or Options()
    rv = ctx.recipe
    model = common.load_body(ctx)
    cams = common.capture_cameras(ctx, list(rv.cameras))
    keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    fits = [BodyFit.load(a) for a, _ in common.fitted_people(ctx)]
    ground = common.ground_of(rv)
    fit_opts = FitOptions()  # the partner fit's default terms and weights
    rig = ctx.inputs.get("rig")  # a rig refined from the person: not scored on its frames
    exclude = (np.load(common.artifact_folder(rig) / "refine.npz")["frames"]
               if rig is not None and not isinstance(rig, dict) else np.zeros(0, np.int64))
    rep, results = compute(model, keypoints, fits, cams, o, fit_opts, ground,
                           progress=ctx.progress, log=lambda s: ctx.log(f"{ctx.unit}: {s}"),
                           exclude_frames=exclude)
    rep["sequence"] = ctx.unit
    rep["rig"] = "refined from the person (stage rig)" if len(exclude) else "as calibrated"
    ctx.out.save_arrays(
        "heldout",
        fit_px=np.concatenate([r.fit_px for r in results]),
        baseline_px=np.concatenate([r.baseline_px for r in results]),
        camera=np.concatenate([[r.camera] * len(r.frames) for r in results]).astype(str),
        person=np.concatenate([[r.person] * len(r.frames) for r in results]).astype(np.int64),
        frame=np.concatenate([r.frames for r in results]).astype(np.int64))
    heldout_plot(ctx.out.path("heldout.png"), rep, f"{ctx.unit}: held-out view")
    rep["plot"] = "heldout.png"
    ctx.out.save_json("report", rep)
    a = rep["all"]
    ctx.log(f"{ctx.unit}: held-out view median {a['fit']['all']['median_px']} px (p90 "
            f"{a['fit']['all']['p90_px']}), triangulation baseline {a['baseline']['all']['median_px']}"
            f" px (p90 {a['baseline']['all']['p90_px']})")


STAGE = Stage(name="heldout", func=run, per="sequence", upstream=("keypoints", "rig", "partner_fit"),
              params=Options, raw_inputs=raw_inputs, version="1",
              reads=("body_model.kind", "cameras", "ground_plane", "sequence.people"),
              doc="a view left out of the fit: reprojection into it against its detections, "
                  "and the triangulation baseline (markerless sequences)")
