"""Body scans as a 3D scanner would deliver them: a point cloud of the surface in a neutral pose
with noise, holes where the scanner can't see (armpits, soles) and uneven sampling density.

Written as binary PLY (``x y z nx ny nz`` float32, metres, the scan's own frame), which
trimesh, Open3D and MeshLab read.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geometry import face_areas, face_normals
from studio import constants as C


@dataclass(frozen=True)
class ScanOptions:
    """n_points: points before holes are cut; noise_m: standard deviation of the noise along the
    surface normal, metres; hole_radius_m: radius of each armpit hole; sole_height_m: points this
    close to the lowest point with a downward normal are dropped (the scanner stands on them);
    density_contrast: ratio of the densest to the sparsest sampled area (the views that the
    scanner's cameras face are denser)."""

    n_points: int = C.SCAN_POINTS
    noise_m: float = C.SCAN_NOISE_M
    hole_radius_m: float = C.SCAN_HOLE_RADIUS_M
    sole_height_m: float = C.SCAN_SOLE_HEIGHT_M
    density_contrast: float = C.SCAN_DENSITY_CONTRAST


def sample_scan(vertices: np.ndarray, faces: np.ndarray, hole_centres: np.ndarray,
                rng: np.random.Generator, opts: ScanOptions = ScanOptions()
                ) -> tuple[np.ndarray, np.ndarray]:
    """Sample a scanner-like point cloud from a triangle mesh.

    vertices: (V, 3) metres, z-up, the person standing on their lowest point; faces: (T, 3);
    hole_centres: (H, 3) metres, points around which a ball of ``opts.hole_radius_m`` is cut
    (armpits). Returns points (N, 3) and unit normals (N, 3) of the true surface at the sampled
    points (the noise is along them), N < opts.n_points.
    """
    fn, area = face_normals(vertices, faces), face_areas(vertices, faces)
    # Uneven density: the scanner's cameras face the person from 4 horizontal directions at a
    # random heading; surfaces facing them are sampled more densely, plus a smooth random field.
    heading = rng.uniform(0, 2 * np.pi)
    dirs = np.stack([[np.cos(heading + k * np.pi / 2), np.sin(heading + k * np.pi / 2), 0.0]
                     for k in range(4)])
    facing = np.clip(fn @ dirs.T, 0, None).max(axis=1) ** 2
    centroid = vertices[faces].mean(axis=1)
    waves = rng.normal(size=(4, 3)) * 6.0
    phase = rng.uniform(0, 2 * np.pi, 4)
    field = np.sin(centroid @ waves.T + phase).mean(axis=1)
    logc = np.log(opts.density_contrast)
    density = np.exp(logc * (0.6 * facing + 0.4 * (field + 1) / 2))
    w = area * density
    face = rng.choice(len(faces), size=opts.n_points, p=w / w.sum())
    r1, r2 = rng.random(opts.n_points), rng.random(opts.n_points)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    pts = np.einsum("nk,nkd->nd", bary, vertices[faces[face]])
    nrm = fn[face]
    keep = np.ones(len(pts), bool)
    for c in np.asarray(hole_centres, float).reshape(-1, 3):
        keep &= np.linalg.norm(pts - c, axis=1) > opts.hole_radius_m
    zmin = vertices[:, 2].min()
    keep &= ~((pts[:, 2] < zmin + opts.sole_height_m) & (nrm[:, 2] < -0.3))
    pts, nrm = pts[keep], nrm[keep]
    pts = pts + nrm * rng.normal(0.0, opts.noise_m, (len(pts), 1))
    return pts, nrm


def write_ply(path: str | Path, points: np.ndarray, normals: np.ndarray) -> Path:
    """Write a binary little-endian PLY point cloud: points (N, 3) metres, normals (N, 3)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = np.empty(len(points), dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate(("x", "y", "z")):
        rec[k] = points[:, i]
        rec["n" + k] = normals[:, i]
    header = ("ply\nformat binary_little_endian 1.0\ncomment synthetic scan (studio), metres\n"
              f"element vertex {len(points)}\n"
              + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + "end_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
    return path
