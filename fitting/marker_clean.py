"""Catch labelled-marker artefacts before they are fitted: ghosts, spikes, label swaps.

Real Vicon trajectories are labelled automatically, and the labeller errs: a marker's label
jumps onto a reflection 0.1-5 m away for a few samples or for seconds (``ghost``), a single
sample is off (``spike``), two nearby markers exchange labels for a few samples or for
hundreds (``swap``), or a trajectory moves faster than a body can (``implausible_speed``). A
robust fit only bounds their pull (fitting/marker_fit.py); the shape fit picks its placement
frames from the data. Both must see these samples removed or repaired, not down-weighted.

:func:`clean_markers` runs four detectors, in this order, each on the output of the previous.
The swap and ghost tests read each marker's distances to its **segment neighbours** (the other
markers of the near-rigid groups ``names_by_segment`` it belongs to: head, pelvis, each forearm,
each foot...; a marker in two groups has the neighbours of both), compared with their typical
values: the median of each distance over the whole capture, so no artefact shorter than half
the capture can shift it, whatever its length.

1. **speed**: a step between two samples faster than ``max_speed_m_s`` (no marker on a
   body moves 5 m in 8 ms) opens a run, the next such step within ``speed_max_run`` samples
   closes it; the samples in between are removed (``implausible_speed``; ``spike`` for one
   sample). Longer runs are left to the tests below, which have no length limit.
2. **swap**: for each pair of markers less than ``swap_max_dist_m`` apart (median), each
   sample scores the straight labelling and the exchanged one (i at j's place and j at i's) by
   both markers' normalised distance errors to their neighbours, ``(d - median) / sd``, sd the
   distance's robust spread over the capture (at least ``swap_sigma_m``), each term capped at
   ``swap_cap``. A two-state path through the capture (straight / exchanged, ``swap_switch``
   per change of state, Viterbi) gives the exchanged runs, of any length; a run is a swap when
   the straight labelling breaks the typical distances (the worse marker's median error above
   ``swap_break`` and ``SWAP_BREAK_OVER_AGREE`` times the exchanged one) and the exchanged one
   agrees with them (below ``swap_agree``; a larger one is accepted only when both ends are
   label jumps: in a bent pose the right labels are off the medians too). Its ends are the
   label jumps: it is exchanged back when both ends are (the crossed continuation of the
   trajectories fits better than the straight one, or a gap or the capture's edge is there),
   else both markers are removed over the run. The search runs again on the repaired
   capture (``SWAP_ROUNDS``): exchanging LASI and RASI back removes the reason LPSI and RPSI
   looked exchanged (a mirrored pelvis keeps its distances). Distances cannot tell an exchange
   that is an isometry of the group (C7 and STRN with T10 and CLAV as neighbours): such a swap
   is left to the tests below, which remove what breaks the segment.
3. **rigid segments**: the distance between two markers of the same segment stays within
   ``tol`` of its reference: its running median (window ``drift_window``, which follows slow
   soft-tissue drift), or its whole-capture median where the running median is further than
   ``tol`` from it (a long ghost fills the running window; it cannot move the capture's
   median). ``tol`` = max(``rigid_tol_m``, ``rigid_tol_mad`` robust SDs of that pair). Per
   sample and segment the marker with the most broken distances is removed until the rest
   agree; ties go against the marker with more evidence over the run of broken samples
   (distance excess over every segment, and its own jump beyond its segment's common motion at
   the run's edges). Removed runs of one sample are ``spike``, longer ones ``ghost``.
4. **acceleration spike**: a sample off the midpoint of its two neighbours by more than an
   acceleration of ``max_accel_m_s2`` allows (``spike``), for markers no segment covers.

Real fast motion and soft tissue are not flagged: measured on every capture of
``../shared/real`` (see ``tests/test_marker_clean.py``), the tennis serve at 50 Hz (wrist
13 m/s; the forearm marker drifts 25 mm against the wrist bar when the forearm pronates) and
jogging at 300 Hz lose almost nothing, and nothing is un-swapped.

The report (:class:`CleanReport`) is JSON-ready: per marker the removed samples by reason,
un-swapped samples, and the runs ``{"marker", "reason", "first_sample", "last_sample",
"action"}`` (sample indices of the ``Markers`` array, 0-based; ``action`` ``removed`` or
``unswapped``, swaps also name the ``partner``); :meth:`CleanReport.codes` gives the same per
marker and sample as ``REPAIR_CODES`` indices.
"""
from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass, field, fields
from numbers import Integral, Real

