"""Catch labelled-marker artefacts before they are fitted: ghosts, spikes, label swaps.

Real Vicon trajectories are labelled automatically, and the labeller errs: a marker's label
jumps onto a reflection 0.1-5 m away for a few samples (``ghost``), a single sample is off
(``spike``), two nearby markers exchange labels for 5-20 samples (``swap``), or a trajectory
moves faster than a body can (``implausible_speed``). A robust fit only bounds their pull
(fitting/marker_fit.py); the shape fit picks its placement frames from the data. Both must see
these samples removed, not down-weighted.

:func:`clean_markers` runs four detectors, in this order, each on the output of the previous:

1. **speed**: a step between two samples faster than ``max_speed_m_s`` (no marker on a
   body moves 5 m in 8 ms) opens a run, the next such step within ``max_run`` samples closes
   it; the samples in between are removed (``implausible_speed``; ``spike`` for one sample).
2. **swap**: for two markers less than ``swap_max_dist_m`` apart, at each sample the crossed
   continuation (marker i continues marker j's extrapolated trajectory and vice versa) fits
   much better than the straight one, and the crossing comes back within ``max_run`` samples:
   the labels are exchanged back (certain: both crossings clear), else both are removed.
3. **rigid segments**: the distance between two markers of the same near-rigid segment
   (``names_by_segment``: head, pelvis, each forearm, each foot...) stays within ``tol`` of its
   running median (window ``2 max_run + 1``); ``tol`` = max(``rigid_tol_m``, ``rigid_tol_mad``
   robust SDs of that pair). Per sample and segment the marker with the most broken distances
   is removed until the rest agree; ties go against the marker with more evidence over the
   run of broken samples (distance excess over every segment, and its own jump beyond its
   segment's common motion at the run's edges). Removed runs of one sample are ``spike``,
   longer ones ``ghost``.
4. **acceleration spike**: a sample off the midpoint of its two neighbours by more than an
   acceleration of ``max_accel_m_s2`` allows (``spike``), for markers no segment covers.

Real fast motion is not flagged: measured on every capture of ``../shared/real`` (see
``tests/test_marker_clean.py``), the tennis serve at 50 Hz (wrist 13 m/s) and jogging at 300 Hz
lose almost nothing.

The report (:class:`CleanReport`) is JSON-ready: per marker the removed samples by reason,
un-swapped samples, and the runs ``{"marker", "reason", "first_sample", "last_sample",
"action"}`` (sample indices of the ``Markers`` array, 0-based; ``action`` ``removed`` or
``unswapped``, swaps also name the ``partner``).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from body.markers import BUILTIN_SEGMENTS, CMU41_SEGMENTS, PLUG_IN_GAIT_SEGMENTS  # noqa: F401
from formats.c3d import Markers

REASONS = ("ghost", "spike", "swap", "implausible_speed")

#: Near-rigid segment groups of each built-in marker set (Plug-in Gait, CMU, Plug-in Gait
#: lower body), defined with the sets in ``body.markers`` (``body.markers.segments_of`` gives
#: them, and a ``markerset/2`` file's own groups, the same way).
MARKERSET_SEGMENTS = BUILTIN_SEGMENTS


@dataclass(frozen=True)
class CleanOptions:
    """max_speed_m_s : a step faster than this is not a body moving (the tennis serve's wrist
    reaches 13 m/s); max_accel_m_s2 : a one-sample detour needing more acceleration is a spike;
    max_run : longest ghost or swap, samples (also fixes the running-median window);
    rigid_tol_m / rigid_tol_mad : a segment distance off its running median by more than
    max(rigid_tol_m, rigid_tol_mad robust SDs of that distance) is broken;
    swap_max_dist_m : only markers closer than this (median) can swap; swap_ratio : a crossing
    needs crossed error < swap_ratio x straight error (certain below half of it);
    swap_min_jump_m : and a straight error above this."""

    max_speed_m_s: float = 30.0
    max_accel_m_s2: float = 2000.0
    max_run: int = 25
    rigid_tol_m: float = 0.03
    rigid_tol_mad: float = 8.0
    swap_max_dist_m: float = 0.35
    swap_ratio: float = 0.4
    swap_min_jump_m: float = 0.03

    def __post_init__(self):
        bad = [f"{n}: must be > 0, got {getattr(self, n)}" for n in (
            "max_speed_m_s", "max_accel_m_s2", "max_run", "rigid_tol_m", "rigid_tol_mad",
            "swap_max_dist_m", "swap_ratio", "swap_min_jump_m") if not getattr(self, n) > 0]
        if bad:
            raise ValueError("; ".join(bad))


@dataclass
class CleanReport:
    """What :func:`clean_markers` did. removed : {marker: {reason: samples}} (only non-zero);
    unswapped : {marker: samples}; runs : [{"marker", "reason", "first_sample", "last_sample",
    "action", ["partner"]}]; samples / markers : the capture's size; observed : samples that
    were not gaps before cleaning."""

    samples: int
    markers: int
    observed: int
    removed: dict[str, dict[str, int]] = field(default_factory=dict)
    unswapped: dict[str, int] = field(default_factory=dict)
    runs: list[dict] = field(default_factory=list)

    @property
    def removed_samples(self) -> int:
        return int(sum(sum(r.values()) for r in self.removed.values()))

    @property
    def removed_fraction(self) -> float:
        """Removed marker samples / observed marker samples."""
        return self.removed_samples / max(self.observed, 1)

    def by_reason(self) -> dict[str, int]:
        out = {r: 0 for r in REASONS}
        for per in self.removed.values():
            for r, n in per.items():
                out[r] += n
        return out

    def to_json(self) -> dict:
        return {"samples": int(self.samples), "markers": int(self.markers),
                "observed": int(self.observed), "removed_samples": self.removed_samples,
                "removed_fraction": float(self.removed_fraction),
                "removed_by_reason": self.by_reason(),
                "removed": {m: {r: int(n) for r, n in d.items()} for m, d in self.removed.items()},
                "unswapped": {m: int(n) for m, n in self.unswapped.items()},
                "runs": [dict(r) for r in self.runs]}


# ----------------------------------------------------------------------------- helpers


def default_segments(names) -> dict[str, tuple[str, ...]]:
    """The segment groups of the built-in marker set that ``names`` matches best (Plug-in Gait,
    CMU or its lower body), restricted to the markers present; groups left with < 2 markers are
    dropped."""
    present = set(names)
    best = max(MARKERSET_SEGMENTS.values(),
               key=lambda g: len(present & {n for v in g.values() for n in v}))
    return _restrict(best, present)


def _restrict(groups, present) -> dict[str, tuple[str, ...]]:
    out = {}
    for g, members in groups.items():
        m = tuple(n for n in members if n in present)
        if len(m) >= 2:
            out[g] = m
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(first, last)] of the True runs of a 1D bool array (inclusive)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


def _running_nanmedian(x: np.ndarray, half: int) -> np.ndarray:
    """Running median over ``2 half + 1`` samples along axis 0, NaNs ignored. x: (F, P)."""
    import warnings

    F = len(x)
    pad = np.full((half,) + x.shape[1:], np.nan)
    xp = np.concatenate([pad, x, pad])
    win = np.lib.stride_tricks.sliding_window_view(xp, 2 * half + 1, axis=0)  # (F, P, W)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(win, axis=-1)[:F]


def _extrapolate(x: np.ndarray) -> np.ndarray:
    """(F, M, 3) the prediction of sample t from t-1 and t-2 (constant velocity; from t-1 alone
    where t-2 is a gap); NaN where t-1 is a gap or t = 0."""
    pred = np.full_like(x, np.nan)
    pred[1:] = x[:-1]
    lin = 2 * x[1:-1] - x[:-2]
    ok = np.all(np.isfinite(lin), axis=-1)
    pred[2:][ok] = lin[ok]
    return pred


# ----------------------------------------------------------------------------- detectors


def _speed_runs(x: np.ndarray, rate: float, o: CleanOptions) -> np.ndarray:
    """(F, M) bool: samples between two implausibly fast steps of the same marker (the step
    out and the step back, at most ``max_run`` samples apart), skipping gaps."""
    F, M, _ = x.shape
    bad = np.zeros((F, M), bool)
    for m in range(M):
        idx = np.flatnonzero(np.all(np.isfinite(x[:, m]), axis=1))
        if len(idx) < 2:
            continue
        step = np.linalg.norm(np.diff(x[idx, m], axis=0), axis=1)
        dt = np.diff(idx) / rate
        jump = np.flatnonzero(step / dt > o.max_speed_m_s)  # jump k: between idx[k] and idx[k+1]
        k = 0
        while k < len(jump) - 1:
            a, b = jump[k], jump[k + 1]
            if idx[b] - idx[a] <= o.max_run:
                bad[idx[a + 1]:idx[b] + 1, m] = True
                k += 2
            else:
                k += 1
    return bad


def _swaps(x: np.ndarray, o: CleanOptions):
    """Label swaps. Returns [(i, j, first, last, certain)] (inclusive sample range)."""
    F, M, _ = x.shape
    pred = _extrapolate(x)
    with np.errstate(invalid="ignore"):
        dist = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1)  # (F, M, M)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(dist, axis=0)
    out = []
    for i, j in zip(*np.nonzero(np.triu(med < o.swap_max_dist_m, 1)), strict=True):
        straight = np.linalg.norm(x[:, i] - pred[:, i], axis=1) + np.linalg.norm(x[:, j] - pred[:, j], axis=1)
        cross = np.linalg.norm(x[:, j] - pred[:, i], axis=1) + np.linalg.norm(x[:, i] - pred[:, j], axis=1)
        with np.errstate(invalid="ignore"):
            c = (cross < o.swap_ratio * straight) & (straight > o.swap_min_jump_m)
        ts = np.flatnonzero(c)
        k = 0
        while k < len(ts) - 1:
            s, e1 = ts[k], ts[k + 1]
            if e1 - s <= o.max_run:
                certain = bool(cross[s] < 0.5 * o.swap_ratio * straight[s]
                               and cross[e1] < 0.5 * o.swap_ratio * straight[e1])
                out.append((int(i), int(j), int(s), int(e1 - 1), certain))
                k += 2
            else:
                k += 1
    return out


def _rigid(x: np.ndarray, names, groups, o: CleanOptions) -> np.ndarray:
    """(F, M) bool: samples breaking their segment's rigidity (see the module docstring)."""
    F, M, _ = x.shape
    col = {n: k for k, n in enumerate(names)}
    glist = [[col[n] for n in members] for members in groups.values()]
    pairs = sorted({(min(a, b), max(a, b)) for g in glist for a, b in itertools.combinations(g, 2)})
    if not pairs:
        return np.zeros((F, M), bool)
    pi = np.array(pairs)
    d = np.linalg.norm(x[:, pi[:, 0]] - x[:, pi[:, 1]], axis=-1)  # (F, P), NaN in gaps
    ref = _running_nanmedian(d, o.max_run)
    e = np.abs(d - ref)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sd = 1.4826 * np.nanmedian(e, axis=0)
    tol = np.maximum(o.rigid_tol_m, o.rigid_tol_mad * np.nan_to_num(sd))
    with np.errstate(invalid="ignore"):
        broken = e > tol  # (F, P); False in gaps
    pcol = {p: k for k, p in enumerate(pairs)}
    excess = np.zeros((F, M))  # broken distance beyond tolerance, in tolerances, per marker
    ex = np.where(broken, e / tol - 1.0, 0.0)
    np.add.at(excess.T, pi[:, 0], ex.T)
    np.add.at(excess.T, pi[:, 1], ex.T)
    with np.errstate(invalid="ignore"):
        step = np.nan_to_num(np.linalg.norm(x - _extrapolate(x), axis=-1))  # (F, M)
    flag = np.zeros((F, M), bool)
    for g in glist:
        local = list(itertools.combinations(range(len(g)), 2))
        gp = [pcol[(min(g[p], g[q]), max(g[p], g[q]))] for p, q in local]
        bg = broken[:, gp]
        # a marker's own jump, beyond its segment's common motion
        rel = np.maximum(step[:, g] - np.median(step[:, g], axis=1, keepdims=True), 0.0)
        for a, b in _runs(bg.any(1)):
            blame = excess[a:b + 1, g].sum(0) + rel[a:b + 2].sum(0) / o.rigid_tol_m
            for t in range(a, b + 1):
                kept = np.ones(len(g), bool)
                while True:
                    cnt = np.zeros(len(g))
                    for k, (p, q) in enumerate(local):
                        if bg[t, k] and kept[p] and kept[q]:
                            cnt[p] += 1
                            cnt[q] += 1
                    if not cnt.any():
                        break
                    # the most broken distances first, then the run's evidence
                    c = int(np.lexsort((blame, cnt))[-1])
                    kept[c] = False
                    flag[t, g[c]] = True
    return flag


