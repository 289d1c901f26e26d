"""Stage ``silhouettes``' typed output: per video frame and camera the people mask (background
subtraction against the clean plate) and the partner's mask (the people less the wearer's
fitted body), bit-packed at a reduced resolution (``masks.npz``).

A mask pixel ``(i, j)`` covers the image pixels whose centres map to it at ``scale`` (mask =
``round(image size * scale)``): the image pixel of its centre is ``((j + 0.5) / scale - 0.5,
(i + 0.5) / scale - 0.5)`` (:meth:`Silhouettes.pixel_centres`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import ArtifactError, FieldSpec, TypedArtifact

#: where a view's people mask comes from (``source`` codes)
SOURCES = ("clean_plate", "mog2")


@dataclass(frozen=True, eq=False)
class Silhouettes(TypedArtifact):
    """Masks of the people per frame and camera.

    frames : (F,) int video frame numbers; cameras : (C,) str camera ids (the recipe's order);
    scale : mask pixels per image pixel (0.5: half resolution); size : (2,) int mask
    ``(height, width)``; people : (F, C, B) uint8 ``np.packbits`` of the (height, width) bool
    people mask (row-major); partner : (F, C, B) the same for the partner (people less the
    wearer's rendered body); people_fraction / partner_fraction : (F, C) float share of the
    image each covers; wearer_cover : (F, C) share of the wearer's rendered body inside the
    people mask (NaN: no wearer in the view); usable : (F, C) bool the view's mask is
    plausible (not empty, not most of the image, holding the wearer: the term uses only these); source : (C,) int8 index into :data:`SOURCES`."""

    KIND: ClassVar[str] = "silhouettes"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "masks"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("frames", "iu", "F"),
        FieldSpec("cameras", "U", "C"),
        FieldSpec("scale", "f", "", finite=True),
        FieldSpec("size", "iu", "2"),
        FieldSpec("people", "u", "F C B"),
        FieldSpec("partner", "u", "F C B"),
        FieldSpec("people_fraction", "f", "F C", finite=True),
        FieldSpec("partner_fraction", "f", "F C", finite=True),
        FieldSpec("wearer_cover", "f", "F C"),
        FieldSpec("usable", "b", "F C"),
        FieldSpec("source", "iu", "C"),
    )

    frames: np.ndarray
    cameras: np.ndarray
    scale: float | np.ndarray
    size: np.ndarray
    people: np.ndarray
    partner: np.ndarray
    people_fraction: np.ndarray
    partner_fraction: np.ndarray
    wearer_cover: np.ndarray
    usable: np.ndarray
    source: np.ndarray

    def _check(self, file: Path) -> None:
        if not 0 < float(self.scale) <= 1:
            raise ArtifactError(file, "scale", f"expected in (0, 1], got {float(self.scale)}")
        h, w = (int(v) for v in self.size)
        if h < 1 or w < 1 or (h * w + 7) // 8 != self.people.shape[-1]:
            raise ArtifactError(file, "size", f"({h}, {w}) does not match {self.people.shape[-1]} "
                                "packed bytes per mask")
        if len(self.frames) > 1 and not np.all(np.diff(self.frames) > 0):
            raise ArtifactError(file, "frames", "not increasing")
        if np.any(np.asarray(self.source) >= len(SOURCES)):
            raise ArtifactError(file, "source", f"codes beyond {SOURCES}")

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.size[0]), int(self.size[1])

    def camera(self, name: str) -> int | None:
        """Index of camera ``name`` (None: not in the masks)."""
        hits = np.flatnonzero(np.asarray(self.cameras) == str(name))
        return int(hits[0]) if len(hits) else None

    def index(self, frame: int) -> int | None:
        """Index of video frame ``frame`` (None: no masks for it)."""
        i = int(np.searchsorted(self.frames, frame))
        return i if i < len(self.frames) and int(self.frames[i]) == int(frame) else None

    def mask(self, i: int, c: int, which: str = "people") -> np.ndarray:
        """(height, width) bool mask of frame index ``i``, camera index ``c`` (``which``:
        ``"people"`` or ``"partner"``)."""
        h, w = self.shape
        bits = getattr(self, which)[i, c]
        return np.unpackbits(bits, count=h * w).reshape(h, w).astype(bool)

    def pixel_centres(self, ij: np.ndarray) -> np.ndarray:
        """(N, 2) image pixels (u, v) of mask pixels ``ij`` (N, 2) (row, column)."""
        s = float(self.scale)
        ij = np.asarray(ij, float)
        return np.stack([(ij[:, 1] + 0.5) / s - 0.5, (ij[:, 0] + 0.5) / s - 0.5], axis=1)

    def mask_pixels(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) mask (row, column) floats of image pixels ``uv`` (N, 2)."""
        s = float(self.scale)
        uv = np.asarray(uv, float)
        return np.stack([(uv[:, 1] + 0.5) * s - 0.5, (uv[:, 0] + 0.5) * s - 0.5], axis=1)


def pack(mask: np.ndarray) -> np.ndarray:
    """``np.packbits`` of a bool mask, flattened row-major."""
    return np.packbits(np.asarray(mask, bool).reshape(-1))
