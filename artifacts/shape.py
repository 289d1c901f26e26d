"""``ShapeFit``: stage shape_fit's ``shape.npz``, a subject's body shape and marker placement."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import ArtifactError, FieldSpec, TypedArtifact, check_range

# constants
MAX_MARKER_OFFSET_M = 0.1  # a marker's offset off the skin; 9.5 (mm) is not metres
BARY_TOL = 1e-6
SHAPE_SOURCES = ("scan", "markers", "mean", "given")  # given: by the caller (e.g. a known truth)
PLACEMENT_SOURCES = ("template", "refined", "given")


@dataclass(frozen=True, eq=False)
class ShapeFit(TypedArtifact):
    """A subject's shape and marker placement on the body model's surface.

    betas : (S,) shape coefficients of the body model (S <= model.num_betas, zero-padded).
    marker_names : (M,) str; marker_face : (M,) int face index of the model's mesh;
    marker_bary : (M, 3) barycentric coordinates on that face (>= 0, sum 1);
    marker_offset : (M,) metres along the outward rest-pose face normal.
    shape_source : where the shape comes from, one of ``SHAPE_SOURCES`` (``scan``: fitted to
    the subject's scan; ``markers``: fitted to marker captures (MoSh++ stage I); ``mean``: the
    mean shape; ``given``: supplied by the caller). placement_source : ``template`` (the marker
    set as defined), ``refined`` (fitted to captures) or ``given``.
    """

    KIND: ClassVar[str] = "shape_fit"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "shape"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("betas", "f", "S", finite=True),
        FieldSpec("marker_names", "U", "M"),
        FieldSpec("marker_face", "iu", "M"),
        FieldSpec("marker_bary", "f", "M 3", finite=True),
        FieldSpec("marker_offset", "f", "M", finite=True, doc="metres"),
        FieldSpec("shape_source", "U", ""),
        FieldSpec("placement_source", "U", ""),
    )

    betas: np.ndarray
    marker_names: np.ndarray
    marker_face: np.ndarray
    marker_bary: np.ndarray
    marker_offset: np.ndarray
    shape_source: str | np.ndarray
    placement_source: str | np.ndarray

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(str(n) for n in self.marker_names)

    def _check(self, file: Path) -> None:
        src = str(self.shape_source)
        if src not in SHAPE_SOURCES:
            raise ArtifactError(file, "shape_source", f"{src!r} is not one of {SHAPE_SOURCES}")
        src = str(self.placement_source)
        if src not in PLACEMENT_SOURCES:
            raise ArtifactError(file, "placement_source",
                                f"{src!r} is not one of {PLACEMENT_SOURCES}")
        names = self.names
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ArtifactError(file, "marker_names", f"duplicate names {dup}")
        if np.any(self.marker_face < 0):
            raise ArtifactError(file, "marker_face", "negative face index")
        check_range(self.marker_bary, file, "marker_bary", -BARY_TOL, 1 + BARY_TOL,
                    " (barycentric coordinates)", per_frame=False)
        s = self.marker_bary.sum(axis=1)
        if len(s) and np.abs(s - 1).max() > BARY_TOL:
            m = int(np.argmax(np.abs(s - 1)))
            raise ArtifactError(file, "marker_bary", f"marker {names[m]}: coordinates sum to "
                                f"{s[m]:.6g}, not 1")
        big = np.abs(self.marker_offset) >= MAX_MARKER_OFFSET_M
        if big.any():
            m = int(np.argmax(big))
            raise ArtifactError(file, "marker_offset", f"marker {names[m]}: "
                                f"{float(self.marker_offset[m]):.4g} >= {MAX_MARKER_OFFSET_M} "
                                "m off the skin: not metres (millimetres?)")