def _accel_spikes(x: np.ndarray, rate: float, o: CleanOptions) -> np.ndarray:
    F, M, _ = x.shape
    bad = np.zeros((F, M), bool)
    if F < 3:
        return bad
    mid = 0.5 * (x[:-2] + x[2:])
    dev = np.linalg.norm(x[1:-1] - mid, axis=-1)  # = |second difference| / 2
    with np.errstate(invalid="ignore"):
        bad[1:-1] = 2 * dev * rate * rate > o.max_accel_m_s2
    return bad


# ----------------------------------------------------------------------------- the cleaner


def clean_markers(markers: Markers, names_by_segment: dict | None = None,
                  opts: CleanOptions = CleanOptions()) -> tuple[Markers, CleanReport]:
    """The capture with its artefacts removed (NaN) or un-swapped, and what was done.

    markers : ``formats.c3d.Markers`` (metres, NaN gaps). names_by_segment : ``{segment:
    (marker names)}`` of near-rigid groups (default: :func:`default_segments` of the names,
    Plug-in Gait or CMU; names absent from the capture are ignored). Returns the cleaned
    :class:`formats.c3d.Markers` (same names, rate, first frame) and a :class:`CleanReport`.
    """
    x = np.array(markers.xyz, dtype=float)
    F, M, _ = x.shape
    names = tuple(markers.names)
    rate = float(markers.rate_hz)
    groups = (default_segments(names) if names_by_segment is None
              else _restrict(names_by_segment, set(names)))
    observed = int(np.all(np.isfinite(x), axis=-1).sum())
    reason = np.full((F, M), "", dtype=object)
    runs: list[dict] = []
    unswapped = np.zeros(M, np.int64)

    def remove(mask, why):
        new = mask & np.all(np.isfinite(x), axis=-1)
        reason[new] = why
        x[new] = np.nan
        return new

    # 1. implausible speed (a one-sample detour is a spike)
    fast = _speed_runs(x, rate, opts)
    one = fast & ~np.roll(fast, 1, axis=0) & ~np.roll(fast, -1, axis=0)
    remove(fast & ~one, "implausible_speed")
    remove(one, "spike")
    # 2. swaps
    for i, j, s, e, certain in _swaps(x, opts):
        if certain:
            x[s:e + 1, [i, j]] = x[s:e + 1, [j, i]]
            unswapped[[i, j]] += e - s + 1
            for a, b in ((i, j), (j, i)):
                runs.append({"marker": names[a], "reason": "swap", "first_sample": s,
                             "last_sample": e, "action": "unswapped", "partner": names[b]})
        else:
            m = np.zeros((F, M), bool)
            m[s:e + 1, [i, j]] = True
            remove(m, "swap")
    # 3. rigid segments: one-sample runs are spikes, longer ones ghosts
    flag = _rigid(x, names, groups, opts)
    for m in range(M):
        for a, b in _runs(flag[:, m]):
            reason[a:b + 1, m] = "spike" if a == b else "ghost"
    new = flag & np.all(np.isfinite(x), axis=-1)
    x[new] = np.nan
    # 4. acceleration spikes (markers without a segment mostly)
    remove(_accel_spikes(x, rate, opts), "spike")

    removed: dict[str, dict[str, int]] = {}
    for m in range(M):
        col = reason[:, m]
        per = {r: int(np.count_nonzero(col == r)) for r in REASONS if np.any(col == r)}
        if per:
            removed[names[m]] = per
        for r in REASONS:
            for a, b in _runs(col == r):
                runs.append({"marker": names[m], "reason": r, "first_sample": int(a),
                             "last_sample": int(b), "action": "removed"})
    runs.sort(key=lambda d: (d["first_sample"], d["marker"]))
    report = CleanReport(samples=F, markers=M, observed=observed, removed=removed,
                         unswapped={names[m]: int(n) for m in range(M) if (n := unswapped[m])},
                         runs=runs)
    return Markers(names, x, markers.rate_hz, markers.first_frame, markers.subject), report
