"""Plots of fit quality (matplotlib, Agg canvas; no pyplot state)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from drawing import constants as C


def worst_frames(values: np.ndarray, count: int, separation: int) -> np.ndarray:
    """Indices of the ``count`` largest finite ``values`` (F,), largest first, each at least
    ``separation`` frames from the ones before (one per spike)."""
    v = np.asarray(values, float)
    picked: list[int] = []
    for i in np.argsort(-np.where(np.isfinite(v), v, -np.inf), kind="stable"):
        if len(picked) >= count or not np.isfinite(v[i]):
            break
        if all(abs(int(i) - p) >= separation for p in picked):
            picked.append(int(i))
    return np.array(picked, dtype=np.int64)


def residual_plot(path: str | Path, res_mm: np.ndarray, fps: float, title: str,
                  frames: np.ndarray | None = None, worst: int = C.WORST_FRAMES):
    """PNG of per-frame marker residuals: median, p90 and max over the visible markers, on a
    logarithmic axis (residuals span ~0.5 mm to ~600 mm on real data), with the ``worst``
    frames of the max curve marked and labelled (``f<frame>: <mm> mm``).

    res_mm: (F, M) marker residuals, mm, NaN where a marker is not seen; fps: frame rate of
    its rows (x axis in seconds); frames: (F,) frame numbers for the labels (default 0..F-1).
    Values below constants.RESIDUAL_FLOOR_MM are drawn on the floor. Writes ``path`` and
    returns the matplotlib ``Figure`` (its one axes: ``fig.axes[0]``).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    res = np.asarray(res_mm, float)
    if res.ndim != 2:
        raise ValueError(f"res_mm: expected (F, M), got {res.shape}")
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps}")
    F = len(res)
    frames = np.arange(F) if frames is None else np.asarray(frames)
    if frames.shape != (F,):
        raise ValueError(f"frames: expected ({F},), got {frames.shape}")
    t = np.arange(F) / fps
    fig = Figure(figsize=C.PLOT_SIZE_IN, dpi=C.PLOT_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    seen = np.isfinite(res).any(axis=1)
    curves = {}
    with np.errstate(all="ignore"):
        for q, lab in ((50, "median"), (90, "p90"), (100, "max")):
            y = np.full(F, np.nan)
            if seen.any():
                y[seen] = np.nanpercentile(res[seen], q, axis=1)
            curves[lab] = y
            ax.plot(t, np.maximum(y, C.RESIDUAL_FLOOR_MM), label=lab, lw=1)
    ax.set_yscale("log")
    top = worst_frames(curves["max"], worst, max(1, int(round(C.WORST_SEPARATION_S * fps))))
    if len(top):
        y = np.maximum(curves["max"][top], C.RESIDUAL_FLOOR_MM)
        ax.plot(t[top], y, "v", color="crimson", ms=5, label=f"worst {len(top)}")
        for i, yi in zip(top, y, strict=True):
            ax.annotate(f"f{frames[i]}: {curves['max'][i]:.0f} mm", (t[i], yi),
                        textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7,
                        color="crimson")
        ax.set_ylim(top=C.PLOT_HEADROOM * y.max())  # room for the labels on a log axis
    ax.set_xlabel("time (s)")
    ax.set_ylabel("marker residual (mm, log)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return fig