import numpy as np

from body.markers import (  # noqa: F401 - the groups, re-exported
    BUILTIN_SEGMENTS,
    CMU41_SEGMENTS,
    PLUG_IN_GAIT_SEGMENTS,
    restrict_groups,
    segments_for_names,
)
from formats.c3d import Markers

REASONS = ("ghost", "spike", "swap", "implausible_speed")
#: Per marker and sample, what was repaired (:meth:`CleanReport.codes`: the code is the index).
#: ``gap_filled`` is never set by :func:`clean_markers` (it leaves gaps NaN); it is the code a
#: later gap filler writes into the same array.
REPAIR_CODES = ("none", "ghost", "spike", "swap_removed", "implausible_speed", "unswapped",
                "gap_filled")
#: a removed run's (reason) -> its repair code name
_REMOVED_CODE = {"ghost": "ghost", "spike": "spike", "swap": "swap_removed",
                 "implausible_speed": "implausible_speed"}
MAD_TO_SD = 1.4826  # robust SD = MAD_TO_SD x median absolute deviation (normal data)
#: a swap run: the labelled error at least this many times the exchanged one
SWAP_BREAK_OVER_AGREE = 2.0
SWAP_ROUNDS = 4  # rounds of the swap search (each on the capture the previous one repaired)

#: Near-rigid segment groups of each built-in marker set (Plug-in Gait, CMU, Plug-in Gait
#: lower body), defined with the sets in ``body.markers`` (``body.markers.segments_of`` gives
#: them, and a ``markerset/2`` file's own groups, the same way).
MARKERSET_SEGMENTS = BUILTIN_SEGMENTS


@dataclass(frozen=True, kw_only=True)
class CleanOptions:
    """The cleaner's thresholds (recipe section ``stages.capture.clean``; every field has a
    default). max_speed_m_s : a step faster than this is not a body moving (the tennis serve's
    wrist reaches 13 m/s); max_accel_m_s2 : a one-sample detour needing more acceleration is a
    spike; speed_max_run : samples between an implausibly fast step out and one back that the
    speed test removes by itself (longer runs are left to the neighbour tests, which have no
    length limit); drift_window : samples of the running median a segment distance is compared
    with (it follows slow soft-tissue drift); rigid_tol_m / rigid_tol_mad : a segment distance
    off its reference by more than max(rigid_tol_m, rigid_tol_mad robust SDs of that distance)
    is broken; swap_max_dist_m : only markers closer than this (median) can swap;
    swap_sigma_m : floor of a neighbour distance's robust SD in the swap test; swap_cap : cap of
    one normalised distance error (a wild one counts this much, no more); swap_switch : the
    evidence (sum of squared normalised errors) a change of labelling costs, so a swap must
    gain more than twice this; swap_agree / swap_break : a swap run needs the worse marker's
    median normalised error above swap_break as labelled, and below swap_agree when exchanged
    (unless both ends are label jumps)."""

    max_speed_m_s: float = 30.0
    max_accel_m_s2: float = 2000.0
    speed_max_run: int = 25
    drift_window: int = 51
    rigid_tol_m: float = 0.03
    rigid_tol_mad: float = 8.0
    swap_max_dist_m: float = 0.35
    swap_sigma_m: float = 0.004
    swap_cap: float = 8.0
    swap_switch: float = 40.0
    swap_agree: float = 2.5
    swap_break: float = 2.0

    def __post_init__(self):
        bad = []
        for f in fields(self):
            v = getattr(self, f.name)
            want = int if f.type in ("int", int) else float
            if isinstance(v, bool) or not isinstance(v, Integral if want is int else Real):
                bad.append(f"{f.name}: must be {'an integer' if want is int else 'a number'}, "
                           f"got {v!r}")
            elif not (np.isfinite(v) and v > 0):
                bad.append(f"{f.name}: must be a finite number > 0, got {v!r}")
        if bad:
            raise ValueError("CleanOptions: " + "; ".join(bad))


