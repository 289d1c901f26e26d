"""What an optical marker system records: the true marker positions plus noise, with gaps
where markers are occluded."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from studio import constants as C


@dataclass(frozen=True)
class MocapOptions:
    """noise_sd_m: per-axis Gaussian noise, metres; gap_fraction: share of markers that get
    gaps; gaps_per_marker: (min, max) gaps on an affected marker; gap_len: (min, max) run
    length in samples."""

    noise_sd_m: float = C.MARKER_NOISE_SD_M
    gap_fraction: float = C.MARKER_GAP_FRACTION
    gaps_per_marker: tuple[int, int] = C.MARKER_GAPS_PER_MARKER
    gap_len: tuple[int, int] = C.MARKER_GAP_LEN


def observe_markers(true_xyz: np.ndarray, rng: np.random.Generator,
                    opts: MocapOptions = MocapOptions()) -> tuple[np.ndarray, np.ndarray]:
    """true_xyz: (F, M, 3) metres, world. Returns (observed (F, M, 3) with NaN in gaps,
    gap mask (F, M) bool). Gaps never cover a whole trajectory: runs are at most F // 2 long."""
    F, M, _ = true_xyz.shape
    obs = true_xyz + rng.normal(0.0, opts.noise_sd_m, true_xyz.shape)
    gap = np.zeros((F, M), bool)
    n_aff = int(round(opts.gap_fraction * M))
    for m in rng.choice(M, size=n_aff, replace=False):
        for _ in range(rng.integers(opts.gaps_per_marker[0], opts.gaps_per_marker[1] + 1)):
            hi = min(opts.gap_len[1], max(opts.gap_len[0], F // 2))
            L = int(rng.integers(min(opts.gap_len[0], hi), hi + 1))
            s = int(rng.integers(0, max(1, F - L)))
            gap[s:s + L, m] = True
    obs[gap] = np.nan
    return obs, gap
