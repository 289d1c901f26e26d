"""Per-face and per-vertex quantities of triangle meshes: the one face-normal function.

A mesh is ``vertices: (..., V, 3) float`` (metres, any frame; leading axes are frames) and
``faces: (T, 3) int`` (counter-clockwise seen from outside, so normals point outwards).
"""
from __future__ import annotations

import numpy as np

from geometry import constants as C


def _check(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim < 2 or v.shape[-1] != 3:
        raise ValueError(f"vertices: expected (..., V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces: expected (T, 3) int, got {f.shape} {f.dtype}")
    return v, f


def face_normals(vertices: np.ndarray, faces: np.ndarray, unit: bool = True) -> np.ndarray:
    """Face normals of triangles ``faces`` over ``vertices``.

    vertices: (..., V, 3) float, leading axes batched (frames); faces: (T, 3) int.
    Returns (..., T, 3): ``(b - a) x (c - a)`` per triangle ``(a, b, c)``, normalised when
    ``unit`` (else its length is twice the triangle's area). A degenerate triangle (cross
    product shorter than constants.DEGENERATE_CROSS) gets the zero vector.
    """
    v, f = _check(vertices, faces)
    a, b, c = v[..., f[:, 0], :], v[..., f[:, 1], :], v[..., f[:, 2], :]
    n = np.cross(b - a, c - a)
    if not unit:
        return n
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length >= C.DEGENERATE_CROSS)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., T) triangle areas (m^2) of ``faces`` (T, 3) over ``vertices`` (..., V, 3)."""
    return 0.5 * np.linalg.norm(face_normals(vertices, faces, unit=False), axis=-1)


def face_centroids(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(..., T, 3) triangle centroids of ``faces`` (T, 3) over ``vertices`` (..., V, 3)."""
    v, f = _check(vertices, faces)
    return v[..., f, :].mean(axis=-2)


class VertexNormals:
    """Area-weighted unit vertex normals of a fixed triangle topology, fast (a sparse
    vertex-face incidence product, built once).

    ``VertexNormals(faces (T, 3), V)(vertices (V, 3)) -> (V, 3)``; a vertex in no face (or whose
    face normals cancel) gets the zero vector."""

    def __init__(self, faces: np.ndarray, num_vertices: int):
        import scipy.sparse as sp

        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"faces: expected (T, 3), got {f.shape}")
        T = len(f)
        self.faces = f
        self.num_vertices = int(num_vertices)
        self.inc = sp.csr_matrix((np.ones(3 * T), (f.T.ravel(), np.tile(np.arange(T), 3))),
                                 shape=(self.num_vertices, T))
        # each vertex sums its faces in ascending order (the same bits as a bincount)
        self.inc.sort_indices()

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        v = np.asarray(vertices, dtype=float)
        if v.shape != (self.num_vertices, 3):
            raise ValueError(f"vertices: expected ({self.num_vertices}, 3), got {v.shape}")
        n = self.inc @ face_normals(v, self.faces, unit=False)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length >= C.VERTEX_NORMAL_EPS)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals of a mesh ``vertices`` (V, 3), ``faces`` (T, 3).
    For many meshes of one topology, build a :class:`VertexNormals` once."""
    v = np.asarray(vertices, dtype=float)
    return VertexNormals(faces, len(v))(v)
