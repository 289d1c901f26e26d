"""Stage ``qa`` (per sequence): what a person reviewing the sequence looks at, prepared.

Thin adapter around ``qa.metrics.sequence_metrics`` / ``flag_frames``: reads the fits of both
people (``marker_fit`` of the wearer, ``partner_fit`` when the sequence has a partner), the
keypoints they were fitted to (the partner fit's refined ones when its second pass ran), the
cameras, the contact annotation and, for the 3D scene, the wearer's markers from the C3D.
Per frame and person it measures marker residuals and the markers the cleaning step repaired
(un-swapped or removed samples: ``marker_fit`` cleans the capture before fitting, so a swap
burst leaves good residuals but a repaired capture), 2D reprojection per view and keypoint
group, interpenetration (deepest point and volume), self-penetration, ground penetration and
foot skating, the contact gap in annotated frames and unexpected contact outside them,
temporal jerk and frames not valid; a per-view time shift against the wearer's fit finds a
camera out of sync. Every frame beyond a threshold (the stage options = ``qa.metrics.QAOptions``,
recipe ``stages.qa.<name>``) is flagged with its reason; flagged frames close together are one
span. Writes

- ``qa.npz`` (``artifacts.QAMetrics``): ``frames (F,)``, ``names (N,)``, ``values (F, N)``
  (NaN = not applicable), ``reasons (R,)``, ``flagged (F, R)``;
- ``flags.json`` (``artifacts.QAResult``, with ``qa.npz``: what release and qa_index read): the
  summary (frames, flagged frames and rate, spans, per reason, not valid per person, sync
  offsets, metrics time), the spans (start, end, reasons, peak frame, worst values), per
  flagged frame its reasons, the thresholds and units, and the relative names of the files
  drawn (report, plot, overlays per frame, video, scene);
- ``report.json``: the summary (frames, flagged frames and rate, spans, frames per reason,
  frames not valid per person, the sequence-level findings such as camera sync offsets),
  the thresholds, what was rendered, and timings (wall seconds of the metrics, the
  drawing, the scene and the whole stage, its CPU seconds, and per frame);
- ``qa.png``: the per-frame curves with thresholds and flagged spans shaded
  (``drawing.qa_plots.qa_plot``);
- ``overlays/overlay_<frame>.png``: both meshes over the four views (``drawing.overlay.
  draw_overlays``: the QA proxy decimated to ``overlay_faces`` triangles, projected with the
  cameras' lenses and filled with OpenCV at the picture's scale) at every span's start, peak
  and end and at a sample of the unflagged frames; ``overlay.mp4`` (and ``overlay.webm``
  beside it, which browsers play): the four views tiled over the sequence at ``video_scale``;
  every video frame is decoded once for both;
- ``scene.mcap``: the 3D scene in Foxglove's schemas (``formats.foxglove_scene``): both bodies
  as decimated triangle meshes (the QA proxy, decimated to ``scene_faces``), the markers, the keypoints triangulated, the cameras as frame
  transforms with their images, the metrics as plot topics;
- ``figures/``: the upstream stages' pictures (marker residuals, partner-fit curves, keypoint
  overlays; ``stages.common.stage_figures``) copied so that the report is one folder;
- ``report.html``: the sequence's report (``qa.report.write_sequence_report``).

A marker-only sequence (no video) gets the marker, ground, skating and jerk metrics of the
wearer, the plot and the report; no overlays, video or images in the scene.
"""
from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from pipeline.spec import Stage, StageContext
from qa.metrics import QAOptions
from stages import common

READS = ("body_model.kind", "cameras", "ground_plane", "sequence.fps", "sequence.mocap",
         "sequence.markers_on", "sequence.partner", "sequence.has_video", "sequence.markerless",
         "wearer.markerset",
         "wearer.label_prefix", "wearer.marker_labels")


