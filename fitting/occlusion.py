"""Which of a person's keypoints another body hides in a view.

A single-person detector reports every keypoint, visible or not: where the marker wearer
stands between a camera and the partner's arm, it places the arm on what it sees (the
wearer's chest, the wearer's hand) with full confidence. On the realistic demo's Handshake the
partner's right elbow and wrist were detected 89 and 127 px off in one view, 20 px from the
wearer's projected thorax, in the frames where the wearer hides that arm. The wearer's body is
known (``marker_fit``), so such keypoints can be told apart: the ray from the camera centre to
the partner's estimated keypoint passes through the wearer's surface before it reaches it.

:func:`hidden` casts those rays against a triangle mesh (the wearer's proxy mesh,
``fitting.collision.ProxyMesh``: ~3,000 triangles) with a vectorised Moeller-Trumbore test.
"""
from __future__ import annotations

import numpy as np

#: a keypoint counts as hidden when the occluding surface is at least this far in front of
#: it along the ray (metres): a hand resting on the other person's hand is not hidden by it
OCCLUSION_MARGIN_M = 0.03


def ray_hits(origin: np.ndarray, targets: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
             margin_m: float = OCCLUSION_MARGIN_M, chunk: int = 200_000) -> np.ndarray:
    """(K,) bool: the segment from ``origin (3,)`` to each of ``targets (K, 3)`` crosses a
    triangle of ``(vertices (V, 3), faces (T, 3))`` at least ``margin_m`` before the target
    (and in front of the origin). ``chunk``: ray-triangle pairs tested at once."""
    O = np.asarray(origin, float)
    P = np.asarray(targets, float)
    V = np.asarray(vertices, float)
    Fc = np.asarray(faces, np.int64)
    K = len(P)
    out = np.zeros(K, bool)
    if K == 0 or len(Fc) == 0:
        return out
    D = P - O  # (K, 3) ray directions, t = 1 at the target
    L = np.linalg.norm(D, axis=1)
    t_max = 1.0 - margin_m / np.maximum(L, 1e-12)
    A = V[Fc[:, 0]]
    E1 = V[Fc[:, 1]] - A  # (T, 3)
    E2 = V[Fc[:, 2]] - A
    S = O - A  # (T, 3)
    Q = np.cross(S, E1)  # (T, 3)
    step = max(1, chunk // len(Fc))
    for k0 in range(0, K, step):
        d = D[k0:k0 + step]  # (k, 3)
        Pv = np.cross(d[:, None, :], E2[None])  # (k, T, 3)
        det = np.einsum("ktc,tc->kt", Pv, E1)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        u = np.einsum("ktc,tc->kt", Pv, S) * inv
        v = np.einsum("kc,tc->kt", d, Q) * inv
        t = np.einsum("tc,tc->t", E2, Q)[None] * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < t_max[k0:k0 + len(d), None])
        out[k0:k0 + len(d)] = hit.any(axis=1)
    return out


def hidden(cams, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
           margin_m: float = OCCLUSION_MARGIN_M) -> np.ndarray:
    """(C, K) bool: keypoint ``points[k]`` (world metres) is hidden from camera ``c`` by the
    mesh ``(vertices, faces)`` (another person's body). NaN points are never hidden."""
    P = np.asarray(points, float)
    good = np.all(np.isfinite(P), axis=1)
    out = np.zeros((len(cams), len(P)), bool)
    for c, cam in enumerate(cams):
        out[c, good] = ray_hits(cam.T, P[good], vertices, faces, margin_m)
    return out
