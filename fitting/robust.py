"""Robust losses for residual groups whose data can be wrong (mislabeled or swapped markers,
a keypoint on the wrong hand).

A loss acts on the squared norm ``s = |e|^2`` of one group of residuals (one marker's 3D error,
one keypoint's 2D error) with a scale ``sigma`` in the residual's units:

- Geman-McClure: ``rho(s) = sigma^2 s / (sigma^2 + s)``; quadratic near 0, saturates at
  ``sigma^2`` so a wrong marker pulls with a bounded force (redescending).
- Huber: ``rho(s) = s`` for ``|e| <= sigma``, ``2 sigma |e| - sigma^2`` beyond (convex, linear tail).
- ``l2``: ``rho(s) = s``.

The LM loop uses iteratively reweighted least squares: each group's rows are scaled by
``sqrt(rho'(s))`` at the current estimate, and steps are accepted on the robust cost
``sum rho(s)``.
"""
from __future__ import annotations

from typing import Literal

import numpy as np

Loss = Literal["l2", "geman_mcclure", "huber"]
LOSSES = ("l2", "geman_mcclure", "huber")


def rho(s: np.ndarray, loss: Loss, sigma: float) -> np.ndarray:
    """Robust cost of squared norms ``s (G,) >= 0``; same units as ``s``."""
    s = np.asarray(s, dtype=float)
    if loss == "l2":
        return s
    if sigma <= 0:
        raise ValueError(f"robust scale sigma must be > 0, got {sigma}")
    s2 = sigma * sigma
    if loss == "geman_mcclure":
        return s2 * s / (s2 + s)
    if loss == "huber":
        n = np.sqrt(s)
        return np.where(n <= sigma, s, 2.0 * sigma * n - s2)
    raise ValueError(f"unknown robust loss {loss!r} (known: {LOSSES})")


def weight(s: np.ndarray, loss: Loss, sigma: float) -> np.ndarray:
    """IRLS weight ``rho'(s)`` of squared norms ``s (G,)``; 1 near zero, in (0, 1]."""
    s = np.asarray(s, dtype=float)
    if loss == "l2":
        return np.ones_like(s)
    if sigma <= 0:
        raise ValueError(f"robust scale sigma must be > 0, got {sigma}")
    s2 = sigma * sigma
    if loss == "geman_mcclure":
        return (s2 / (s2 + s)) ** 2
    if loss == "huber":
        n = np.sqrt(s)
        return np.where(n <= sigma, 1.0, sigma / np.maximum(n, 1e-300))
    raise ValueError(f"unknown robust loss {loss!r} (known: {LOSSES})")