@dataclass(frozen=True)
class Options(QAOptions):
    """The thresholds (``qa.metrics.QAOptions``) and what is drawn: overlay_sample :
    unflagged frames rendered as a sample of the rest; overlay_max : at most this many overlay
    images in all (spans first, by their peak excess); video : write ``overlay.mp4``;
    video_max_frames : at most this many frames in it (evenly spaced); scene : write
    ``scene.mcap``; scene_faces : triangles per body in the scene; scene_images : put the
    camera images into the scene; image_scale : scale of overlay and scene images;
    video_scale : scale of the views in ``overlay.mp4``; overlay_faces, video_faces :
    triangles per body in the overlay pictures and in the video's smaller views (the QA proxy
    decimated; ``drawing.overlay.raster_people`` fills them)."""

    overlay_sample: int = 4
    overlay_max: int = 24
    video: bool = True
    video_max_frames: int = 240
    scene: bool = True
    scene_faces: int = 4000
    scene_images: bool = True
    image_scale: float = 0.5
    video_scale: float = 0.25
    overlay_faces: int = 1500
    video_faces: int = 800

    def __post_init__(self):
        thresholds(self)  # QAOptions validates its own fields
        for f in ("overlay_sample", "overlay_max", "video_max_frames", "scene_faces",
                  "overlay_faces", "video_faces"):
            if getattr(self, f) < 0:
                raise ValueError(f"{f}: must be >= 0, got {getattr(self, f)}")
        for f in ("image_scale", "video_scale"):
            if not 0 < getattr(self, f) <= 1:
                raise ValueError(f"{f}: must be in (0, 1], got {getattr(self, f)}")


def thresholds(o: Options) -> QAOptions:
    """The ``QAOptions`` part of the stage options."""
    names = {f.name for f in fields(QAOptions)}
    return QAOptions(**{k: v for k, v in asdict(o).items() if k in names})


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out = {"body_model": common.body_model_file(recipe)}  # markers, cameras: stage capture
    for cam in recipe.cameras:
        if cam in seq.videos:
            out[f"video:{cam}"] = Path(seq.videos[cam])
    if seq.contact is not None:
        out["contact"] = Path(seq.contact)
    return out


# ------------------------------------------------------------------------------ pure helpers
def overlay_frames(frames, flags, sample: int, cap: int) -> tuple[list[int], list[int]]:
    """Which frames get an overlay image: each span's start, peak and end (spans with the
    largest ``peak_excess`` first, at most ``cap`` frames in all), then ``sample`` unflagged
    frames evenly spread. Returns ``(span frames, sample frames)``, each sorted."""
    frames = np.asarray(frames)
    chosen: list[int] = []
    for sp in sorted(flags.spans, key=lambda s: -s.peak_excess):
        for f in (sp.peak_frame, sp.start, sp.end):
            if f not in chosen and len(chosen) < cap:
                chosen.append(int(f))
    rest = frames[~np.asarray(flags.any, bool)]
    k = min(sample, len(rest), max(cap - len(chosen), 0))
    picks = [int(rest[i]) for i in np.linspace(0, len(rest) - 1, k).round().astype(int)] if k else []
    return sorted(chosen), sorted(set(picks))


def summary(m, flags) -> dict:
    """The figures a reviewer sorts by: frames, flagged frames and rate, spans, frames per
    reason, frames not valid per person, the sequence-level findings."""
    per_reason = {r: int(flags.flagged[:, i].sum()) for i, r in enumerate(flags.reasons)
                  if flags.flagged[:, i].any()}
    not_valid = {p: int(np.nansum(m.values[f"{p}.not_valid"]))
                 for p in m.people if f"{p}.not_valid" in m.values}
    seq = {("people_detail" if k == "people" else k): v for k, v in m.sequence.items()}
    return {"frames": int(len(m.frames)), "flagged": int(flags.any.sum()),
            "rate": float(flags.rate), "spans": len(flags.spans), "reasons": per_reason,
            "not_valid": not_valid, **seq, "people": list(m.people)}


# ------------------------------------------------------------------------------------- stage
def run(ctx: StageContext) -> None:
    import contextlib

    # what _run starts beside itself (the video frames' decoding thread, the plot's worker
    # process) is stopped when it ends, in any case
    with contextlib.ExitStack() as beside:
        _run(ctx, beside)


