"""Marker placement and shape from markers (MoSh / MoSh++ stage I), robust to real captures.

What :func:`refine_placement` does on a subject's captures (template placement, no scan
shape or a scan shape):

1. ``track``: every ``step``-th frame of each capture fitted in order with the current shape
   and the template placement, warm-started from the previous frame
   (``fitting.marker_fit.fit_sequence``); ``outlier_mask`` flags marker-frames far from the
   tracked prediction (ghosts, glitches, swapped labels: residual above the marker's robust
   median plus ``OUTLIER_MIN_MM`` / ``OUTLIER_MADS`` spreads) and markers > ``FAR_M`` from the
   frame's median marker (a 5 m ghost never reaches the solver).
2. ``select_frames``: well-spread frames among well-tracked ones (no flagged marker, mostly
   visible), farthest-point sampling on the tracked *pose* (joint rotation vectors), never on
   raw marker positions (a glitch is the most distant configuration of all).
3. with ``fit_betas``, ``size_start``: a grid over the first betas, each scored after one
   placement update.
4. alternation (MoSh stage I) from the tracked poses of those frames: poses (the compiled
   marker graph, warm-started), the placement (:func:`update_placement`: Geman-McClure IRLS
   over frames per marker, tangential slide capped at ``max_slide_m`` from the template, the
   skin offset pulled to the nominal ``body.markers.DEFAULT_OFFSET_M`` and bounded in
   ``[min_offset_m, max_offset_m]``), betas with the poses (:func:`fit_shape_and_poses`: robust
   Levenberg-Marquardt, weak prior, rest posture kept at the mean's; ``fit_betas`` only).
5. segments (``segment_groups``: trunk = pelvis + spine, head = neck + head): a slide is
   held on its template's body segment or an adjacent one; a marker whose solution lay
   elsewhere in the last round is reported and refitted from the template with the tight
   cap ``tight_slide_m``.

Placement: ``face (M,)``, ``bary (M, 3)``, ``offset (M,)`` metres along the rest face normal
(``fitting.marker_graph.Placement``). Poses: ``x`` of ``fitting.skinned`` (body joints).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from body.lbs import rest_state
from body.markers import DEFAULT_OFFSET_M
from body.model import BodyModel
from body.rotations import skew
from fitting import marker_fit, robust, skinned
from fitting.marker_graph import (
    Placement,
    body_joints,
    marker_coeffs,
    marker_weights,
)
from geometry import face_normals

# constants
FAR_M = 1.5  # a marker this far from its frame's median marker is a ghost (a body is < 2.5 m)
OUTLIER_MIN_MM = 30.0  # marker-frame outlier: tracked residual > marker median + this ...
OUTLIER_MADS = 6.0  # ... and > median + this many robust spreads (1.4826 MAD)
SIZE_TRIM = 0.9  # size start score: mean of the markers' median residuals, best 90 % of them
# size start: values tried for beta 0 (and 1, every other), then halving steps around the best
# down to SIZE_STEP_MIN (the studio draws people of 1.4-2.0 m: beta 0 of -1 to +1 and beyond;
# a grid of +-0.8 left a 1.46 m subject 15 cm too tall, v2v 40 mm)
SIZE_GRID = np.linspace(-3.0, 3.0, 13)
SIZE_STEP_MIN = 0.1
WAND_MIN_MM = 10.0  # a marker at the offset bound with a median residual in this range ...
WAND_MAX_MM = 60.0  # ... is on a wand (larger: misplaced, not on a wand)
BEYOND_CAP_M = 0.05  # a marker held at its slide cap with a larger median error is out of reach
MIN_VISIBLE = 0.9  # a placement frame sees at least this share of the markers (or the max)


# ---------------------------------------------------------------------------- surface


def surface_tree(rest_vertices: np.ndarray, faces: np.ndarray):
    """libigl's AABB tree of a mesh, for :func:`project_to_surface` calls on the same mesh
    (building it is what a call of a few points costs: ~30 ms on Anny's mesh)."""
    import igl

    tree = igl.AABB()
    tree.init(np.ascontiguousarray(rest_vertices, float), np.ascontiguousarray(faces, np.int64))
    return tree


def project_to_surface(rest_vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                       tree=None):
    """Closest surface points of ``points (M, 3)``: (face (M,), bary (M, 3), signed offset (M,)
    along the face normal). tree : :func:`surface_tree` of this mesh (None: built here)."""
    import igl

    if tree is None:
        tree = surface_tree(rest_vertices, faces)
    _, fidx, closest = tree.squared_distance(
        np.ascontiguousarray(rest_vertices, float), np.ascontiguousarray(faces, np.int64),
        np.ascontiguousarray(points, float).reshape(-1, 3))
    fidx = np.asarray(fidx, dtype=np.int64)
    tri = rest_vertices[faces[fidx]]
    bary = igl.barycentric_coordinates(closest, tri[:, 0].copy(), tri[:, 1].copy(), tri[:, 2].copy())
    bary = np.clip(np.asarray(bary), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    n = face_normals(rest_vertices, faces[fidx])
    surf = np.einsum("mk,mkd->md", bary, tri)
    off = np.einsum("md,md->m", points - surf, n)
    return fidx, bary, off


def surface_points(rest_vertices: np.ndarray, faces: np.ndarray, pl: Placement) -> np.ndarray:
    """(M, 3) the markers' skin points (offset 0) on a rest mesh."""
    return np.einsum("mk,mkd->md", pl.bary, rest_vertices[faces[pl.face]])


def segment_weights(model: BodyModel, skel: skinned.FitSkeleton, pl: Placement) -> np.ndarray:
    """(M, Q) skinning weight of each marker's skin point per fitted joint (owner-summed)."""
    W = marker_weights(model, pl).toarray()  # (M, J)
    out = np.zeros((len(W), len(skel.joints)))
    np.add.at(out.T, skel.owner, W.T)
    return out


def segment_groups(skel: skinned.FitSkeleton) -> tuple[np.ndarray, np.ndarray]:
    """Body segments of the fitted joints: (group (Q,) id per fitted joint, parent (G,) group
    of each group, -1 at the root). The root (pelvis) and the spine joints are one segment
    (the trunk: a pelvis marker skins to both), neck and head one, and a joint whose name differs from its parent's only by digits (anny's
    ``lowerarm01`` / ``lowerarm02``) joins its parent's segment."""
    import re

    names = [str(n).lower() for n in skel.names]
    par = np.asarray(skel.parents)

    def stem(q):
        n = names[q]
        if "spine" in n or "chest" in n or par[q] < 0:
            return "spine"
        if "neck" in n or "head" in n:
            return "head"
        return re.sub(r"\d+", "", n)

    group = np.full(len(names), -1)
    gpar: list[int] = []
    for q in range(len(names)):  # parents come first
        p_ = int(par[q])
        if p_ >= 0 and stem(p_) == stem(q):
            group[q] = group[p_]
        else:
            group[q] = len(gpar)
            gpar.append(int(group[p_]) if p_ >= 0 else -1)
    return group, np.array(gpar)


def marker_segments(model: BodyModel, skel: skinned.FitSkeleton, pl: Placement,
                    groups=None) -> np.ndarray:
    """(M,) the body segment (:func:`segment_groups`) skinning most of each marker's skin
    point."""
    group, gpar = groups if groups is not None else segment_groups(skel)
    W = segment_weights(model, skel, pl)
    G = np.zeros((len(W), len(gpar)))
    np.add.at(G.T, group, W.T)
    return np.argmax(G, axis=1)


def same_or_adjacent(gpar: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M,) bool: segments ``a`` and ``b`` are one segment or parent and child."""
    a, b = np.asarray(a), np.asarray(b)
    return (a == b) | (gpar[a] == b) | (gpar[b] == a)


# ---------------------------------------------------------------------------- options


@dataclass(frozen=True)
class PlacementOptions:
    """rounds: alternations (poses, placement, betas); slide_sd_m: prior spread of the
    tangential slide from the template; max_slide_m: hard cap on it; offset_sd_m: prior spread
    of the skin offset around ``nominal_offset_m``; min_offset_m / max_offset_m: its bounds;
    data_sd_m: expected marker error weighing the data against the priors; robust_sigma_m:
    Geman-McClure scale of the placement and betas IRLS; irls_iters: reweightings per
    placement update; num_betas, beta_sd, posture_sd_rad, beta_steps: the marker-based shape
    (coefficients, prior spread of the whitened betas, of the rest posture's bind rotations,
    Levenberg-Marquardt steps per round); wand_offset_m: the offset bound of a marker left at
    ``max_offset_m`` with a median residual above ``WAND_MIN_MM`` (a marker on a wand, e.g.
    Plug-in Gait's thigh and tibia wands: refitted with this bound); track_step: every
    k-th frame of a capture is tracked; frames: placement frames; placement_from: with static
    trials, where the placement and the shape come from: ``"all"`` (the static trials first,
    alone, then refined on ``frames`` movement frames plus ``static_frames`` static ones),
    ``"static"`` (the static trials alone), ``"movement"`` (the movement captures alone, the
    static trials unused); static_frames: static frames kept in the movement refinement."""

    rounds: int = 6
    slide_sd_m: float = 0.02
    max_slide_m: float = 0.20
    tight_slide_m: float = 0.05
    offset_sd_m: float = 0.005
    nominal_offset_m: float = DEFAULT_OFFSET_M
    min_offset_m: float = 0.0
    max_offset_m: float = 0.035
    wand_offset_m: float = 0.08
    data_sd_m: float = 0.005
    robust_sigma_m: float = 0.015
    irls_iters: int = 4
    pose_iters: int = 30
    num_betas: int = 30
    beta_sd: float = 3.0
    posture_sd_rad: float = 0.01
    beta_steps: int = 3
    track_step: int = 2
    frames: int = 12
    placement_from: str = "all"
    static_frames: int = 4


PLACEMENT_FROM = ("all", "static", "movement")


# ---------------------------------------------------------------------------- tracking


def ghost_mask(obs: np.ndarray) -> np.ndarray:
    """(F, M) bool: samples farther than ``FAR_M`` from their frame's median marker."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        c = np.nanmedian(obs, axis=1, keepdims=True)
    d = np.linalg.norm(obs - c, axis=2)
    return np.isfinite(d) & (d > FAR_M)


@dataclass
class Track:
    """One capture tracked: frames (T,) indices into the capture, X (T, n), residual_m (T, M)
    NaN where not visible, visible (T, M) after the ghost mask, ghost (T, M) the masked
    ghost samples."""

    frames: np.ndarray
    X: np.ndarray
    residual_m: np.ndarray
    visible: np.ndarray
    ghost: np.ndarray


def track(solver: marker_fit.FrameSolver, obs: np.ndarray, step: int) -> Track:
    """Every ``step``-th frame of ``obs (F, M, 3)`` (NaN gaps) fitted in order, warm-started
    (:func:`fitting.marker_fit.fit_sequence`), from the first frame seeing half the markers."""
    ghost = ghost_mask(obs)
    vis = np.all(np.isfinite(obs), axis=2) & ~ghost
    M = obs.shape[1]
    start = np.flatnonzero(vis.sum(1) >= max(3, M // 2))
    if not len(start):
        start = np.flatnonzero(vis.sum(1) >= 3)
    if not len(start):
        return Track(np.zeros(0, int), np.zeros((0, solver.skel.n)), np.zeros((0, M)),
                     np.zeros((0, M), bool), np.zeros((0, M), bool))
    idx = np.arange(start[0], len(obs), max(1, step))
    o = np.where(vis[idx, :, None], obs[idx], np.nan)
    fit = marker_fit.fit_sequence(solver, o, vis[idx].astype(float))
    return Track(idx, fit.x, fit.marker_residual_m, vis[idx], ghost[idx])


def outlier_mask(residual_m: np.ndarray) -> np.ndarray:
    """(T, M) bool: marker-frames far from the tracked prediction (per-marker robust scale)."""
    r = residual_m * 1000
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(r, axis=0)
        mad = 1.4826 * np.nanmedian(np.abs(r - med), axis=0)
    thr = med + np.maximum(OUTLIER_MIN_MM, OUTLIER_MADS * np.nan_to_num(mad))
    return np.isfinite(r) & (r > thr)


def select_frames(tracks: list[Track], k: int) -> list[tuple[int, int]]:
    """``k`` well-spread, well-tracked frames as (capture, row of its track): frames with no
    outlier marker seeing >= ``MIN_VISIBLE`` of the markers (or the most any frame sees),
    farthest-point sampling on the tracked joint rotations, starting from the best-fitted."""
    rows, feats, scores = [], [], []
    for c, t in enumerate(tracks):
        if not len(t.frames):
            continue
        out = outlier_mask(t.residual_m) | t.ghost
        vis = t.visible & ~out
        frac = vis.mean(axis=1)
        good = ~out.any(axis=1)
        for i in np.flatnonzero(good):
            rows.append((c, int(i)))
            feats.append(t.X[i, 6:])
            scores.append((frac[i], -float(np.nanmedian(t.residual_m[i]))))
    if not rows:  # nothing clean: the least-bad frames (outliers are masked anyway)
        for c, t in enumerate(tracks):
            for i in range(len(t.frames)):
                rows.append((c, i))
                feats.append(t.X[i, 6:])
                scores.append((t.visible[i].mean(), -float(np.nanmedian(t.residual_m[i]))))
    frac = np.array([s[0] for s in scores])
    keep = np.flatnonzero(frac >= min(MIN_VISIBLE, frac.max()))
    if len(keep) <= k:
        return [rows[i] for i in keep]
    F = np.array(feats)[keep]
    first = max(range(len(keep)), key=lambda i: scores[keep[i]])
    chosen = [first]
    d = np.linalg.norm(F - F[first], axis=1)
    while len(chosen) < k:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(F - F[i], axis=1))
    return sorted(rows[keep[i]] for i in chosen)


# ---------------------------------------------------------------------------- placement


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane normal to unit ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1)
    return np.stack([t1, np.cross(n, t1)], 1)


def _capped_solve(H: np.ndarray, g: np.ndarray, cap: float) -> np.ndarray:
    """argmin z^T H z - 2 g^T z subject to |z[:2]| <= cap (bisection on the multiplier)."""
    z = np.linalg.solve(H, g)
    if np.linalg.norm(z[:2]) <= cap:
        return z
    E = np.diag([1.0, 1.0, 0.0])
    lo, hi = 0.0, 1.0
    while np.linalg.norm(np.linalg.solve(H + hi * E, g)[:2]) > cap:
        hi *= 10
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if np.linalg.norm(np.linalg.solve(H + mid * E, g)[:2]) > cap:
            lo = mid
        else:
            hi = mid
    return np.linalg.solve(H + hi * E, g)


def update_placement(model: BodyModel, rest, skel, u, pl: Placement, template: Placement,
                     X: np.ndarray, obs: np.ndarray, vis: np.ndarray,
                     opts: PlacementOptions, caps: np.ndarray | None = None,
                     groups=None, max_offsets: np.ndarray | None = None
                     ) -> tuple[Placement, np.ndarray]:
    """Per marker: the skin point (tangential slide ``t`` from the template's skin point) and
    offset ``o`` minimising the robust (Geman-McClure IRLS) marker error over frames plus the
    priors, with ``|t| <= caps[m]`` (default ``max_slide_m``) and ``o`` in the bounds
    (``[min_offset_m, max_offsets[m]]``, default ``max_offset_m``). The slide is linearised at
    the current skin point (its tangent plane and face normal), so rounds can carry a marker
    around a curved limb.
    The robust scale of a marker is the larger of ``robust_sigma_m`` and its median error
    over the frames (a marker whose template is 10 cm off in every frame is moved, not
    ignored; a frame far from the marker's consensus is). Skinning weights and poses are
    those of the current placement (linearised); the point is then put on the surface, and
    kept on its template's body segment or an adjacent one (:func:`segment_groups`: the slide
    is shortened until it is). Returns (placement, left (M,) bool: the markers whose solution
    lay on another segment and were held back, or that sit at their cap with a median error
    above ``BEYOND_CAP_M``)."""
    faces = np.asarray(model.faces)
    rv = rest.vertices[0]
    groups = groups if groups is not None else segment_groups(skel)
    Wm = marker_weights(model, pl).toarray()  # (M, J)
    h = rest.joints[0]
    A = rest.bind_rot[0] if rest.bind_rot is not None else np.broadcast_to(np.eye(3), (len(h), 3, 3))
    _, s = skinned.reduced_offsets(model, rest, skel)
    frames = [skinned._fk_np(skel, u, x) for x in X]
    s0 = surface_points(rv, faces, template)
    M = len(s0)
    caps = np.full(M, opts.max_slide_m) if caps is None else np.asarray(caps, float)
    omax = (np.full(M, opts.max_offset_m) if max_offsets is None
            else np.asarray(max_offsets, float))
    slide = np.zeros((M, 3))
    beyond = np.zeros(M, bool)
    offset = np.array(pl.offset, float)
    cur = surface_points(rv, faces, pl)
    n_cur = face_normals(rv, faces[pl.face])
    for m in range(M):
        js = np.flatnonzero(Wm[m] > 0)
        # linearised at the current skin point: its tangent plane and face normal (a marker
        # slid 8 cm around a knee has another normal than its template's); the slide z[:2]
        # is measured from the template's skin point projected on that plane
        B = np.concatenate([_tangent_basis(n_cur[m]), n_cur[m][:, None]], 1)  # (3, 3): t1 t2 n
        origin = cur[m] + B[:, :2] @ (B[:, :2].T @ (s0[m] - cur[m]))
        Ls, cs = [], []
        for f, (G, t) in enumerate(frames):
            if vis[f, m] <= 0:
                continue
            # world = sum_j w_j (G_o A_j (p - h_j) + G_o s_j + t_o), o = owner(j), p rest point
            L = np.zeros((3, 3))
            c = np.zeros(3)
            for j in js:
                o = skel.owner[j]
                L += Wm[m, j] * G[o] @ A[j]
                c += Wm[m, j] * (G[o] @ (s[j] - A[j] @ h[j]) + t[o])
            Ls.append(L @ B)
            cs.append(L @ origin + c - obs[f, m])
        z = np.append(B[:, :2].T @ (cur[m] - origin), offset[m])
        prior = np.diag([1 / opts.slide_sd_m ** 2] * 2 + [1 / opts.offset_sd_m ** 2])
        ptarget = np.array([0.0, 0.0, opts.nominal_offset_m])
        if Ls:
            LB = np.stack(Ls)  # (K, 3, 3) maps z -> world
            C = np.stack(cs)
            for _ in range(opts.irls_iters):
                e = np.einsum("kab,b->ka", LB, z) + C
                e2 = np.sum(e * e, 1)
                sig = max(opts.robust_sigma_m, float(np.sqrt(np.median(e2))))
                w = robust.weight(e2, "geman_mcclure", sig)
                w = w / opts.data_sd_m ** 2
                H = np.einsum("k,kab,kac->bc", w, LB, LB) + prior
                g = -np.einsum("k,kab,ka->b", w, LB, C) + prior @ ptarget
                z = _capped_solve(H, g, caps[m])
                z[2] = np.clip(z[2], opts.min_offset_m, omax[m])
            e = np.einsum("kab,b->ka", LB, z) + C
            # held at its cap and still far in most frames: the marker's data lie out of
            # reach (a template on the wrong body part), reported like a marker off segment
            beyond[m] = (np.linalg.norm(z[:2]) >= 0.999 * caps[m]
                         and float(np.median(np.linalg.norm(e, axis=1))) > BEYOND_CAP_M)
        slide[m] = origin + B[:, :2] @ z[:2] - s0[m]
        offset[m] = np.clip(z[2], opts.min_offset_m, omax[m])
    tree = surface_tree(rv, faces)  # one tree for every query on this rest mesh
    face, bary, _ = project_to_surface(rv, faces, s0 + slide, tree)
    face, bary = face.copy(), bary.copy()
    seg0 = marker_segments(model, skel, template, groups)

    def at(m, a):  # the marker's surface point at the share a of its slide
        f_, b_, _ = project_to_surface(rv, faces, (s0[m] + a * slide[m])[None], tree)
        return f_[0], b_[0]

    def ok(m, f_, b_):  # under the cap on the surface (it wraps) and on an allowed segment
        one = replace(template, names=(template.names[m],), face=np.array([f_]),
                      bary=b_[None], offset=np.zeros(1))
        d = np.linalg.norm(np.einsum("k,kd->d", b_, rv[faces[f_]]) - s0[m])
        seg = marker_segments(model, skel, one, groups)
        return d <= caps[m] * 1.001, bool(same_or_adjacent(groups[1], seg, seg0[m:m + 1])[0])

    left = beyond.copy()
    for m in range(M):
        under, on = ok(m, face[m], bary[m])
        if under and on:
            continue
        left[m] |= not on
        lo, hi = 0.0, 1.0
        for _ in range(10):
            mid = 0.5 * (lo + hi)
            if all(ok(m, *at(m, mid))):
                lo = mid
            else:
                hi = mid
        face[m], bary[m] = at(m, lo)
    return replace(pl, face=face, bary=bary, offset=offset), left


def slides_and_offsets(model, betas, pl: Placement, template: Placement):
    """(slide (M,) m: skin-point distance from the template's on the rest body of ``betas``,
    offset (M,) m)."""
    rv = rest_state(model, betas).vertices[0]
    faces = np.asarray(model.faces)
    d = np.linalg.norm(surface_points(rv, faces, pl) - surface_points(rv, faces, template), axis=1)
    return d, np.asarray(pl.offset, float)


# ---------------------------------------------------------------------------- betas


def _markers_at(model, skel, betas, pl, X):
    rest = rest_state(model, betas)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    return marker_coeffs(model, rest, skel, pl).positions(skel, u, X)  # all frames at once


def _markers_and_jacobian(skel, u, Hm, x, sub):
    """Marker positions (M, 3) and their exact Jacobian (M, 3, n) w.r.t. the pose ``x``
    (the corners by ``skinned.point_jacobian``, the offset along the posed unit normal
    differentiated through the corners)."""
    M, _, Q, _ = Hm.corners.shape
    pos, J = skinned.point_jacobian(skel, u, Hm.corners.reshape(3 * M, Q, 4), x, sub)
    c = pos.reshape(M, 3, 3)
    Jc = J.reshape(M, 3, 3, -1)
    e1, e2 = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    cr = np.cross(e1, e2)
    ln = np.linalg.norm(cr, axis=1)
    nh = cr / ln[:, None]
    dcr = (-np.einsum("mab,mbn->man", skew(e2), Jc[:, 1] - Jc[:, 0])
           + np.einsum("mab,mbn->man", skew(e1), Jc[:, 2] - Jc[:, 0]))
    Pn = (np.eye(3)[None] - nh[:, :, None] * nh[:, None, :]) / ln[:, None, None]
    Jm = np.einsum("mk,mkan->man", Hm.bary, Jc) + Hm.offset[:, None, None] * np.einsum(
        "mab,mbn->man", Pn, dcr)
    p = np.einsum("mk,mkd->md", Hm.bary, c) + Hm.offset[:, None] * nh
    return p, Jm


def fit_shape_and_poses(model, skel, betas, pl, X, obs, vis, opts: PlacementOptions, quad, box,
                        iters: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Betas and the poses of the K frames jointly (MoSh stage I with the placement fixed):
    robust (Geman-McClure) marker errors in units of ``data_sd_m``, each frame's pose prior
    ``quad`` and joint-limit hinge ``box`` (``FrameSolver.quad_prior`` / ``.box``, metres^2),
    prior ``|betas / beta_sd|^2``, and the rest posture kept at the mean body's (Anny's bind
    rotations change with the shape; markers with free poses cannot see them but the pose-0
    mesh does): ``|A_j(betas) - A_j(0)|_F / posture_sd_rad`` over the fitted joints.
    Levenberg-Marquardt: exact pose Jacobians, forward
    differences on betas. Returns (betas (S,), X (K, n))."""
    S = len(betas)
    K, n = X.shape
    ok = vis > 0
    tgt = np.nan_to_num(obs)
    sub = skinned.subtree(skel)
    sig2, d2 = opts.robust_sigma_m ** 2, opts.data_sd_m ** 2

    def pose_prior(x):
        c = quad.cost(x)
        if box is not None:
            rb = box.residual(x)
            c += float(rb @ rb)
        return c

    def cost(b, XX):
        e = _markers_at(model, skel, b, pl, XX) - tgt
        s = np.sum(e * e, 2)[ok]
        data = np.sum(sig2 * s / (sig2 + s))
        return float((data + sum(pose_prior(x) for x in XX)) / d2 + np.sum((b / opts.beta_sd) ** 2))

    A0 = rest_state(model, np.zeros(1)).bind_rot
    jj = np.asarray(skel.joints)

    def posture(b):
        if A0 is None:
            return np.zeros(0)
        return (rest_state(model, b).bind_rot[0, jj] - A0[0, jj]).reshape(-1) / opts.posture_sd_rad

    def cost(b, XX, _cost=cost):
        rp = posture(b)
        return _cost(b, XX) + float(rp @ rp)

    lam = 1e-3
    c0 = cost(betas, X)
    for _ in range(iters):
        rp = posture(betas)
        Jp = np.zeros((len(rp), S))
        rest = rest_state(model, betas)
        u, _ = skinned.reduced_offsets(model, rest, skel)
        Hm = marker_coeffs(model, rest, skel, pl)
        P0, Jx = zip(*[_markers_and_jacobian(skel, u, Hm, x, sub) for x in X], strict=True)
        P0, Jx = np.stack(P0), np.stack(Jx)  # (K, M, 3), (K, M, 3, n)
        Jb = np.zeros((K, len(pl.face), 3, S))
        for k in range(S):
            e = np.zeros(S)
            e[k] = 1e-4
            Jb[..., k] = (_markers_at(model, skel, betas + e, pl, X) - P0) / 1e-4
            Jp[:, k] = (posture(betas + e) - rp) / 1e-4
        E = P0 - tgt
        s = np.sum(E * E, 2)
        w = np.where(ok, (sig2 / (sig2 + s)) ** 2, 0.0) / d2  # (K, M)
        N = S + K * n
        H = np.zeros((N, N))
        g = np.zeros(N)
        H[:S, :S] = (np.einsum("km,kmas,kmat->st", w, Jb, Jb) + np.eye(S) / opts.beta_sd ** 2
                     + Jp.T @ Jp)
        g[:S] = np.einsum("km,kmas,kma->s", w, Jb, E) + betas / opts.beta_sd ** 2 + Jp.T @ rp
        for f in range(K):
            sl = slice(S + f * n, S + (f + 1) * n)
            H[sl, sl] = np.einsum("m,man,mao->no", w[f], Jx[f], Jx[f]) + quad.H / d2
            g[sl] = np.einsum("m,man,ma->n", w[f], Jx[f], E[f]) + (quad.H @ X[f] - quad.g) / d2
            if box is not None:
                rb = box.residual(X[f])
                act = rb != 0
                i = S + f * n + box.idx[act]
                H[i, i] += box.weight / d2
                g[i] += np.sqrt(box.weight) * rb[act] / d2
            Hbx = np.einsum("m,mas,man->sn", w[f], Jb[f], Jx[f])
            H[:S, sl] = Hbx
            H[sl, :S] = Hbx.T
        dg = np.maximum(np.diag(H), 1e-9)
        improved = False
        while lam < 1e8:
            step = -np.linalg.solve(H + lam * np.diag(dg), g)
            b1 = betas + step[:S]
            X1 = X + step[S:].reshape(K, n)
            c1 = cost(b1, X1)
            if c1 < c0:
                betas, X, c0 = b1, np.stack([marker_fit.rewrap(x) for x in X1]), c1
                lam = max(lam * 0.3, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved:
            break
    return betas, X


# ---------------------------------------------------------------------------- stage I


@dataclass
class PlacementFit:
    """placement; betas (S,); frames: the placement frames as (capture, frame index into that
    capture); X (K, n) their poses; residual_mm (K, M) NaN where not visible or an outlier;
    off_segment: names of markers that left their segment (refitted with the tight cap); tracks: the captures tracked
    with the final shape and placement; slide_m, offset_m (M,); outliers: flagged marker-frames of the first tracking;
    static: what the static trials contributed (None without static trials):
    ``placement_from``, ``static_residual_mm`` (the static-only placement on its static frames,
    (K_s, M)), ``static_placement``/``static_betas`` (placed from the static trials alone),
    ``movement_tracking_static_m`` (per movement capture (T, M): tracked with that placement)."""

    placement: Placement
    betas: np.ndarray
    frames: list[tuple[int, int]]
    X: np.ndarray
    residual_mm: np.ndarray
    off_segment: list[str]
    tracks: list[Track]
    slide_m: np.ndarray
    offset_m: np.ndarray
    outliers: int
    on_wand: list[str] = field(default_factory=list)
    static: dict | None = None


def refine_placement(model: BodyModel, betas: np.ndarray, template: Placement, captures,
                     make_solver, opts: PlacementOptions = PlacementOptions(),
                     fit_betas: bool = False, log=None, static=()) -> PlacementFit:
    """MoSh stage I on a subject's captures (module docstring).

    betas : the starting shape (a scan fit's, or zeros with ``fit_betas``); template : the
    marker set's template placement; captures : list of (F_i, M, 3) metres, NaN gaps (the
    movement captures); static : the same for the subject's static trials;
    make_solver(rest, skel, u, Hm) -> ``marker_fit.FrameSolver`` over the body joints.

    With static trials and ``opts.placement_from`` ``"all"`` (default): the shape and the
    placement are fitted to the static trials alone first (size grid, alternation, segment
    and wand checks, from the template), then refined from there on ``opts.frames`` movement
    frames chosen by the pose tracked with the static placement plus ``opts.static_frames``
    static frames (no size grid: the static shape is the start). ``"static"`` stops after
    the first step; ``"movement"`` ignores the static trials. ``PlacementFit.frames`` index
    the static trials first, then the captures."""
    from threadpoolctl import threadpool_limits

    if opts.placement_from not in PLACEMENT_FROM:
        raise ValueError(f"placement_from: must be one of {', '.join(PLACEMENT_FROM)}, "
                         f"got {opts.placement_from!r}")
    with threadpool_limits(limits=1):
        return _refine(model, np.array(betas, float), template, list(static), list(captures),
                       make_solver, opts, fit_betas, log)


def _solver(model, skel, betas, pl, make_solver):
    rest = rest_state(model, betas)
    u, _ = skinned.reduced_offsets(model, rest, skel)
    return rest, u, make_solver(rest, skel, u, marker_coeffs(model, rest, skel, pl))


def _residual_mm(solver, X, obs, vis):
    r = np.stack([np.linalg.norm(solver.Hm.positions(solver.skel, solver.u, x) - np.nan_to_num(o),
                                 axis=1) for x, o in zip(X, obs, strict=True)])
    return np.where(vis > 0, 1000 * r, np.nan)


def _poses(solver, X, obs, vis, sweeps=1):
    for _ in range(sweeps):
        X = np.stack([marker_fit.rewrap(solver.solve(x, o, v).x)
                      for x, o, v in zip(X, obs, vis, strict=True)])
    return X


def size_start(model, skel, betas, template, X, obs, vis, make_solver, opts: PlacementOptions,
               groups=None, log=None) -> tuple[np.ndarray, np.ndarray]:
    """The body size from the markers: a grid over the first betas (``SIZE_GRID`` on beta 0,
    then on beta 1 at the best beta 0), each candidate scored by the mean over markers (the
    best ``SIZE_TRIM`` of them) of their median residual in the placement frames after its poses are refitted (warm-started from ``X``) and one
    placement update (a lab's protocol puts markers far from the template: a size scored
    with the template placement fits those, not the body). Returns (betas, X)."""
    def score(b, XX):
        rest, u, solver = _solver(model, skel, b, template, make_solver)
        XX = _poses(solver, XX, obs, vis, 2)
        pl, _ = update_placement(model, rest, skel, u, template, template, XX, obs, vis, opts,
                                 groups=groups)
        _, _, solver = _solver(model, skel, b, pl, make_solver)
        XX = _poses(solver, XX, obs, vis)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per = np.nanmedian(_residual_mm(solver, XX, obs, vis), axis=0)
        per = np.sort(per[np.isfinite(per)])
        return float(np.mean(per[:max(1, int(np.ceil(SIZE_TRIM * len(per))))])), XX

    best = (*score(betas, X), np.array(betas, float))
    for k in range(min(2, len(betas))):
        base = best[2].copy()
        grid = list(SIZE_GRID if k == 0 else SIZE_GRID[::2])
        step = float(SIZE_GRID[1] - SIZE_GRID[0]) * (1 if k == 0 else 2)
        while grid:  # the grid, then halving steps around the best value (coarse to fine)
            for v in grid:
                cand = base.copy()
                cand[k] = v
                if np.allclose(cand, base):
                    continue
                r, XX = score(cand, X)
                if r < best[0]:
                    best = (r, XX, cand)
            step /= 2
            base = best[2].copy()
            grid = [base[k] - step, base[k] + step] if step >= SIZE_STEP_MIN else []
        if log:
            log(f"size start: beta {k} = {best[2][k]:+.2f} (placement-frame marker medians "
                f"{best[0]:.2f} mm)")
    return best[2], best[1]


def _stage_one(model, skel, betas, pl, template, X, obs, vis, make_solver, opts, fit_betas,
               rounds, caps, groups, say, max_offsets=None):
    left = np.zeros(len(template.names), bool)
    for k in range(rounds):
        rest, u, solver = _solver(model, skel, betas, pl, make_solver)
        X = _poses(solver, X, obs, vis)
        pl, left = update_placement(model, rest, skel, u, pl, template, X, obs, vis, opts,
                                    caps=caps, groups=groups, max_offsets=max_offsets)
        if fit_betas:
            betas, X = fit_shape_and_poses(model, skel, betas, pl, X, obs, vis, opts,
                                           solver.quad_prior, solver.box, iters=opts.beta_steps)
        res = _residual_mm(_solver(model, skel, betas, pl, make_solver)[2], X, obs, vis)
        say(f"placement round {k + 1}/{rounds}: median {np.nanmedian(res):.2f} mm, "
            f"|betas| {np.linalg.norm(betas):.2f}")
    return betas, pl, X, left


def _no_track(skel, M) -> Track:
    """An unused capture's empty track."""
    return Track(np.zeros(0, int), np.zeros((0, skel.n)), np.zeros((0, M)),
                 np.zeros((0, M), bool), np.zeros((0, M), bool))


def _track_all(solver, captures, opts):
    tracks = [track(solver, c, opts.track_step) for c in captures]
    n_out = int(sum((outlier_mask(t.residual_m) | t.ghost).sum() for t in tracks))
    return tracks, n_out


def _place(model, skel, groups, betas, pl, template, captures, tracks, chosen, make_solver,
           opts, fit_betas, size, say):
    """Placement (and with ``fit_betas`` the shape) from the ``chosen`` (capture, track row)
    frames, starting at ``pl`` / ``betas``: size grid (``size``), alternation, markers off
    their segment refitted with the tight cap, markers on a wand refitted with the wand's
    bound. Returns (betas, placement, X, residual_mm (K, M), frames [(capture, frame)],
    left (M,), on_wand)."""
    if not chosen:
        raise ValueError("no capture frame sees 3 markers: cannot place the markers")
    frames = [(c, int(tracks[c].frames[i])) for c, i in chosen]
    out = [(outlier_mask(tracks[c].residual_m) | tracks[c].ghost)[i] for c, i in chosen]
    obs = np.stack([captures[c][f] for c, f in frames])
    vis = np.stack([tracks[c].visible[i] & ~o for (c, i), o in zip(chosen, out, strict=True)]
                   ).astype(float)
    X = np.stack([tracks[c].X[i] for c, i in chosen])
    if fit_betas and size:
        betas, X = size_start(model, skel, betas, template, X, obs, vis, make_solver, opts,
                              groups, say)
    betas, pl, X, left = _stage_one(model, skel, betas, pl, template, X, obs, vis, make_solver,
                                    opts, fit_betas, opts.rounds, None, groups, say)
    if left.any():  # refitted from the template with the tight cap, poses and shape kept
        caps = np.where(left, opts.tight_slide_m, opts.max_slide_m)
        face, bary, off = pl.face.copy(), pl.bary.copy(), pl.offset.copy()
        face[left], bary[left], off[left] = template.face[left], template.bary[left], template.offset[left]
        pl = replace(pl, face=face, bary=bary, offset=off)
        _, pl, X, _ = _stage_one(model, skel, betas, pl, template, X, obs, vis, make_solver,
                                 opts, False, 2, caps, groups, say)
        say(f"off their segment (refitted from the template, slide <= "
            f"{1000 * opts.tight_slide_m:.0f} mm): "
            f"{', '.join(n for n, b in zip(template.names, left, strict=True) if b)}")
    caps = np.where(left, opts.tight_slide_m, opts.max_slide_m)
    _, _, solver = _solver(model, skel, betas, pl, make_solver)
    X = _poses(solver, X, obs, vis)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(_residual_mm(solver, X, obs, vis), axis=0)
    wand = ((pl.offset >= opts.max_offset_m - 1e-6) & (np.nan_to_num(med) > WAND_MIN_MM)
            & (np.nan_to_num(med) < WAND_MAX_MM) & ~left)
    on_wand = [n for n, b in zip(template.names, wand, strict=True) if b]
    if wand.any():  # on a wand: refitted with the wand's offset bound, shape kept
        _, pl, X, _ = _stage_one(model, skel, betas, pl, template, X, obs, vis, make_solver,
                                 opts, False, 2, caps, groups, say,
                                 np.where(wand, opts.wand_offset_m, opts.max_offset_m))
        say(f"on a wand (offset bound {1000 * opts.wand_offset_m:.0f} mm): "
            f"{', '.join(n for n, b in zip(template.names, wand, strict=True) if b)}")
        _, _, solver = _solver(model, skel, betas, pl, make_solver)
        X = _poses(solver, X, obs, vis)
    return betas, pl, X, _residual_mm(solver, X, obs, vis), frames, left, on_wand


def _refine(model, betas, template, static, captures, make_solver, opts, fit_betas, log):
    say = log or (lambda _s: None)
    skel = skinned.fit_skeleton(model, body_joints(model))
    groups = segment_groups(skel)
    static = [np.asarray(c, float) for c in static]
    captures = [np.asarray(c, float) for c in captures]
    mode = opts.placement_from if static else "movement"
    if static and not captures:
        mode = "static"
    use_static = mode in ("static", "all")
    S = len(static)
    every = static + captures  # the frames' capture index runs over both
    info = None
    if use_static:  # 1. shape and placement from the static trials alone
        _, _, solver = _solver(model, skel, betas, template, make_solver)
        st_tracks, n_out = _track_all(solver, static, opts)
        say(f"static trials: tracked {sum(len(t.frames) for t in st_tracks)} frames, "
            f"{n_out} outlier marker-frames")
        chosen = select_frames(st_tracks, opts.frames)
        betas, pl, X, res, frames, left, on_wand = _place(
            model, skel, groups, betas, template, template, static, st_tracks, chosen,
            make_solver, opts, fit_betas, True, lambda t: say(f"static: {t}"))
        info = {"placement_from": mode, "static_residual_mm": res,
                "static_placement": pl, "static_betas": betas.copy(),
                "movement_tracking_static_m": []}
    else:
        pl = template
    if mode == "static":
        _, _, solver = _solver(model, skel, betas, pl, make_solver)
        if captures:
            info["movement_tracking_static_m"] = [
                t.residual_m for t in _track_all(solver, captures, opts)[0]]
        final = [track(solver, c, opts.track_step) for c in every]
    else:  # 2. the movement captures, tracked with the current placement and shape
        _, _, solver = _solver(model, skel, betas, pl, make_solver)
        mv_tracks, n_out = _track_all(solver, captures, opts)
        say(f"tracked {sum(len(t.frames) for t in mv_tracks)} frames, {n_out} outlier "
            "marker-frames")
        chosen = [(c + S, i) for c, i in select_frames(mv_tracks, opts.frames)]
        if use_static:
            info["movement_tracking_static_m"] = [t.residual_m for t in mv_tracks]
            chosen = select_frames(st_tracks, opts.static_frames) + chosen
            tracks = st_tracks + mv_tracks
        else:
            tracks = [_no_track(skel, len(template.names)) for _ in static] + mv_tracks
        betas, pl, X, res, frames, left, on_wand = _place(
            model, skel, groups, betas, pl, template, every, tracks, chosen, make_solver,
            opts, fit_betas, not use_static, say)
        _, _, solver = _solver(model, skel, betas, pl, make_solver)
        final = [track(solver, c, opts.track_step) if (use_static or k >= S)
                 else _no_track(skel, len(template.names)) for k, c in enumerate(every)]
    slide, offset = slides_and_offsets(model, betas, pl, template)
    return PlacementFit(pl, betas, frames, X, res,
                        [n for n, b in zip(template.names, left, strict=True) if b], final,
                        slide, offset, n_out, on_wand, info)
