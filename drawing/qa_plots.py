"""The QA figure of one sequence: the per-frame metric curves (``qa.metrics`` names) in one
panel per metric family, threshold lines dashed, the flagged spans shaded and labelled
(matplotlib, Agg canvas; no pyplot state).

Families, top to bottom (a family whose series are all NaN or absent is left out):

========================  ===============================================================
markers                   ``wearer.marker_median_mm``, ``wearer.marker_max_mm``
reprojection <group>      ``<person>.reproj_<group>_px.<cam>``: one line per person and
                          view (colour: the view; wearer solid, partner dotted), one panel
                          per keypoint group (body, hands, face)
sync                      ``sync_offset_frames.<cam>``
interpenetration          ``penetration_mm`` and ``penetration_volume_cm3`` (right axis)
self-penetration          ``<person>.self_penetration_mm``
ground + skating          ``<person>.ground_penetration_mm``, ``<person>.foot_skate_m_s``
                          (right axis)
contact                   ``contact_gap_mm``, ``unexpected_contact_mm``
jerk                      ``<person>.jerk_m_s3``
not valid                 ``<person>.not_valid``
other                     any other name
========================  ===============================================================

x: video frame (bottom axis), seconds on the top axis (``frame / fps``). A panel with two
units draws the second on a right-hand axis. NaN values are gaps in the curves (an isolated
finite value between gaps is drawn as a dot).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from drawing import qa_constants as Q

#: (family key, panel title, predicate on a metric name), in panel order.
_FAMILIES = (
    ("markers", "markers", lambda n: ".marker_" in n or n.startswith("marker_")),
    ("reproj", "reprojection", lambda n: ".reproj_" in n or n.startswith("reproj_")),
    ("sync", "sync", lambda n: n.startswith("sync_offset")),
    ("interpenetration", "interpenetration + volume",
     lambda n: n in ("penetration_mm", "penetration_volume_cm3")),
    ("self", "self-penetration", lambda n: n.endswith("self_penetration_mm")),
    ("ground", "ground + skating",
     lambda n: n.endswith("ground_penetration_mm") or n.endswith("foot_skate_m_s")),
    ("contact", "contact", lambda n: n in ("contact_gap_mm", "unexpected_contact_mm")),
    ("jerk", "jerk", lambda n: n.endswith("jerk_m_s3")),
    ("not_valid", "not valid", lambda n: n.endswith("not_valid")),
)
_REPROJ = re.compile(r"^(?:(?P<person>[^.]+)\.)?reproj_(?P<group>[a-z0-9]+)_px(?:\.(?P<cam>.+))?$")
_UNIT_OF_SUFFIX = (("_mm", "mm"), ("_px", "px"), ("_cm3", "cm3"), ("_m_s3", "m/s3"),
                   ("_m_s", "m/s"), ("_frames", "frames"))


def metric_family(name: str) -> tuple[str, str]:
    """(panel key, panel title) of a metric name: reprojection names get one panel per keypoint
    group (``reproj.body``, ...), unknown names the ``other`` panel."""
    for key, title, pred in _FAMILIES:
        if pred(name):
            if key == "reproj":
                m = _REPROJ.match(name)
                g = m.group("group") if m else "all"
                return f"reproj.{g}", f"reprojection {g}"
            return key, title
    return "other", "other"


def _unit(name: str, units: dict[str, str]) -> str:
    """The unit of a metric: ``units[name]``, else from its name's suffix (``_mm``...)."""
    if name in units:
        return str(units[name])
    for suf, u in _UNIT_OF_SUFFIX:
        if re.search(re.escape(suf) + r"(\.|$)", name):
            return u
    return ""


def _cam_of(name: str) -> str | None:
    """The view a per-view metric is about (``<person>.reproj_<g>_px.<cam>``,
    ``sync_offset_frames.<cam>``), else None."""
    m = _REPROJ.match(name)
    if m:
        return m.group("cam")
    if name.startswith("sync_offset") and "." in name:
        return name.split(".", 1)[1]
    return None


