"""Keypoints of a markerless sequence: the people found in the views, nobody's markers to
crop around (issue #28 item 1).

Per view and frame, the single-person detector (mediapipe) is run on the whole image, then
once more in a crop around what it found (more pixels per person), and the person is painted
out (:mod:`detect.mask`) before the next look: up to ``max_candidates`` people per view. Each
candidate's hands come from crops around its wrists (as the partner's in :mod:`detect.people`).

Across views, candidates are associated by triangulation (:func:`associate`): every pair of
candidates in two views is triangulated (linear DLT on the undistorted body keypoints) and
kept when it reprojects within ``assoc_frac`` of the person's box height in both; groups grow
from the best pair by adding the candidates of the other views that the group's 3D skeleton
projects onto. A group seen in at least two views is a person in 3D; the people fitted are
the groups nearest the previous frame's people (the capture volume centre at the start: the
point nearest every camera's optical axis), within ``volume_radius_m`` of that centre on the
ground. Every other group (an operator in the background) is a bystander: it is counted, per
frame, and its detections are dropped.

No file I/O: the keypoints stage (``stages/keypoints.py``) reads the videos and the
calibration and hands this module the frames and cameras.
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from artifacts.keypoints import Keypoints2D
from calib.dlt import triangulate_points
from detect import constants as K
from detect import layout
from detect.base import call_detector

N_BODY = 23
ROOT = (layout.IDX["l_hip"], layout.IDX["r_hip"])
SHOULDERS = (layout.IDX["l_shoulder"], layout.IDX["r_shoulder"])


@dataclass(frozen=True)
class MarkerlessOptions:
    """people : persons fitted (1 or 2). max_candidates : people looked for per view.
    min_body_kp : confident body keypoints (of 23) a candidate needs. min_conf : keypoint
    confidence counted. assoc_frac : two views' candidates are one person when their
    triangulation reprojects within this fraction of the person's box height (median over
    the body keypoints). volume_radius_m : a person farther than this from the capture
    volume centre on the ground is a bystander. track_m : a person moves at most this far
    between detected frames (beyond it the nearest group is not the same person).
    duplicate_m : a group this near a chosen person is a duplicate of it, not a bystander.
    refine_crop : detect again in a crop around each person found on the whole image.
    hands : detect hand keypoints. workers / chunk : detector processes, frames per task."""

    people: int = 1
    max_candidates: int = 3
    min_body_kp: int = 8
    min_conf: float = K.MIN_CONF
    assoc_frac: float = 0.08
    volume_radius_m: float = 2.5
    track_m: float = 0.6
    duplicate_m: float = 0.5
    refine_crop: bool = True
    hands: bool = True
    workers: int = 1
    chunk: int = 16

    def __post_init__(self):
        if self.people not in (1, 2):
            raise ValueError(f"people: 1 or 2, got {self.people}")
        if self.max_candidates < self.people:
            raise ValueError(f"max_candidates: at least people ({self.people}), got "
                             f"{self.max_candidates}")
        for name in ("assoc_frac", "volume_radius_m", "track_m", "duplicate_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        if self.workers < 1 or self.chunk < 1:
            raise ValueError(f"workers / chunk: must be >= 1, got {self.workers} / {self.chunk}")


# ------------------------------------------------------------------------------ one view


def _n_good(kp: np.ndarray, conf: float) -> int:
    return int((kp[:N_BODY, 2] >= conf).sum())


def _box(kp: np.ndarray, conf: float) -> np.ndarray:
    from detect.crops import box_from_points

    return box_from_points(kp[:N_BODY, :2], kp[:N_BODY, 2] >= conf)


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1); 0 when either is NaN."""
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return 0.0
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def is_duplicate(kp: np.ndarray, others: list, conf: float, iou: float = 0.4) -> bool:
    """Whether a candidate is a person already found in this view (the detector finding what
    the painting left of it): its box overlaps an earlier one's by ``iou``."""
    b = _box(kp, conf)
    return any(box_iou(b, _box(k, conf)) > iou for k in others)