def _run(ctx: StageContext, beside) -> None:
    from artifacts import BodyFit, QAMetrics, QAResult
    from artifacts.keypoints import Keypoints2D
    from artifacts.qa import QAFiles, QASpan, QASummary
    from fitting.contact_signature import load_contact
    from qa.metrics import (
        capture_repairs,
        flag_frames,
        marker_track,
        qa_frames,
        qa_region_map,
        sequence_metrics,
    )
    from qa.report import write_sequence_report

    t_start, c_start = time.perf_counter(), _cpu_s()
    o: Options = ctx.params or Options()
    rv = ctx.recipe
    out = Path(ctx.out.path("report.html")).parent
    model = common.load_body(ctx)
    cams = common.capture_cameras(ctx)
    videos = [ctx.raw[f"video:{c.name}"] for c in cams if f"video:{c.name}" in ctx.raw]
    has_video = bool(rv.sequence.has_video) and len(videos) == len(cams) and len(cams) > 0
    contact = None
    if "contact" in ctx.raw and has_video:
        action = ctx.unit.split("/", 1)[1]
        family = "smplx" if model.name == "smplx" else "anny"
        contact = load_contact(ctx.raw["contact"], action, model,
                               common.video_length(videos)[0], family=family,  # the shortest
                               rmap=qa_region_map(model))  # its default, built once per process
    people = common.fitted_people(ctx)  # markerless: both from partner_fit
    wearer = BodyFit.load(people[0][0])
    partner = BodyFit.load(people[1][0]) if len(people) > 1 else None
    pf_art = ctx.inputs.get("partner_fit")
    keypoints = None
    if pf_art is not None and Keypoints2D.exists_in(pf_art):
        keypoints = Keypoints2D.load(pf_art)  # the keypoints the partner fit used
    elif ctx.inputs.get("keypoints") is not None:
        keypoints = Keypoints2D.load(ctx.inputs["keypoints"])
    ground = common.ground_of(rv)
    if rv.sequence.markerless:  # nobody's markers: no marker metrics, no markers in the scene
        from fitting.mocap import VideoClock

        markers, repaired = None, None
        clock = VideoClock(common.sequence_fps(rv.sequence.fps, videos[0]), 0.0, None)
    else:
        captured, markers, clock = wearer_markers(ctx, videos)
        repaired = capture_repairs(captured.repaired, captured.rate_hz, captured.first_frame,
                                   wearer.frames, clock)
    fps = float(clock.fps)
    qo = thresholds(o)
    parallel = geometry_workers(ctx.cores) > 1
    # a worker process when there is a second core, for the metrics' per-frame geometry (while
    # this process computes the other metrics) and then the plot (libigl and matplotlib hold
    # the GIL: in a thread they would take turns with the rest); spawned now, it imports
    # what they need while this process reads the inputs
    worker = None
    if parallel:
        from pipeline.procs import process_pool

        worker = beside.enter_context(process_pool(1, initializer=_worker_init))
        worker.submit(int, 0)  # start it now
    # the video frames the overlays, the video and the scene's images show: decoded once, in a
    # thread that starts now (beside the metrics), kept at the scales drawn
    feed = None
    scene_feed = parallel and o.scene and o.scene_images
    if has_video and (o.video or scene_feed):
        from drawing.overlay import FrameFeed

        feed = FrameFeed(cams, videos, qa_frames(wearer, partner),
                         {o.image_scale} | ({o.video_scale} if o.video else set()),
                         ["overlay"] + (["scene"] if scene_feed else []))
        beside.callback(feed.close)

    t0 = time.perf_counter()
    m = sequence_metrics(model, wearer, partner, keypoints, cams if has_video else [], contact,
                         ground, fps, qo, progress=ctx.progress, repaired=repaired,
                         marker_track=marker_track(markers, clock)
                         if has_video and markers is not None else None,
                         workers=geometry_workers(ctx.cores), pool=worker)
    flags = flag_frames(m, qo)
    metrics_s = time.perf_counter() - t0
    F = len(m.frames)
    names = sorted(m.values)
    metrics = QAMetrics(frames=np.asarray(m.frames, np.int64), names=np.array(names, dtype=str),
                        values=np.stack([np.asarray(m.values[n], float) for n in names], axis=1)
                        if names else np.zeros((F, 0)),
                        reasons=np.array(flags.reasons, dtype=str),
                        flagged=np.asarray(flags.flagged, bool).reshape(F, len(flags.reasons)))
    per_frame = {str(int(f)): [r for r, x in zip(flags.reasons, row, strict=True) if x]
                 for f, row in zip(m.frames, flags.flagged, strict=True) if row.any()}
    ctx.log(f"{ctx.unit}: {int(flags.any.sum())}/{F} frames flagged in {len(flags.spans)} spans"
            + (": " + ", ".join(sorted({r for s in flags.spans for r in s.reasons}))
               if flags.spans else ""))

    # the 3D scene and the plot: in a thread beside the overlays when there is a second core,
    # the plot in its worker process (each writes its own files; the timings are measured
    # where they run). The scene first: it takes its images from the feed while the overlays do.
    plot_args = (out / "qa.png", np.asarray(m.frames), fps, m.values, m.units, m.thresholds,
                 [(s.start, s.end, ", ".join(s.reasons)) for s in flags.spans],
                 f"{ctx.unit}: {int(flags.any.sum())}/{F} frames flagged")
    plot_future = worker.submit(_plot, *plot_args) if worker is not None else None

    def plot_and_scene():
        t_scene = time.perf_counter()
        scene = None
        try:
            if o.scene and m.vertices:
                scene = _write_scene(out / "scene.mcap", model, m, flags, cams, videos,
                                     has_video, keypoints, markers, clock, fps, o,
                                     feed=feed if scene_feed else None)
        finally:
            if feed is not None:
                feed.done("scene")
        t = time.perf_counter()
        plot_s = plot_future.result() if plot_future is not None else _plot(*plot_args)
        return scene, plot_s, t - t_scene

    side = _Beside(plot_and_scene, parallel)
    t1 = time.perf_counter()

    try:
        # overlays and the tiled video
        span_frames, sample_frames = overlay_frames(m.frames, flags, o.overlay_sample, o.overlay_max)
        images: dict[int, Path] = {}
        rendered = {"overlays": 0, "video_frames": 0}
        index = {int(f): i for i, f in enumerate(m.frames)}
        if has_video and m.vertices:
            from drawing.overlay import draw_overlays

            titles = {f: f"{ctx.unit} frame {f}: " + (", ".join(per_frame.get(str(f), [])) or "not flagged")
                      for f in span_frames + sample_frames}
            pick = []
            if o.video and o.video_max_frames:
                pick = np.unique(np.linspace(0, F - 1, min(F, o.video_max_frames)).round().astype(int))
            step = max(1, int(np.median(np.diff(m.frames))) if F > 1 else 1)
            faces, small = overlay_meshes(model, m.vertices, o.overlay_faces)
            coarse = overlay_meshes(model, m.vertices, o.video_faces)
            images, video = draw_overlays(
                cams, videos, small, faces, index, png_frames=span_frames + sample_frames,
                png_dir=out / "overlays", titles=titles, png_scale=o.image_scale,
                video_path=out / "overlay.mp4", video_frames=[int(m.frames[i]) for i in pick],
                video_fps=fps / step * (len(pick) / F if F else 1), video_scale=o.video_scale,
                webm=True, video_mesh=(coarse[1], coarse[0]), progress=ctx.progress, feed=feed)
            rendered["overlays"] = len(images)
            rendered["video_frames"] = len(pick)
            rendered["overlay_faces_per_body"] = int(len(faces))
            rendered["video_faces_per_body"] = int(len(coarse[0]))
        if feed is not None:
            feed.done("overlay")  # nothing drawn (no mesh): the feed must not wait for it
        draw_s = time.perf_counter() - t1

        scene, plot_s, scene_s = side.result()
        if worker is not None:  # done: reaped now, its CPU seconds count in the timing
            worker.shutdown(wait=True)
    finally:
        side.close()

    # upstream pictures, the report
    figures = [("QA metrics per frame, flagged spans shaded", "qa.png")]
    (out / "figures").mkdir(exist_ok=True)
    for stage in ("marker_fit", "partner_fit", "keypoints", "rig"):
        art = ctx.inputs.get(stage)
        if art is None:
            continue
        for png in common.stage_figures(art):
            dst = out / "figures" / f"{stage}_{png.name}"
            shutil.copyfile(png, dst)
            figures.append((f"{stage}: {png.stem.replace('_', ' ')}", f"figures/{dst.name}"))
    spans_html = []
    for s in flags.spans:
        shown = [f for f in (s.start, s.peak_frame, s.end) if f in images]
        spans_html.append({**s.to_json(),
                           "images": [str(images[f].relative_to(out)) for f in dict.fromkeys(shown)]})
    for f in sample_frames:
        if f in images:
            spans_html.append({"start": f, "end": f, "reasons": [], "peak_frame": f, "worst": {},
                               "sample": True, "images": [str(images[f].relative_to(out))]})
    summ = {**summary(m, flags), "thresholds": m.thresholds, "units": m.units}
    stage_reports = {}
    for stage in ("shape_fit", "keypoints", "rig", "marker_fit", "partner_fit"):
        art = ctx.inputs.get(stage)
        if isinstance(art, dict):
            for unit, a in art.items():
                stage_reports[f"{stage} [{unit}]"] = common.stage_report(a)
        elif art is not None:
            stage_reports[stage] = common.stage_report(art)
    report = {"sequence": ctx.unit, "summary": summ, "spans": [s.to_json() for s in flags.spans],
              "thresholds": m.thresholds, "rendered": rendered,
              "overlay_frames": {"spans": span_frames, "sample": sample_frames},
              "scene": scene,
              "timing": _timing(F, t_start, c_start, metrics_s, plot_s, draw_s, scene_s)}
    stage_reports = {k: v for k, v in stage_reports.items() if v is not None}
    write_sequence_report(out, sequence=ctx.unit, title=f"QA: {ctx.unit}", summary=summ,
                          spans=spans_html, figures=figures,
                          video="overlay.mp4" if (out / "overlay.mp4").exists() else None,
                          stage_reports={"qa": {k: report[k] for k in ("summary", "timing", "rendered")},
                                         **stage_reports},
                          links={"3D scene (open in Foxglove)": "scene.mcap"} if scene else None,
                          heldout=common.stage_report(ctx.inputs["heldout"])
                          if ctx.inputs.get("heldout") is not None else None)
    ctx.out.save_json("report", report)
    QAResult(
        metrics=metrics,
        summary=QASummary(frames=F, flagged_frames=int(flags.any.sum()),
                          flagged_rate=float(flags.any.sum()) / max(F, 1), spans=len(flags.spans),
                          per_reason=summ["reasons"], not_valid=summ["not_valid"],
                          sync_offset_frames={c: int(v) for c, v in
                                              (m.sequence.get("sync_offset_frames") or {}).items()},
                          people=tuple(m.people), metrics_s=float(metrics_s)),
        spans=tuple(QASpan(s.start, s.end, tuple(s.reasons), s.peak_frame, dict(s.worst))
                    for s in flags.spans),
        frame_reasons={int(k): tuple(v) for k, v in per_frame.items()},
        thresholds={k: float(v) for k, v in m.thresholds.items()},
        units={k: m.units.get(k, "") for k in m.thresholds},
        files=QAFiles(report="report.html", plot="qa.png",
                      overlays={int(f): p.relative_to(out).as_posix() for f, p in images.items()},
                      span_frames=tuple(span_frames), sample_frames=tuple(sample_frames),
                      video="overlay.mp4" if (out / "overlay.mp4").exists() else None,
                      scene=scene["file"] if scene else None)).save(ctx.out)