@dataclass
class CleanReport:
    """What :func:`clean_markers` did. removed : {marker: {reason: samples}} (only non-zero);
    unswapped : {marker: samples}; runs : [{"marker", "reason", "first_sample", "last_sample",
    "action", ["partner"]}] (inclusive sample ranges; ``action`` ``removed`` or ``unswapped``;
    swap runs name the ``partner``); samples / markers : the capture's size; observed :
    samples that were not gaps before cleaning."""

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

    @property
    def repaired_fraction(self) -> float:
        """Removed or un-swapped marker samples / observed marker samples."""
        return (self.removed_samples + sum(self.unswapped.values())) / max(self.observed, 1)

    def by_reason(self) -> dict[str, int]:
        out = {r: 0 for r in REASONS}
        for per in self.removed.values():
            for r, n in per.items():
                out[r] += n
        return out

    def codes(self, names) -> np.ndarray:
        """(F, M) int8: per sample and marker of ``names`` (any order; a name the report does
        not know stays 0) the index in ``REPAIR_CODES`` of what was done: 0 untouched, else
        ghost, spike, swap_removed, implausible_speed or unswapped (a removal over an
        un-swapped sample wins)."""
        col = {n: k for k, n in enumerate(names)}
        out = np.zeros((self.samples, len(col)), np.int8)
        # un-swapped runs first: a sample removed after it was un-swapped ends up removed
        for r in sorted(self.runs, key=lambda r: r["action"] != "unswapped"):
            k = col.get(r["marker"])
            if k is None:
                continue
            code = "unswapped" if r["action"] == "unswapped" else _REMOVED_CODE[r["reason"]]
            out[r["first_sample"]:r["last_sample"] + 1, k] = REPAIR_CODES.index(code)
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
    dropped (``body.markers.segments_for_names``)."""
    return segments_for_names(names)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(first, last)] of the True runs of a 1D bool array (inclusive)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return [(int(a), int(b)) for a, b in
            zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True)]


def _nanmedian(x, axis):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(x, axis=axis)


def _running_nanmedian(x: np.ndarray, window: int) -> np.ndarray:
    """Running median over ``window`` samples (centred; odd) along axis 0, NaNs ignored.
    x: (F, P)."""
    F = len(x)
    half = window // 2
    pad = np.full((half,) + x.shape[1:], np.nan)
    xp = np.concatenate([pad, x, pad])
    win = np.lib.stride_tricks.sliding_window_view(xp, 2 * half + 1, axis=0)  # (F, P, W)
    return _nanmedian(win, -1)[:F]


def _extrapolate(x: np.ndarray) -> np.ndarray:
    """(F, M, 3) the prediction of sample t from t-1 and t-2 (constant velocity; from t-1 alone
    where t-2 is a gap); NaN where t-1 is a gap or t = 0."""
    pred = np.full_like(x, np.nan)
    pred[1:] = x[:-1]
    lin = 2 * x[1:-1] - x[:-2]
    ok = np.all(np.isfinite(lin), axis=-1)
    pred[2:][ok] = lin[ok]
    return pred


def _neighbours(names, groups) -> list[list[int]]:
    """Per marker column, the sorted columns sharing a segment group with it."""
    col = {n: k for k, n in enumerate(names)}
    nb = [set() for _ in names]
    for members in groups.values():
        for a, b in itertools.permutations([col[n] for n in members], 2):
            nb[a].add(b)
    return [sorted(s) for s in nb]


def _typical(d: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Whole-capture median and robust SD (at least ``floor``) along axis 0 of d (F, ...)."""
    med = _nanmedian(d, 0)
    sd = MAD_TO_SD * _nanmedian(np.abs(d - med), 0)
    return med, np.maximum(np.nan_to_num(sd, nan=floor), floor)


# ----------------------------------------------------------------------------- detectors


