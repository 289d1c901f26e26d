"""Typed artifacts: one frozen dataclass per artifact kind, owning its file layout, its checks
on load and save, and its version (conventions in ``artifacts/base.py``).

- :class:`ShapeFit` (``shape.npz`` of shape_fit), :class:`BodyFit` (``fit.npz`` of marker_fit,
  with the per-frame ``valid`` mask and ``invalid_reason``), ``Keypoints2D``
  (``keypoints.npz`` of keypoints, ``artifacts/keypoints.py``).
"""
from __future__ import annotations

import importlib.util

from artifacts.base import ArtifactError, FieldSpec, TypedArtifact
from artifacts.body_fit import INVALID_REASONS, REASON_CODE, BodyFit
from artifacts.shape import ShapeFit

__all__ = ["ArtifactError", "FieldSpec", "TypedArtifact", "ShapeFit", "BodyFit",
           "INVALID_REASONS", "REASON_CODE"]

if importlib.util.find_spec("artifacts.keypoints") is not None:
    from artifacts.keypoints import Keypoints2D  # noqa: F401

    __all__.append("Keypoints2D")
