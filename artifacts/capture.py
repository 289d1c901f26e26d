"""Stage ``capture``'s typed outputs: the wearer's cleaned markers and the camera rig.

A sequence's capture is read, checked and cleaned ONCE, by the ``capture`` stage; every stage
that needs the markers or the cameras reads these two classes, never the C3D or the
calibration files again:

- :class:`Markers` (``markers.npz``): the marker-wearing subject's markers in the order of its
  marker set, metres, NaN where not observed (gaps, and samples the cleaning removed), with
  per marker and sample what the cleaning repaired (``repair``, codes
  ``fitting.marker_clean.REPAIR_CODES`` stored by name in ``repair_codes``) and what the file
  held before cleaning (``raw_observed``);
- :class:`CameraRig` (``rig.npz``): the calibrated cameras in the recipe's order
  (``calib.Camera`` fields, stacked); absent on a marker-only sequence.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import ArtifactError, FieldSpec, TypedArtifact, check_metres, check_rotations

# constants
MAX_MARKER_M = 50.0  # a marker farther than this from the origin is not metres (or a ghost the
#                      cleaning let through): the capture stage refuses it before writing
CAMERA_MODELS = ("h36m", "opencv")


@dataclass(frozen=True, eq=False)
class Markers(TypedArtifact):
    """The marker-wearing subject's capture after reading, unit check and cleaning.

    names : (M,) marker names of the subject's marker set (the fit's names);
    labels : (M,) the labels they were read under in the C3D (prefix and lab labels included;
    ``""`` for a marker of the set the file does not have);
    xyz : (F, M, 3) float metres, world; NaN = not observed or removed by the cleaning
    (sample ``i`` is at capture time ``(first_frame + i) / rate_hz`` s);
    raw_observed : (F, M) bool, the sample was present in the file before cleaning;
    repair : (F, M) int8, what the cleaning did to the sample (0 = nothing; code = index in
    ``repair_codes``, e.g. ghost, spike, swap_removed, implausible_speed, unswapped);
    repair_codes : (R,) str, the code names; rate_hz, first_frame (0-based: the C3D frame
    number - 1), unit_scale (the factor from the file's units to metres) : scalars;
    source : the C3D's file name (for messages).
    """

    KIND: ClassVar[str] = "capture_markers"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "markers"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("names", "U", "M"),
        FieldSpec("labels", "U", "M"),
        FieldSpec("xyz", "f", "F M 3", doc="metres, NaN = not observed"),
        FieldSpec("raw_observed", "b", "F M"),
        FieldSpec("repair", "iu", "F M"),
        FieldSpec("repair_codes", "U", "R"),
        FieldSpec("rate_hz", "f", "", finite=True),
        FieldSpec("first_frame", "iu", ""),
        FieldSpec("unit_scale", "f", "", finite=True),
        FieldSpec("source", "U", ""),
    )

    names: np.ndarray
    labels: np.ndarray
    xyz: np.ndarray
    raw_observed: np.ndarray
    repair: np.ndarray
    repair_codes: np.ndarray
    rate_hz: float | np.ndarray
    first_frame: int | np.ndarray
    unit_scale: float | np.ndarray
    source: str | np.ndarray

    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(str(n) for n in self.names)

    @property
    def observed(self) -> np.ndarray:
        """(F, M) bool: the sample is evidence (present after cleaning)."""
        return np.all(np.isfinite(self.xyz), axis=-1)

    @property
    def repaired(self) -> np.ndarray:
        """(F, M) bool: the cleaning changed the sample (removed or un-swapped)."""
        return np.asarray(self.repair) != 0

    def capture(self):
        """The cleaned markers as ``formats.c3d.Markers`` (what the fitting code takes)."""
        from formats.c3d import Markers as C3DMarkers

        return C3DMarkers(self.marker_names, np.array(self.xyz, dtype=float), float(self.rate_hz),
                          int(self.first_frame), None)

    def repairs_by_code(self) -> dict[str, int]:
        """Samples per repair code (only codes that occur, ``none`` left out)."""
        codes = [str(c) for c in self.repair_codes]
        counts = np.bincount(np.asarray(self.repair, np.int64).ravel(), minlength=len(codes))
        return {codes[i]: int(n) for i, n in enumerate(counts) if i and n}

    def markers_repaired_as(self, *codes: str) -> set[str]:
        """Names of the markers with a sample repaired as one of ``codes`` (e.g.
        ``"unswapped", "swap_removed"``: the markers the cleaning found in a label swap)."""
        ids = [i for i, c in enumerate(self.repair_codes) if str(c) in codes]
        hit = np.isin(np.asarray(self.repair), ids).any(axis=0)
        return {n for n, h in zip(self.marker_names, hit, strict=True) if h}

    def _check(self, file: Path) -> None:
        names = self.marker_names
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ArtifactError(file, "names", f"duplicate names {dup}")
        if not float(self.rate_hz) > 0:
            raise ArtifactError(file, "rate_hz", f"must be > 0, got {float(self.rate_hz)}")
        if int(self.first_frame) < 0:
            raise ArtifactError(file, "first_frame", f"must be >= 0, got {int(self.first_frame)}")
        r = np.asarray(self.repair, np.int64)
        if r.size and (r.min() < 0 or r.max() >= len(self.repair_codes)):
            raise ArtifactError(file, "repair", f"codes outside 0..{len(self.repair_codes) - 1}")
        check_metres(np.nan_to_num(np.asarray(self.xyz, float)), file, "xyz", MAX_MARKER_M)
        fin = np.all(np.isfinite(self.xyz), axis=-1)
        if np.any(fin & ~np.asarray(self.raw_observed, bool)):
            f = int(np.argmax((fin & ~np.asarray(self.raw_observed, bool)).any(axis=1)))
            raise ArtifactError(file, "xyz", "a sample observed after cleaning but not in the "
                                "file (cleaning never invents samples)", f)


@dataclass(frozen=True, eq=False)
class CameraRig(TypedArtifact):
    """The sequence's calibrated cameras (recipe order), as ``calib.Camera`` fields stacked:
    names (C,), f (C, 2), c (C, 2), k (C, 3), p (C, 2), R (C, 3, 3) cam_from_world,
    T (C, 3) camera centres (world, metres), width/height (C,) pixels, model (C,) lens model
    (``h36m`` or ``opencv``), source (C,) the calibration file names (for messages)."""

    KIND: ClassVar[str] = "camera_rig"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "rig"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("names", "U", "C"),
        FieldSpec("f", "f", "C 2", finite=True),
        FieldSpec("c", "f", "C 2", finite=True),
        FieldSpec("k", "f", "C 3", finite=True),
        FieldSpec("p", "f", "C 2", finite=True),
        FieldSpec("R", "f", "C 3 3", finite=True),
        FieldSpec("T", "f", "C 3", finite=True),
        FieldSpec("width", "iu", "C"),
        FieldSpec("height", "iu", "C"),
        FieldSpec("model", "U", "C"),
        FieldSpec("source", "U", "C"),
    )

    names: np.ndarray
    f: np.ndarray
    c: np.ndarray
    k: np.ndarray
    p: np.ndarray
    R: np.ndarray
    T: np.ndarray
    width: np.ndarray
    height: np.ndarray
    model: np.ndarray
    source: np.ndarray

    @classmethod
    def from_cameras(cls, cams, sources=None) -> CameraRig:
        """From ``calib.Camera`` objects (and the files they were read from)."""
        cams = list(cams)
        return cls(names=np.array([c.name for c in cams], dtype=str),
                   f=np.array([c.f for c in cams], float).reshape(-1, 2),
                   c=np.array([c.c for c in cams], float).reshape(-1, 2),
                   k=np.array([c.k for c in cams], float).reshape(-1, 3),
                   p=np.array([c.p for c in cams], float).reshape(-1, 2),
                   R=np.array([c.R for c in cams], float).reshape(-1, 3, 3),
                   T=np.array([c.T for c in cams], float).reshape(-1, 3),
                   width=np.array([c.width for c in cams], np.int64),
                   height=np.array([c.height for c in cams], np.int64),
                   model=np.array([c.model for c in cams], dtype=str),
                   source=np.array([str(s) for s in (sources or [""] * len(cams))], dtype=str))

    def cameras(self, names=None) -> list:
        """``calib.Camera`` objects, all or those of ``names`` (in that order)."""
        from calib.camera import Camera

        ids = [str(n) for n in self.names]
        want = ids if names is None else [str(n) for n in names]
        out = []
        for n in want:
            if n not in ids:
                raise ArtifactError("rig.npz", "names", f"no camera {n!r} (has {ids})")
            i = ids.index(n)
            out.append(Camera(n, self.f[i], self.c[i], self.k[i], self.p[i], self.R[i], self.T[i],
                              int(self.width[i]), int(self.height[i]), str(self.model[i])))
        return out

    def _check(self, file: Path) -> None:
        ids = [str(n) for n in self.names]
        if len(set(ids)) != len(ids):
            raise ArtifactError(file, "names", f"duplicate camera ids {ids}")
        bad = [str(m) for m in self.model if str(m) not in CAMERA_MODELS]
        if bad:
            raise ArtifactError(file, "model", f"{bad} not in {CAMERA_MODELS}")
        if len(self.R):
            check_rotations(self.R, file, "R")
        check_metres(self.T, file, "T", per_frame=False)
        if np.any(np.asarray(self.f) <= 0):
            raise ArtifactError(file, "f", "focal lengths must be > 0")
        if np.any(np.asarray(self.width) <= 0) or np.any(np.asarray(self.height) <= 0):
            raise ArtifactError(file, "width", "image sizes must be > 0")