def view_candidates(image: np.ndarray, det, o: MarkerlessOptions, cam: int = 0,
                    frame: int = 0) -> np.ndarray:
    """(N, 65, 3) the people found in one image (N <= ``max_candidates``), each painted out
    before looking for the next; hands from crops around each one's wrists."""
    from detect.crops import expand_box
    from detect.mask import paint_out, silhouette_mask
    from detect.people import PeopleOptions, _hands, _partner_hand_boxes

    img = image
    out = []
    for _ in range(o.max_candidates + 2):  # duplicates do not count
        if len(out) >= o.max_candidates:
            break
        found = call_detector(det, img, kind="body", cam=cam, frame=frame).kp
        if not len(found) or _n_good(found[0], o.min_conf) < o.min_body_kp:
            break
        kp = found[0].copy()
        if o.refine_crop:
            box = expand_box(_box(kp, o.min_conf), 0.25, square=True)
            again = call_detector(det, img, kind="body", box=box, cam=cam, frame=frame).kp
            if len(again) and _n_good(again[0], o.min_conf) >= _n_good(kp, o.min_conf) - 2:
                kp = again[0].copy()
        b = _box(kp, o.min_conf)
        h = float(b[3] - b[1]) if np.all(np.isfinite(b)) else 100.0
        mask = silhouette_mask(img.shape[:2], kp, layout.EDGES, max(0.06 * h, 4.0),
                               polygons=(layout.TORSO,), blobs=((layout.FACE, 0.12 * h),),
                               min_conf=o.min_conf)
        if is_duplicate(kp, out, o.min_conf):  # what is left of someone found: paint, go on
            img = paint_out(img, mask)
            continue
        if o.hands:
            boxes, wrists = _partner_hand_boxes(kp, o.min_conf)
            _hands(image, kp, boxes, wrists, det, PeopleOptions(), cam, frame, who=f"c{len(out)}")
        out.append(kp)
        img = paint_out(img, mask)
    return np.stack(out) if out else np.zeros((0, layout.N, 3), np.float32)


def _detect_chunk(source, factory, frames: np.ndarray, n_cam: int, o: MarkerlessOptions):
    """Worker: candidates of every view of ``frames`` ([frame][cam] -> (N, 65, 3)) and the
    CPU seconds."""
    from detect.run import _silence_native_stderr

    _silence_native_stderr()
    c0 = time.process_time()
    det = factory.build()
    reader = source.open()
    try:
        res = [[view_candidates(reader.read(c, int(f)), det, o, c, int(f)) for c in range(n_cam)]
               for f in frames]
    finally:
        reader.close()
        det.close()
    return res, time.process_time() - c0


def detect_candidates(source, factory, frames: np.ndarray, n_cam: int, o: MarkerlessOptions,
                      progress: Callable[..., Any] = lambda it, **_: it):
    """Every view's candidates at every frame, ``[F][C] (N, 65, 3)``, and the detector
    processes' CPU seconds; chunks of ``o.chunk`` frames over ``o.workers`` processes."""
    parts = [frames[i:i + o.chunk] for i in range(0, len(frames), o.chunk)]
    out: list = []
    cpu = 0.0
    if o.workers == 1:
        for p in progress(parts, total=len(parts), desc="keypoints"):
            r, c = _detect_chunk(source, factory, p, n_cam, o)
            out += r
            cpu += c
        return out, cpu
    import multiprocessing as mp

    with ProcessPoolExecutor(max_workers=o.workers, mp_context=mp.get_context("spawn")) as ex:
        futs = [ex.submit(_detect_chunk, source, factory, p, n_cam, o) for p in parts]
        for fu in progress(futs, total=len(futs), desc="keypoints"):
            r, c = fu.result()
            out += r
            cpu += c
    return out, cpu


# ------------------------------------------------------------------------------ 3D


def _project(cam, X: np.ndarray) -> np.ndarray:
    from calib import project

    out = np.full(X.shape[:-1] + (2,), np.nan)
    fin = np.all(np.isfinite(X), axis=-1)
    if fin.any():
        Xc = (X[fin] - np.asarray(cam.T, float)) @ np.asarray(cam.R, float).T
        front = Xc[:, 2] > 0.05
        uv = np.full((int(fin.sum()), 2), np.nan)
        if front.any():
            uv[front] = project(cam, X[fin][front])
        out[fin] = uv
    return out