def _speed_runs(x: np.ndarray, rate: float, o: CleanOptions) -> np.ndarray:
    """(F, M) bool: samples between two implausibly fast steps of the same marker (the step
    out and the step back, at most ``speed_max_run`` samples apart), skipping gaps."""
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
            if idx[b] - idx[a] <= o.speed_max_run:
                bad[idx[a + 1]:idx[b] + 1, m] = True
                k += 2
            else:
                k += 1
    return bad


def _viterbi2(c0: np.ndarray, c1: np.ndarray, switch: float) -> np.ndarray:
    """(F, P) bool: the cheapest two-state path per column (state 1 where True) with per-sample
    costs c0 / c1 (F, P) and ``switch`` per change of state; the path starts in state 0 (a run
    of state 1 at the capture's start pays one switch, as one at its end does)."""
    F, P = c0.shape
    v0, v1 = np.zeros(P), np.full(P, switch)
    back0 = np.zeros((F, P), bool)  # state 0 at t came from state 1 at t-1
    back1 = np.zeros((F, P), bool)  # state 1 at t came from state 0 at t-1
    for t in range(F):
        s0, s1 = v1 + switch < v0, v0 + switch < v1
        back0[t], back1[t] = s0, s1
        v0, v1 = np.where(s0, v1 + switch, v0) + c0[t], np.where(s1, v0 + switch, v1) + c1[t]
    state = v1 + switch < v0  # ending in state 1 pays the switch back
    out = np.zeros((F, P), bool)
    for t in range(F - 1, -1, -1):
        out[t] = state
        state = np.where(state, ~back1[t], back0[t])
    return out


def _label_jump(x: np.ndarray, i: int, j: int, t: int, forward: bool) -> bool:
    """Is there a label jump between samples t-1 and t (forward) or t and t+1 (backward): the
    crossed continuation of the two trajectories fits better than the straight one, from the
    constant-velocity prediction over the two samples outside the run (one where the second is
    a gap). A gap or the capture's edge next to the run counts as a jump (labels are re-assigned
    after an occlusion)."""
    F = len(x)
    s = -1 if forward else 1
    p1 = t + s
    if not 0 <= p1 < F or not np.isfinite(x[p1, [i, j]]).all():
        return True
    p2 = p1 + s
    prev = x[p1, [i, j]]
    if 0 <= p2 < F and np.isfinite(x[p2, [i, j]]).all():
        prev = 2 * prev - x[p2, [i, j]]
    now = x[t, [i, j]]
    if not np.isfinite(now).all():
        return True
    straight = np.linalg.norm(now - prev, axis=1).sum()
    crossed = np.linalg.norm(now - prev[::-1], axis=1).sum()
    return bool(crossed < straight)