def _plot(*args) -> float:
    """``drawing.qa_plots.qa_plot(*args)``; returns its wall seconds."""
    from drawing.qa_plots import qa_plot

    t = time.perf_counter()
    qa_plot(*args)
    return time.perf_counter() - t


def _worker_init() -> None:
    """The worker process's imports for the geometry, done on its start (the plot's,
    matplotlib's 0.3 s, when the plot runs: after the geometry, off the metrics' path)."""
    import igl  # noqa: F401
    import scipy.spatial  # noqa: F401

    import fitting.collision  # noqa: F401
    import geometry.queries  # noqa: F401
    import qa.metrics  # noqa: F401


class _Beside:
    """``func()`` run in a thread while the caller goes on (``parallel``), else in the
    caller's thread when the result is asked for; its error comes out of :meth:`result`.

    A thread, not a forked process: a fork of this process (worker, watchdog and tqdm threads,
    OpenMP pools, the engine's SIGTERM handler) could deadlock in the child or outlive a
    ``Pool.terminate`` (CI hung on it). The plot and the scene write their own files and
    touch no state the overlays use."""

    def __init__(self, func, parallel: bool):
        self.func, self.pool, self.future = func, None, None
        if parallel:
            import concurrent.futures as cf

            self.pool = cf.ThreadPoolExecutor(1, thread_name_prefix="qa-beside")
            self.future = self.pool.submit(func)

    def result(self):
        if self.future is None:
            return self.func()
        try:
            return self.future.result()
        finally:
            self.close()

    def close(self) -> None:
        """Wait for the thread if it is still running (the caller failed first): it owns
        files in the stage's temporary folder."""
        if self.pool is not None:
            self.pool.shutdown(wait=True)
            self.pool, self.future = None, None


