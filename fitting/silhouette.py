"""``L_sil``: the partner's outline in the views (issue #27 item 2), an extra term of the partner
fit's seam (``fitting.partner_fit.ExtraTerm``: Blocks of points on the skinned surface, the
targets fixed for an LM round).

Input: :class:`artifacts.silhouettes.Silhouettes` (stage ``silhouettes``: the people mask by
background subtraction against the clean plate, the partner's = people less the wearer's
fitted body) and the cameras. Per usable view, with the partner's proxy points ``P``
(``fitting.collision.ProxyMesh``, as ``L_ic`` uses) projected to ``uv = pi_c(P)``:

(a) inside: a proxy point whose projection falls outside the people mask dilated by
    ``inside_tol_px`` is pulled toward the nearest people pixel (2D residual ``uv - target``,
    pixels); a point farther than ``max_px`` from any people pixel is left alone (something
    static of the room hides it, or the mask missed a part);
(b) cover: partner-mask pixels (a grid of every ``stride``-th mask pixel, of the mask's
    components that the projected partner touches: a bystander's or a far wearer fringe's
    component is not the partner's) farther than ``cover_tol_px`` from every projected proxy
    point pull their nearest projected proxy point toward them (``uv_n - pixel``; a pixel
    farther than ``max_px`` is left alone).

Rows are pixels (as ``L_2d``'s), scaled so the view's cost is a mean: (a) by
``1 / sqrt(P V)``, (b) by ``1 / sqrt(S)`` for the ``P`` proxy points, ``V`` usable views,
``S`` pixel samples over the views; so ``w_sil = 1`` weighs a mean squared pixel of outline as
``L_2d`` weighs a keypoint's. The derivative is ``calib.project_jacobian``'s (lens distortion
included) times the point's Jacobian (``Block``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from artifacts.silhouettes import Silhouettes
from calib import project, project_jacobian
from fitting import collision

# constants
# Realistic demo, partner MPJPE (100 frames, w_sil 10) at (INSIDE_TOL_PX, COVER_TOL_PX) = (2, 8):
# Push 30.5, Handshake 28.5 mm; (0, 8): 28.4, 25.4; (2, 4): 28.9, 26.4; (0, 4): 27.2, 25.4
# (without L_sil: 33.2, 31.1); the masks' outline is half a mask pixel wide already
INSIDE_TOL_PX = 0  # (a) the people mask is dilated by this (mask pixels) before judging "outside"
COVER_TOL_PX = 4.0  # (b) a partner pixel this near (image pixels) a projected proxy point is covered
MAX_PX = 80.0  # (a), (b) farther than this (image pixels): not pulled
STRIDE = 3  # (b) every STRIDE-th mask pixel in each direction is a sample
MIN_HITS = 3  # (b) a partner-mask component counts as the partner's when this many projected
#               proxy points fall on it


@dataclass(frozen=True)
class SilhouetteInput:
    """What ``L_sil`` needs beside the fit: the masks and the fit's cameras (matched by id)."""

    masks: Silhouettes
    cams: list