def _swaps(x: np.ndarray, nb: list[list[int]], o: CleanOptions):
    """Label swaps of any length (module docstring, step 2). Returns [(i, j, first, last,
    certain)] (inclusive sample ranges), no two sharing a marker sample."""
    F, M, _ = x.shape
    cols = [k for k in range(M) if nb[k]]
    if len(cols) < 2:
        return []

    def dist(pq: np.ndarray) -> np.ndarray:
        """(F, len(pq)) distances of the column pairs pq (n, 2), computed once per pair."""
        key, inv = np.unique(np.sort(pq, axis=1), axis=0, return_inverse=True)
        with np.errstate(invalid="ignore"):
            d = np.linalg.norm(x[:, key[:, 0]] - x[:, key[:, 1]], axis=-1)
        return d[:, inv.ravel()]

    cand_pairs = np.array(list(itertools.combinations(cols, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med_ab = np.nanmedian(dist(cand_pairs), axis=0)
    # candidate pairs and their terms: (pair, position column, role column, neighbour)
    pairs, terms = [], []
    for (a, b), dab in zip(cand_pairs.tolist(), med_ab, strict=True):
        if not (dab < o.swap_max_dist_m or b in nb[a]):
            continue
        ka = [k for k in nb[a] if k != b]
        kb = [k for k in nb[b] if k != a]
        if not ka and not kb:
            continue
        p = len(pairs)
        pairs.append((a, b, ka, kb))
        terms += [(p, a, a, k) for k in ka] + [(p, b, b, k) for k in kb]
    if not pairs:
        return []
    T = np.array(terms)  # straight terms; crossed: position a <-> b
    tp, tpos, trole, tk = T.T
    other = np.array([pairs[p][1] if pos == pairs[p][0] else pairs[p][0]
                      for p, pos in zip(tp, tpos, strict=True)])
    ds = dist(np.stack([tpos, tk], 1))  # (F, T) as labelled (position = role)
    ref, sig = _typical(ds, o.swap_sigma_m)  # each neighbour distance's typical value
    with np.errstate(invalid="ignore"):
        rs = np.abs(ds - ref) / sig
        rc = np.abs(dist(np.stack([other, tk], 1)) - ref) / sig  # exchanged
    both = np.isfinite(rs) & np.isfinite(rc)
    cost_s = np.where(both, np.minimum(rs, o.swap_cap) ** 2, 0.0)
    cost_c = np.where(both, np.minimum(rc, o.swap_cap) ** 2, 0.0)
    onehot = np.zeros((len(T), len(pairs)))
    onehot[np.arange(len(T)), tp] = 1.0
    S, C = cost_s @ onehot, cost_c @ onehot  # (F, P)
    path = _viterbi2(S, C, o.swap_switch)
    cand = []
    for p in np.flatnonzero(path.any(0)):
        a, b, ka, kb = pairs[p]
        mine = [np.flatnonzero((tp == p) & (tpos == m)) for m in (a, b)]
        mine = [t for t in mine if len(t)]
        for s, e in _runs(path[:, p]):
            seg = slice(s, e + 1)
            # per sample, each marker's median normalised error over its neighbours; over the
            # run, the median of the worse marker
            ok = both[seg]
            agree, broken = (
                _nanmedian(np.fmax.reduce([_nanmedian(np.where(ok[:, t], r[seg][:, t], np.nan), 1)
                                           for t in mine]), 0) for r in (rc, rs))
            gain = float((S[seg, p] - C[seg, p]).sum())
            certain = _label_jump(x, a, b, s, True) and _label_jump(x, a, b, e, False)
            if not (broken > max(o.swap_break, SWAP_BREAK_OVER_AGREE * agree)
                    and (agree < o.swap_agree or certain)):
                continue
            cand.append((gain, int(a), int(b), s, e, certain))
    # the strongest first; a weaker one touching its markers or their neighbours over the same
    # samples waits for the next round (exchanging LASI and RASI back may remove the reason
    # LPSI and RPSI looked exchanged: the mirror image of a pelvis keeps its distances)
    out, taken = [], np.zeros((F, M), bool)
    for _gain, a, b, s, e, certain in sorted(cand, reverse=True):
        near = sorted({a, b, *nb[a], *nb[b]})
        if taken[s:e + 1, near].any():
            continue
        taken[s:e + 1, near] = True
        out.append((a, b, s, e, certain))
    return out


def _long_ghost_reference(d: np.ndarray, o: CleanOptions) -> np.ndarray:
    """(F, P) the reference of each segment distance d (F, P): its running median (window
    ``drift_window``), except over a long ghost: where the running median is further than
    ``tol`` from the capture's median and the distance jumped (by more than ``tol`` in one
    sample, or a gap, or the capture's edge) within a window before and after, the capture's
    median is the reference from jump to jump. Soft tissue moves the distance as much but
    smoothly: there the running median stays the reference."""
    F, P = d.shape
    gmed, gsd = _typical(d, 0.0)
    gtol = np.maximum(o.rigid_tol_m, o.rigid_tol_mad * gsd)
    ref = _running_nanmedian(d, o.drift_window)
    with np.errstate(invalid="ignore"):
        far = np.abs(ref - gmed) > gtol
        # jump[t]: between samples t-1 and t (the capture's edges count, so do gaps)
        jump = np.ones((F + 1, P), bool)
        jump[1:F] = ~(np.abs(np.diff(d, axis=0)) <= gtol)
    W = o.drift_window
    for p in np.flatnonzero(far.any(0)):
        for a, b in _runs(far[:, p]):
            left = np.flatnonzero(jump[max(a - W, 0):a + 1, p])
            right = np.flatnonzero(jump[b + 1:b + W + 2, p])
            if len(left) and len(right):
                ref[max(a - W, 0) + left[-1]:b + 1 + right[0], p] = gmed[p]
    return ref


def _rigid(x: np.ndarray, names, groups, o: CleanOptions) -> np.ndarray:
    """(F, M) bool: samples breaking their segment's rigidity (see the module docstring)."""
    F, M, _ = x.shape
    col = {n: k for k, n in enumerate(names)}
    glist = [[col[n] for n in members] for members in groups.values()]
    pairs = sorted({(min(a, b), max(a, b)) for g in glist for a, b in itertools.combinations(g, 2)})
    if not pairs:
        return np.zeros((F, M), bool)
    pi = np.array(pairs)
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(x[:, pi[:, 0]] - x[:, pi[:, 1]], axis=-1)  # (F, P), NaN in gaps
    ref = _long_ghost_reference(d, o)
    e = np.abs(d - ref)
    sd = MAD_TO_SD * _nanmedian(e, 0)
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
              else restrict_groups(names_by_segment, names))
    observed = int(np.all(np.isfinite(x), axis=-1).sum())
    reason = np.full((F, M), "", dtype=object)
    partner = np.full((F, M), -1, dtype=np.int64)
    runs: list[dict] = []
    unswapped = np.zeros(M, np.int64)

    def remove(mask, why):
        new = mask & np.all(np.isfinite(x), axis=-1)
        reason[new] = why
        x[new] = np.nan
        return new

    # 1. swaps, of any length (first: a swap of markers far apart is also a fast step out and
    # back), in rounds until none is left
    nb = _neighbours(names, groups)
    for _ in range(SWAP_ROUNDS):
        found = _swaps(x, nb, opts)
        for i, j, s, e, certain in found:
            if certain:
                x[s:e + 1, [i, j]] = x[s:e + 1, [j, i]]
                unswapped[[i, j]] += e - s + 1
                for a, b in ((i, j), (j, i)):
                    runs.append({"marker": names[a], "reason": "swap", "first_sample": s,
                                 "last_sample": e, "action": "unswapped", "partner": names[b]})
            else:
                m = np.zeros((F, M), bool)
                m[s:e + 1, [i, j]] = True
                new = remove(m, "swap")
                partner[s:e + 1, i] = np.where(new[s:e + 1, i], j, -1)
                partner[s:e + 1, j] = np.where(new[s:e + 1, j], i, -1)
        if not found:
            break
    # 2. implausible speed (a one-sample detour is a spike)
    fast = _speed_runs(x, rate, opts)
    one = fast & ~np.roll(fast, 1, axis=0) & ~np.roll(fast, -1, axis=0)
    remove(fast & ~one, "implausible_speed")
    remove(one, "spike")
    # 3. rigid segments: one-sample runs are spikes, longer ones ghosts
    flag = _rigid(x, names, groups, opts) & np.all(np.isfinite(x), axis=-1)
    for m in range(M):
        for a, b in _runs(flag[:, m]):
            reason[a:b + 1, m] = "spike" if a == b else "ghost"
    x[flag] = np.nan
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
                run = {"marker": names[m], "reason": r, "first_sample": a, "last_sample": b,
                       "action": "removed"}
                if r == "swap":  # split where the partner changes
                    for pa, pb in _split(partner[a:b + 1, m]):
                        runs.append({**run, "first_sample": a + pa, "last_sample": a + pb,
                                     "partner": names[partner[a + pa, m]]})
                else:
                    runs.append(run)
    runs.sort(key=lambda d: (d["first_sample"], d["marker"]))
    report = CleanReport(samples=F, markers=M, observed=observed, removed=removed,
                         unswapped={names[m]: int(n) for m in range(M) if (n := unswapped[m])},
                         runs=runs)
    return Markers(names, x, markers.rate_hz, markers.first_frame, markers.subject), report


def _split(v: np.ndarray) -> list[tuple[int, int]]:
    """[(first, last)] of the runs of equal values of a 1D array."""
    cut = np.flatnonzero(np.diff(v) != 0) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut - 1, [len(v) - 1]])
    return list(zip(starts.tolist(), ends.tolist(), strict=True))