def geometry_workers(cores: int) -> int:
    """Processes for the metrics' per-frame geometry: the cores the executor granted (0: the
    machine's), one when the stage runs outside the main thread (a Dask worker's task thread:
    a pool's workers die with the thread that started them, see ``pipeline.procs``)."""
    import os
    import threading

    if threading.current_thread() is not threading.main_thread():
        return 1
    n = os.cpu_count() or 1
    return max(1, min(n, int(cores) if cores else n))


def _cpu_s() -> float:
    """CPU seconds of this process and of its finished children (worker processes)."""
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _timing(frames: int, t_start: float, c_start: float, metrics_s: float, plot_s: float,
            draw_s: float, scene_s: float) -> dict:
    """The stage's timings: wall seconds of the metrics, the plot, the overlays and video
    (``draw_s``) and the scene (plot and scene run beside the overlays when there is a second
    core: the parts then add up to more than the whole), the whole stage's wall and CPU
    seconds up to its report (the figures copied, the pages written after it take
    milliseconds), and per frame."""
    total = time.perf_counter() - t_start
    cpu = _cpu_s() - c_start
    n = max(frames, 1)
    return {"metrics_s": round(metrics_s, 3), "plot_s": round(plot_s, 3),
            "draw_s": round(draw_s, 3),
            "scene_s": round(scene_s, 3), "total_s": round(total, 3), "cpu_s": round(cpu, 3),
            "s_per_frame": round(total / n, 4), "cpu_s_per_frame": round(cpu / n, 4),
            "metrics_s_per_frame": round(metrics_s / n, 4)}