def volume_centre(cams) -> np.ndarray:
    """(3,) the point nearest every camera's optical axis (least squares): where the cameras
    look, the middle of the capture volume."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = np.asarray(c.R, float)[2]  # the optical axis in the world (row 3 of cam_from_world)
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ np.asarray(c.T, float)
    return np.linalg.lstsq(A, b, rcond=None)[0]


@dataclass
class Group:
    """One person in 3D at one frame: ``members`` {view: candidate index}, ``X (23, 3)`` the
    triangulated body keypoints, ``root (3,)``, ``err`` median reprojection px."""

    members: dict
    X: np.ndarray
    root: np.ndarray
    err: float


def _root(X: np.ndarray) -> np.ndarray:
    for idx in (ROOT, SHOULDERS):
        p = X[list(idx)]
        if np.all(np.isfinite(p)):
            return p.mean(0)
    fin = np.all(np.isfinite(X), axis=1)
    return np.median(X[fin], axis=0) if fin.any() else np.full(3, np.nan)


def _fit_group(cams, cands, members: dict, conf: float):
    views = sorted(members)
    kp = np.stack([cands[v][members[v]][:N_BODY] for v in views])
    ok = kp[..., 2] >= conf
    X = triangulate_points([cams[v] for v in views], kp[..., :2], ok)
    errs = []
    for i, v in enumerate(views):
        pr = _project(cams[v], X)
        e = np.linalg.norm(pr - kp[i, :, :2], axis=1)
        errs.append(e[ok[i] & np.isfinite(e)])
    allv = np.concatenate(errs) if errs else np.zeros(0)
    return X, (float(np.median(allv)) if len(allv) >= 4 else np.inf)


def _height_px(kp: np.ndarray, conf: float) -> float:
    b = _box(kp, conf)
    return float(max(b[3] - b[1], b[2] - b[0])) if np.all(np.isfinite(b)) else np.nan


def associate(cams, cands: list, o: MarkerlessOptions) -> list[Group]:
    """One frame's candidates (``cands[c] (N_c, 65, 3)``) grouped into people across views."""
    C = len(cams)
    H = [[_height_px(k, o.min_conf) for k in cands[c]] for c in range(C)]
    pairs = []
    for a in range(C):
        for b in range(a + 1, C):
            for i in range(len(cands[a])):
                for j in range(len(cands[b])):
                    X, err = _fit_group(cams, cands, {a: i, b: j}, o.min_conf)
                    thr = o.assoc_frac * np.nanmean([H[a][i], H[b][j]])
                    if err <= thr:
                        pairs.append((err / thr, a, i, b, j))
    pairs.sort()
    used: set = set()
    groups: list[Group] = []
    for _, a, i, b, j in pairs:
        if (a, i) in used or (b, j) in used:
            continue
        members = {a: i, b: j}
        X, err = _fit_group(cams, cands, members, o.min_conf)
        for c in range(C):  # the other views: the candidate the skeleton projects onto
            if c in members:
                continue
            pr = _project(cams[c], X)
            best, best_e = None, np.inf
            for n, k in enumerate(cands[c]):
                if (c, n) in used:
                    continue
                ok = (k[:N_BODY, 2] >= o.min_conf) & np.all(np.isfinite(pr), axis=1)
                if ok.sum() < 4:
                    continue
                e = float(np.median(np.linalg.norm(pr[ok] - k[:N_BODY][ok, :2], axis=1)))
                if e <= 2 * o.assoc_frac * H[c][n] and e < best_e:
                    best, best_e = n, e
            if best is not None:
                trial = {**members, c: best}
                X2, err2 = _fit_group(cams, cands, trial, o.min_conf)
                if err2 <= 1.5 * max(err, 1.0) + o.assoc_frac * 0.5 * H[c][best]:
                    members, X, err = trial, X2, err2
        used |= {(v, n) for v, n in members.items()}
        groups.append(Group(members, X, _root(X), err))
    return groups


def _horizontal(d: np.ndarray, up: np.ndarray) -> np.ndarray:
    return d - np.outer(d @ up, up) if d.ndim == 2 else d - (d @ up) * up


@dataclass(frozen=True)
class Selection:
    """The people chosen at every frame: ``slot[f]`` list (per person slot) of a group index
    or None; ``groups[f]`` the frame's groups; ``bystanders (F,)`` groups not fitted;
    ``far (F,)`` of those, the ones rejected for their distance to the volume centre;
    ``duplicates (F,)`` groups within ``duplicate_m`` of a chosen person (what is left of it
    in some views, associated: not another person), ``duplicate[f]`` per group."""

    slot: list
    groups: list
    bystanders: np.ndarray
    far: np.ndarray
    duplicates: np.ndarray
    duplicate: list


