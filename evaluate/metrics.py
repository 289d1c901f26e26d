"""The CHI3D benchmark metrics as pure numpy functions (no file I/O).

Shapes: any leading axes ``...`` (persons, frames) are kept; every metric returns the error per
leading index in the input's units (metres in, metres out; the report converts to mm).

- ``mpjpe``: mean distance over the 14 LSP joints taken from the H36M 17 (the public tools'
  ``H36M_TO_J17``, first 14), each skeleton centred on its own pelvis (H36M joint 0).
- ``pa_mpjpe``: the same after a per-frame similarity Procrustes (rotation, scale, translation)
  of the prediction onto the truth.
- ``mpvpe`` / ``pa_mpvpe``: mean vertex distance, vertices centred on the model's joint 0.
- ``translation_error``: distance between the pelvis (joint 0) positions.
- ``match_people``: per-frame assignment of predicted people to true people by the Hungarian
  method on the IoU of their 2D bounding boxes.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from evaluate import constants as K


def _points(x, name: str, min_points: int = 1) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim < 2 or a.shape[-1] != 3 or a.shape[-2] < min_points:
        raise ValueError(f"{name}: expected (..., N >= {min_points}, 3), got {a.shape}")
    return a


def _same(a: np.ndarray, b: np.ndarray, na: str, nb: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{na} {a.shape} and {nb} {b.shape} differ in shape")


def lsp_centred(joints) -> np.ndarray:
    """(..., >= 17, 3) H36M-ordered joints (joints3d_25 or H36M 17) -> (..., 14, 3) LSP joints
    minus the pelvis."""
    j = _points(joints, "joints", 17)[..., K.H36M_TO_J17, :]
    return j[..., : K.NUM_LSP, :] - j[..., K.PELVIS_J17: K.PELVIS_J17 + 1, :]


def mean_distance(a, b) -> np.ndarray:
    """(..., N, 3) x2 -> (...,) mean Euclidean distance over N."""
    a, b = _points(a, "a"), _points(b, "b")
    _same(a, b, "a", "b")
    return np.linalg.norm(a - b, axis=-1).mean(axis=-1)


def similarity_procrustes(X, Y) -> np.ndarray:
    """The similarity transform ``s R X + t`` of X closest to Y in least squares (det R = +1),
    applied to X, per leading index. X, Y: (..., N, 3) -> (..., N, 3).

    Closed form (Umeyama): with centred Xc, Yc and ``Xc^T Yc = U S V^T``,
    ``R = V D U^T`` (``D = diag(1, 1, sign det(V U^T))``), ``s = tr(D S) / |Xc|^2``,
    ``t = mean(Y) - s R mean(X)``. A prediction of zero spread maps to the truth's mean.
    """
    X, Y = _points(X, "X"), _points(Y, "Y")
    _same(X, Y, "X", "Y")
    mx, my = X.mean(axis=-2, keepdims=True), Y.mean(axis=-2, keepdims=True)
    Xc, Yc = X - mx, Y - my
    U, S, Vt = np.linalg.svd(np.swapaxes(Xc, -1, -2) @ Yc)          # (..., 3, 3)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(S.shape)
    D[..., -1] = d
    R = (V * D[..., None, :]) @ np.swapaxes(U, -1, -2)               # V diag(D) U^T
    var = (Xc**2).sum(axis=(-1, -2))
    s = np.where(var > K.PROCRUSTES_EPS, (S * D).sum(axis=-1) / np.maximum(var, K.PROCRUSTES_EPS), 0.0)
    return s[..., None, None] * (Xc @ np.swapaxes(R, -1, -2)) + my


def mpjpe(pred, gt) -> np.ndarray:
    """(..., >= 17, 3) H36M-ordered joints -> (...,) pelvis-centred LSP-14 MPJPE."""
    return mean_distance(lsp_centred(pred), lsp_centred(gt))


def pa_mpjpe(pred, gt) -> np.ndarray:
    """(..., >= 17, 3) -> (...,) LSP-14 MPJPE after a per-frame similarity Procrustes."""
    p, g = lsp_centred(pred), lsp_centred(gt)
    return mean_distance(similarity_procrustes(p, g), g)


def translation_error(pred, gt) -> np.ndarray:
    """(..., >= 1, 3) joints -> (...,) distance of joint 0 (the pelvis)."""
    p, g = _points(pred, "pred"), _points(gt, "gt")
    _same(p, g, "pred", "gt")
    return np.linalg.norm(p[..., K.PELVIS_H36M, :] - g[..., K.PELVIS_H36M, :], axis=-1)


def _centred_vertices(v, root, name: str) -> np.ndarray:
    v = _points(v, f"{name} vertices")
    r = np.asarray(root, dtype=np.float64)
    if r.shape != v.shape[:-2] + (3,):
        raise ValueError(f"{name} root: expected {v.shape[:-2] + (3,)}, got {r.shape}")
    return v - r[..., None, :]


def mpvpe(pred_vertices, gt_vertices, pred_root, gt_root) -> np.ndarray:
    """(..., V, 3) vertices and (..., 3) model joint 0 -> (...,) MPVPE, each mesh centred on its
    own joint 0."""
    return mean_distance(_centred_vertices(pred_vertices, pred_root, "pred"),
                         _centred_vertices(gt_vertices, gt_root, "gt"))


def pa_mpvpe(pred_vertices, gt_vertices, pred_root, gt_root) -> np.ndarray:
    """MPVPE after a per-frame similarity Procrustes of the centred prediction."""
    p = _centred_vertices(pred_vertices, pred_root, "pred")
    g = _centred_vertices(gt_vertices, gt_root, "gt")
    return mean_distance(similarity_procrustes(p, g), g)


# ----------------------------------------------------------------------------- person matching
def boxes_from_points(uv) -> np.ndarray:
    """(..., K, 2) pixels -> (..., 4) boxes (x0, y0, x1, y1) enclosing the K points."""
    a = np.asarray(uv, dtype=np.float64)
    if a.ndim < 2 or a.shape[-1] != 2:
        raise ValueError(f"uv: expected (..., K, 2), got {a.shape}")
    return np.concatenate([a.min(axis=-2), a.max(axis=-2)], axis=-1)


def box_iou(a, b) -> np.ndarray:
    """IoU of boxes (..., 4) x (..., 4) (broadcast), continuous areas; empty union -> 0."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    lo = np.maximum(a[..., :2], b[..., :2])
    hi = np.minimum(a[..., 2:], b[..., 2:])
    inter = np.prod(np.clip(hi - lo, 0.0, None), axis=-1)

    def area(x):
        return np.prod(np.clip(x[..., 2:] - x[..., :2], 0.0, None), axis=-1)

    return inter / (area(a) + area(b) - inter + K.IOU_EPS)