def _style(name: str, panel: str, index: int, cams: list[str]):
    """Colour and line style of one series: reprojection and sync lines coloured by view,
    the partner dotted."""
    import matplotlib as mpl

    cycle = mpl.rcParams["axes.prop_cycle"].by_key()["color"]
    cam = _cam_of(name)
    if (panel.startswith("reproj") or panel == "sync") and cam in cams:
        col = cycle[cams.index(cam) % len(cycle)]
    else:
        col = cycle[index % len(cycle)]
    return col, (":" if name.startswith("partner.") else "-")


def _label(name: str, panel: str) -> str:
    """Legend text: per-view series as ``<person> <cam>`` (the panel names the metric)."""
    m = _REPROJ.match(name)
    if m and panel.startswith("reproj"):
        return " ".join(p for p in (m.group("person"), m.group("cam")) if p) or name
    if panel == "sync" and _cam_of(name):
        return _cam_of(name)
    return name


def _plot_series(ax, x, y, col, ls, label, steps=False):
    ax.plot(x, y, color=col, ls=ls, lw=1.1, label=label,
            drawstyle="steps-mid" if steps else "default")
    fin = np.isfinite(y)
    prev = np.r_[False, fin[:-1]]
    nxt = np.r_[fin[1:], False]
    lone = fin & ~prev & ~nxt  # a value between two gaps: no line segment shows it
    if lone.any():
        ax.plot(x[lone], y[lone], ".", color=col, ms=3)