class SilhouetteTerm:
    """``L_sil`` (see the module docstring). frames : (F,) the fit's video frames (``Posed
    .frame`` indexes them); proxy : the partner's proxy mesh."""

    name = "L_sil"

    def __init__(self, data: SilhouetteInput, frames: np.ndarray, proxy: collision.ProxyMesh,
                 inside_tol_px: int = INSIDE_TOL_PX, cover_tol_px: float = COVER_TOL_PX,
                 max_px: float = MAX_PX, stride: int = STRIDE, min_hits: int = MIN_HITS):
        self.masks, self.proxy = data.masks, proxy
        self.frames = np.asarray(frames, np.int64)
        self.views = [(c, cam) for c, cam in ((data.masks.camera(cam.name), cam) for cam in data.cams)
                      if c is not None]
        self.inside_tol_px, self.cover_tol_px = int(inside_tol_px), float(cover_tol_px)
        self.max_px, self.stride, self.min_hits = float(max_px), int(stride), int(min_hits)
        self._cache: dict[int, list] = {}

    def frame_data(self, f: int) -> list:
        """Per usable view of fit frame ``f``: ``(cam, nearest (2, h, w) mask index of the
        nearest dilated-people pixel, outside (h, w) bool, distance (h, w) mask px, partner
        component labels (h, w), sample pixels (S, 2) mask ij)``; one frame cached."""
        if f in self._cache:
            return self._cache[f]
        out = []
        i = self.masks.index(int(self.frames[f]))
        if i is not None:
            for c, cam in self.views:
                if not self.masks.usable[i, c]:
                    continue
                ppl = self.masks.mask(i, c, "people")
                if self.inside_tol_px:
                    ppl = ndimage.binary_dilation(ppl, iterations=self.inside_tol_px)
                dist, idx = ndimage.distance_transform_edt(~ppl, return_indices=True)
                par = self.masks.mask(i, c, "partner")
                lab, _ = ndimage.label(par, structure=np.ones((3, 3)))
                grid = np.zeros_like(par)
                grid[self.stride // 2::self.stride, self.stride // 2::self.stride] = True
                ij = np.argwhere(par & grid)
                out.append((cam, idx, ~ppl, dist, lab, ij))
        self._cache = {f: out}
        return out

    def __call__(self, posed) -> list:
        from fitting.partner_fit import Block

        views = self.frame_data(posed.frame)
        if not views:
            return []
        pr = self.proxy
        P = pr.points(posed.vertices)
        nP = len(P)
        s = self.masks
        h, w = s.shape
        scale = float(s.scale)
        n_samples = max(sum(len(v[5]) for v in views), 1)
        sa = 1.0 / np.sqrt(nP * len(views))
        sb = 1.0 / np.sqrt(n_samples)
        blocks = []
        for cam, idx, outside, dist, lab, ij in views:
            uv = project(cam, P)
            rc = np.rint(s.mask_pixels(uv)).astype(np.int64)
            inimg = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
            inimg &= np.isfinite(uv).all(1)
            r0 = np.where(inimg, rc[:, 0], 0)
            c0 = np.where(inimg, rc[:, 1], 0)
            # (a) proxy points outside the dilated people mask -> the nearest people pixel
            out_a = inimg & outside[r0, c0] & (dist[r0, c0] / scale <= self.max_px)
            a_idx = np.flatnonzero(out_a)
            a_tgt = s.pixel_centres(np.stack([idx[0][r0[a_idx], c0[a_idx]],
                                              idx[1][r0[a_idx], c0[a_idx]]], axis=1))
            # (b) partner-mask pixels of the partner's components far from every projected point
            b_pts = np.zeros(0, np.int64)
            b_tgt = np.zeros((0, 2))
            if len(ij):
                hits = np.bincount(lab[r0[inimg], c0[inimg]], minlength=int(lab.max()) + 1)
                hits[0] = 0
                mine = hits >= self.min_hits
                sel = ij[mine[lab[ij[:, 0], ij[:, 1]]]]
                if len(sel):
                    pix = s.pixel_centres(sel)
                    d, near = cKDTree(uv[inimg]).query(pix) if inimg.any() else (None, None)
                    if d is not None:
                        far = (d > self.cover_tol_px) & (d <= self.max_px)
                        b_pts = np.flatnonzero(inimg)[near[far]]
                        b_tgt = pix[far]
            if not len(a_idx) and not len(b_pts):
                continue
            pts, inv = np.unique(np.concatenate([a_idx, b_pts]), return_inverse=True)
            point = inv  # per pixel row pair: the point it moves
            targets = np.concatenate([a_tgt, b_tgt])
            wrow = np.concatenate([np.full(len(a_idx), sa), np.full(len(b_pts), sb)])
            H = posed.slots(pr.corners[pts], pr.bary[pts])
            blocks.append(Block(self.name, H, silhouette_residual(cam, targets, point, wrow)))
        return blocks


def silhouette_residual(cam, targets: np.ndarray, point: np.ndarray, weights: np.ndarray):
    """The rows of ``sum_m weights[m]^2 |pi(p[point[m]]) - targets[m]|^2`` (pixels) of points
    ``p`` (N, 3) seen by ``cam``, two per point: the targets of one point are summed into
    ``W |pi(p) - t_mean|`` (``W^2 = sum weights^2``, ``t_mean`` their weighted mean), the same
    sum up to a constant, so the same gradient and Gauss-Newton Hessian with a row pair per
    point instead of per target (an uncovered mask pulls one point with many pixels).
    ``residual(pos) -> (r (2P,), dr (2P, 3), point (2P,))`` with ``dr`` from
    ``calib.project_jacobian`` (lens distortion included)."""
    targets = np.asarray(targets, float).reshape(-1, 2)
    w2 = np.asarray(weights, float) ** 2
    point, inv = np.unique(np.asarray(point, np.int64), return_inverse=True)
    inv = inv.reshape(-1)
    W2 = np.bincount(inv, w2, len(point))
    targets = np.stack([np.bincount(inv, w2 * targets[:, a], len(point)) for a in (0, 1)],
                       axis=1) / np.maximum(W2, 1e-300)[:, None]
    wt = np.sqrt(W2)
    rows_point = np.repeat(point, 2)

    def residual(pos):
        with np.errstate(all="ignore"):
            uv, J = project_jacobian(cam, np.asarray(pos, float))
        r = wt[:, None] * (uv[point] - targets)
        dr = wt[:, None, None] * J[point]
        return r.reshape(-1), dr.reshape(-1, 3), rows_point

    return residual


def silhouette_term(model, frames: np.ndarray, data: SilhouetteInput,
                    proxy_vertices: int) -> SilhouetteTerm:
    """``L_sil`` over the fit's ``frames`` with the masks and cameras of ``data``, on the
    model's proxy of ``proxy_vertices`` vertices."""
    return SilhouetteTerm(data, frames, collision.ProxyMesh.from_model(model, proxy_vertices))
