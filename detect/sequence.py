"""The keypoints stage's domain function: 2D body and hand keypoints of both people in every
view of a sequence, from frames, cameras and the marker wearer's markers. No file I/O: the
stage (``stages/keypoints.py``) reads the videos' lengths, the calibration, the C3D and any
precomputed detections, and hands this module typed inputs.

The marker wearer (person 0) is detected in a tight crop around its projected markers, its
hands in crops around the projected wrist and knuckle markers (:mod:`detect.hints`). The
partner (person 1) is found over the image with the wearer painted out, then per keypoint
type by the paper's rule (:mod:`detect.people`); frames run in chunks in worker processes
(:mod:`detect.run`). Then, with at least three views, the cross-view check
(:mod:`detect.multiview`) drops observations that disagree with what two other views agree
on, drops the partner's unconfirmed keypoints in views where the wearer was not found, and
a final guard drops what is left of the partner in a view where it matches the wearer's
markers (:func:`detect.people.partner_looks_like_wearer`). Last, each view's detection of
each person is judged as a whole skeleton (:mod:`detect.identity`): one that is the other
person's or a mix of both, or that no other view or neighbouring frame agrees with, is
dropped; the partner's left/right-mirrored detections are relabelled.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from artifacts.keypoints import Keypoints2D
from detect import constants as K
from detect import layout
from detect.base import DetectorFactory
from detect.people import PeopleOptions
from detect.run import FrameSource

#: Fewer confident body keypoints of the wearer than this in a view: the wearer counts as not
#: found there (nothing told the two people apart; see :func:`cross_view_guard`).
MIN_WEARER_BODY_KP = 3

#: Names of :attr:`Keypoints2D.partner_mode` codes, in code order.
PARTNER_MODES = ("missing", "tracked", "whole_image")


@dataclass(frozen=True)
class SequenceOptions:
    """Knobs of :func:`detect_keypoints` (defaults in detect/constants.py).

    hands : detect hand keypoints. track / mask_wearer : partner search (:mod:`detect.people`).
    body_margin : wearer crop margin (fraction of the marker box's larger side).
    near_frac : the paper's "close proximity", fraction of the wearer's box height.
    cross_view / cross_view_px : the cross-view check and its RANSAC threshold (pixels).
    identity : after it, judge each view's detection of each person as a whole
        (:mod:`detect.identity`: swaps, inconsistent and flipped detections).
    workers : detector processes (>= 1; 1 runs in this process). chunk : frames per task
        (each task starts its partner search afresh; results do not depend on ``workers``).
    """

    hands: bool = True
    track: bool = True
    mask_wearer: bool = True
    body_margin: float = K.BODY_MARGIN
    near_frac: float = K.NEAR_FRAC
    cross_view: bool = True
    cross_view_px: float = K.CROSS_VIEW_PX
    identity: bool = True
    workers: int = 1
    chunk: int = 32

    def __post_init__(self):
        if self.workers < 1:
            raise ValueError(f"workers: must be >= 1, got {self.workers}")
        if self.chunk < 1:
            raise ValueError(f"chunk: must be >= 1, got {self.chunk}")
        if not self.body_margin >= 0:
            raise ValueError(f"body_margin: must be >= 0, got {self.body_margin}")
        if not self.near_frac > 0:
            raise ValueError(f"near_frac: must be > 0, got {self.near_frac}")
        if not self.cross_view_px > 0:
            raise ValueError(f"cross_view_px: must be > 0 pixels, got {self.cross_view_px}")

    def people(self) -> PeopleOptions:
        """The per-view options of :func:`detect.people.find_people`."""
        return PeopleOptions(body_margin=self.body_margin, near_frac=self.near_frac,
                             track=self.track, mask_wearer=self.mask_wearer, hands=self.hands)


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
            out["detected"][f"{who}.{g}"] = round(float((c >= K.MIN_CONF).mean()), 4) if c.size else None
    return out


def cross_view_guard(cams, kp: np.ndarray, hints, opts: SequenceOptions,
                     head_xyz: np.ndarray | None = None) -> np.ndarray:
    """(C, F, 2, 65) bool: observations of ``kp (C, F, 2, 65, 3)`` to drop (not modified).

    1. :func:`detect.multiview.cross_view_check`: disagrees with what two other views agree on;
    2. where the wearer was not found in a view (< MIN_WEARER_BODY_KP confident body
       keypoints) nothing there told the two people apart (the people overlap in that view),
       so the partner's keypoints in that view are kept only where other views confirm them;
    3. what is left of a partner candidate that mixed both people may be the wearer's part of
       it: a partner that passes the wearer's marker check in a view is dropped there;
    4. the partner's face keypoints that the views agree to put within PARTNER_FACE_HEAD_M of
       the wearer's head centre ``head_xyz (F, 3)`` (world metres, the mean of its head
       markers, :func:`detect.hints.head_centre`; None: not checked): the wearer's face taken
       for the partner's (hugs);
    5. a person whose confident body keypoints in a view were mostly dropped by 1-4
       (:func:`mostly_dropped`) was a skeleton mixing both people there: when its leftovers
       look like the other person's by the wearer's markers (:func:`leftovers_look_swapped`)
       they are dropped too (on the bench session 4 of the 7 swapped views were such
       leftovers), except the wearer's hands (found in crops around its hand markers, not
       from that skeleton).
    """
    from detect.multiview import CrossViewOptions, cross_view_check
    from detect.people import partner_looks_like_wearer

    conf = kp[..., 2]
    xv = cross_view_check(cams, kp, CrossViewOptions(max_error_px=opts.cross_view_px))
    alone = (conf[:, :, 0, layout.BODY] >= K.MIN_CONF).sum(axis=-1) < MIN_WEARER_BODY_KP
    unconfirmed = alone[..., None] & ~xv.confirmed[:, :, 1] & (conf[:, :, 1] >= K.MIN_CONF)
    outlier = xv.outlier.copy()
    outlier[:, :, 1] |= unconfirmed
    left = kp[:, :, 1].copy()
    left[..., 2][outlier[:, :, 1]] = 0.0
    mixed = partner_looks_like_wearer(left, hints, opts.people())
    outlier[:, :, 1] |= mixed[..., None] & (left[..., 2] > 0)
    if head_xyz is not None and xv.xyz is not None:
        X = xv.xyz[:, 1][:, layout.FACE]  # (F, 5, 3) the partner's face as the views agree
        with np.errstate(invalid="ignore"):
            on_head = np.linalg.norm(X - np.asarray(head_xyz)[:, None], axis=-1) < K.PARTNER_FACE_HEAD_M
        bad = np.zeros(conf.shape[1:2] + (layout.N,), bool)  # (F, 65)
        bad[:, layout.FACE] = on_head
        outlier[:, :, 1] |= bad[None] & (conf[:, :, 1] > 0)
    gone = mostly_dropped(conf, outlier) & leftovers_look_swapped(kp, outlier, hints)
    gone = gone[..., None] & (conf > 0)
    gone[:, :, 0, layout.BODY.stop:] = False  # the wearer's hands come from its own marker crops
    return outlier | gone


FEET = [layout.IDX[n] for n in ("l_ankle", "r_ankle", "l_heel", "r_heel")]


def standing_far(cams, kp: np.ndarray, marker_xyz: np.ndarray, ground,
                 reach_m: float = K.PARTNER_REACH_M, min_conf: float = K.ACCEPT_CONF) -> np.ndarray:
    """(C, F) bool: in that view the partner's detection stands farther than ``reach_m`` from
    the wearer, so it is somebody else (an operator or a bystander in the background).

    Where it stands: its confident ankle and heel keypoints (at least two, inside the image)
    back-projected onto the floor raised by ``K.FOOT_HEIGHT_M`` (``ground``: ``(normal (3,),
    offset)``, the plane ``normal . x = offset``, normal up), the least of their distances
    along the floor from the wearer's markers' centre (``marker_xyz (F, M, 3)``, world metres,
    NaN = unseen): a person stands on at least one foot, and a raised foot's ray meets the
    floor beyond it (the median flagged a kicking partner, detected within 8 px). One view is
    enough: a bystander seen by a single camera never meets the
    cross-view check. Not judged (False) without a wearer marker in the frame, with too few
    feet, or with rays that do not come down to the floor in front of the camera.
    kp : (C, F, 2, 65, 3) pixels and confidences."""
    from calib.camera import rays_from_pixels

    n = np.asarray(ground[0], float)
    n = n / np.linalg.norm(n)
    level = float(ground[1]) + K.FOOT_HEIGHT_M
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        centre = np.nanmean(np.asarray(marker_xyz, float), axis=1)  # (F, 3)
    kp = np.asarray(kp, float)
    out = np.zeros(kp.shape[:2], bool)
    for c, cam in enumerate(cams):
        feet = kp[c, :, 1][:, FEET]  # (F, 4, 3)
        uv = feet[..., :2]
        inside = np.all((uv >= 0) & (uv <= np.array([cam.width, cam.height])), axis=-1)
        ok = (feet[..., 2] >= min_conf) & inside & np.all(np.isfinite(uv), axis=-1)
        d = rays_from_pixels(cam, np.nan_to_num(uv)) @ cam.R  # world directions (F, 4, 3)
        down = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (level - cam.T @ n) / down
        ok &= (down < -1e-6) & (t > 0)
        P = cam.T + np.where(ok, t, 0.0)[..., None] * d
        v = P - centre[:, None]
        along = np.linalg.norm(v - (v @ n)[..., None] * n, axis=-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            dist = np.nanmin(np.where(ok, along, np.nan), axis=1)  # (F,) the nearest foot
        judged = (ok.sum(1) >= 2) & np.isfinite(dist)
        out[c] = judged & (dist > reach_m)
    return out


def identity_guard(cams, kp: np.ndarray, outlier: np.ndarray, hints, frames: np.ndarray,
                   opts: SequenceOptions):
    """:func:`detect.identity.identity_check` of ``kp (C, F, 2, 65, 3)`` (the detector's
    confidences) after :func:`cross_view_guard`'s drops ``outlier (C, F, 2, 65)``, with the
    wearer's marker anchors of ``hints``; the views agree within ``opts.cross_view_px``.
    Returns the :class:`detect.identity.IdentityCheck` (its ``outlier`` indexed as relabelled
    by :func:`relabel_flipped`)."""
    from detect.identity import IdentityOptions, identity_check

    return identity_check(cams, kp, outlier, hints.anchors, frames,
                          IdentityOptions(view_px=opts.cross_view_px))


def relabel_flipped(flip: np.ndarray, kp: np.ndarray, conf_raw: np.ndarray,
                    hand_boxes: np.ndarray):
    """Exchange left and right of the detections ``flip (C, F, 2)`` marks: ``kp (C, F, 2,
    65, 3)`` and ``conf_raw (C, F, 2, 65)`` by :data:`detect.layout.FLIP`, ``hand_boxes
    (C, F, 2, 2, 4)`` by side. Returns new arrays (kp, conf_raw, hand_boxes)."""
    kp, conf_raw, hand_boxes = (a.copy() for a in (kp, conf_raw, hand_boxes))
    if flip.any():
        kp[flip] = kp[flip][:, layout.FLIP]
        conf_raw[flip] = conf_raw[flip][:, layout.FLIP]
        hand_boxes[flip] = hand_boxes[flip][:, ::-1]
    return kp, conf_raw, hand_boxes


def identity_counts(verdict: np.ndarray | None) -> dict:
    """The report's view counts per person of each non-ok identity verdict
    (:data:`detect.identity.VERDICTS`); empty when the check did not run."""
    from detect.identity import VERDICTS

    if verdict is None:
        return {}
    return {who: {v: int((verdict[:, :, p] == i).sum()) for i, v in enumerate(VERDICTS) if i}
            for p, who in enumerate(("wearer", "partner"))}


def leftovers_look_swapped(kp: np.ndarray, outlier: np.ndarray, hints) -> np.ndarray:
    """(C, F, 2) bool: the confident body keypoints of ``kp (C, F, 2, 65, 3)`` left after
    ``outlier (C, F, 2, 65)`` look like the other person's, by the wearer's markers: the
    wearer's lie (median) farther than LEFTOVER_OFF_ANCHOR_FRAC x its crop-box height from
    its marker anchors of the same type (either side), the partner's nearer than
    LEFTOVER_ON_WEARER_FRAC to one of the wearer's projected markers. No anchors or markers
    to judge by: False."""
    C, F = kp.shape[:2]
    out = np.zeros((C, F, 2), bool)
    hw = hints.box[..., 3] - hints.box[..., 1]
    body = kp[:, :, :, layout.BODY]
    left = (body[..., 2] >= K.MIN_CONF) & ~outlier[:, :, :, layout.BODY]
    A = hints.anchors[:, :, layout.BODY]
    flip = layout.FLIP[layout.BODY]
    with np.errstate(invalid="ignore"):
        for c, f in zip(*np.nonzero(left.any(axis=-1).any(axis=-1)), strict=True):
            w = body[c, f, 0]
            da = np.fmin(np.linalg.norm(w[:, :2] - A[c, f], axis=-1),
                         np.linalg.norm(w[:, :2] - A[c, f][flip], axis=-1))[left[c, f, 0]]
            if np.isfinite(da).any():
                out[c, f, 0] = np.nanmedian(da) > K.LEFTOVER_OFF_ANCHOR_FRAC * hw[c, f]
            P = body[c, f, 1][left[c, f, 1], :2]
            M = hints.markers[c, f]
            M = M[np.all(np.isfinite(M), axis=-1)]
            if len(P) and len(M):
                dm = np.linalg.norm(P[:, None] - M[None], axis=-1).min(axis=1)
                out[c, f, 1] = np.median(dm) < K.LEFTOVER_ON_WEARER_FRAC * hw[c, f]
    return out


def mostly_dropped(conf: np.ndarray, outlier: np.ndarray, frac: float | None = None) -> np.ndarray:
    """(C, F, 2) bool: fewer than ``frac`` (default MIN_KEPT_FRAC) of the person's confident
    body keypoints in that view survive ``outlier``, and at most MAX_LEFTOVER_KP do (a few
    leftovers of a skeleton that mixed both people). conf : (C, F, 2, 65) detector
    confidences; outlier : (C, F, 2, 65) bool."""
    frac = K.MIN_KEPT_FRAC if frac is None else frac
    body = conf[..., layout.BODY] >= K.MIN_CONF
    raw = body.sum(axis=-1)
    kept = (body & ~outlier[..., layout.BODY]).sum(axis=-1)
    return (raw > 0) & (kept < frac * raw) & (kept <= K.MAX_LEFTOVER_KP)


def detect_keypoints(cams: list, source: FrameSource, marker_xyz: np.ndarray,
                     marker_names: list[str], frames: np.ndarray, detector: DetectorFactory,
                     opts: SequenceOptions = SequenceOptions(),
                     progress: Callable[..., Any] = lambda it, **_: it,
                     log: Callable[[str], None] = lambda _msg: None,
                     ground=None) -> tuple[Keypoints2D, dict]:
    """Both people's keypoints in every view of every frame in ``frames``.

    cams : C :class:`calib.Camera` (their ``name`` becomes ``Keypoints2D.cameras``), in the
        order of ``source``'s views. source : where the pixels come from (opened by the
        workers; not read when the detector needs no pixels). marker_xyz : (F, M, 3) metres,
        world, the wearer's markers at the video frames ``frames (F,)``, NaN where not seen
        (the stage resamples the C3D onto the video clock). marker_names : M labels
        (Plug-in Gait names, any ``subject:`` prefix). detector : a picklable factory
        (:class:`detect.mediapipe_detector.MediapipeOptions`,
        :class:`detect.precomputed.PrecomputedDetector`). ground : ``(normal, offset)`` of
        the floor (the recipe's ``ground_plane``) or None: with it, a partner detection that
        stands out of the wearer's reach (:func:`standing_far`) is somebody else and dropped
        in that view before the cross-view checks (all its keypoints, ``partner_far_views``
        in the report).
    Returns the :class:`Keypoints2D` (cross-view outliers at confidence 0; the detector's own
    confidences in ``conf_raw``; the partner's left/right-mirrored detections relabelled,
    ``conf_raw`` with them) and the report's facts (workers, markers, detector calls,
    partner modes, outliers, identity verdicts per person (:func:`identity_counts`),
    detection rates, speed: ``cpu_s`` is the detector processes' CPU plus ``guard_cpu_s``,
    the cross-view and identity checks in this process).
    Raises ValueError when no marker is seen at any frame (the stage checks that first and
    names the C3D)."""
    from detect.hints import head_centre, wearer_hints
    from detect.run import detect_sequence

    frames = np.asarray(frames, dtype=np.int64)
    marker_xyz = np.asarray(marker_xyz, dtype=np.float64)
    if marker_xyz.ndim != 3 or marker_xyz.shape[0] != len(frames) or marker_xyz.shape[2] != 3:
        raise ValueError(f"detect_keypoints: marker_xyz {marker_xyz.shape} does not match "
                         f"{len(frames)} frames")
    seen = np.isfinite(marker_xyz[..., 0]).any(axis=1)
    if not seen.any():
        raise ValueError("detect_keypoints: no marker observed at any frame")
    hints = wearer_hints(cams, marker_xyz, list(marker_names), opts.body_margin)
    log(f"keypoints: {len(frames)} frames x {len(cams)} views, {opts.workers} worker(s)")
    res = detect_sequence(source, detector, hints, frames, opts.people(), workers=opts.workers,
                          chunk=opts.chunk, progress=progress)
    kp = res.kp
    hand_boxes = res.hand_boxes
    conf_raw = kp[..., 2].copy()
    outlier = np.zeros(conf_raw.shape, bool)
    verdicts = None
    t_guard, w_guard = time.process_time(), time.perf_counter()
    far = np.zeros(kp.shape[:2], bool)  # (C, F): the partner slot holds somebody else
    if ground is not None:
        far = standing_far(cams, kp, marker_xyz, ground)
        outlier[:, :, 1] |= far[..., None] & (conf_raw[:, :, 1] > 0)
        kp[..., 2][outlier] = 0.0
    if opts.cross_view and len(cams) >= 3:
        outlier |= cross_view_guard(cams, kp, hints, opts,
                                    head_centre(marker_xyz, list(marker_names)))
        kp[..., 2][outlier] = 0.0
        if opts.identity:
            raw = kp.copy()
            raw[..., 2] = conf_raw
            ic = identity_guard(cams, raw, outlier, hints, frames, opts)
            kp, conf_raw, hand_boxes = relabel_flipped(ic.flip, raw, conf_raw, hand_boxes)
            outlier = ic.outlier
            outlier[:, :, 1] |= far[..., None] & (conf_raw[:, :, 1] > 0)  # whatever it judged
            kp[..., 2][outlier] = 0.0
            verdicts = ic.verdict
    guard_cpu_s, guard_wall_s = time.process_time() - t_guard, time.perf_counter() - w_guard
    out = Keypoints2D(kp=kp.astype(np.float32), boxes=res.boxes.astype(np.float32),
                      hand_boxes=hand_boxes.astype(np.float32), frames=res.frames,
                      wearer_retry=res.wearer_retry, partner_mode=res.partner_mode,
                      cross_view_outlier=outlier, conf_raw=conf_raw.astype(np.float32),
                      cameras=np.array([c.name for c in cams], dtype=str))
    report = {"workers": opts.workers, "markers": len(marker_names),
              "frames_with_markers": int(seen.sum()),
              "wearer_retries": int(res.wearer_retry.sum()),
              "partner_mode_counts": {m: int((res.partner_mode == i).sum())
                                      for i, m in enumerate(PARTNER_MODES)},
              "detector_calls": {k: (round(v, 3) if isinstance(v, float) else int(v))
                                 for k, v in res.meter.items()},
              "cross_view_outliers": {who: int(outlier[:, :, p].sum())
                                      for p, who in enumerate(("wearer", "partner"))},
              "identity": identity_counts(verdicts),
              "partner_far_views": int(far.sum()),
              "guard_cpu_s": round(guard_cpu_s, 3),
              **summary(kp, res.cpu_s + guard_cpu_s, res.wall_s + guard_wall_s, len(frames))}
    return out, report
