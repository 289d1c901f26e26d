"""What the page proposes before the annotator clicks anything.

With both fits (:func:`from_fits`): per frame, the signed distance of person 0's surface to
person 1's (``geometry.nearest_surface``; negative inside, ``geometry.is_inside``); the frames
where it is below ``near_m`` (a few mm: the surfaces touch or go through each other) are in
contact; the proposed interval is the run of such frames (gaps of up to ``GAP`` frames closed)
with the most touching vertices, its contact frame the frame of that run where the most
vertices touch; the candidate facet pairs are person 0's facets at that frame whose centroid
is within ``near_m`` of person 1's surface, each with the nearest facet of person 1, a few per
region pair (the closest first, then spread at least ``SPREAD_M`` apart).

With keypoints only (:func:`from_keypoints`): the two people's keypoints triangulated per frame
(``calib.geometry.triangulate``); the frame where the closest pair of keypoints of the two
people is nearest is the proposed contact frame, the interval the frames around it within
``KP_MARGIN_M`` of that closest distance. No facet pairs (no surfaces).
"""
from __future__ import annotations

import numpy as np

NEAR_M = 0.005       # surfaces within this distance touch (a few mm)
GAP = 2              # frames: holes in a contact run this short are closed
PER_REGION_PAIR = 3  # candidate facet pairs kept per region pair
MAX_PAIRS = 24       # candidate facet pairs in all
SPREAD_M = 0.02      # candidates of one region pair at least this far apart
VERTEX_STRIDE = 2    # person 0's vertices sampled for the per-frame scan
MAX_SCAN_FRAMES = 600  # longer sequences: every k-th frame is scanned
SCAN_MARGIN_M = 0.05  # only person 0's vertices within person 1's box + this are scanned
KP_MARGIN_M = 0.05   # keypoints-only interval: within this of the closest approach


def signed_distance(points: np.ndarray, V: np.ndarray, F: np.ndarray):
    """(distance (N,) metres, negative inside the mesh; nearest face (N,)) of ``points``.
    Only points inside the mesh's bounding box are tested for being inside."""
    from geometry import is_inside, nearest_surface

    points = np.asarray(points, float)
    near = nearest_surface(points, V, F)
    d = near.distance.copy()
    box = np.all((points >= V.min(0)) & (points <= V.max(0)), axis=1)
    if box.any():
        d[box] = np.where(is_inside(points[box], V, F), -d[box], d[box])
    return d, near.face


def _runs(mask: np.ndarray, gap: int) -> list[tuple[int, int]]:
    """(start, end) row ranges (inclusive) of True in ``mask`` with holes <= gap closed."""
    idx = np.flatnonzero(mask)
    if not len(idx):
        return []
    out, s, e = [], idx[0], idx[0]
    for i in idx[1:]:
        if i - e <= gap + 1:
            e = i
        else:
            out.append((int(s), int(e)))
            s = e = i
    out.append((int(s), int(e)))
    return out