def match_people(pred_boxes, gt_boxes) -> np.ndarray:
    """Per-frame assignment of predicted people to true people.

    pred_boxes, gt_boxes: (F, P, 4). Returns ``order (F, P)`` int: ``order[f, g]`` is the
    predicted person matched to true person g in frame f (the Hungarian assignment maximising
    the summed IoU; ties keep the identity order).
    """
    p, g = np.asarray(pred_boxes, np.float64), np.asarray(gt_boxes, np.float64)
    if p.ndim != 3 or p.shape[-1] != 4 or p.shape != g.shape:
        raise ValueError(f"pred_boxes {p.shape} and gt_boxes {g.shape}: expected both (F, P, 4)")
    F, P = p.shape[:2]
    iou = box_iou(p[:, :, None, :], g[:, None, :, :])                  # (F, Ppred, Pgt)
    order = np.tile(np.arange(P), (F, 1))
    identity = np.trace(iou, axis1=1, axis2=2)
    for f in range(F):
        rows, cols = linear_sum_assignment(iou[f], maximize=True)
        if iou[f, rows, cols].sum() > identity[f] + K.IOU_EPS:
            order[f, cols] = rows
    return order


def reorder_people(x, order) -> np.ndarray:
    """Apply a matching: x (P, F, ...) predicted people, order (F, P) from :func:`match_people`
    -> (P, F, ...) with person g of frame f = predicted person ``order[f, g]``."""
    a = np.asarray(x)
    o = np.asarray(order)
    if a.shape[:2] != o.shape[::-1]:
        raise ValueError(f"x {a.shape} does not fit order {o.shape} (expected x (P, F, ...))")
    return a[o.T, np.arange(o.shape[0])[None, :]]
