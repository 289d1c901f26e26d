"""Body scans: PLY/OBJ meshes or point clouds (trimesh) as points and normals."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from formats.errors import InputError

MIN_SCAN_POINTS = 100  # fewer is not a body scan


def read_scan(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Scan points (N, 3) metres and unit normals (N, 3) or None. Meshes give their vertices
    (and vertex normals); PLY point clouds their ``nx ny nz`` properties when present.
    Raises InputError naming the file when missing, unreadable, empty or too small."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "scan", "file not found")
    try:
        obj = trimesh.load(str(path), process=False)
    except Exception as e:  # trimesh raises many types on bad files
        raise InputError(path, "scan", f"unreadable: {e}") from None
    if isinstance(obj, trimesh.Scene):
        geoms = list(obj.geometry.values())
        obj = trimesh.util.concatenate(geoms) if geoms else None
    pts = None if obj is None else np.asarray(getattr(obj, "vertices", np.zeros((0, 3))), float)
    if pts is None or len(pts) == 0:
        raise InputError(path, "scan", "no points (empty scan)")
    if not np.all(np.isfinite(pts)):
        raise InputError(path, "scan", "non-finite coordinates")
    normals = None
    if isinstance(obj, trimesh.Trimesh) and len(obj.faces):
        normals = np.asarray(obj.vertex_normals, float)
    else:
        # PLY point clouds: trimesh keeps the raw vertex properties (dict in ASCII files, a
        # structured array in binary ones)
        data = getattr(obj, "metadata", {}).get("_ply_raw", {}).get("vertex", {}).get("data")
        names = () if data is None else (data.dtype.names if hasattr(data, "dtype") else tuple(data))
        if names and all(k in names for k in ("nx", "ny", "nz")):
            normals = np.stack([np.asarray(data[k], float).reshape(-1) for k in ("nx", "ny", "nz")], 1)
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            if len(normals) != len(pts):
                normals = None
    if len(pts) < MIN_SCAN_POINTS:
        raise InputError(path, "scan", f"only {len(pts)} points: not a body scan")
    return pts, normals
