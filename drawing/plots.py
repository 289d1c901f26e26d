"""Plots of fit quality (matplotlib, Agg canvas; no pyplot state)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from drawing import constants as C

# worst-frame labels: offsets tried (points from the marked point), in order, until a label's
# box keeps LABEL_GAP_PX from every label placed before it and stays inside the axes
# (above, then beside it on alternate sides, then higher, then below)
LABEL_OFFSETS_PT = tuple((dx, dy) for dy in (6, 16, 26, -14, 36, -24, 46)
                         for dx in (0, -45, 45, -90, 90))
LABEL_GAP_PX = 2.0

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


def _overlaps(box, others, gap: float) -> bool:
    return any(box.x0 < o.x1 + gap and o.x0 < box.x1 + gap and box.y0 < o.y1 + gap
               and o.y0 < box.y1 + gap for o in others)


def separate_labels(fig, texts, gap: float = LABEL_GAP_PX) -> None:
    """Move ``texts`` (annotations in ``offset points``, most important first) among
    ``LABEL_OFFSETS_PT`` so that no two bounding boxes come closer than ``gap`` pixels: each
    takes the first offset clear of the labels placed before it and inside its axes, else the
    first clear one, else the first. Run after ``tight_layout`` (the boxes are measured on
    the final layout)."""
    renderer = fig.canvas.get_renderer()
    placed = []

    def put(t, off):
        t.xyann = off
        t.set_va("bottom" if off[1] >= 0 else "top")
        return t.get_window_extent(renderer)

    for t in texts:
        inside = t.axes.get_window_extent(renderer)
        clear = None
        for off in LABEL_OFFSETS_PT:
            box = put(t, off)
            if _overlaps(box, placed, gap):
                continue
            if (box.x0 >= inside.x0 and box.x1 <= inside.x1 and box.y0 >= inside.y0
                    and box.y1 <= inside.y1):
                clear = off
                break
            clear = clear or off
        placed.append(put(t, clear or LABEL_OFFSETS_PT[0]))


def text_boxes(fig):
    """Display-pixel bounding boxes of every text drawn in ``fig``'s axes (tests: no two
    labels overlap)."""
    renderer = fig.canvas.get_renderer()
    return [t.get_window_extent(renderer) for ax in fig.axes for t in ax.texts]


def residual_plot(path: str | Path, res_mm: np.ndarray, fps: float, title: str,
                  frames: np.ndarray | None = None, worst: int = C.WORST_FRAMES):
    """PNG of per-frame marker residuals: median, p90 and max over the visible markers, on a
    logarithmic axis (residuals span ~0.5 mm to ~600 mm on real data), with the ``worst``
    frames of the max curve marked and labelled (``f<frame>: <mm> mm``); labels of close
    frames are moved apart (:func:`separate_labels`), never stacked on each other.

    res_mm: (F, M) marker residuals, mm, NaN where a marker is not seen; fps: frame rate of
    its rows (x axis in seconds); frames: (F,) frame numbers for the labels, in the capture's
    own numbering (callers pass the C3D frame number ``first_frame + sample + 1`` of a
    marker-only fit, the video frame otherwise; default 0..F-1).
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
        labels = [ax.annotate(f"f{frames[i]}: {curves['max'][i]:.0f} mm", (t[i], yi),
                              textcoords="offset points", xytext=LABEL_OFFSETS_PT[0],
                              ha="center", fontsize=7, color="crimson")
                  for i, yi in zip(top, y, strict=True)]
        ax.set_ylim(top=C.PLOT_HEADROOM * y.max())  # room for the labels on a log axis
    ax.set_xlabel("time (s)")
    ax.set_ylabel("marker residual (mm, log)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    if len(top):
        separate_labels(fig, labels)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return fig


def marker_residual_plot(path: str | Path, res_mm: np.ndarray, names, title: str,
                         frames: np.ndarray | None = None, warn_mm: float | None = None):
    """PNG of each marker's residuals over the sequence on a logarithmic axis: per marker (x)
    the median (dot), the p90 (bar top) and the max (cross) over its visible frames, with
    the frame of its max written over the worst markers (``f<frame>``, moved apart when they
    would overlap: :func:`separate_labels`). Markers whose median
    exceeds ``warn_mm`` are drawn in red, with the threshold as a dashed line: one glance
    shows a lost arm that a median over all markers hides.

    res_mm: (F, M) mm, NaN where not seen; names: (M,) labels; frames: (F,) frame numbers for
    the labels in the capture's own numbering (as :func:`residual_plot`; default 0..F-1). Writes ``path``, returns the ``Figure`` (``fig.axes[0]``).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    res = np.asarray(res_mm, float)
    names = [str(n) for n in names]
    if res.ndim != 2 or res.shape[1] != len(names):
        raise ValueError(f"res_mm: expected (F, {len(names)}), got {res.shape}")
    F, M = res.shape
    frames = np.arange(F) if frames is None else np.asarray(frames)
    if frames.shape != (F,):
        raise ValueError(f"frames: expected ({F},), got {frames.shape}")
    seen = np.isfinite(res).any(axis=0)
    med, p90, mx = (np.full(M, np.nan) for _ in range(3))
    arg = np.zeros(M, dtype=np.int64)
    if seen.any():
        r = res[:, seen]
        med[seen] = np.nanmedian(r, axis=0)
        p90[seen] = np.nanpercentile(r, 90, axis=0)
        mx[seen] = np.nanmax(r, axis=0)
        arg[seen] = np.nanargmax(r, axis=0)
    fig = Figure(figsize=(max(C.PLOT_SIZE_IN[0], 0.22 * M), C.PLOT_SIZE_IN[1] + 0.6),
                 dpi=C.PLOT_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(M)
    bad = np.zeros(M, bool) if warn_mm is None else np.nan_to_num(med) > warn_mm
    floor = C.RESIDUAL_FLOOR_MM
    for sel, col in ((~bad, "tab:blue"), (bad, "crimson")):
        if sel.any():
            ax.vlines(x[sel], np.maximum(med[sel], floor), np.maximum(p90[sel], floor),
                      color=col, lw=3, alpha=0.6)
            ax.plot(x[sel], np.maximum(med[sel], floor), "o", color=col, ms=4)
            ax.plot(x[sel], np.maximum(mx[sel], floor), "x", color=col, ms=4)
    if warn_mm is not None:
        ax.axhline(warn_mm, ls="--", color="crimson", lw=0.8, label=f"warning: median > {warn_mm:g} mm")
    worst = np.argsort(-np.nan_to_num(mx, nan=-1))[:C.WORST_FRAMES]
    labels = [ax.annotate(f"f{frames[arg[m]]}", (m, max(mx[m], floor)),
                          textcoords="offset points", xytext=LABEL_OFFSETS_PT[0], ha="center",
                          fontsize=6, rotation=90, color="crimson")  # one marker column wide
              for m in worst if np.isfinite(mx[m])]
    for m in np.flatnonzero(~seen):
        ax.annotate("not seen", (m, floor), rotation=90, fontsize=6, ha="center", va="bottom")
    ax.set_yscale("log")
    if np.isfinite(mx).any():  # headroom for the upright frame labels
        ax.set_ylim(floor, C.PLOT_HEADROOM ** 2 * np.nanmax(np.maximum(mx, floor)))
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=90, fontsize=7)
    ax.set_ylabel("residual (mm, log): median, p90, max")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3, which="both", axis="y")
    if warn_mm is not None:
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    separate_labels(fig, labels)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return fig


def partner_fit_plot(path: str | Path, frames: np.ndarray, fps: float, reproj_px: np.ndarray,
                     penetration_mm: np.ndarray, contact_mm: np.ndarray, ground_mm: np.ndarray,
                     valid: np.ndarray, title: str, views: list[str] | None = None):
    """PNG of the partner fit's per-frame figures over the sequence, two panels sharing the
    time axis (seconds, from the video ``frames`` and ``fps``; frames not valid shaded):
    top, the median 2D reprojection error per view (pixels, ``reproj_px (F, C)``, NaN where
    the view saw nothing); bottom, in mm, the deepest penetration into the other body,
    the contact distance in contact frames and the depth below the ground plane
    (``(F,)`` each, NaN = not computed). Writes ``path``, returns the ``Figure``
    (``fig.axes[0]``, ``fig.axes[1]``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    frames = np.asarray(frames)
    F = len(frames)
    rp = np.asarray(reproj_px, float)
    if rp.ndim != 2 or len(rp) != F:
        raise ValueError(f"reproj_px: expected ({F}, C), got {rp.shape}")
    for name, a in (("penetration_mm", penetration_mm), ("contact_mm", contact_mm),
                    ("ground_mm", ground_mm), ("valid", valid)):
        if np.shape(a) != (F,):
            raise ValueError(f"{name}: expected ({F},), got {np.shape(a)}")
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps}")
    t = frames / fps
    fig = Figure(figsize=(C.PLOT_SIZE_IN[0], 2 * C.PLOT_SIZE_IN[1]), dpi=C.PLOT_DPI)
    FigureCanvasAgg(fig)
    ax0, ax1 = fig.subplots(2, 1, sharex=True)
    views = views or [f"view {c}" for c in range(rp.shape[1])]
    for c in range(rp.shape[1]):
        ax0.plot(t, rp[:, c], lw=1, label=str(views[c]))
    for name, y in (("penetration", penetration_mm), ("contact distance", contact_mm),
                    ("below ground", ground_mm)):
        ax1.plot(t, np.asarray(y, float), lw=1, label=name)
    bad = ~np.asarray(valid, bool)
    dt = 0.5 * (np.median(np.diff(t)) if F > 1 else 1.0 / fps)
    for ax in (ax0, ax1):
        for i in np.flatnonzero(bad):
            ax.axvspan(t[i] - dt, t[i] + dt, color="0.85", lw=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    ax0.set_ylabel("reprojection (px, median)")
    ax1.set_ylabel("mm")
    ax1.set_xlabel("time (s); grey: frames not valid")
    ax0.set_title(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return fig