def from_fits(frames: np.ndarray, V, faces: np.ndarray, rmap, near_m: float = NEAR_M,
              progress=None, max_frames: int = MAX_SCAN_FRAMES) -> dict:
    """Proposal from both fitted meshes. frames (F,) video frames; V: (2, F, V, 3) metres, or a
    function of the row giving (2, V, 3). Over ``max_frames`` frames, every k-th frame is
    scanned (``"stride"``: k; the interval's ends are then that coarse).

    Returns {"source": "fits", "near_mm", "distance_mm" (F,) the closest approach per frame
    (negative: through the other body), "touching" (F,) vertices within ``near_m``,
    "frames" (F,), "interval" [start, end] | None, "fr_id" | None, "pairs" [[f0, f1], ...],
    "pair_distance_mm" [...]}."""
    F = np.asarray(faces)
    if callable(V):
        get = V
    else:
        Varr = np.asarray(V)

        def get(i):
            return Varr[:, i]
    stride = max(1, -(-len(frames) // max_frames))
    rows = np.arange(0, len(frames), stride)
    frames = np.asarray(frames)[rows]
    n = len(rows)
    dmin = np.full(n, np.inf)
    touching = np.zeros(n, np.int64)
    for i, row in enumerate(rows):
        Vi = np.asarray(get(int(row)), float)
        P0, V1 = Vi[0, ::VERTEX_STRIDE], Vi[1]
        lo, hi = V1.min(0) - SCAN_MARGIN_M, V1.max(0) + SCAN_MARGIN_M
        inbox = np.all((P0 >= lo) & (P0 <= hi), axis=1)
        if not inbox.any():  # far apart: the closest approach from a coarse sample
            P0 = P0[::8]
        else:
            P0 = P0[inbox]
        d, _ = signed_distance(P0, V1, F)
        dmin[i] = d.min()
        touching[i] = int((d < near_m).sum())
        if progress is not None:
            progress(i + 1, n)
    out = {"source": "fits", "near_mm": near_m * 1000, "stride": stride, "frames": frames.tolist(),
           "distance_mm": np.round(dmin * 1000, 2).tolist(), "touching": touching.tolist(),
           "interval": None, "fr_id": None, "pairs": [], "pair_distance_mm": []}
    runs = _runs(dmin < near_m, GAP)
    if not runs:
        return out
    s, e = max(runs, key=lambda r: touching[r[0]:r[1] + 1].sum())
    peak = s + int(np.argmax(touching[s:e + 1]))
    out["interval"] = [int(frames[s]), int(frames[e])]
    out["fr_id"] = int(frames[peak])
    Vp = np.asarray(get(int(rows[peak])), float)
    pairs, dist = contact_pairs(Vp[0], Vp[1], F, rmap, near_m)
    out["pairs"], out["pair_distance_mm"] = pairs.tolist(), np.round(dist * 1000, 2).tolist()
    return out


def contact_pairs(V0: np.ndarray, V1: np.ndarray, faces: np.ndarray, rmap, near_m: float = NEAR_M):
    """Candidate facet pairs (K, 2) and their distances (K,) metres at one frame (module doc)."""
    from geometry import face_centroids

    F = np.asarray(faces)
    c0 = face_centroids(V0, F)
    d, f1 = signed_distance(c0, V1, F)
    close = np.flatnonzero(d < near_m)
    if not len(close):
        return np.zeros((0, 2), np.int64), np.zeros(0)
    r0, r1 = rmap.region_of(close), rmap.region_of(f1[close])
    keep = []
    for key in sorted(set(zip(r0.tolist(), r1.tolist(), strict=True))):
        if min(key) < 0:
            continue
        cand = close[(r0 == key[0]) & (r1 == key[1])]
        cand = cand[np.argsort(np.abs(d[cand]))]
        chosen = [cand[0]]
        for f in cand[1:]:
            if len(chosen) >= PER_REGION_PAIR:
                break
            if np.min(np.linalg.norm(c0[chosen] - c0[f], axis=1)) >= SPREAD_M:
                chosen.append(f)
        keep += chosen
    keep = np.array(keep, np.int64)
    keep = keep[np.argsort(np.abs(d[keep]), kind="stable")][:MAX_PAIRS]
    return np.stack([keep, f1[keep]], 1).astype(np.int64), d[keep]


def from_keypoints(cams, kp: np.ndarray, frames: np.ndarray, progress=None) -> dict:
    """Proposal from 2D keypoints only. kp (C, F, 2, K, 3) pixels + confidence (the page's
    camera order), frames (F,) video frames. Returns {"source": "keypoints", "frames",
    "distance_mm" (F,) closest keypoint pair of the two people (null: not triangulated),
    "interval", "fr_id", "pairs": []}."""
    from calib.geometry import triangulate

    kp = np.asarray(kp, float)
    n = kp.shape[1]
    dmin = np.full(n, np.nan)
    for i in range(n):
        X = [triangulate(cams, kp[:, i, p]).xyz for p in range(2)]
        X = [x[np.all(np.isfinite(x), axis=1)] for x in X]
        if len(X[0]) and len(X[1]):
            dmin[i] = np.linalg.norm(X[0][:, None] - X[1][None], axis=-1).min()
        if progress is not None:
            progress(i + 1, n)
    out = {"source": "keypoints", "frames": np.asarray(frames).tolist(),
           "distance_mm": [None if not np.isfinite(v) else round(float(v) * 1000, 1) for v in dmin],
           "interval": None, "fr_id": None, "pairs": [], "pair_distance_mm": []}
    if not np.isfinite(dmin).any():
        return out
    best = int(np.nanargmin(dmin))
    near = np.nan_to_num(dmin, nan=np.inf) <= dmin[best] + KP_MARGIN_M
    s = e = best
    while s > 0 and near[s - 1]:
        s -= 1
    while e < n - 1 and near[e + 1]:
        e += 1
    out["interval"] = [int(frames[s]), int(frames[e])]
    out["fr_id"] = int(frames[best])
    return out