def overlay_meshes(model, vertices, n_faces: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The bodies the overlays draw: the QA proxy (``qa.metrics.body_proxy``: points riding on
    the full mesh) decimated to ``n_faces`` triangles (``formats.foxglove_scene.
    decimate_for_scene``), posed on every QA frame. Returns ``(faces (T, 3), [(F, V', 3) per
    person])``."""
    from formats.foxglove_scene import decimate_for_scene
    from qa.metrics import body_proxy

    proxy = body_proxy(model)
    ids, tri = decimate_for_scene(proxy.points(np.asarray(model.v_template, float)),
                                  np.asarray(proxy.faces), max(int(n_faces), 4))
    sub = dataclasses.replace(proxy, corners=proxy.corners[ids], face=proxy.face[ids],
                              bary=proxy.bary[ids], face_region=None, vertex_region=None,
                              region_adjacency=None)
    return tri, [sub.points(V) for V in vertices]


def wearer_markers(ctx, videos):
    """The wearer's capture from stage ``capture`` (``artifacts.capture.Markers``: what the
    cleaning repaired), the cleaned markers ``marker_fit`` fitted (``formats.c3d.Markers``)
    and their clock onto the fit's frames: ``(captured, cleaned markers, clock)``."""
    from artifacts import ShapeFit

    sh = ctx.inputs["shape_fit"]
    shape = ShapeFit.load(sh[ctx.recipe.sequence.markers_on] if isinstance(sh, dict) else sh)
    captured = common.capture_markers(ctx, shape.names)
    mk = captured.capture()
    _, clock, _ = common.marker_timeline(ctx.recipe.sequence, {"video": videos[0]} if videos else {},
                                         mk, None)
    return captured, mk, clock


def _write_scene(path: Path, model, m, flags, cams, videos, has_video, keypoints, markers, clock,
                 fps, o, feed=None):
    """The Foxglove scene: decimated bodies, the wearer's markers at the QA frames, both
    people's body keypoints triangulated, the cameras with their images (from ``feed``, a
    ``drawing.overlay.FrameFeed`` with the consumer ``scene`` and ``o.image_scale``, when
    given; else read here), the metrics."""
    from calib.convert import convert_distortion
    from calib.geometry import triangulate
    from fitting.mocap import video_observations
    from formats.foxglove_scene import CameraView, MeshTrack, write_scene
    from formats.video import VideoReader

    tri, small = overlay_meshes(model, m.vertices, o.scene_faces)  # the QA proxy, decimated
    colors = {"wearer": (0.85, 0.25, 0.2, 0.9), "partner": (0.2, 0.45, 0.85, 0.9)}
    meshes = [MeshTrack(p, V, tri, colors.get(p, (0.7, 0.7, 0.7, 0.9)))
              for p, V in zip(m.people, small, strict=True)]
    frames = np.asarray(m.frames)
    marker_xyz = None if markers is None else video_observations(markers, frames, clock)[0]
    points = {}
    if keypoints is not None and has_video:
        rows = np.searchsorted(np.asarray(keypoints.frames), frames)
        ok = (rows < len(keypoints.frames))
        rows = np.minimum(rows, len(keypoints.frames) - 1)
        ok &= np.asarray(keypoints.frames)[rows] == frames
        ci = [keypoints.camera(c.name) for c in cams]
        for p, who in enumerate(("wearer", "partner")):
            kp = np.asarray(keypoints.kp, float)[ci][:, rows, p, :23]  # (C, F, 23, 3) body
            xyz = triangulate(cams, kp).xyz
            xyz[~ok] = np.nan
            points[f"{who}_keypoints"] = xyz
    views = []
    for c in cams:  # Foxglove's plumb_bob: the lens in OpenCV's 5 coefficients (fitted if h36m)
        cv = convert_distortion(c, "opencv").camera
        views.append(CameraView(c.name, np.asarray(c.R), np.asarray(c.T), np.asarray(cv.K),
                                np.array([*cv.k[:2], *cv.p, cv.k[2]]), int(c.width), int(c.height)))
    images = None
    readers = []
    if has_video and o.scene_images and feed is not None:  # already at image_scale
        images = {c.name: (lambda f, k=k: feed.get("scene", int(f), o.image_scale)[k])
                  for k, c in enumerate(cams)}
    elif has_video and o.scene_images:
        readers = [VideoReader(v, size=(c.width, c.height))  # padded to the calibration's
                   for v, c in zip(videos, cams, strict=True)]
        images = {c.name: (lambda f, r=r: r[int(f)]) for c, r in zip(cams, readers, strict=True)}
    try:
        res = write_scene(path, fps, frames, meshes, views, markers=marker_xyz,
                          marker_names=None if markers is None else list(markers.names),
                          points3d=points, images=images, metrics=m.values, flags=flags.any,
                          image_scale=o.image_scale)
    finally:
        for r in readers:
            r.close()
    return {"file": path.name, **res, "faces_per_body": int(len(tri))}


STAGE = Stage(name="qa", func=run, per="sequence",
              upstream=("capture", "shape_fit", "keypoints", "rig", "marker_fit", "partner_fit",
                        "heldout"),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="per-frame quality flags, overlays on the four views, plots, HTML report, 3D scene")