def select_people(groups_per_frame: list[list[Group]], centre: np.ndarray, up: np.ndarray,
                  o: MarkerlessOptions) -> Selection:
    """The ``o.people`` persons at every frame: the groups nearest the previous frame's
    people (the volume centre before anyone was seen), within ``volume_radius_m`` of the
    centre on the ground and ``track_m`` per frame of their previous place (further: a new
    start from the centre). Every other group is a bystander."""
    from scipy.optimize import linear_sum_assignment

    up = np.asarray(up, float) / np.linalg.norm(up)
    prev: list = [None] * o.people
    slots, nby, nfar, ndup, dups = [], [], [], [], []
    for groups in groups_per_frame:
        roots = np.array([g.root for g in groups]).reshape(-1, 3)
        okg = np.all(np.isfinite(roots), axis=1)
        dc = (np.linalg.norm(_horizontal(roots - centre, up), axis=1) if len(roots)
              else np.zeros(0))
        near = okg & (dc <= o.volume_radius_m)
        slot: list = [None] * o.people
        cand = np.flatnonzero(near)
        if len(cand):
            cost = np.zeros((o.people, len(cand)))
            for p in range(o.people):
                anchor = prev[p]
                for j, g in enumerate(cand):
                    if anchor is None:
                        cost[p, j] = 10.0 + dc[g]  # nobody yet: nearest the centre
                    else:
                        d = float(np.linalg.norm(_horizontal(roots[g] - anchor, up)))
                        cost[p, j] = d if d <= o.track_m * 3 else 100.0 + dc[g]
            if o.people == 2 and all(p is None for p in prev) and len(cand) >= 2:
                # the first time both are seen: left to right along the first camera-free axis
                pick = cand[np.argsort(dc[cand])[:2]]
                pick = pick[np.argsort(roots[pick, 0])]
                slot = [int(pick[0]), int(pick[1])]
            else:
                rows, cols = linear_sum_assignment(cost)
                for r, c in zip(rows, cols, strict=True):
                    slot[r] = int(cand[c])
        for p, g in enumerate(slot):
            if g is not None:
                prev[p] = roots[g]
        chosen = {g for g in slot if g is not None}
        dup = np.zeros(len(roots), bool)
        for g in range(len(roots)):
            if g not in chosen and okg[g]:
                dup[g] = any(np.linalg.norm(_horizontal(roots[g] - roots[c], up)) < o.duplicate_m
                             for c in chosen)
        slots.append(slot)
        nby.append(int((okg & ~dup).sum()) - len(chosen))
        nfar.append(int((okg & ~near).sum()))
        ndup.append(int(dup.sum()))
        dups.append(dup)
    return Selection(slots, groups_per_frame, np.array(nby, np.int64), np.array(nfar, np.int64),
                     np.array(ndup, np.int64), dups)


# ------------------------------------------------------------------------------ the sequence


