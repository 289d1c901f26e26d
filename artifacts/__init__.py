"""Typed artifacts: one frozen dataclass per artifact kind, owning its file layout, its checks
on load and save, and its version (conventions in ``artifacts/base.py``).

- capture: ``Markers`` (``markers.npz``: the cleaned capture, repairs per sample) and
  :class:`CameraRig` (``rig.npz``; ``artifacts/capture.py``);
- :class:`ShapeFit` (``shape.npz`` of shape_fit), :class:`BodyFit` (``fit.npz`` of marker_fit,
  with the per-frame ``valid`` mask and ``invalid_reason``), :class:`FitSummary`
  (``summary.json`` of marker_fit and partner_fit: what the export republishes), ``Keypoints2D``
  (``keypoints.npz`` of keypoints, ``artifacts/keypoints.py``);
- convert: :class:`SMPLXFit` (``smplx.npz``), :class:`SurfaceCorrespondence`
  (``correspondence.npz``), :class:`ConversionReport` (``report.json``;
  ``artifacts/smplx_fit.py``); qa: :class:`QAResult` (``flags.json`` + ``qa.npz``,
  :class:`QAMetrics`; ``artifacts/qa.py``); export: :class:`SequenceExport` (``export.json`` +
  ``figures.json``, :class:`SequenceFigures`; ``artifacts/export.py``); release:
  :class:`Release` (``verification.json`` + the datasheet; ``artifacts/release.py``). The JSON
  ones are :class:`JsonArtifact` (``artifacts/base.py``).
"""
from __future__ import annotations

import importlib.util

from artifacts.base import ArtifactError, FieldSpec, JsonArtifact, TypedArtifact
from artifacts.body_fit import INVALID_REASONS, REASON_CODE, BodyFit
from artifacts.capture import CameraRig
from artifacts.export import SequenceExport, SequenceFigures
from artifacts.fit_summary import FitSummary
from artifacts.qa import QAMetrics, QAResult
from artifacts.release import Release
from artifacts.shape import ShapeFit
from artifacts.smplx_fit import ConversionReport, SMPLXFit, SurfaceCorrespondence

__all__ = ["ArtifactError", "FieldSpec", "TypedArtifact", "JsonArtifact", "ShapeFit", "BodyFit",
           "INVALID_REASONS", "REASON_CODE", "SMPLXFit", "SurfaceCorrespondence",
           "ConversionReport", "QAMetrics", "QAResult", "SequenceExport", "SequenceFigures",
           "Release", "CameraRig", "FitSummary"]

if importlib.util.find_spec("artifacts.keypoints") is not None:
    from artifacts.keypoints import Keypoints2D  # noqa: F401

    __all__.append("Keypoints2D")
