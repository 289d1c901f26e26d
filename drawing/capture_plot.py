"""The capture stage's picture: per marker and sample, observed, missing or repaired."""
from __future__ import annotations

from pathlib import Path

import numpy as np

# constants
COLORS = {"missing": (1.0, 1.0, 1.0), "observed": (0.72, 0.75, 0.8), "repaired": (0.85, 0.15, 0.1)}
MAX_COLUMNS = 2000  # samples drawn per marker row (longer captures are binned; a bin shows
#                     repaired if any of its samples was, missing if all were)


def capture_plot(path: str | Path, raw_observed: np.ndarray, repaired: np.ndarray, names,
                 first_frame: int = 0, title: str = ""):
    """PNG: rows = markers, columns = samples (C3D frame numbers on the x axis: ``first_frame``
    is 0-based, the axis shows ``first_frame + i + 1``); grey observed, white missing, red
    repaired by the cleaning. Returns the matplotlib Figure (closed after saving)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs = np.asarray(raw_observed, bool)
    rep = np.asarray(repaired, bool)
    F, M = obs.shape
    step = max(1, int(np.ceil(F / MAX_COLUMNS)))
    n = int(np.ceil(F / step)) if F else 0
    pad = n * step - F
    o = np.pad(obs, ((0, pad), (0, 0))).reshape(n, step, M).any(axis=1) if F else obs
    r = np.pad(rep, ((0, pad), (0, 0))).reshape(n, step, M).any(axis=1) if F else rep
    img = np.ones((M, max(n, 1), 3))
    img[o.T] = COLORS["observed"]
    img[r.T] = COLORS["repaired"]
    fig, ax = plt.subplots(figsize=(10, 0.16 * M + 1.6))
    x0 = first_frame + 1
    ax.imshow(img, aspect="auto", interpolation="nearest",
              extent=(x0 - 0.5, x0 + n * step - 0.5, M - 0.5, -0.5))
    ax.set_yticks(range(M))
    ax.set_yticklabels([str(s) for s in names], fontsize=6)
    ax.set_xlabel("capture frame (C3D numbering)")
    ax.set_title(title or "markers observed (grey) and repaired (red)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return fig
