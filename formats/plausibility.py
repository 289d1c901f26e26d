"""Body-size plausibility: catch a capture or scan read in the wrong unit.

A C3D that says ``POINT:UNITS = mm`` but holds metres reads as a person 1.8 mm tall; a scan
exported in mm reads (scans are taken as metres) as one 1.8 km tall. Nothing downstream fails
loudly on that (fits converge to a tiny or huge body), so the stages check the size first.

Size estimate (:func:`marker_extent`): the *largest extent* of the point cloud, i.e. its
diameter (largest distance between two points), of the points that are not outliers. Outliers
are points farther from the coordinate-wise median than ``OUTLIER_FACTOR`` times the median
distance (a body's farthest markers, hands raised or feet, are at most ~3x the median distance
from the median; a ghost marker 5 m away is ~10x). For a capture: per frame, over the visible
(finite) markers, then the median over frames (at most ``MAX_FRAMES`` frames, evenly spaced), so
ghosts in a few frames do not count either.

Plausible range ``HUMAN_EXTENT_M = (0.3, 3.0)`` metres:

- low end 0.3 m: a newborn lying stretched has a marker extent of ~0.45 m, a crouched toddler
  ~0.35 m; an adult in mm labelled cm reads 0.17 m, in cm labelled m 0.017 m;
- high end 3.0 m: a 2.2 m player reaching up spans ~2.9 m tip to toe (standing reach ~1.33 x
  height); markers sit on the skin, inside that;
- the ratio is 10, the smallest unit error (mm vs cm): any person whose true extent is inside the
  range lands outside it under any unit error of 10x or more, so no unit error passes.

The check assumes the points cover the whole body (a full-body marker set, a body scan); a
capture of only the feet would look like a unit error.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from formats.errors import InputError

HUMAN_EXTENT_M = (0.3, 3.0)
OUTLIER_FACTOR = 4.0
MAX_FRAMES = 200
_UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
_UNIT_NAMES = {"mm": "millimetres", "cm": "centimetres", "m": "metres"}


def _inliers(p: np.ndarray) -> np.ndarray:
    """Points of ``p`` (n, 3) no farther from the median than OUTLIER_FACTOR x the median distance."""
    if len(p) < 4:
        return p
    d = np.linalg.norm(p - np.median(p, axis=0), axis=1)
    return p[d <= OUTLIER_FACTOR * max(float(np.median(d)), 1e-12)]


def _diameter(p: np.ndarray) -> float:
    """Largest distance between two of the points ``p`` (n, 3); 0 for fewer than 2."""
    if len(p) < 2:
        return 0.0
    if len(p) > 64:
        from scipy.spatial import ConvexHull, QhullError

        try:
            p = p[ConvexHull(p).vertices]
        except (QhullError, ValueError):  # flat or degenerate cloud: keep every point
            pass
        if len(p) > 2000:  # a degenerate cloud left whole: the extremes along the axes
            idx = np.unique(np.concatenate([np.argsort(p[:, k])[[0, -1]] for k in range(3)]))
            rest = np.linspace(0, len(p) - 1, 2000).astype(int)
            p = p[np.unique(np.concatenate([idx, rest]))]
    diff = p[:, None, :] - p[None, :, :]
    return float(np.sqrt((diff ** 2).sum(-1)).max())


def marker_extent(xyz: np.ndarray) -> float:
    """Robust largest extent (metres if ``xyz`` is) of a capture ``xyz`` (F, M, 3): per frame
    the diameter of the visible non-outlier markers, median over frames with 2 or more visible
    markers. NaN when no frame has 2 visible markers."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz: expected (F, M, 3), got {xyz.shape}")
    vis = np.all(np.isfinite(xyz), axis=2)
    frames = np.flatnonzero(vis.sum(1) >= 2)
    if len(frames) == 0:
        return float("nan")
    if len(frames) > MAX_FRAMES:
        frames = frames[np.linspace(0, len(frames) - 1, MAX_FRAMES).round().astype(int)]
    return float(np.median([_diameter(_inliers(xyz[f][vis[f]])) for f in frames]))


def scan_extent(points: np.ndarray) -> float:
    """Robust largest extent of a scan's points (N, 3): the diameter of the finite non-outlier
    points. NaN when fewer than 2 finite points."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected (N, 3), got {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    return float("nan") if len(p) < 2 else _diameter(_inliers(p))


def format_length(m: float) -> str:
    """A length in metres, 2 significant figures, in mm, cm, m or km (``1.8 mm``, ``17 m``)."""
    a = abs(m)
    for unit, f, lim in (("mm", 1e-3, 1e-2), ("cm", 1e-2, 1.0), ("m", 1.0, 1e3), ("km", 1e3, np.inf)):
        if a < lim:
            return f"{float(f'{m / f:.2g}'):g} {unit}"
    return f"{m:g} m"


def _check(size: float, file, field: str, declared_unit: str, says: str) -> float:
    lo, hi = HUMAN_EXTENT_M
    if not np.isfinite(size) or size <= 0:
        raise InputError(file, field, "cannot judge the person's size: fewer than 2 visible "
                         "points in every frame")
    if lo <= size <= hi:
        return size
    declared = declared_unit.strip().lower() or "mm"
    raw = size / _UNITS_M.get(declared, 1.0)  # the numbers as stored in the file
    fits = [(abs(np.log(raw * f / 1.7)), u) for u, f in _UNITS_M.items()
            if lo <= raw * f <= hi and u != declared]
    if fits:
        hint = f"the coordinates look like {_UNIT_NAMES[min(fits)[1]]}, {says} {declared}"
    else:
        hint = f"{says} {declared} and no unit of {', '.join(_UNITS_M)} gives a human size"
    raise InputError(file, field, f"person is {format_length(size)} tall: {hint} (largest "
                     f"extent of the points; a person is {lo:g} m to {hi:g} m)")


def check_capture_scale(xyz: np.ndarray, file: str | Path, field: str = "POINT:UNITS",
                        declared_unit: str = "mm") -> float:
    """Check that a capture ``xyz`` (F, M, 3), metres as read with the file's ``declared_unit``,
    shows a person of human size. Returns the size estimate (the robust largest extent,
    :func:`marker_extent`) in metres; raises InputError naming ``file``, ``field`` and the unit
    the coordinates seem to be in when it is outside :data:`HUMAN_EXTENT_M` (or when no frame
    has 2 visible markers)."""
    return _check(marker_extent(xyz), file, field, declared_unit, "the file says")


def check_scan_scale(points: np.ndarray, file: str | Path, field: str = "scan",
                     declared_unit: str = "m") -> float:
    """Check that a body scan's points (N, 3), metres as read (scans are taken as
    ``declared_unit``, metres), show a person of human size. Returns the robust largest extent
    (:func:`scan_extent`) in metres; raises InputError naming ``file``, ``field`` and the unit
    the coordinates seem to be in otherwise."""
    return _check(scan_extent(points), file, field, declared_unit, "the scan is read as")
