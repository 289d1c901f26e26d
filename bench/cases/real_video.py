"""Real video (issue #28 item 5): the Pose2Sim demo lab recording
(``/work/shared/real/video/pose2sim_demo``: four Qualisys video cameras, 60 fps, 100 frames,
one person, an operator in the background of two views; ``recipes/pose2sim_demo.yaml``, a
markerless sequence) through the engine as ``make sequence`` runs it (same ``outputs/``
folder: a ``make sequence RECIPE=recipes/pose2sim_demo.yaml SEQ="demo/Walk 1"`` before makes
this case read its cache), and the studio's markerless preset (the small studio session with
nobody's markers used and no scans: :func:`markerless_recipe`) measured the same way and
against its truth.

No 3D truth on the real recording: the honest figure is the held-out view (stage
``heldout``: each camera left out, the fit from the other three projected into it against its
detections), beside the plain per-keypoint triangulation of the other three views.

Keys (``<p>`` = ``real_video`` for the lab recording, ``real_video.studio`` for the preset):
- ``<p>.heldout_median_px`` / ``heldout_p90_px``: all keypoints, all cameras;
  ``<p>.heldout_<group>_median_px`` (body, hands, face);
- ``<p>.baseline_median_px`` / ``baseline_p90_px`` (and per group): the triangulation;
- ``<p>.heldout_minus_baseline_px``: median fit - median baseline (goal < 0);
- ``<p>.heldout_<camera>_median_px``: per left-out camera;
- ``<p>.operator_frames`` (lab): frames with a bystander found in 3D (the operator);
  ``<p>.operator_fitted_frames``: of the fitted frames, those whose fitted root (pelvis) is
  nearer a bystander's root than the subject's triangulated root (goal 0);
  ``<p>.others_in_views_frames``: frames where some view has a detection that is not the
  subject (the operator, seen by one view or two); ``<p>.operator_fitted_frames_2d``: frames
  where, in such a view, the fitted pelvis projects nearer that detection's hips than the
  subject's (goal 0);
- ``<p>.frames_valid_share``: valid fitted frames / frames;
- ``<p>.fps_per_cpu_s``: frames per CPU second of the keypoints and the fit together;
- ``<p>.shape_bone_rms_mm``: the shape from the views, bone rms after the fit (and
  ``..._mean_shape_mm`` before);
- studio: ``real_video.studio.mpjpe_mm`` / ``pa_mpjpe_mm`` / ``transl_err_mm`` / ``mpvpe_mm``
  (the evaluator against the truth, every valid person-frame);
  ``real_video.studio.shape_v2v_mm`` (pose-0 vertex error of the shape from the views
  against the true shape, roots together; ``..._mean_shape_mm``: the mean shape's) and
  ``shape_height_error_mm``.
- the rig refined from the person (stage ``rig``, ``refine_rig: true`` in the recipe; the
  held-out view then scores only the frames the refinement did not see):
  ``<p>.rig_<camera>_moved_mm`` / ``_rotated_deg``, ``<p>.rig_before_median_px`` /
  ``rig_after_median_px`` (every view's detections against their all-view triangulation on
  the refinement frames); ``<p>.given_rig.heldout_median_px`` / ``_p90_px`` /
  ``baseline_*`` / per camera: the held-out view with the rig as calibrated on the same
  scored frames (the people's shapes of the refined run), what the refinement brings;
- studio: ``real_video.studio.given_rig.mpjpe_mm`` (...): the same preset run with the rig as
  calibrated (no refinement), against the truth.
- Every ``given_rig`` figure (the lab's and the studio's) is measured only with
  ``BENCH_REAL_VIDEO_GIVEN_RIG=1`` (:func:`given_rig_wanted`): they refit the held-out
  frames once more and run the studio preset a second time, about half the case's wall, and
  ``make bench`` has 45 minutes for every case (issue #29); without it their rows say which
  code measured them.
The overlay of the fitted mesh on all four views: ``bench/work/real_video/real_video_overlay.png``.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "pose2sim_demo.yaml"
SEQ = "demo/Walk 1"
STUDIO_SEQ = "s01/Handshake 1"
STUDIO_PLAN = {"seed": 7, "frames": 24, "scenarios": ("handshake", "push")}  # tests' session
GOALS = {"real_video.heldout_median_px": ("<=", 8.0),
         "real_video.heldout_minus_baseline_px": ("<", 0.0),
         "real_video.operator_fitted_frames": ("==", 0.0),
         "real_video.operator_fitted_frames_2d": ("==", 0.0),
         "real_video.studio.heldout_minus_baseline_px": ("<", 0.0)}
LIMITS = {"real_video.heldout_median_px": (
    "the detections and what is left of the calibration: the Qualisys calibration put the "
    "three-view triangulation ~20 px off in the fourth view with a consistent direction per "
    "camera (median offset cam01 (-20, -4) px, cam03 (-17, -16) px); the rig refined from the "
    "person (stage rig, refine_rig in the recipe: a bundle adjustment on the even blocks of 10 "
    "frames, the held-out view scored on the others; real_video.given_rig.* is the same "
    "figure with the rig as calibrated) removes those offsets (per-camera median offset < 2 px "
    "after) and brings the held-out view and the baseline to ~12 px; what is left is not a "
    "constant offset per camera: the mediapipe keypoints disagree between views by about that "
    "much on a person ~1100 px tall (the refinement frames' all-view reprojection is ~6 px "
    "median after the refinement, a three-view triangulation doubles it in the fourth)"),
    "real_video.heldout_minus_baseline_px": (
        "with the refined rig the fit and the triangulation agree within ~0.5 px on this "
        "recording (one person, walking, no contact: the body model has little to add over "
        "four views' triangulation of a clear person); on the studio's markerless preset the "
        "fit from three views is better than the triangulation "
        "(real_video.studio.heldout_minus_baseline_px)")}


def markerless_recipe(src: Path, dst: Path, sequences: list[str] | None = None,
                      scans: bool = False, stages: dict | None = None,
                      refine_rig: bool = False, session_suffix: str = "") -> Path:
    """A markerless recipe from a studio recipe: the same videos and calibration, nobody's
    markers (``markers_on`` and ``c3d`` dropped, the wearer and partner become ``people``),
    scans dropped unless ``scans`` (the shape is then estimated from the views), the truth
    kept for ``evaluate``; paths made absolute (the studio's data stay where they are);
    ``refine_rig`` on every sequence; the session named ``<session>_markerless<suffix>``."""
    src, dst = Path(src).resolve(), Path(dst)
    r = yaml.safe_load(src.read_text())
    base = src.parent

    def ab(p):
        return str((base / p).resolve())

    for s in r["subjects"].values():
        if scans and s.get("scan"):
            s["scan"] = ab(s["scan"])
        else:
            s.pop("scan", None)
    seqs = {}
    actions = {q.split("/", 1)[1] for q in r["sequences"]}
    for q, s in r["sequences"].items():
        if sequences is not None and q not in sequences:
            continue
        t = {k: v for k, v in s.items() if k not in ("markers_on", "partner", "c3d", "mocap")}
        t["people"] = [s["markers_on"]] + ([s["partner"]] if s.get("partner") else [])
        t["videos"] = {c: ab(p) for c, p in s["videos"].items()}
        t["calibration"] = {c: ab(p) for c, p in s["calibration"].items()}
        if s.get("contact"):
            t["contact"] = ab(s["contact"])
        if refine_rig:
            t["refine_rig"] = True
        seqs[q] = t
    r["sequences"] = seqs
    r["session"] = f"{r['session']}_markerless{session_suffix}"
    st = dict(stages or {})
    truth = (r.get("stages") or {}).get("evaluate", {}).get("truth")
    if truth:
        st["evaluate"] = {"truth": ab(truth)}
        if sequences is not None:  # the truth of the kept sequences only (the evaluator
            # wants every action of its truth in the release)
            drop = actions - {q.split("/", 1)[1] for q in seqs}
            own = dst.parent / f"truth_{r['session']}"
            shutil.rmtree(own, ignore_errors=True)
            shutil.copytree(ab(truth), own, ignore=lambda _d, names: [
                n for n in names if Path(n).stem in drop])
            st["evaluate"] = {"truth": str(own.resolve())}
    r["stages"] = st
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(yaml.safe_dump(r, sort_keys=False))
    return dst


def studio_recipe(work: Path) -> Path:
    """The small studio session (the tests' one), copied into ``work`` from
    ``assets/cache/test_session`` when it is there, else generated there."""
    from studio import plan as PL
    from studio.session import generate, source_hash

    own = work / f"studio_{source_hash()}"
    if (own / "recipe.yaml").is_file():
        return own / "recipe.yaml"
    for old in work.glob("studio_*"):  # older studio versions
        if old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
    cached = REPO / "assets" / "cache" / "test_session" / source_hash()
    tmp = work / f".studio_tmp_{source_hash()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:  # a copy: the tests' cache is replaced whenever the studio's code changes
        shutil.copytree(cached, tmp)
        if not (tmp / "recipe.yaml").is_file():
            raise FileNotFoundError(cached)
    except (OSError, shutil.Error):
        shutil.rmtree(tmp, ignore_errors=True)
        generate(tmp, PL.make_plan(STUDIO_PLAN["seed"], STUDIO_PLAN["frames"],
                                   STUDIO_PLAN["scenarios"]))
    tmp.rename(own)
    return own / "recipe.yaml"


def _rig_folder(base: Path) -> Path:
    """The artifact holding the rig the fit used: ``rig/`` (refined from the person) when the
    sequence has one, else ``keypoints/`` (as calibrated)."""
    return base / "rig" if (base / "rig" / "rig.npz").is_file() else base / "keypoints"


def rig_keys(p: str, base: Path) -> dict[str, float]:
    """How far the refinement moved each camera, and the refinement frames' reprojection
    before / after (stage ``rig``'s report); {} when the rig was not refined."""
    f = base / "rig" / "report.json"
    if not f.is_file():
        return {}
    rep = json.loads(f.read_text())
    out = {f"{p}.rig_before_median_px": rep["all"]["before"]["median_px"],
           f"{p}.rig_after_median_px": rep["all"]["after"]["median_px"],
           f"{p}.rig_frames": float(len(rep["frames_used"]))}
    for c, r in rep["cameras"].items():
        out[f"{p}.rig_{c}_moved_mm"] = r["moved_mm"]
        out[f"{p}.rig_{c}_rotated_deg"] = r["rotated_deg"]
        out[f"{p}.rig_{c}_before_median_px"] = r["before"]["median_px"]
        out[f"{p}.rig_{c}_after_median_px"] = r["after"]["median_px"]
    return {k: float(v) for k, v in out.items()}


def given_rig_wanted() -> bool:
    """Whether this run measures the ``given_rig`` figures (``BENCH_REAL_VIDEO_GIVEN_RIG=1``):
    the held-out view refitted with the rig as calibrated (one partner fit per left-out camera
    and scored frame again, ~1/4 of the case) and the studio preset's second run."""
    return os.environ.get("BENCH_REAL_VIDEO_GIVEN_RIG", "") not in ("", "0")


def given_rig_heldout(base: Path, recipe) -> dict:
    """The held-out view with the rig as calibrated (``keypoints/rig.npz``) on the frames the
    ``heldout`` stage scored with the refined rig (the refinement's frames excluded), the
    people's shapes as the refined run found them: the report of ``stages.heldout.compute``."""
    from artifacts import BodyFit
    from artifacts.capture import CameraRig
    from artifacts.keypoints import Keypoints2D
    from body import load_model
    from stages.heldout import Options as HeldOptions
    from stages.heldout import compute
    from stages.partner_fit import Options as FitOptions

    model = load_model(recipe.body_model.kind)
    kp = Keypoints2D.load(base / "keypoints")
    cams = CameraRig.load(base / "keypoints").cameras(list(recipe.cameras))
    fits = [BodyFit.load(base / "partner_fit" / "person0")]
    if (base / "partner_fit" / "fit.npz").is_file():
        fits.append(BodyFit.load(base / "partner_fit"))
    o = HeldOptions(**(recipe.stages.get("heldout") or {}))
    exclude = np.load(base / "rig" / "refine.npz")["frames"]
    ground = (np.asarray(recipe.ground_plane.normal, float), float(recipe.ground_plane.offset))
    rep, _ = compute(model, kp, fits, cams, o, FitOptions(), ground, exclude_frames=exclude)
    scored = json.loads((base / "heldout" / "report.json").read_text())["frames"]
    if rep["frames"] != scored:
        raise RuntimeError(f"given-rig held-out frames {rep['frames']} != the stage's {scored}")
    return rep


def _heldout_keys(p: str, rep: dict) -> dict[str, float]:
    out: dict[str, float] = {}
    a = rep["all"]
    for who, key in (("fit", "heldout"), ("baseline", "baseline")):
        out[f"{p}.{key}_median_px"] = a[who]["all"]["median_px"]
        out[f"{p}.{key}_p90_px"] = a[who]["all"]["p90_px"]
        for g in ("body", "hands", "face"):
            if a[who][g]["median_px"] is not None:
                out[f"{p}.{key}_{g}_median_px"] = a[who][g]["median_px"]
    out[f"{p}.heldout_minus_baseline_px"] = (a["fit"]["all"]["median_px"]
                                            - a["baseline"]["all"]["median_px"])
    for cam, r in rep["cameras"].items():
        if r["fit"]["all"]["median_px"] is not None:
            out[f"{p}.heldout_{cam}_median_px"] = r["fit"]["all"]["median_px"]
            out[f"{p}.baseline_{cam}_median_px"] = r["baseline"]["all"]["median_px"]
    return {k: float(v) for k, v in out.items() if v is not None}


def _fit_keys(p: str, base: Path) -> dict[str, float]:
    """Validity, speed and the shape from the views, from the keypoints and partner_fit
    reports of a markerless sequence's artifact folder ``base``."""
    kr = json.loads((base / "keypoints" / "report.json").read_text())
    pr = json.loads((base / "partner_fit" / "report.json").read_text())
    people = pr.get("people") or {}
    frames = int(pr["frames"])
    valid = [r["frames_valid"] for r in people.values()] or [pr["frames_valid"]]
    cpu = float(kr["cpu_s"]) + sum(float(r["fit_cpu_s"]) for r in people.values())
    out = {f"{p}.frames_valid_share": float(np.mean(valid)) / max(frames, 1),
           f"{p}.fps_per_cpu_s": frames / cpu if cpu > 0 else float("nan"),
           f"{p}.keypoints_fps_per_cpu_s": float(kr["fps_per_core"])}
    bones = [r["shape"] for r in people.values() if r["shape"].get("source") == "views"]
    if bones:
        out[f"{p}.shape_bone_rms_mm"] = float(np.mean([b["bone_rms_mm"] for b in bones]))
        out[f"{p}.shape_bone_rms_mean_shape_mm"] = float(
            np.mean([b["bone_rms_mean_shape_mm"] for b in bones]))
    return out


def operator_counts(base: Path) -> dict[str, float]:
    """Frames with a bystander found in 3D, and fitted frames whose fitted pelvis is nearer a
    bystander's root than the subject's own triangulated root (the operator fitted as the
    subject)."""
    from artifacts import BodyFit
    from body import forward, load_model

    z = np.load(base / "keypoints" / "people.npz")
    fr = np.asarray(z["frames"])
    subj = np.asarray(z["people_root"])[:, 0]
    bf, broot = np.asarray(z["bystander_frame"]), np.asarray(z["bystander_root"])
    fit = BodyFit.load(base / "partner_fit" / "person0")
    model = load_model("anny")
    J = forward(model, np.asarray(fit.betas, float), fit.body_pose, fit.global_orient,
                fit.transl).joints
    pelvis = J[:, 0]  # the root joint
    from artifacts.capture import CameraRig
    from artifacts.keypoints import Keypoints2D
    from fitting.heldout import project_front

    cams = CameraRig.load(_rig_folder(base)).cameras()
    kp = Keypoints2D.load(base / "keypoints")
    of, oc, ouv = (np.asarray(z["others_2d_frame"]), np.asarray(z["others_2d_camera"]),
                   np.asarray(z["others_2d_uv"]))
    wrong2d: set = set()
    for i, f in enumerate(np.asarray(fit.frames)):  # in 2D: every view an other one is seen in
        if not fit.valid[i]:
            continue
        k = int(np.searchsorted(fr, f))
        for c in np.unique(oc[of == f]):
            hips = np.asarray(kp.kp[c, k, 0, 11:13], float)  # l_hip, r_hip of the subject
            if not np.all(hips[:, 2] > 0):
                continue
            p = project_front(cams[c], pelvis[i])
            d_subj = np.linalg.norm(p - hips[:, :2].mean(0))
            d_other = np.linalg.norm(ouv[(of == f) & (oc == c)] - p, axis=1).min()
            if d_other < d_subj:
                wrong2d.add(int(f))
    wrong = 0
    for i, f in enumerate(np.asarray(fit.frames)):
        if not fit.valid[i]:
            continue
        k = np.searchsorted(fr, f)
        ops = broot[bf == f]
        if not len(ops) or k >= len(fr) or not np.all(np.isfinite(subj[k])):
            continue
        if np.linalg.norm(ops - pelvis[i], axis=1).min() < np.linalg.norm(subj[k] - pelvis[i]):
            wrong += 1
    return {"operator_frames": float(len(np.unique(bf))), "operator_fitted_frames": float(wrong),
            "others_in_views_frames": float(len(np.unique(of))),
            "operator_fitted_frames_2d": float(len(wrong2d))}


def shape_accuracy(base: Path, truth_npz: Path) -> dict[str, float]:
    """How well the shape from the views matches the studio's truth: each fitted person
    matched to the true person nearest its root at its first valid frame; the pose-0
    meshes (roots together) compared vertex to vertex, mm, for the estimated betas and for the
    mean shape they started from; and the height (the pose-0 mesh's extent along z) error."""
    from artifacts import BodyFit
    from body import forward, load_model

    model = load_model("anny")
    gt = np.load(truth_npz)
    tb, tj, tf = gt["betas"], gt["joints"], np.asarray(gt["frames"])
    fits = [BodyFit.load(base / "partner_fit" / "person0")]
    if (base / "partner_fit" / "fit.npz").is_file():
        fits.append(BodyFit.load(base / "partner_fit"))
    v2v, v2v0, dh = [], [], []

    def rest(b):  # pose 0 (bench.cases.shape_fit.v2v_mm says why not the template space)
        r = forward(model, np.asarray(b, float), np.zeros((1, model.num_joints, 3)),
                    np.eye(3)[None], np.zeros((1, 3)))
        V, J = r.vertices[0], r.joints[0]
        return V - J[0], np.ptp(V[:, 2])

    for fit in fits:
        i = int(np.flatnonzero(fit.valid)[0])
        root = forward(model, np.asarray(fit.betas, float), fit.body_pose[i:i + 1],
                       fit.global_orient[i:i + 1], fit.transl[i:i + 1]).joints[0, 0]
        k = int(np.searchsorted(tf, fit.frames[i]))
        who = int(np.argmin(np.linalg.norm(tj[:, k, 0] - root, axis=1)))
        ve, he = rest(fit.betas)
        vt, ht = rest(tb[who])
        v0, _ = rest(np.zeros_like(fit.betas))
        v2v.append(np.linalg.norm(ve - vt, axis=1).mean() * 1000)
        v2v0.append(np.linalg.norm(v0 - vt, axis=1).mean() * 1000)
        dh.append(abs(he - ht) * 1000)
    return {"shape_v2v_mm": float(np.mean(v2v)), "shape_v2v_mean_shape_mm": float(np.mean(v2v0)),
            "shape_height_error_mm": float(np.mean(dh))}


def overlay_png(base: Path, videos: list[Path], dst: Path, frame: int | None = None) -> Path:
    """The fitted mesh on all four views (``videos`` in the rig's order) at one frame (the
    middle one), tiled: ``dst``."""
    from artifacts import BodyFit
    from artifacts.capture import CameraRig
    from body import forward, load_model
    from drawing.overlay import render_overlays

    model = load_model("anny")
    rig = CameraRig.load(_rig_folder(base))
    fits = [BodyFit.load(base / "partner_fit" / "person0")]
    if (base / "partner_fit" / "fit.npz").is_file():
        fits.append(BodyFit.load(base / "partner_fit"))
    frames = np.asarray(fits[0].frames)
    f = int(frames[len(frames) // 2]) if frame is None else int(frame)
    verts = [forward(model, np.asarray(b.betas, float), b.body_pose, b.global_orient,
                     b.transl).vertices for b in fits]
    index = {int(x): i for i, x in enumerate(frames)}
    tmp = dst.parent / "overlay_tmp"
    out = render_overlays(rig.cameras(), videos, [f], verts, np.asarray(model.faces), index, tmp,
                          titles={f: f"{base.parent.name}/{base.name} frame {f}: fitted mesh"},
                          scale=0.5)
    shutil.copyfile(out[f], dst)
    shutil.rmtree(tmp, ignore_errors=True)
    return dst


def _run(recipe: Path, seq: str, outputs: Path, until: str | None = None) -> None:
    from bench.cases._engine import run_engine

    args = ["sequence", seq, "--recipe", str(recipe), "--outputs", str(outputs)]
    run_engine(args + (["--until", until] if until else []), seq, echo=8, tail=20)


def run(work: Path) -> dict[str, float]:
    from recipes import load_recipe

    out: dict[str, float] = {}
    # the lab recording, in the engine's own outputs/ (what make sequence writes)
    t0 = time.perf_counter()
    _run(RECIPE, SEQ, REPO / "outputs")
    g, a = SEQ.split("/")
    base = REPO / "outputs" / load_recipe(RECIPE).session / g / a
    out.update(_heldout_keys("real_video", json.loads((base / "heldout" / "report.json").read_text())))
    out.update(_fit_keys("real_video", base))
    out.update({f"real_video.{k}": v for k, v in operator_counts(base).items()})
    lab = load_recipe(RECIPE)
    overlay_png(base, [lab.sequences[SEQ].videos[c] for c in lab.cameras],
                work / "real_video_overlay.png")
    out["real_video.pipeline_wall_s"] = time.perf_counter() - t0
    out.update(rig_keys("real_video", base))
    if (base / "rig" / "refine.npz").is_file() and given_rig_wanted():
        out.update(_heldout_keys("real_video.given_rig", given_rig_heldout(base, lab)))
    # the studio's markerless preset: the same studio, nobody's markers, no scans
    try:
        out.update(_studio(work))
    except Exception as e:  # the lab's figures stand on their own
        import traceback

        traceback.print_exc()
        out["real_video.studio.error"] = f"{type(e).__name__}: {str(e)[-300:]}"
    return out


#: the studio preset's rig refinement: blocks of 4 of its 24 frames, the held-out view on
#: every other frame of the others (6 frames)
STUDIO_STAGES = {"qa": {"video": False, "scene": False}, "rig": {"block": 4},
                 "heldout": {"stride": 2}}


def _studio(work: Path) -> dict:
    """The studio preset with the rig refined from the people (``real_video.studio.*``) and,
    for comparison, with the rig as calibrated (``real_video.studio.given_rig.*``: the truth
    figures of its own run, the held-out view on the refined run's scored frames)."""
    out = _studio_run(work, refine=True)
    from recipes import load_recipe

    rec = load_recipe(work / "studio_markerless.yaml")
    g, a = STUDIO_SEQ.split("/")
    sb = work / "outputs" / rec.session / g / a
    out.update(rig_keys("real_video.studio", sb))
    if not given_rig_wanted():
        return out
    out.update(_heldout_keys("real_video.studio.given_rig", given_rig_heldout(sb, rec)))
    given = _studio_run(work, refine=False)
    out.update({k.replace("real_video.studio.", "real_video.studio.given_rig.", 1): v
                for k, v in given.items()
                if not k.split(".")[-1].startswith(("heldout", "baseline"))})
    return out


def _studio_run(work: Path, refine: bool) -> dict:
    from recipes import load_recipe

    out: dict = {}
    src = studio_recipe(work)
    name = "studio_markerless.yaml" if refine else "studio_markerless_given_rig.yaml"
    rec = markerless_recipe(src, work / name, [STUDIO_SEQ], stages=STUDIO_STAGES,
                            refine_rig=refine, session_suffix="" if refine else "_given_rig")
    from bench.cases._engine import run_engine

    run_engine(["release", "--recipe", str(rec), "--outputs", str(work / "outputs"),
                "--executor", "serial"], "studio markerless release", echo=8, tail=20)
    r = load_recipe(rec)
    g, a = STUDIO_SEQ.split("/")
    sb = work / "outputs" / r.session / g / a
    out.update(_heldout_keys("real_video.studio", json.loads((sb / "heldout" / "report.json").read_text())))
    out.update(_fit_keys("real_video.studio", sb))
    ev = next((work / "outputs" / r.session / "session").glob("evaluate/evaluation.json"), None)
    if ev is not None:
        over = json.loads(ev.read_text())["overall"]["all"]  # mm, every valid person-frame
        for k in ("mpjpe", "pa_mpjpe", "transl_err", "mpvpe"):
            if over.get(k) is not None:
                out[f"real_video.studio.{k}_mm"] = float(over[k])
    truth = Path(yaml.safe_load(rec.read_text())["stages"]["evaluate"]["truth"]) / g / f"{a}.npz"
    if truth.is_file():
        out.update({f"real_video.studio.{k}": v for k, v in shape_accuracy(sb, truth).items()})
    if refine:
        overlay_png(sb, [r.sequences[STUDIO_SEQ].videos[c] for c in r.cameras],
                    work / "real_video_studio_overlay.png")
    return out
