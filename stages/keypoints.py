"""Stage ``keypoints`` (per sequence): 2D body and hand keypoints of both people in every view.

The thin adapter around :func:`detect.sequence.detect_keypoints` (the algorithm is described
there): it reads the cleaned capture and the camera rig of stage ``capture``
(``artifacts.capture``), the videos' lengths and rates through ``formats.video``, precomputed
detections through ``formats.openpose`` / ``formats.coco``, resamples the wearer's markers
onto the selected video frames (``fitting.mocap``), calls the domain function, and writes:

- ``keypoints.npz``: :class:`artifacts.keypoints.Keypoints2D` (layout in
  docs/ARCHITECTURE.md, "Keypoints artifact");
- ``keypoints.mcap``: the keypoints and boxes per camera and frame (Foxglove-viewable);
- ``overlay_<camera>.png``: one sample frame per view with both people drawn;
- ``report.json``: detector, frames, detection rates per person and joint group, detector
  calls, the identity check's verdicts per person (``identity``: views dropped as swapped or
  inconsistent, the partner's relabelled and the wearer's dropped as mirrored), timings
  (``fps_per_core``: the detector processes' CPU plus ``guard_cpu_s``, the cross-view and
  identity checks).

A markerless sequence (no marker wearer; ``sequence.people``) has no ``capture`` stage: this
stage reads its calibration (``calib.io.read_camera``, the recipe's ``calibration_format``)
and writes the rig beside the keypoints (``rig.npz``, ``artifacts.capture.CameraRig``; later
stages find it through ``stages.common.capture_cameras``), finds the people in the views
(:func:`detect.markerless.detect_markerless`: person detection per view, association across
views by triangulation, bystanders rejected and counted in the report's ``bystanders``) and
writes ``people.npz``: the people's triangulated roots per frame (``people_root (F, 2, 3)``)
and every bystander's (``bystander_frame``, ``bystander_root``, ``bystander_views``; groups
near a person fitted are its duplicates, not bystanders), and in 2D every view's candidate
that is none of the people fitted (``others_2d_frame``, ``_camera``, ``_uv``: its hips).

The videos of a sequence must have the same length and the recipe's frame rate
(:func:`stages.common.check_videos`); ``stride`` keeps every n-th video frame (the detector
dominates the pipeline's run time).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from artifacts.keypoints import Keypoints2D
from detect import constants as DK
from detect.sequence import SequenceOptions
from formats.errors import InputError
from pipeline.spec import Stage, StageContext
from stages import common


@dataclass(frozen=True)
class Options:
    """detector : ``auto`` (precomputed files when the sequence names them, else mediapipe),
        ``mediapipe`` or ``precomputed``.
    stride : keep every ``stride``-th video frame; start / stop : video frame range
        (stop None: to the end).
    workers : detector processes (0: one per core). chunk : frames per chunk (each chunk
        starts its partner search and tracking afresh; a pool task runs a few chunks with
        one detector).
    hands : detect hand keypoints. track / mask_wearer : partner search (detect.people).
    body_margin : wearer crop margin (fraction of the marker box's larger side).
    near_frac : the paper's "close proximity", fraction of the wearer's box height.
    pose_min_conf / hand_min_conf : mediapipe detection thresholds.
    video_mode : mediapipe pose and hands track each person (each hand) within a chunk, one
        view at a time (skips the person and palm detectors between frames;
        detect/mediapipe_detector.py); ``auto``: only when the frames are consecutive
        (stride 1): across strided frames people move farther, and the six tracking graphs'
        first detections (~0.2 s each) cost more than tracking saves on a short sequence.
    cross_view / cross_view_px : drop observations that disagree with what the other views
        agree on (detect/multiview.py; RANSAC threshold in pixels), and the partner's
        unconfirmed keypoints in views where the wearer was not found.
    identity : then judge each view's detection of each person as a whole skeleton against
        the other views and neighbouring frames (detect/identity.py): swapped, inconsistent
        and the wearer's mirrored detections dropped, the partner's mirrored ones relabelled.
    overlay_frame : video frame drawn in the overlay PNGs (None: the middle one).
    mcap : write keypoints.mcap.
    max_candidates / assoc_frac / volume_radius_m : a markerless sequence
    (``detect.markerless``): people looked for per view, the cross-view association's
    reprojection threshold (fraction of the person's box height), and how far from the
    capture volume centre a person may stand before it counts as a bystander (metres).
    """

    detector: Literal["auto", "mediapipe", "precomputed"] = "auto"
    stride: int = 1
    start: int = 0
    stop: int | None = None
    workers: int = 0
    chunk: int = 32
    hands: bool = True
    track: bool = True
    mask_wearer: bool = True
    body_margin: float = DK.BODY_MARGIN
    near_frac: float = DK.NEAR_FRAC
    pose_min_conf: float = 0.3
    hand_min_conf: float = 0.3
    video_mode: Literal["auto", "on", "off"] = "auto"
    cross_view: bool = True
    cross_view_px: float = DK.CROSS_VIEW_PX
    identity: bool = True
    overlay_frame: int | None = None
    mcap: bool = True
    max_candidates: int = 3
    assoc_frac: float = 0.08
    volume_radius_m: float = 2.5

    def __post_init__(self):
        if self.stride < 1:
            raise ValueError(f"stride: must be >= 1, got {self.stride}")
        if self.start < 0 or (self.stop is not None and self.stop <= self.start):
            raise ValueError(f"start/stop: need 0 <= start < stop, got {self.start}, {self.stop}")
        if self.workers < 0:
            raise ValueError(f"workers: must be >= 0 (0: one per core), got {self.workers}")
        for name in ("pose_min_conf", "hand_min_conf"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name}: must be in [0, 1], got {v}")
        if self.overlay_frame is not None and self.overlay_frame < 0:
            raise ValueError(f"overlay_frame: must be >= 0, got {self.overlay_frame}")
        self.sequence_options()  # chunk, body_margin, near_frac, cross_view_px

    def sequence_options(self, cores: int = 0) -> SequenceOptions:
        """The domain options (workers 0 resolved to ``cores``, the cores the executor granted
        the stage, or when that is 0 to the number of cores of the machine)."""
        return SequenceOptions(hands=self.hands, track=self.track, mask_wearer=self.mask_wearer,
                               body_margin=self.body_margin, near_frac=self.near_frac,
                               cross_view=self.cross_view, cross_view_px=self.cross_view_px,
                               identity=self.identity,
                               workers=self.workers or cores or (os.cpu_count() or 1), chunk=self.chunk)


def _precomputed_files(seq, cam: str) -> list[Path]:
    root = Path(seq.keypoints[cam])
    return sorted(root.glob("*.json")) if root.is_dir() else [root]


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)  # markers and cameras come from the ``capture`` stage
    out: dict[str, Path] = {}
    if seq.markerless:  # no capture stage: the calibration is read here
        out.update(common.calibration_inputs(recipe, seq))
    for cam in recipe.cameras:
        out[f"video:{cam}"] = Path(seq.videos[cam])
        if seq.keypoints and cam in seq.keypoints:
            for i, p in enumerate(_precomputed_files(seq, cam)):
                out[f"keypoints:{cam}:{i:06d}"] = p
    return out


def read_rig(view, raw: dict[str, Path], recipe_path="<recipe>", unit: str = ""):
    """The ``artifacts.capture.CameraRig`` of a markerless sequence, read from its calibration
    files (``calib.io.read_camera``, the recipe's ``calibration_format``): the keypoints stage
    stands in for the capture stage, which does not run without markers."""
    from artifacts.capture import CameraRig
    from calib.io import read_camera

    cams = []
    for c in view.cameras:
        if f"calibration:{c}" not in raw:
            raise InputError(recipe_path, f"sequences.{unit}.calibration.{c}",
                             "a markerless sequence needs every camera's calibration")
        cams.append((c, raw[f"calibration:{c}"]))
    fmt = view.sequence.calibration_format
    return CameraRig.from_cameras([read_camera(p, c, fmt) for c, p in cams],
                                  [Path(p).name for _, p in cams])


def frame_indices(n_video: int, o: Options) -> np.ndarray:
    """(F,) video frames to detect: start, start + stride, ... < min(stop, n_video)."""
    stop = n_video if o.stop is None else min(o.stop, n_video)
    return np.arange(o.start, max(stop, o.start), o.stride, dtype=np.int64)


def markers_on_frames(markers, frames: np.ndarray, clock) -> np.ndarray:
    """Marker positions at video frames: (F, M, 3) metres, world, NaN where not observed.

    markers : ``formats.c3d.Markers``; clock : ``fitting.mocap.VideoClock`` (video frame f is
    at f / fps - sync_offset_s on the mocap clock; ``rate_hz`` overrides the C3D's rate). The
    marker fit's own resampling (``fitting.mocap.video_observations``); gaps are never bridged."""
    from fitting.mocap import video_observations

    obs, vis = video_observations(markers, frames, clock)
    return np.where(vis[..., None], obs, np.nan)


def read_precomputed(raw: dict[str, Path], cam_names: list[str], fmt: str | None,
                     recipe_path, unit: str):
    """The :class:`detect.precomputed.PrecomputedDetector` of the sequence's OpenPose (a folder
    of per-frame JSON files per camera) or COCO (one JSON file per camera) detections, read
    from the raw inputs ``keypoints:<camera>:<n>``."""
    from detect.precomputed import PrecomputedDetector
    from formats.coco import read_coco
    from formats.openpose import read_openpose

    fmt = fmt or "openpose"
    per_cam = []
    for cam in cam_names:
        files = [p for k, p in sorted(raw.items()) if k.startswith(f"keypoints:{cam}:")]
        if not files:
            raise InputError(recipe_path, f"sequences.{unit}.keypoints.{cam}",
                             "no keypoint files for this camera")
        if fmt == "openpose":
            per_cam.append(read_openpose(files))
        else:
            if len(files) != 1:
                raise InputError(files[0].parent, "keypoints", f"COCO: expected one JSON file "
                                 f"for camera {cam}, got {len(files)}")
            per_cam.append(read_coco(files[0]))
    return PrecomputedDetector.from_frames(per_cam)


@dataclass(frozen=True)
class Computed:
    """What :func:`compute` returns: the :class:`Keypoints2D`, the report, and the frame source
    (:class:`detect.run.VideoSource`, for the overlays)."""

    keypoints: Keypoints2D
    report: dict
    source: object


def compute(view, raw: dict[str, Path], o: Options, *, markers, cams, unit: str = "",
            recipe_path="<recipe>", progress=lambda it, **_: it, log=lambda _msg: None,
            cores: int = 0) -> Computed:
    """The stage without the artifact store (used by :func:`run` and the bench): check the
    videos (``raw_inputs`` paths), resample the markers, run
    :func:`detect.sequence.detect_keypoints`. ``view`` : the stage's recipe view
    (``ctx.recipe``, or ``stages.view_for(recipe, "keypoints", unit)``); ``markers`` : the
    cleaned capture (``artifacts.capture.Markers``, stage ``capture``; outside the engine
    ``stages.capture.capture_of``), ``cams`` : its rig's cameras in the recipe's order;
    ``unit`` and ``recipe_path`` name the recipe field in errors."""
    from detect.mediapipe_detector import MediapipeOptions
    from detect.run import VideoSource
    from detect.sequence import detect_keypoints
    from fitting.mocap import VideoClock
    from stages.common import sequence_fps, video_errors, video_length

    seq = view.sequence
    cam_names = list(view.cameras)
    if [c.name for c in cams] != cam_names:
        raise InputError(recipe_path, f"sequences.{unit}.calibration",
                         f"cameras {[c.name for c in cams]} calibrated, the recipe names {cam_names}")
    videos = [raw[f"video:{c}"] for c in cam_names]
    problems = video_errors(videos, seq.fps)
    if problems:
        raise problems[0]
    fps = sequence_fps(seq.fps, videos[0])
    n_video, video_warnings = video_length(videos, cams)  # the shortest video wins
    for w in video_warnings:
        log(f"keypoints: WARNING {w}")
    frames = frame_indices(n_video, o)
    if len(frames) == 0:
        raise InputError(videos[0], "frames", f"no frame in [{o.start}, {o.stop}) of {n_video}")

    kind = o.detector
    if kind == "auto":
        kind = "precomputed" if seq.has_keypoints else "mediapipe"
    if markers is None:  # markerless: the people are found in the views
        return _compute_markerless(view, o, cams, videos, frames, n_video, video_warnings,
                                   kind, unit, recipe_path, progress, log, cores)
    capture_file = str(markers.source)
    markers = markers.capture()
    xyz = markers_on_frames(markers, frames, VideoClock(fps, seq.mocap.sync_offset_s,
                                                        seq.mocap.rate_hz))
    if not np.isfinite(xyz[..., 0]).any():
        raise InputError(capture_file, "markers", "no marker observed at any video frame "
                         "(check mocap.sync_offset_s and fps)")

    if kind == "precomputed":
        if not seq.has_keypoints:
            raise InputError(recipe_path, f"sequences.{unit}.keypoints",
                             "detector 'precomputed' but the sequence names no keypoint files")
        factory = read_precomputed(raw, cam_names, seq.keypoints_format, recipe_path, unit)
    else:
        video = o.video_mode == "on" or (o.video_mode == "auto" and o.stride == 1)
        factory = MediapipeOptions(pose_min_conf=o.pose_min_conf, hand_min_conf=o.hand_min_conf,
                                   video=video)
    source = VideoSource(tuple(str(v) for v in videos))
    log(f"keypoints: detector {kind}")
    kp, facts = detect_keypoints(cams, source, xyz, list(markers.names), frames, factory,
                                 o.sequence_options(cores), progress=progress, log=log,
                                 ground=common.ground_of(view))
    report = {"detector": kind, "cameras": cam_names, "video_frames": n_video,
              "stride": o.stride, "video_warnings": video_warnings, **facts}
    return Computed(kp, report, source)


def _compute_markerless(view, o: Options, cams, videos, frames, n_video, video_warnings,
                        kind, unit, recipe_path, progress, log, cores) -> Computed:
    """:func:`compute` of a markerless sequence (``detect.markerless``): person detection per
    view, cross-view association by triangulation, bystanders rejected."""
    from detect.markerless import MarkerlessOptions, detect_markerless
    from detect.mediapipe_detector import MediapipeOptions
    from detect.run import VideoSource

    if kind != "mediapipe":
        raise InputError(recipe_path, f"sequences.{unit}.keypoints",
                         "a markerless sequence is detected by the keypoints stage (mediapipe); "
                         "precomputed keypoints are not read for it yet")
    people = list(view.sequence.people)
    mo = MarkerlessOptions(people=len(people), max_candidates=max(o.max_candidates, len(people)),
                           assoc_frac=o.assoc_frac, volume_radius_m=o.volume_radius_m,
                           hands=o.hands, workers=o.workers or cores or (os.cpu_count() or 1),
                           chunk=max(1, min(o.chunk, -(-len(frames) // max(1, o.workers or cores
                                                                            or 1)))))
    factory = MediapipeOptions(pose_min_conf=o.pose_min_conf, hand_min_conf=o.hand_min_conf)
    source = VideoSource(tuple(str(v) for v in videos))
    kp, facts = detect_markerless(cams, source, frames, factory, mo,
                                  up=tuple(view.ground_plane.normal), progress=progress, log=log)
    roots = facts.pop("roots")
    report = {"detector": kind, "cameras": list(view.cameras), "video_frames": n_video,
              "stride": o.stride, "video_warnings": video_warnings, "subjects": people, **facts,
              "_roots": roots}
    log(f"keypoints: bystanders in {facts['bystanders']['frames_with']}/{len(frames)} frames "
        f"({facts['bystanders']['groups']} rejected), people found in "
        f"{facts['people_found_frames']} frames")
    return Computed(kp, report, source)


def write_overlays(out, source, kp: Keypoints2D, frame: int) -> list[str]:
    """overlay_<camera>.png of one video frame (the nearest detected one)."""
    from detect.overlay import draw_overlay
    from drawing.sheet import write_png

    i = int(np.argmin(np.abs(kp.frames - frame)))
    fr = int(kp.frames[i])
    reader = source.open()
    names = []
    try:
        for c, cam in enumerate(kp.camera_ids):
            ov = draw_overlay(reader.read(c, fr), kp.kp[c, i], kp.boxes[c, i], kp.hand_boxes[c, i],
                              label=f"{cam} frame {fr}")
            name = f"overlay_{cam}.png"
            write_png(out.path(name), ov)
            names.append(name)
    finally:
        reader.close()
    return names


BOXES_SCHEMA = {
    "title": "keypoints.CropBoxes", "type": "object",
    "properties": {"frame": {"type": "integer"}, "camera": {"type": "string"},
                   "body": {"type": "array", "description": "per person [x0, y0, x1, y1] or null"},
                   "hands": {"type": "array",
                             "description": "per person [left, right] boxes or null"}},
    "required": ["frame", "camera", "body", "hands"],
}


def _box_or_none(b) -> list | None:
    return np.round(np.asarray(b, float), 1).tolist() if np.all(np.isfinite(b)) else None


def write_mcap(path: Path, kp: Keypoints2D, fps: float) -> str:
    """keypoints.mcap (formats.mcap_log): ``/keypoints/<camera>`` (both people, KP65) and
    ``/boxes/<camera>`` (their body and hand crop boxes) per detected frame."""
    from formats.mcap_log import SequenceLog

    with SequenceLog(path, fps=fps) as log:
        for i, fr in enumerate(kp.frames):
            for c, cam in enumerate(kp.camera_ids):
                log.log_keypoints(int(fr), cam, kp.kp[c, i])
                log.add_json_channel(f"/boxes/{cam}", BOXES_SCHEMA)
                log.log_json(f"/boxes/{cam}", int(fr), {
                    "frame": int(fr), "camera": cam,
                    "body": [_box_or_none(b) for b in kp.boxes[c, i]],
                    "hands": [[_box_or_none(b) for b in hb] for hb in kp.hand_boxes[c, i]]})
    return path.name


def run(ctx: StageContext) -> None:
    o: Options = ctx.params or Options()
    if ctx.recipe.sequence.markerless:  # no capture: the rig is read here and kept beside
        rig = read_rig(ctx.recipe, ctx.raw, ctx.recipe_path or "<recipe>", ctx.unit)
        markers, cams = None, rig.cameras(list(ctx.recipe.cameras))
    else:
        rig, markers = None, common.capture_markers(ctx)
        cams = common.capture_cameras(ctx, list(ctx.recipe.cameras))
    c = compute(ctx.recipe, ctx.raw, o, markers=markers, cams=cams, unit=ctx.unit,
                recipe_path=ctx.recipe_path or "<recipe>", progress=ctx.progress, log=ctx.log,
                cores=ctx.cores)
    kp = c.keypoints
    kp.save(ctx.out)
    if rig is not None:
        rig.save(ctx.out)
        roots = c.report.pop("_roots")
        ctx.out.save_arrays("people", frames=kp.frames, **roots)  # people and bystanders in 3D
    sample = int(kp.frames[len(kp.frames) // 2]) if o.overlay_frame is None else o.overlay_frame
    report = dict(c.report)
    report["overlays"] = write_overlays(ctx.out, c.source, kp, sample)
    report["mcap"] = (write_mcap(ctx.out.path("keypoints.mcap"), kp,
                                 common.sequence_fps(ctx.recipe.sequence.fps,
                                                     ctx.raw[f"video:{ctx.recipe.cameras[0]}"]))
                      if o.mcap else None)
    ctx.out.save_json("report", report)
    ctx.log(f"keypoints: {report['fps_per_core']} frames/s per core (all {len(kp.cameras)} "
            f"views), partner tracked in {report['partner_mode_counts']['tracked']} view-frames")
    if rig is not None:
        report["rig"] = "rig.npz"  # the cameras of a markerless sequence (no capture stage)
        ctx.out.save_json("report", report)


STAGE = Stage(name="keypoints", func=run, per="sequence", upstream=("capture",), params=Options,
              raw_inputs=raw_inputs, version="1", cores=2, memory_gb=4.0,
              reads=("cameras", "sequence.fps", "sequence.mocap", "sequence.has_keypoints",
                     "sequence.keypoints_format", "sequence.markerless", "sequence.people",
                     "sequence.calibration_format", "ground_plane"),
              doc="2D body and hand keypoints of both people in every view")
