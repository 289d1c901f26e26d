"""Stage ``keypoints`` (per sequence): 2D body and hand keypoints of both people in every view.

The marker wearer (person 0) is detected in a tight crop around its projected markers (C3D
resampled to the video frames, projected with each camera), its hands in crops around the
projected wrist and knuckle markers. The partner (person 1) is found over the image with the
wearer painted out, then per keypoint type by the paper's rule (drop candidates near the
wearer's keypoint, keep the most confident); between frames its box is tracked
(:mod:`detect.people` explains the choices). With precomputed detections (the recipe's
``keypoints`` folders) the same rules pick the two people among the file's candidates.

Writes:

- ``keypoints.npz``: ``kp (C, F, 2, 65, 3)`` float32 (x, y full-image pixels, confidence;
  0 = missing; KP65 layout; person 0 = marker wearer), ``boxes (C, F, 2, 4)`` body crop boxes,
  ``hand_boxes (C, F, 2, 2, 4)``, ``frames (F,)`` video frame indices, ``wearer_retry (C, F)``,
  ``partner_mode (C, F)`` (0 not found, 1 tracked, 2 whole image), ``cross_view_outlier
  (C, F, 2, 65)`` (observations dropped by the cross-view check, detect/multiview.py: they
  disagree with what two other views agree on, or are the partner's, unconfirmed, in a view
  where the wearer was not found, or what remains of the partner there matches the wearer's
  markers) and
  ``conf_raw (C, F, 2, 65)`` (the detector's confidences before it);
- ``keypoints.mcap``: the keypoints and boxes per camera and frame (Foxglove-viewable);
- ``overlay_<camera>.png``: one sample frame per view with both people drawn;
- ``report.json``: detector, frames, detection rates per person and joint group, timings
  (``fps_per_core``).

Frames run in parallel worker processes (``workers``), each with its own detector; ``stride``
keeps every n-th video frame (the detector dominates the pipeline's run time).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from detect import constants as DK
from formats.errors import InputError
from pipeline.spec import Stage, StageContext


@dataclass(frozen=True)
class Options:
    """detector : ``auto`` (precomputed files when the sequence names them, else mediapipe),
        ``mediapipe`` or ``precomputed``.
    stride : keep every ``stride``-th video frame; start / stop : video frame range
        (stop None: to the end).
    workers : detector processes (0: one per core). chunk : frames per task (each task
        starts its partner search afresh).
    hands : detect hand keypoints. track / mask_wearer : partner search (detect.people).
    body_margin : wearer crop margin (fraction of the marker box's larger side).
    near_frac : the paper's "close proximity", fraction of the wearer's box height.
    pose_min_conf / hand_min_conf : mediapipe detection thresholds.
    cross_view / cross_view_px : drop observations that disagree with what the other views
        agree on (detect/multiview.py; RANSAC threshold in pixels), and the partner's
        unconfirmed keypoints in views where the wearer was not found.
    overlay_frame : video frame drawn in the overlay PNGs (None: the middle one).
    mcap : write keypoints.mcap.
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
    cross_view: bool = True
    cross_view_px: float = DK.CROSS_VIEW_PX
    overlay_frame: int | None = None
    mcap: bool = True

    def __post_init__(self):
        if self.stride < 1:
            raise ValueError(f"stride: must be >= 1, got {self.stride}")
        if self.start < 0 or (self.stop is not None and self.stop <= self.start):
            raise ValueError(f"start/stop: need 0 <= start < stop, got {self.start}, {self.stop}")
        if self.workers < 0 or self.chunk < 1:
            raise ValueError(f"workers >= 0 and chunk >= 1, got {self.workers}, {self.chunk}")


def _precomputed_files(seq, cam: str) -> list[Path]:
    root = Path(seq.keypoints[cam])
    return sorted(root.glob("*.json")) if root.is_dir() else [root]


def raw_inputs(recipe, unit: str) -> dict[str, Path]:
    seq = recipe.sequence(unit)
    out: dict[str, Path] = {"c3d": Path(seq.c3d)}
    for cam in recipe.cameras:
        out[f"video:{cam}"] = Path(seq.videos[cam])
        out[f"calibration:{cam}"] = Path(seq.calibration[cam])
        if seq.keypoints and cam in seq.keypoints:
            for i, p in enumerate(_precomputed_files(seq, cam)):
                out[f"keypoints:{cam}:{i:06d}"] = p
    return out


def frame_indices(n_video: int, o: Options) -> np.ndarray:
    """(F,) video frames to detect: start, start + stride, ... < min(stop, n_video)."""
    stop = n_video if o.stop is None else min(o.stop, n_video)
    return np.arange(o.start, max(stop, o.start), o.stride, dtype=np.int64)


def markers_on_frames(times_s: np.ndarray, xyz: np.ndarray, frames: np.ndarray, fps: float,
                      sync_offset_s: float) -> np.ndarray:
    """Marker positions at video frames: (F, M, 3) metres, world, NaN where not observed.

    times_s : (Fs,) mocap sample times (mocap clock); xyz : (Fs, M, 3) with NaN gaps; video
    frame f is at f / fps - sync_offset_s on the mocap clock. Gaps are never bridged."""
    from fitting.mocap import resample

    t = np.asarray(frames, dtype=np.float64) / float(fps) - float(sync_offset_s)
    obs, vis = resample(times_s, xyz, t)
    return np.where(vis[..., None], obs, np.nan)


def video_frame_count(paths: list[Path]) -> int:
    """Frames in the shortest of the videos (InputError naming a bad file)."""
    from formats.video import video_info

    return min(video_info(p).n_frames for p in paths)


def people_options(o: Options):
    from detect.people import PeopleOptions

    return PeopleOptions(body_margin=o.body_margin, near_frac=o.near_frac, track=o.track,
                         mask_wearer=o.mask_wearer, hands=o.hands)


def summary(kp: np.ndarray, cpu_s: float, wall_s: float, n_frames: int) -> dict:
    """Detection rates per person and joint group, and speed. kp (C, F, 2, 65, 3)."""
    from detect.metrics import GROUPS

    out: dict = {"frames": int(n_frames), "cpu_s": round(cpu_s, 3), "wall_s": round(wall_s, 3),
                 "fps_per_core": round(n_frames / cpu_s, 4) if cpu_s > 0 else None,
                 "fps_wall": round(n_frames / wall_s, 4) if wall_s > 0 else None,
                 "detected": {}}
    for p, who in enumerate(("wearer", "partner")):
        for g, idx in GROUPS.items():
            c = kp[:, :, p][..., idx, 2]
            out["detected"][f"{who}.{g}"] = round(float((c >= DK.MIN_CONF).mean()), 4) if c.size else None
    return out


def write_overlays(out, source, res, cams: list[str], frame: int) -> list[str]:
    """overlay_<camera>.png of one video frame (the nearest detected one)."""
    import cv2

    from detect.overlay import draw_overlay

    i = int(np.argmin(np.abs(res.frames - frame)))
    reader = source.open()
    names = []
    try:
        for c, cam in enumerate(cams):
            img = reader.read(c, int(res.frames[i]))
            ov = draw_overlay(img, res.kp[c, i], res.boxes[c, i], res.hand_boxes[c, i],
                              label=f"{cam} frame {int(res.frames[i])}")
            name = f"overlay_{cam}.png"
            cv2.imwrite(str(out.path(name)), ov[..., ::-1])
            names.append(name)
    finally:
        reader.close()
    return names


@dataclass(frozen=True)
class Computed:
    """What :func:`compute` returns: the detections (:class:`detect.run.SequenceKeypoints`,
    cross-view outliers already at confidence 0), the frame source (for overlays), the camera
    ids, the report's facts, the detector's confidences before the cross-view check
    ``conf_raw (C, F, 2, 65)`` and the ``outlier (C, F, 2, 65)`` mask."""

    res: object
    source: object
    cam_names: list
    report: dict
    conf_raw: np.ndarray
    outlier: np.ndarray


def compute(recipe, unit: str, raw: dict[str, Path], o: Options, progress=lambda it, **_: it,
            log=lambda _msg: None) -> Computed:
    """The stage without the artifact store: read the raw inputs (``raw_inputs`` paths),
    detect both people in every view of every selected frame. Used by :func:`run` and by the
    bench (bench/cases/keypoints.py)."""
    from calib.io import read_chi3d_camera
    from detect import layout
    from detect.hints import wearer_hints
    from detect.mediapipe_detector import MediapipeOptions
    from detect.run import VideoSource, detect_sequence
    from formats.c3d import read_c3d

    seq = recipe.sequence(unit)
    cam_names = list(recipe.cameras)
    cams = [read_chi3d_camera(raw[f"calibration:{c}"], name=c) for c in cam_names]
    videos = [raw[f"video:{c}"] for c in cam_names]
    n_video = video_frame_count(videos)
    frames = frame_indices(n_video, o)
    if len(frames) == 0:
        raise InputError(videos[0], "frames", f"no frame in [{o.start}, {o.stop}) of {n_video}")

    markers = read_c3d(raw["c3d"])
    times = markers.times_s if seq.mocap.rate_hz is None else \
        (markers.first_frame + np.arange(len(markers.xyz))) / seq.mocap.rate_hz
    xyz = markers_on_frames(times, markers.xyz, frames, seq.fps, seq.mocap.sync_offset_s)
    seen = np.isfinite(xyz[..., 0]).any(axis=1)
    if not seen.any():
        raise InputError(raw["c3d"], "markers", "no marker observed at any video frame "
                         "(check mocap.sync_offset_s and fps)")
    hints = wearer_hints(cams, xyz, list(markers.names), o.body_margin)

    kind = o.detector
    if kind == "auto":
        kind = "precomputed" if seq.keypoints else "mediapipe"
    if kind == "precomputed":
        if not seq.keypoints:
            raise InputError(recipe.source, f"sequences.{unit}.keypoints",
                             "detector 'precomputed' but the sequence names no keypoint files")
        factory = load_precomputed(recipe, unit, raw, seq, cam_names)
    else:
        factory = MediapipeOptions(pose_min_conf=o.pose_min_conf, hand_min_conf=o.hand_min_conf)
    workers = o.workers or (os.cpu_count() or 1)
    source = VideoSource(tuple(str(v) for v in videos))
    log(f"keypoints: {len(frames)} frames x {len(cams)} views, detector {kind}, "
        f"{workers} worker(s)")
    res = detect_sequence(source, factory, hints, frames, people_options(o), workers=workers,
                          chunk=o.chunk, progress=progress)
    conf_raw = res.kp[..., 2].copy()
    outlier = np.zeros(conf_raw.shape, bool)
    if o.cross_view and len(cams) >= 3:
        from detect.multiview import CrossViewOptions, cross_view_check

        xv = cross_view_check(cams, res.kp, CrossViewOptions(max_error_px=o.cross_view_px))
        # Where the wearer was not found in a view, nothing there told the two people apart
        # (the wearer check failed: the people overlap in that view), so the partner's
        # keypoints in that view are kept only where other views confirm them.
        alone = (conf_raw[:, :, 0, layout.BODY] >= DK.MIN_CONF).sum(axis=-1) < 3  # (C, F)
        unconfirmed = alone[..., None] & ~xv.confirmed[:, :, 1] & (conf_raw[:, :, 1] >= DK.MIN_CONF)
        outlier = xv.outlier.copy()
        outlier[:, :, 1] |= unconfirmed
        res.kp[..., 2][outlier] = 0.0
        # What is left of a candidate that mixed both people may be the wearer's part of it.
        from detect.people import partner_looks_like_wearer

        mixed = partner_looks_like_wearer(res.kp[:, :, 1], hints, people_options(o))
        drop = mixed[..., None] & (res.kp[:, :, 1, :, 2] > 0)
        outlier[:, :, 1] |= drop
        res.kp[:, :, 1, :, 2][drop] = 0.0
    report = {"detector": kind, "cameras": cam_names, "video_frames": n_video,
              "stride": o.stride, "workers": workers, "markers": len(markers.names),
              "frames_with_markers": int(seen.sum()),
              "wearer_retries": int(res.wearer_retry.sum()),
              "partner_mode_counts": {m: int((res.partner_mode == i).sum())
                                      for i, m in enumerate(("missing", "tracked", "whole_image"))},
              "detector_calls": {k: (round(v, 3) if isinstance(v, float) else int(v))
                                 for k, v in res.meter.items()},
              "cross_view_outliers": {who: int(outlier[:, :, p].sum())
                                      for p, who in enumerate(("wearer", "partner"))},
              **summary(res.kp, res.cpu_s, res.wall_s, len(frames))}
    return Computed(res, source, cam_names, report, conf_raw, outlier)


def run(ctx: StageContext) -> None:
    o: Options = ctx.params or Options()
    seq = ctx.recipe.sequence(ctx.unit)
    c = compute(ctx.recipe, ctx.unit, ctx.raw, o, progress=ctx.progress, log=ctx.log)
    res = c.res
    ctx.out.save_arrays("keypoints", kp=res.kp, boxes=res.boxes.astype(np.float32),
                        hand_boxes=res.hand_boxes.astype(np.float32), frames=res.frames,
                        wearer_retry=res.wearer_retry, partner_mode=res.partner_mode,
                        conf_raw=c.conf_raw.astype(np.float32), cross_view_outlier=c.outlier)
    frames = res.frames
    sample = int(frames[len(frames) // 2]) if o.overlay_frame is None else o.overlay_frame
    report = dict(c.report)
    report["overlays"] = write_overlays(ctx.out, c.source, res, c.cam_names, sample)
    report["mcap"] = (write_mcap(ctx.out.path("keypoints.mcap"), res, c.cam_names, seq.fps)
                      if o.mcap else None)
    ctx.out.save_json("report", report)
    ctx.log(f"keypoints: {report['fps_per_core']} frames/s per core (all {len(c.cam_names)} "
            f"views), partner tracked in {report['partner_mode_counts']['tracked']} view-frames")


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


def write_mcap(path: Path, res, cam_names: list[str], fps: float) -> str:
    """keypoints.mcap (formats.mcap_log): ``/keypoints/<camera>`` (both people, KP65) and
    ``/boxes/<camera>`` (their body and hand crop boxes) per detected frame."""
    from formats.mcap_log import SequenceLog

    with SequenceLog(path, fps=fps) as log:
        for i, fr in enumerate(res.frames):
            for c, cam in enumerate(cam_names):
                log.log_keypoints(int(fr), cam, res.kp[c, i])
                log.add_json_channel(f"/boxes/{cam}", BOXES_SCHEMA)
                log.log_json(f"/boxes/{cam}", int(fr), {
                    "frame": int(fr), "camera": cam,
                    "body": [_box_or_none(b) for b in res.boxes[c, i]],
                    "hands": [[_box_or_none(b) for b in hb] for hb in res.hand_boxes[c, i]]})
    return path.name


def load_precomputed(recipe, unit: str, raw: dict[str, Path], seq, cam_names: list[str]):
    """A PrecomputedDetector from the sequence's OpenPose (a folder of per-frame JSON files per
    camera) or COCO (one JSON file per camera) detections: every camera's candidates on the
    union of the frames the files cover (a frame missing from one camera has no candidates
    there)."""
    from detect.precomputed import PrecomputedDetector
    from formats.coco import read_coco
    from formats.openpose import read_openpose

    fmt = seq.keypoints_format or "openpose"
    per_cam = []
    for cam in cam_names:
        files = [p for k, p in sorted(raw.items()) if k.startswith(f"keypoints:{cam}:")]
        if not files:
            raise InputError(recipe.source, f"sequences.{unit}.keypoints.{cam}",
                             "no keypoint files for this camera")
        if fmt == "openpose":
            per_cam.append(read_openpose(files))
        else:
            if len(files) != 1:
                raise InputError(files[0].parent, "keypoints", f"COCO: expected one JSON file "
                                 f"for camera {cam}, got {len(files)}")
            per_cam.append(read_coco(files[0]))
    frames = np.unique(np.concatenate([k.frames for k in per_cam]))
    n = max([k.kp.shape[1] for k in per_cam] + [1])
    kp = np.zeros((len(cam_names), len(frames), n, 65, 3), np.float32)
    for c, k in enumerate(per_cam):
        rows = np.searchsorted(frames, k.frames)
        kp[c, rows, :k.kp.shape[1]] = k.kp
    return PrecomputedDetector(kp, tuple(int(f) for f in frames))


STAGE = Stage(name="keypoints", func=run, per="sequence", upstream=(), params=Options,
              raw_inputs=raw_inputs, version="1",
              doc="2D body and hand keypoints of both people in every view")