def qa_figure(frames: np.ndarray, fps: float, values: dict[str, np.ndarray],
              units: dict[str, str], thresholds: dict[str, float],
              spans: list[tuple[int, int, str]], title: str):
    """The matplotlib ``Figure`` of :func:`qa_plot` (module doc); its panels' main axes are
    ``fig.qa_axes`` (list, top to bottom; ``fig.qa_panels`` their family keys)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import blended_transform_factory

    frames = np.asarray(frames)
    if frames.ndim != 1 or len(frames) == 0:
        raise ValueError(f"frames: expected (F,) with F > 0, got {frames.shape}")
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps}")
    F = len(frames)
    x = frames.astype(float)
    series: dict[str, np.ndarray] = {}
    for name, v in values.items():
        v = np.asarray(v, float)
        if v.shape != (F,):
            raise ValueError(f"values[{name!r}]: expected ({F},), got {v.shape}")
        series[name] = v
    for s in spans:
        if len(s) != 3 or not s[0] <= s[1]:
            raise ValueError(f"spans: expected (start, end, label) with start <= end, got {s!r}")
    # panels in family order, keeping only series with data
    order = [k for k, _, _ in _FAMILIES]
    panels: dict[str, tuple[str, list[str]]] = {}
    for name, v in series.items():
        if not np.isfinite(v).any():
            continue
        key, ptitle = metric_family(name)
        panels.setdefault(key, (ptitle, []))[1].append(name)

    def rank(key):
        base = key.split(".")[0]
        grp = {"body": 0, "hands": 1, "face": 2}.get(key.split(".")[1], 3) if "." in key else 0
        return (order.index(base) if base in order else len(order), grp, key)

    keys = sorted(panels, key=rank)
    cams = []
    for name in series:
        cam = _cam_of(name)
        if cam is not None and cam not in cams:
            cams.append(cam)

    n = max(1, len(keys))
    fig = Figure(figsize=(Q.QA_PLOT_WIDTH_IN, Q.QA_PLOT_PANEL_IN * n + 1.4), dpi=Q.QA_PLOT_DPI)
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    step = float(np.median(np.diff(x))) if F > 1 else 1.0
    lo, hi = x[0] - 0.5 * step, x[-1] + 0.5 * step
    for ax in axes:
        for s0, s1, _lab in spans:
            ax.axvspan(s0 - 0.5 * step, s1 + 0.5 * step, color=Q.QA_SPAN_RGB, alpha=Q.QA_SPAN_ALPHA,
                       lw=0, zorder=0)
        ax.grid(alpha=0.3)
        ax.set_xlim(lo, hi)
    if not keys:
        axes[0].text(0.5, 0.5, "no per-frame metrics", ha="center", va="center",
                     transform=axes[0].transAxes)
    for ax, key in zip(axes, keys, strict=False):
        ptitle, names = panels[key]
        names = sorted(names, key=lambda nm: (0 if nm.startswith("wearer.") else
                                              1 if nm.startswith("partner.") else 2, nm))
        ulist = []
        for nm in names:
            u = _unit(nm, units)
            if u not in ulist:
                ulist.append(u)
        axis_of = {ulist[0]: ax}
        for u in ulist[1:]:
            axis_of[u] = ax.twinx() if len(axis_of) == 1 else axis_of[ulist[1]]
        handles_done: dict[tuple, list] = {}
        for i, nm in enumerate(names):
            u = _unit(nm, units)
            a = axis_of[u]
            col, ls = _style(nm, key, i, cams)
            _plot_series(a, x, series[nm], col, ls, _label(nm, key), steps=key == "not_valid")
            if nm in thresholds and np.isfinite(thresholds[nm]):
                handles_done.setdefault((u, float(thresholds[nm])), []).append(col)
        for (u, thr), cols in handles_done.items():
            a = axis_of[u]
            col = cols[0] if len(set(cols)) == 1 else Q.QA_THRESHOLD_RGB
            a.axhline(thr, ls="--", lw=0.9, color=col, zorder=1)
        for u, a in axis_of.items():
            a.set_ylabel(f"{ptitle}\n({u})" if a is ax and u else (f"({u})" if u else ptitle),
                         fontsize=8)
            a.tick_params(labelsize=7)
        hs, ls_ = [], []
        for a in dict.fromkeys(axis_of.values()):
            h, lab = a.get_legend_handles_labels()
            hs += h
            ls_ += lab
        if hs:
            ax.legend(hs, ls_, fontsize=6, loc="upper left", bbox_to_anchor=(1.06, 1.0),
                      ncol=1 + (len(hs) - 1) // 8, frameon=False, borderaxespad=0.0)
    top = axes[0]
    tr = blended_transform_factory(top.transData, top.transAxes)
    for s0, _s1, lab in spans:
        if lab:
            top.text(s0 - 0.5 * step, 1.02, str(lab), transform=tr, fontsize=6, rotation=0,
                     color=Q.QA_SPAN_TEXT_RGB, ha="left", va="bottom", clip_on=False)
    sec = top.secondary_xaxis("top", functions=(lambda f: f / fps, lambda t: t * fps))
    sec.set_xlabel("time (s)", fontsize=8)
    sec.tick_params(labelsize=7, pad=10)
    axes[-1].set_xlabel("video frame", fontsize=8)
    axes[-1].tick_params(labelsize=7)
    H = fig.get_figheight()
    fig.suptitle(title, fontsize=10, y=1 - 0.08 / H, va="top")
    fig.subplots_adjust(left=0.08, right=0.78, top=1 - 0.95 / H,
                        bottom=0.45 / H, hspace=0.12)
    fig.qa_axes = list(axes)
    fig.qa_panels = keys
    return fig


def qa_plot(path: Path, frames: np.ndarray, fps: float, values: dict[str, np.ndarray],
            units: dict[str, str], thresholds: dict[str, float],
            spans: list[tuple[int, int, str]], title: str) -> Path:
    """One PNG of the per-frame QA metrics of a sequence (module doc).

    frames: (F,) video frames of the rows; fps: the video's rate (top axis in seconds);
    values: metric name -> (F,) float, NaN = not applicable; units: name -> unit;
    thresholds: name -> the value it is flagged beyond (dashed line); spans: flagged spans
    (start, end video frames inclusive, label), shaded on every panel and labelled on top.
    Returns ``path`` (parents created)."""
    fig = qa_figure(frames, fps, values, units, thresholds, spans, title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
