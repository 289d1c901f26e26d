"""Identity and left/right consistency of each person's detection in each view, judged as a
whole skeleton against the other views and the neighbouring frames.

The per-view rules (:mod:`detect.people`) and the per-keypoint cross-view check
(:mod:`detect.multiview`) leave errors where the people overlap: a view's detection that is
the other person's, or a mix of both, or made up (the partner hidden behind the wearer in a
hug); a person detected with its left and right exchanged (back views fool the detector);
and per-keypoint checks are fooled by two wrong observations that happen to agree (the
error lies along the epipolar line). A whole skeleton agreeing by chance is far rarer, so
here each view's detection of a person is judged as a whole (medians over its confident body
keypoints, as labelled or mirrored):

1. **The partner's skeleton** (:func:`consensus`), per frame: every pair of views whose rays
   meet at a usable angle (``min_angle_deg``: opposite cameras see a point along nearly the
   same line, any depth fits) is triangulated on the keypoints both reproject within
   ``pair_px``; such a pair is a hypothesis, supported by the other views whose detection it
   reprojects within ``view_px`` and contradicted by those it fits neither as labelled nor
   mirrored. The best balance wins (ties: nearer the previous frame's skeleton, since two
   views mirrored alike make a consistent mirrored skeleton; then the smaller pair error),
   and each keypoint is triangulated again from the observations that agree with it. Frames
   without a consistent pair (a lone view, two views that disagree) get the skeleton of the
   neighbouring frames (within ``window`` video frames, interpolated), judged at
   ``time_px``; without either, nothing is judged. Single keypoints of an agreeing view
   that miss the skeleton are dropped.
2. **The wearer's reference**: its body triangulated from its other views (each passed the
   marker check; per keypoint from the pair the others agree with, :func:`leave_one_out`)
   where that agrees with its markers, else its projected markers moved by the detector's
   own median offset from them around that time (:func:`calibrated_anchors`: markers sit on
   the skin, a few centimetres off the joints).
3. **Verdicts** (:func:`identity_check`, :data:`VERDICTS`) per view and person, against both
   references (the partner's projected into every view, also where it was not detected):
   a *swap* when the detection is not clearly nearer its own reference than the other
   person's (``ambiguous_ratio``: where both overlap that much nothing tells whose
   keypoints these are); *inconsistent* when the partner's detection agrees with its
   skeleton neither way; *flipped* when the whole detection as detected (before the
   per-keypoint drops: a mirrored skeleton loses its keypoints one by one, and its few
   symmetric leftovers, the face, look fine) fits its reference mirrored under
   ``flip_ratio`` x as labelled and by ``flip_min_px``, and, for the partner, within the
   threshold.

The partner's flipped detections are relabelled (left and right exchanged, hand blocks
included: its hand crops followed the labelled wrists), keeping the mirrored keypoints that
agree with its skeleton; swapped, inconsistent and the wearer's flipped ones (its detection
passed the marker check, which rejects a mirrored wearer; what is left is not trusted) are
dropped, body and hands, except the wearer's hands: those come from crops around its hand
markers.

Measured (bench session, every 10th frame, 96 frames): identity swaps 4 -> 0 views, left/right
flips wearer 1 -> 0, partner 2 -> 0; on frames 0-95 of Grab, HoldingHands, Hug and Kick at
stride 1 (not used to choose the thresholds) swaps 17 -> 7 views and flips 8 -> 3 (what is
left: Hug, where the partner is seen by one or two views, often both wrong alike, and a
profile view of HoldingHands where the wearer's detection lies halfway to the partner).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from detect import constants as K
from detect import layout

#: Codes of :attr:`IdentityCheck.verdict`, in code order.
VERDICTS = ("ok", "swap", "inconsistent", "flip", "flip_dropped")

_FLIP_BODY = layout.FLIP[layout.BODY]


@dataclass(frozen=True)
class IdentityOptions:
    """Thresholds (pixels unless said; defaults in detect/constants.py).

    pair_px : a pair of views is consistent when its triangulated skeleton reprojects into
        both within this (the larger of the two errors) at ``min_kp`` keypoints and at least
        ``pair_frac`` of those both views observe; the skeleton is made of those.
    view_px : another view supports the pair's skeleton within this (median).
    time_px : a view agrees with the neighbouring frames' skeleton within this (median; the
        person moved in between). window : neighbouring frames searched (video frames,
        either side; 0: none).
    min_angle_deg : smallest angle between two rays to triangulate from them.
    min_kp : keypoints needed to judge a detection (or a pair).
    ambiguous_ratio : a detection is a swap unless its median distance to the other
        person's reference exceeds ``ambiguous_ratio`` x that to its own.
    flip_ratio / flip_min_px : a detection is mirrored when, mirrored, it lies nearer its
        reference by this factor and by this many pixels.
    min_conf : observations below are ignored.
    """

    pair_px: float = K.IDENTITY_PAIR_PX
    pair_frac: float = K.IDENTITY_PAIR_FRAC
    view_px: float = K.IDENTITY_VIEW_PX
    time_px: float = K.IDENTITY_TIME_PX
    window: int = K.IDENTITY_WINDOW_FRAMES
    min_angle_deg: float = K.IDENTITY_MIN_ANGLE_DEG
    min_kp: int = K.IDENTITY_MIN_KP
    ambiguous_ratio: float = K.IDENTITY_AMBIGUOUS_RATIO
    flip_ratio: float = K.IDENTITY_FLIP_RATIO
    flip_min_px: float = K.IDENTITY_FLIP_MIN_PX
    min_conf: float = K.MIN_CONF


@dataclass(frozen=True)
class Consensus:
    """One person's skeleton as the views agree (see the module doc, step 1).

    xyz : (F, 23, 3) world metres (NaN: no consensus for that keypoint and frame).
    source : (F,) int8: 0 none, 1 the views of the frame agree, 2 from the neighbouring
        frames (no consistent pair in the frame).
    agrees : (C, F) bool, the view's detection agrees as labelled.
    judged : (C, F) bool, the view had a detection and a skeleton to judge it by.
    err_px : (C, F) its median distance to the skeleton (the better reading: as labelled or
        mirrored; NaN: not judged).
    outlier : (C, F, 23) bool, single keypoints of an agreeing view that miss the skeleton by
        more than its threshold (``view_px``, or ``time_px`` against neighbouring frames).
    """

    xyz: np.ndarray
    source: np.ndarray
    agrees: np.ndarray
    judged: np.ndarray
    err_px: np.ndarray
    outlier: np.ndarray


@dataclass(frozen=True)
class IdentityCheck:
    """verdict : (C, F, 2) int8 codes of :data:`VERDICTS` per view, frame and person.
    flip : (C, F, 2) bool, detections to relabel left/right (``kp[c, f, p] =
    kp[c, f, p][layout.FLIP]``): the partner's only.
    outlier : (C, F, 2, 65) bool, the observations to drop (confidence 0), the earlier
    checks' included, indexed as relabelled (after ``flip``).
    off_px : (C, F, 2, 2) median distance of each detection to its own and to the other
    person's reference (the nearer reading; NaN: not judged).
    partner : the partner's :class:`Consensus`."""

    verdict: np.ndarray
    outlier: np.ndarray
    flip: np.ndarray
    off_px: np.ndarray
    partner: Consensus