def detect_markerless(cams, source, frames: np.ndarray, factory, o: MarkerlessOptions,
                      up=(0.0, 0.0, 1.0), progress: Callable[..., Any] = lambda it, **_: it,
                      log: Callable[[str], None] = lambda _msg: None,
                      candidates: list | None = None) -> tuple[Keypoints2D, dict]:
    """The people of a markerless sequence in every view of ``frames``: a
    :class:`Keypoints2D` with person ``p`` in slot ``p`` (a one-person sequence leaves slot 1
    empty), and the report's facts (bystanders per frame, people found per frame, speed;
    ``roots``: arrays of the people's triangulated roots ``people_root (F, 2, 3)`` and of every
    bystander group ``bystander_frame / _root / _views``, which the stage writes to
    ``people.npz``).
    ``candidates``: the per-view detections ``[F][C] (N, 65, 3)`` when already known (tests;
    then ``source`` and ``factory`` are not used)."""
    frames = np.asarray(frames, np.int64)
    C, F = len(cams), len(frames)
    t0, w0 = time.process_time(), time.perf_counter()
    cpu = 0.0
    if candidates is None:
        log(f"keypoints: markerless, {F} frames x {C} views, {o.workers} worker(s)")
        candidates, cpu = detect_candidates(source, factory, frames, C, o, progress)
    t1 = time.process_time()
    groups = [associate(cams, candidates[f], o) for f in range(F)]
    centre = volume_centre(cams)
    sel = select_people(groups, centre, np.asarray(up, float), o)
    kp = np.zeros((C, F, 2, layout.N, 3), np.float32)
    boxes = np.full((C, F, 2, 4), np.nan, np.float32)
    hand_boxes = np.full((C, F, 2, 2, 4), np.nan, np.float32)
    found = np.zeros((F, 2), bool)
    for f in range(F):
        for p, g in enumerate(sel.slot[f]):
            if g is None:
                continue
            found[f, p] = True
            for c, n in groups[f][g].members.items():
                k = candidates[f][c][n]
                kp[c, f, p] = k
                boxes[c, f, p] = _box(k, o.min_conf)
    kp[..., 2] = np.where(kp[..., 2] >= o.min_conf, kp[..., 2], 0.0)
    assoc_cpu = time.process_time() - t1
    out = Keypoints2D(kp=kp, boxes=boxes, hand_boxes=hand_boxes, frames=frames,
                      wearer_retry=np.zeros((C, F), bool),
                      partner_mode=np.where(kp[:, :, 1, :N_BODY, 2].max(-1) > 0, 2, 0).astype(np.int8),
                      cross_view_outlier=np.zeros((C, F, 2, layout.N), bool),
                      conf_raw=kp[..., 2].copy(), cameras=np.array([c.name for c in cams], str))
    n_cands = np.array([[len(candidates[f][c]) for c in range(C)] for f in range(F)])
    people_root = np.full((F, 2, 3), np.nan)
    by_frame, by_root, by_views = [], [], []
    v_frame, v_cam, v_uv = [], [], []
    for f in range(F):
        taken = {c: [] for c in range(C)}
        for g, grp in enumerate(groups[f]):
            if g in sel.slot[f]:
                people_root[f, sel.slot[f].index(g)] = grp.root
                for c, n in grp.members.items():
                    taken[c].append(candidates[f][c][n])
            elif np.all(np.isfinite(grp.root)) and not sel.duplicate[f][g]:
                by_frame.append(int(frames[f]))
                by_root.append(grp.root)
                by_views.append(len(grp.members))
        for c in range(C):  # in 2D: every candidate that is none of the people fitted
            for k in candidates[f][c]:
                if not is_duplicate(k, taken[c], o.min_conf, iou=0.3):
                    hips = k[list(ROOT)]
                    uv = (hips[:, :2].mean(0) if np.all(hips[:, 2] >= o.min_conf)
                          else np.nanmean(_box(k, o.min_conf).reshape(2, 2), axis=0))
                    v_frame.append(int(frames[f]))
                    v_cam.append(c)
                    v_uv.append(uv)
    #: the people's and the bystanders' places in 3D (the bench counts frames where a fitted
    #: person is nearer a bystander than the person found)
    roots = {"people_root": people_root,
             "bystander_frame": np.array(by_frame, np.int64),
             "bystander_root": np.array(by_root, float).reshape(-1, 3),
             "bystander_views": np.array(by_views, np.int64),
             "others_2d_frame": np.array(v_frame, np.int64),
             "others_2d_camera": np.array(v_cam, np.int64),
             "others_2d_uv": np.array(v_uv, float).reshape(-1, 2)}
    wall = time.perf_counter() - w0
    total_cpu = cpu + (time.process_time() - t0)
    facts = {
        "markerless": True, "people": o.people, "workers": o.workers,
        "volume_centre_m": np.round(centre, 3).tolist(),
        "candidates_per_view": {"mean": float(n_cands.mean()) if n_cands.size else 0.0,
                                "max": int(n_cands.max()) if n_cands.size else 0},
        "people_found_frames": [int(found[:, p].sum()) for p in range(o.people)],
        "bystanders": {"frames_with": int((sel.bystanders > 0).sum()),
                       "groups": int(sel.bystanders.sum()),
                       "far_from_volume": int(sel.far.sum()),
                       "duplicates_of_people": int(sel.duplicates.sum()),
                       "candidates_not_people": int(len(v_frame)),
                       "per_frame": sel.bystanders.tolist()},
        "views_per_person": [float(np.mean([len(groups[f][sel.slot[f][p]].members)
                                            for f in range(F) if sel.slot[f][p] is not None]))
                             if found[:, p].any() else 0.0 for p in range(o.people)],
        "association_cpu_s": round(assoc_cpu, 3), "cpu_s": round(total_cpu, 3),
        "wall_s": round(wall, 3),
        "fps_per_core": round(F / max(total_cpu, 1e-9), 3),
        "partner_mode_counts": {"missing": int((out.partner_mode == 0).sum()), "tracked": 0,
                                "whole_image": int((out.partner_mode == 2).sum())},
        "roots": roots,
    }
    return out, facts