# ------------------------------------------------------------------------------- ray geometry
def _rays(cams, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (C, 3) and unit world ray directions (C, ..., 3) of pixels uv
    (C, ..., 2) (NaN where not invertible)."""
    from calib.camera import rays_from_pixels

    centres = np.stack([np.asarray(c.T, float) for c in cams])
    dirs = np.stack([rays_from_pixels(c, uv[i]) @ np.asarray(c.R, float) for i, c in enumerate(cams)])
    return centres, dirs


def _closest_point(centres: np.ndarray, dirs: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(..., 3) least-squares point nearest the rays ``centres (C, 3) + s dirs (C, ..., 3)``
    with ``use (C, ...)``; NaN with fewer than two rays."""
    d = np.where(use[..., None], np.nan_to_num(dirs), 0.0)
    P = np.eye(3) - d[..., :, None] * d[..., None, :]  # (C, ..., 3, 3)
    P = np.where(use[..., None, None], P, 0.0)
    c = centres.reshape((len(centres),) + (1,) * (dirs.ndim - 2) + (3,))
    A = P.sum(axis=0)
    b = (P @ c[..., None]).sum(axis=0)[..., 0]
    ok = use.sum(axis=0) >= 2
    X = np.full(b.shape, np.nan)
    if ok.any():
        X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return X


def _angle_deg(da: np.ndarray, db: np.ndarray) -> np.ndarray:
    """Angle between two lines of directions da, db (..., 3), in [0, 90] degrees."""
    cos = np.abs(np.sum(da * db, axis=-1)).clip(0.0, 1.0)
    return np.degrees(np.arccos(cos))


def _project(cams, X: np.ndarray) -> np.ndarray:
    """(C, ..., 2) pixels of world points X (..., 3) in every camera (NaN: behind it or NaN)."""
    from calib import project, world_to_cam

    fin = np.all(np.isfinite(X), axis=-1)
    Xs = np.where(fin[..., None], X, 0.0)
    out = []
    for cam in cams:
        uv = project(cam, Xs)
        uv[~fin | (world_to_cam(cam, Xs)[..., 2] <= 0)] = np.nan
        out.append(uv)
    return np.stack(out)


def _median_dist(a: np.ndarray, b: np.ndarray, ok: np.ndarray, min_kp: int) -> np.ndarray:
    """(...,) median over the last keypoint axis of |a - b| (..., K, 2) where ``ok`` (..., K)
    and both finite; NaN with fewer than ``min_kp``."""
    d = np.linalg.norm(a - b, axis=-1)
    m = ok & np.isfinite(d)
    d = np.where(m, d, np.nan)
    out = np.full(d.shape[:-1], np.nan)
    enough = m.sum(axis=-1) >= min_kp
    if enough.any():
        out[enough] = np.nanmedian(d[enough], axis=-1)
    return out


def _readings(D: np.ndarray, R: np.ndarray, ok: np.ndarray, min_kp: int) -> tuple[np.ndarray, np.ndarray]:
    """(as labelled, mirrored) median distances (...,) between detections D (..., 23, 2)
    with ``ok`` (..., 23) and a reference R (..., 23, 2); the mirrored reading (D's left and
    right exchanged) only where the labelled one has ``min_kp`` pairs (else NaN: readings
    over different keypoints do not compare)."""
    d = _median_dist(D, R, ok, min_kp)
    dm = _median_dist(D[..., _FLIP_BODY, :], R, ok[..., _FLIP_BODY], min_kp)
    return d, np.where(np.isfinite(d), dm, np.nan)


# --------------------------------------------------------------------------------- consensus
def consensus(cams, body: np.ndarray, frames: np.ndarray,
              opts: IdentityOptions = IdentityOptions()) -> Consensus:
    """One person's skeleton as the views agree, and how each view's detection relates to it
    (see the module doc, step 1).

    cams : C calib.Camera. body : (C, F, 23, 3) the person's body keypoints (x, y pixels,
    confidence; 0 = not observed). frames : (F,) increasing video frame indices."""
    body = np.asarray(body, dtype=np.float64)
    C, F, nk = body.shape[:3]
    frames = np.asarray(frames, dtype=np.int64)
    obs = (body[..., 2] >= opts.min_conf) & np.all(np.isfinite(body[..., :2]), axis=-1)
    uv = np.where(obs[..., None], body[..., :2], 0.0)
    centres, dirs = _rays(cams, uv)
    obs &= np.all(np.isfinite(dirs), axis=-1)
    has = obs.sum(axis=-1) >= opts.min_kp  # (C, F) a detection to judge
    xyz = np.full((F, nk, 3), np.nan)
    source = np.zeros(F, np.int8)
    views = np.zeros((C, F), bool)
    last = None  # the latest frame with a consensus
    for f in range(F):
        best = None
        prev = xyz[last] if last is not None and frames[f] - frames[last] <= opts.window else None
        for a, b in combinations(np.flatnonzero(has[:, f]), 2):
            use = np.zeros((C, nk), bool)
            use[[a, b]] = obs[[a, b], f]
            use[:, _angle_deg(dirs[a, f], dirs[b, f]) < opts.min_angle_deg] = False
            if use[a].sum() < opts.min_kp:
                continue
            X = _closest_point(centres, dirs[:, f], use)
            P = _project([cams[a], cams[b]], X)
            e = np.fmax(np.linalg.norm(P[0] - body[a, f, :, :2], axis=-1),
                        np.linalg.norm(P[1] - body[b, f, :, :2], axis=-1))
            # the keypoints both views agree on (a detection may be half wrong: the legs of
            # a partner hidden behind the wearer), at least half of those they share
            inl = use[a] & (e <= opts.pair_px)
            if inl.sum() < opts.min_kp or inl.sum() < opts.pair_frac * use[a].sum():
                continue
            use &= inl[None]
            X = _closest_point(centres, dirs[:, f], use)
            P = _project([cams[a], cams[b]], X)
            e = np.fmax(np.linalg.norm(P[0] - body[a, f, :, :2], axis=-1),
                        np.linalg.norm(P[1] - body[b, f, :, :2], axis=-1))
            pair_err = float(np.nanmedian(np.where(use[a], e, np.nan)))
            if not pair_err <= opts.pair_px:
                continue
            d, dm = _readings(body[:, f, :, :2], _project(cams, X), obs[:, f], opts.min_kp)
            sup = has[:, f] & (d <= opts.view_px)
            sup[[a, b]] = True
            against = has[:, f] & np.isfinite(d) & ~sup & ~(dm <= opts.view_px)
            # views that agree, less those that agree neither way (a mirrored one is neutral:
            # two views agreeing by chance are contradicted by a third that sees otherwise);
            # then the nearer to the previous frame's skeleton (two views mirrored alike
            # make a consistent mirrored skeleton, as good as the right one in this frame)
            moved = np.nan
            if prev is not None:
                dist = np.linalg.norm(X - prev, axis=-1)
                if np.isfinite(dist).sum() >= opts.min_kp:
                    moved = float(np.nanmedian(dist))
            score = (int(sup.sum() - against.sum()), int(sup.sum()),
                     -moved if np.isfinite(moved) else 0.0, -pair_err)
            if best is None or score > best[0]:
                best = (score, sup, X)
        if best is not None:
            _, sup, X = best
            xyz[f] = _skeleton(cams, centres, dirs[:, f], body[:, f, :, :2],
                               obs[:, f] & sup[:, None], X, opts)
            source[f], views[:, f] = 1, sup
            last = f
    same = source == 1
    X_time = _from_other_frames(np.where(same[:, None, None], xyz, np.nan), frames, opts.window)
    lone = ~same & np.all(np.isfinite(X_time), axis=-1).any(axis=-1)
    xyz[lone] = X_time[lone]
    source[lone] = 2
    R = _project(cams, xyz)  # (C, F, 23, 2)
    d, dm = _readings(body[..., :2], R, obs, opts.min_kp)
    limit = np.where(source == 2, opts.time_px, opts.view_px)[None]
    judged = has & np.isfinite(d) & (source > 0)[None]
    agrees = judged & ((d <= limit) | views)
    err = np.where(judged, np.fmin(d, dm), np.nan)
    # single keypoints of an agreeing view that miss the skeleton
    e = np.linalg.norm(body[..., :2] - R, axis=-1)
    outlier = agrees[..., None] & obs & (e > limit[..., None])
    return Consensus(xyz, source, agrees, judged, err, outlier)


def calibrated_anchors(anchors: np.ndarray, body: np.ndarray, frames: np.ndarray,
                       opts: IdentityOptions = IdentityOptions()) -> np.ndarray:
    """(C, F, 23, 2) the wearer's marker anchors ``anchors`` (C, F, 23, 2) moved by the
    median offset, in the same view, of its detected keypoints ``body`` (C, F, 23, 3) from
    them over the *other* frames within ``window`` video frames (at least ``min_kp``
    samples; else the anchors as they are). Markers sit on the skin, a few centimetres off
    the joints, and in a profile view those offsets reach ~25 px, as much as a detection
    that strays halfway to the other person: the detector's own offsets from the markers,
    in that view and around that time, put the anchors where its joints are."""
    anchors = np.asarray(anchors, dtype=np.float64)
    body = np.asarray(body, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.int64)
    ok = (body[..., 2] >= opts.min_conf) & np.all(np.isfinite(anchors), axis=-1)
    r = np.where(ok[..., None], body[..., :2] - anchors, np.nan)  # (C, F, 23, 2)
    out = anchors.copy()
    if opts.window <= 0:
        return out
    for f in range(len(frames)):
        lo = np.searchsorted(frames, frames[f] - opts.window, side="left")
        hi = np.searchsorted(frames, frames[f] + opts.window, side="right")
        idx = [g for g in range(lo, hi) if g != f]
        if len(idx) < opts.min_kp:
            continue
        w = r[:, idx]  # (C, G, 23, 2)
        enough = np.isfinite(w[..., 0]).sum(axis=1) >= opts.min_kp  # (C, 23)
        if not enough.any():
            continue
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(w, axis=1)  # (C, 23, 2)
        out[:, f] = np.where(enough[..., None], anchors[:, f] + med, anchors[:, f])
    return out


def leave_one_out(cams, body: np.ndarray, opts: IdentityOptions = IdentityOptions()) -> np.ndarray:
    """(C, F, 23, 2) each keypoint of ``body`` (C, F, 23, 3) triangulated from the views
    other than each one and projected into it (pixels; NaN: not triangulated). Robust to one
    wrong view among the others: per keypoint from the pair of views (rays spread over
    ``min_angle_deg``) the most other observations agree with (:func:`_skeleton`)."""
    body = np.asarray(body, dtype=np.float64)
    C, F, nk = body.shape[:3]
    obs = (body[..., 2] >= opts.min_conf) & np.all(np.isfinite(body[..., :2]), axis=-1)
    centres, dirs = _rays(cams, np.where(obs[..., None], body[..., :2], 0.0))
    obs &= np.all(np.isfinite(dirs), axis=-1)
    out = np.full((C, F, nk, 2), np.nan)
    # all frames at once: _skeleton works keypoint by keypoint
    dirs, uv, obs = dirs.reshape(C, F * nk, 3), body[..., :2].reshape(C, F * nk, 2), obs.reshape(C, F * nk)
    for c, cam in enumerate(cams):
        use = obs.copy()
        use[c] = False
        if (use.sum(axis=0) >= 2).any():
            X = _skeleton(cams, centres, dirs, uv, use, np.full((F * nk, 3), np.nan), opts)
            out[c] = _project([cam], X)[0].reshape(F, nk, 2)
    return out


def _skeleton(cams, centres: np.ndarray, dirs: np.ndarray, uv: np.ndarray, obs: np.ndarray,
              X: np.ndarray, opts: IdentityOptions) -> np.ndarray:
    """(K, 3) the keypoints triangulated from the observations ``obs`` (C, K) (rays ``dirs``
    (C, K, 3) through pixels ``uv`` (C, K, 2)) within ``view_px`` of the starting skeleton
    ``X`` (K, 3); where X is NaN, it starts from the pair of views (rays spread over
    ``min_angle_deg``, reprojecting within ``pair_px``) that most other observations agree
    with (a view may see that keypoint mirrored: averaging all of them would not do). Twice;
    NaN where the rays left do not spread over ``min_angle_deg``."""
    C = len(cams)
    X = np.array(X, dtype=np.float64)
    todo = ~np.all(np.isfinite(X), axis=-1)
    if todo.any():
        best = np.full(X.shape[0], -1.0)
        for a, b in combinations(range(C), 2):
            use = np.zeros_like(obs)
            use[[a, b]] = obs[[a, b]] & todo[None]
            use[:, _angle_deg(dirs[a], dirs[b]) < opts.min_angle_deg] = False
            if not use[a].any():
                continue
            Xab = _closest_point(centres, dirs, use)
            e = np.linalg.norm(_project(cams, Xab) - uv, axis=-1)  # (C, K)
            good = use[a] & (np.fmax(e[a], e[b]) <= opts.pair_px)
            score = np.where(good, (obs & (e <= opts.view_px)).sum(axis=0)
                             - np.fmax(e[a], e[b]) / (2 * opts.pair_px), -1.0)
            better = score > best
            X[better] = Xab[better]
            best[better] = score[better]
    for _ in range(2):
        e = np.linalg.norm(_project(cams, X) - uv, axis=-1)
        use = obs & (e <= opts.view_px)
        spread = np.zeros(use.shape[1], bool)
        for a, b in combinations(range(C), 2):
            spread |= use[a] & use[b] & (_angle_deg(dirs[a], dirs[b]) >= opts.min_angle_deg)
        X = _closest_point(centres, dirs, use & spread[None])
    return X


def _from_other_frames(X: np.ndarray, frames: np.ndarray, window: int) -> np.ndarray:
    """(F, K, 3): for each frame, ``X (F, K, 3)`` of the *other* frames within ``window``
    video frames: linear between the nearest solved frame before and after, or the nearest
    one (NaN: none). ``frames`` (F,) increasing video frame indices."""
    out = np.full_like(X, np.nan)
    if window <= 0:
        return out
    ok = np.all(np.isfinite(X), axis=-1)  # (F, K)
    for f in range(len(frames)):
        lo = np.searchsorted(frames, frames[f] - window, side="left")
        hi = np.searchsorted(frames, frames[f] + window, side="right")
        for k in range(X.shape[1]):
            before = next((g for g in range(f - 1, lo - 1, -1) if ok[g, k]), None)
            after = next((g for g in range(f + 1, hi) if ok[g, k]), None)
            if before is not None and after is not None:
                w = (frames[f] - frames[before]) / (frames[after] - frames[before])
                out[f, k] = (1 - w) * X[before, k] + w * X[after, k]
            elif before is not None or after is not None:
                out[f, k] = X[before if before is not None else after, k]
    return out


# ---------------------------------------------------------------------------------- identity
def identity_check(cams, kp: np.ndarray, outlier: np.ndarray, anchors: np.ndarray,
                   frames: np.ndarray, opts: IdentityOptions = IdentityOptions()) -> IdentityCheck:
    """Judge every view's detection of both people (see the module doc).

    cams : C calib.Camera. kp : (C, F, 2, 65, 3) keypoints as detected (person 0 = the
    wearer). outlier : (C, F, 2, 65) bool, observations the earlier checks dropped
    (:func:`detect.sequence.cross_view_guard`): the references and swaps are judged on what
    they kept, flips on the whole detection (a mirrored skeleton's keypoints are mostly
    dropped one by one, and its few symmetric leftovers, the face, look fine). anchors :
    (C, F, 65, 2) where the wearer's markers put its keypoints in each view (pixels, NaN:
    none; :attr:`WearerHints.anchors`). frames : (F,) video frame indices (increasing)."""
    kp = np.asarray(kp, dtype=np.float64)
    outlier = np.asarray(outlier, bool)
    C, F = kp.shape[:2]
    raw = kp[:, :, :, layout.BODY]
    raw_ok = raw[..., 2] >= opts.min_conf  # (C, F, 2, 23)
    ok = raw_ok & ~outlier[..., layout.BODY]
    kept = np.where(ok[..., None], raw, 0.0)
    cp = consensus(cams, kept[:, :, 1], frames, opts)
    ok[:, :, 1] &= ~cp.outlier  # the partner is judged on what is left of it
    # references in every view: the wearer's body triangulated from its other views (each
    # passed the marker check), else its markers; the partner's skeleton (consensus or
    # neighbouring frames)
    Rw = leave_one_out(cams, kept[:, :, 0], opts)
    A = calibrated_anchors(np.asarray(anchors, dtype=np.float64)[:, :, layout.BODY],
                           kept[:, :, 0], frames, opts)
    # (the other views' point only where it agrees with the markers: with one of those views
    # wrong, and the others opposite each other, it can be the other person's)
    near = np.linalg.norm(Rw - A, axis=-1) <= 2 * opts.view_px
    Rw = np.where((near | ~np.all(np.isfinite(A), axis=-1))[..., None] & np.isfinite(Rw), Rw, A)
    Rp = _project(cams, cp.xyz)
    refs = (Rw, Rp)
    limit = np.where(cp.source == 2, opts.time_px, opts.view_px)[None]  # (1, F)
    off = np.full((C, F, 2, 2), np.nan)
    verdict = np.zeros((C, F, 2), np.int8)
    for p in (0, 1):
        D = raw[:, :, p, :, :2]
        own, other = refs[p], refs[1 - p]
        d, dm = _readings(D, own, ok[:, :, p], opts.min_kp)
        mine = np.fmin(d, dm)
        do = np.fmin(*_readings(D, other, ok[:, :, p], opts.min_kp))
        off[:, :, p] = np.stack([mine, do], axis=-1)
        swap = np.isfinite(mine) & (do <= opts.ambiguous_ratio * mine)
        dr, dmr = _readings(D, own, raw_ok[:, :, p], opts.min_kp)
        flip = np.isfinite(dmr) & (dmr < opts.flip_ratio * dr) & (dr - dmr >= opts.flip_min_px)
        v = verdict[:, :, p]
        if p == 1:
            flip &= dmr <= limit  # mirrored, it agrees with the partner's skeleton
            v[cp.judged & ~cp.agrees & ~flip] = VERDICTS.index("inconsistent")

        v[flip] = VERDICTS.index("flip" if p == 1 else "flip_dropped")
        v[swap] = VERDICTS.index("swap")
        v[raw_ok[:, :, p].sum(axis=-1) < opts.min_kp] = 0
    flip = verdict == VERDICTS.index("flip")
    out = outlier.copy()
    out[:, :, 1, layout.BODY] |= cp.outlier
    # a relabelled partner keeps the (mirrored) keypoints that agree with its skeleton
    mirrored = raw[:, :, 1][:, :, _FLIP_BODY]
    e = np.linalg.norm(mirrored[..., :2] - Rp, axis=-1)
    flipped_out = np.where(np.isfinite(e), e > limit[..., None],
                           outlier[:, :, 1][:, :, layout.FLIP][..., layout.BODY])
    flipped_out &= mirrored[..., 2] > 0
    fo = out[:, :, 1][:, :, layout.FLIP]  # relabelled: hands keep what the checks said
    fo[..., layout.BODY] = flipped_out
    out[:, :, 1] = np.where(flip[:, :, 1][..., None], fo, out[:, :, 1])
    gone = np.isin(verdict, [VERDICTS.index(v) for v in ("swap", "inconsistent", "flip_dropped")])
    gone_kp = np.repeat(gone[..., None], layout.N, axis=-1)
    gone_kp[:, :, 0, layout.BODY.stop:] = False  # the wearer's hands come from its marker crops
    out |= gone_kp
    conf = np.where(flip[..., None], kp[..., 2][..., layout.FLIP], kp[..., 2])
    return IdentityCheck(verdict, out & (conf > 0), flip, off, cp)
