"""Per-frame QA metrics of a sequence's fits, their thresholds, flags and flagged spans
(issue #18, part 1). Pure domain code: typed inputs in, arrays out, no file I/O.

``sequence_metrics`` poses both bodies on the QA frames and measures, per frame:

- ``wearer.marker_median_mm`` / ``wearer.marker_max_mm``: the marker fit's residuals
  (``BodyFit.marker_residual_m``) over the markers seen in the frame;
- ``<person>.reproj_<group>_px.<cam>``: the fitted mesh's KP65 keypoints (``body.joints``
  regressor) projected with the camera (distortion included, ``calib.project``) against the
  person's confident detections (conf >= ``min_conf``) of that view; groups
  ``qa.constants.GROUPS`` (body, hands, face). With ``reproj_statistic="limb"`` (default) a
  group's value is the largest of its limbs' median errors (``qa.constants.LIMBS``: each arm,
  leg, foot, hand): one limb off by 30 degrees moves only 2-3 of the 18 body keypoints, which
  the group's median (``"median"``) hides. Each limb counts the better of the detections and
  their left/right mirror (a detector that swapped the legs in a view is not a fit error);
  ``<person>.reproj_views_<group>_px``: per keypoint (per hand for the hands) the second
  largest error over the views (at least ``MIN_VIEWS``), the largest in the group: a fit
  error moves a keypoint in most views, a wrong detection in one (on the clean sessions this
  separates a 40-degree shoulder rotation better than the median over the views); the
  per-view figures are flagged at higher thresholds (a view that is off altogether);
- ``sync_offset_frames.<cam>``: the wearer (whose marker fit does not depend on the video)
  and the partner projected at video frame ``f + s`` against the view's detections of frame
  ``f`` (body and hands), for ``s`` in ``constants.SYNC_SHIFTS``: the ``s`` of the lowest
  cost, one number per view repeated on every frame. The cost is the mean error (clipped at
  ``SYNC_CAP_PX``) over the confident detections whose projected person moves by
  ``SYNC_MIN_MOTION_PX`` or more across the shifts (a still keypoint says nothing of time).
  A shift other than 0 is kept only when its gain over 0 is ``SYNC_MIN_Z`` standard errors
  or more, over the person-frames (:func:`_paired_z`): a wearer standing still or a noisy
  view keeps 0. The partner's fit took the view under test in, which pulls it toward no
  shift: it adds evidence (the wearer alone moves too little in many actions) and can only
  make the test more cautious. Between the wearer's fit frames (a keypoint stride) its
  keypoints follow its markers (:func:`_sync_people`), the partner's a cubic spline. A view
  is not measurable (no number; ``sync_not_measurable`` and, per view, the reason in
  ``sync_not_measurable_why``) with fewer than ``SYNC_MIN_POINTS`` such detections, a best
  cost above ``SYNC_MAX_COST_PX``, a best shift at the end of the range, or a cost that
  rises by less than ``SYNC_MIN_RISE`` ``SYNC_SENSE_FRAMES`` frames away on either side
  (:func:`_sync_rise`): detections that do not follow the motion cannot say "in sync";
- ``penetration_mm``: the deepest surface point of either body inside the other (subsampled:
  the ``PROXY_VERTICES`` proxy points of one body, inside the other's proxy by the generalized
  winding number; their depth is exact, to the other's full mesh); ``penetration_volume_cm3``:
  the cells of a ``VOLUME_CELL_M`` grid (coarser beyond ``VOLUME_MAX_CELLS`` cells) over the
  bounding box of the penetrating points that lie inside both proxies;
- ``<person>.self_penetration_mm``: ``fitting.collision.self_penetration`` on the body's proxy
  (``PROXY_VERTICES`` vertices: a subsample of the surface, depth to the proxy surface);
- ``<person>.ground_penetration_mm``: the lowest vertex below the ground plane (0 above);
- ``<person>.foot_skate_m_s``: the median horizontal speed of the foot vertices (sole, heel,
  toes) within ``FOOT_CONTACT_M`` of the floor in this and the previous fit frame, the faster
  foot; NaN when no foot is on the floor;
- ``contact_gap_mm``: in annotated contact frames (``contact.active(frame)``), the largest
  over the annotated region pairs of the pair's smallest facet distance (wearer region,
  partner region; ``geometry.facet_distances``);
- ``unexpected_contact_mm``: outside the contact interval widened by
  ``contact_margin_frames``, the two meshes' closest distance (0 when they interpenetrate;
  the proxy points of each against the other's full mesh, clipped at ``NEAR_M``); flagged
  when *below* its threshold;
- ``<person>.jerk_m_s3``: the largest over the KP65 body and face keypoints (joint centres,
  feet, head) of ``|x[i+k] - 3 x[i] + 3 x[i-k] - x[i-2k]| / dt^3`` on fit frames ``k`` apart,
  ``dt`` = their time step, the smallest multiple of the fit step of at least ``JERK_DT_S``
  (so that the figure does not depend on the keypoint stride: at full rate, frame-to-frame
  fitting noise would dominate); NaN where the four frames are not evenly spaced;
- ``<person>.not_valid``: 1.0 where the fit marks the frame not valid.

``flag_frames`` turns the metrics beyond their thresholds into per-frame reasons and spans.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from formats import skeletons as S
from qa import constants as K

PEOPLE = ("wearer", "partner")
GROUP_NAMES = tuple(K.GROUPS)
#: Metrics flagged when *below* their threshold (all others: above).
LOWER_IS_BAD = ("unexpected_contact_mm",)


# ---------------------------------------------------------------------------- options


@dataclass(frozen=True)
class QAOptions:
    """Thresholds of the QA flags (the ``qa`` stage's recipe section ``stages.qa.<field>``).

    marker_max_mm, marker_median_mm : per frame, the wearer's worst / median marker residual.
    markers_repaired : per frame, markers whose capture samples the cleaning step
        (``fitting.marker_clean``) un-swapped or removed (ghosts, spikes, swaps) near the frame:
        the fit there rests on a repaired capture.
    reproj_body_px, reproj_hands_px, reproj_face_px : per person, view and keypoint group, the
        reprojection error (``reproj_statistic``: ``"limb"`` the worst limb's median,
        ``"median"`` the group's median) of confident detections (conf >= ``min_conf``).
    sync_max_frames : a view whose best time shift (wearer) is beyond this is flagged.
    penetration_mm, penetration_volume_cm3 : deepest interpenetration between the two bodies
        and the volume inside both.
    self_penetration_mm, ground_penetration_mm : per person.
    foot_skate_m_s : horizontal speed of a foot in ground contact.
    contact_gap_mm : annotated contact frames whose annotated regions are farther apart.
    unexpected_contact_mm : frames outside the annotated interval (+ ``contact_margin_frames``)
        where the bodies are closer than this.
    jerk_m_s3 : max over the body keypoints of |third difference| / dt^3.
    merge_gap_frames : flagged frames at most this many fit frames apart form one span.
    min_conf : detections below this confidence are not used.
    """

    marker_max_mm: float = K.MARKER_MAX_MM
    markers_repaired: float = K.MARKERS_REPAIRED
    marker_median_mm: float = K.MARKER_MEDIAN_MM
    reproj_body_px: float = K.REPROJ_BODY_PX
    reproj_hands_px: float = K.REPROJ_HANDS_PX
    reproj_face_px: float = K.REPROJ_FACE_PX
    reproj_views_body_px: float = K.REPROJ_VIEWS_BODY_PX
    reproj_views_hands_px: float = K.REPROJ_VIEWS_HANDS_PX
    reproj_views_face_px: float = K.REPROJ_VIEWS_FACE_PX
    sync_max_frames: int = K.SYNC_MAX_FRAMES
    penetration_mm: float = K.PENETRATION_MM
    penetration_volume_cm3: float = K.PENETRATION_VOLUME_CM3
    self_penetration_mm: float = K.SELF_PENETRATION_MM
    ground_penetration_mm: float = K.GROUND_PENETRATION_MM
    foot_skate_m_s: float = K.FOOT_SKATE_M_S
    contact_gap_mm: float = K.CONTACT_GAP_MM
    unexpected_contact_mm: float = K.UNEXPECTED_CONTACT_MM
    jerk_m_s3: float = K.JERK_M_S3
    merge_gap_frames: int = K.MERGE_GAP_FRAMES
    min_conf: float = K.MIN_CONF
    contact_margin_frames: int = K.CONTACT_MARGIN_FRAMES
    reproj_statistic: str = "limb"

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "reproj_statistic":
                if v not in ("limb", "median"):
                    raise ValueError(f"reproj_statistic: expected 'limb' or 'median', got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"{f.name}: expected a number, got {v!r}")
            if f.type in ("int", int):
                if not float(v).is_integer() or v < 0:
                    raise ValueError(f"{f.name}: expected an integer >= 0, got {v!r}")
                continue
            if math.isnan(v):
                raise ValueError(f"{f.name}: NaN")
            if f.name == "min_conf":
                if not 0.0 <= v <= 1.0:
                    raise ValueError(f"min_conf: expected a confidence in [0, 1], got {v!r}")
            elif not v > 0:
                raise ValueError(f"{f.name}: expected a threshold > 0 (inf disables), got {v!r}")


def threshold_name(metric: str) -> str | None:
    """The ``QAOptions`` field a metric is flagged against (None: ``not_valid``, flagged at
    ``constants.NOT_VALID``, and unknown names)."""
    parts = metric.split(".")
    if parts[0] == "sync_offset_frames":
        return "sync_max_frames"
    if parts[0] in PEOPLE and len(parts) >= 2:
        name = parts[1]
        if name == "not_valid":
            return None
        if name.startswith("reproj_views_") and len(parts) == 2:
            return name if name in _FIELDS else None
        if name.startswith("reproj_") and len(parts) >= 3:
            return name if name in _FIELDS else None
        if len(parts) == 2 and name in _FIELDS and name in (
                "marker_median_mm", "marker_max_mm", "markers_repaired", "self_penetration_mm",
                "ground_penetration_mm", "foot_skate_m_s", "jerk_m_s3"):
            if name.startswith("marker") and parts[0] != "wearer":
                return None
            return name
        return None
    if len(parts) == 1 and parts[0] in ("penetration_mm", "penetration_volume_cm3",
                                        "contact_gap_mm", "unexpected_contact_mm"):
        return parts[0]
    return None


_FIELDS = {f.name for f in dataclasses.fields(QAOptions)}
#: Every threshold field a reason can be flagged against (the names ``stages.export.withhold``
#: lists; each classified in ``constants.FIT_WRONG`` or ``constants.NOT_FIT_WRONG``).
REASON_KINDS = tuple(sorted({*K.FIT_WRONG, *K.NOT_FIT_WRONG}))


def reason_people(metric: str) -> tuple[str, ...]:
    """Whom a flagged reason (a metric name) is about: ``("wearer",)`` / ``("partner",)`` for
    a ``<person>.`` metric, both people for the others (the pair reasons
    ``constants.PAIR_REASONS``: interpenetration, contact; a camera's sync offset)."""
    head = metric.split(".", 1)[0]
    return (head,) if head in PEOPLE else PEOPLE


def _threshold(metric: str, opts: QAOptions) -> float:
    t = threshold_name(metric)
    if t is None:
        return K.NOT_VALID
    return float(getattr(opts, t))


# ---------------------------------------------------------------------------- results


@dataclass
class QAMetrics:
    """Per-frame metrics of a sequence (see the module doc for each name).

    frames : (F,) video frames (the partner's when there is a partner, those the wearer's fit
        also has; else the wearer's). values : name -> (F,) float, NaN = not applicable.
    units : name -> unit. thresholds : name -> the threshold it is flagged against (flagged
        names only). sequence : sequence-level findings, JSON-able. vertices : per person
        present (F, V, 3) float32 posed on ``frames``; people : their roles, wearer first.
    """

    frames: np.ndarray
    values: dict[str, np.ndarray]
    units: dict[str, str]
    thresholds: dict[str, float]
    sequence: dict
    vertices: list[np.ndarray] = field(default_factory=list)
    people: list[str] = field(default_factory=list)


@dataclass
class Span:
    """Flagged video frames ``start..end`` (inclusive), the reasons flagged inside, the frame of
    the worst excess (value / threshold; below-threshold metrics: threshold / value), each
    reason's worst value, and that worst excess (``peak_excess``, > 1)."""

    start: int
    end: int
    reasons: list[str]
    peak_frame: int
    worst: dict[str, float]
    peak_excess: float = 1.0

    def to_json(self) -> dict:
        return {"start": int(self.start), "end": int(self.end), "reasons": list(self.reasons),
                "peak_frame": int(self.peak_frame),
                "worst": {k: _json_float(v) for k, v in self.worst.items()}}


@dataclass
class Flags:
    """reasons : (R,) metric names that can flag; flagged : (F, R) bool; spans."""

    reasons: tuple[str, ...]
    flagged: np.ndarray
    spans: list[Span]

    @property
    def any(self) -> np.ndarray:
        """(F,) bool: frames flagged by at least one reason."""
        if self.flagged.ndim != 2 or not self.flagged.shape[1]:
            return np.zeros(len(self.flagged), bool)
        return self.flagged.any(axis=1)

    @property
    def rate(self) -> float:
        """Fraction of frames flagged."""
        a = self.any
        return float(a.mean()) if len(a) else 0.0


def _json_float(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


# ---------------------------------------------------------------------------- flags


def _excess(name: str, v: np.ndarray, thr: float) -> np.ndarray:
    """(F,) how far beyond its threshold each value is (> 1: flagged), NaN -> 0."""
    v = np.asarray(v, float)
    base = name.split(".")[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        if base in LOWER_IS_BAD:
            e = thr / np.maximum(v, 1e-3 * thr)
            e = np.where(v < thr, np.maximum(e, 1.0 + 1e-9), np.minimum(e, 1.0))
        elif base == "sync_offset_frames":
            e = np.abs(v) / max(thr, 0.5)
            e = np.where(np.abs(v) > thr, np.maximum(e, 1.0 + 1e-9), np.minimum(e, 1.0))
        else:
            e = v / thr if thr > 0 else np.where(v > thr, np.inf, 0.0)
            e = np.where(v > thr, np.maximum(e, 1.0 + 1e-9), np.minimum(e, 1.0))
    return np.where(np.isfinite(v), e, 0.0)


def flag_frames(m: QAMetrics, opts: QAOptions = QAOptions()) -> Flags:
    """The frames beyond a threshold, with their reasons, merged into spans: flagged frames at
    most ``opts.merge_gap_frames`` fit frames (positions in ``m.frames``) apart share a span.
    Thresholds come from ``opts`` (``not_valid``: ``m.thresholds``, 0.5)."""
    reasons = tuple(n for n in m.thresholds if n in m.values)
    F = len(m.frames)
    thr = {n: (float(m.thresholds[n]) if threshold_name(n) is None else _threshold(n, opts))
           for n in reasons}
    exc = np.zeros((F, len(reasons)))
    for r, n in enumerate(reasons):
        exc[:, r] = _excess(n, m.values[n], thr[n])
    flagged = exc > 1.0
    spans: list[Span] = []
    rows = np.flatnonzero(flagged.any(axis=1)) if len(reasons) else np.zeros(0, int)
    if len(rows):
        cuts = np.flatnonzero(np.diff(rows) > opts.merge_gap_frames) + 1
        for grp in np.split(rows, cuts):
            a, b = int(grp[0]), int(grp[-1])
            sub = flagged[a:b + 1]
            rs = [reasons[r] for r in range(len(reasons)) if sub[:, r].any()]
            e = np.where(flagged[a:b + 1], exc[a:b + 1], 0.0)
            peak = a + int(np.unravel_index(int(np.argmax(e)), e.shape)[0])
            peak_excess = float(e.max())
            worst = {}
            for n in rs:
                v = np.asarray(m.values[n][a:b + 1], float)
                v = v[np.isfinite(v)]
                base = n.split(".")[0]
                if base in LOWER_IS_BAD:
                    worst[n] = float(v.min())
                elif base == "sync_offset_frames":
                    worst[n] = float(v[np.argmax(np.abs(v))])
                else:
                    worst[n] = float(v.max())
            spans.append(Span(int(m.frames[a]), int(m.frames[b]), rs, int(m.frames[peak]), worst,
                              peak_excess))
    return Flags(reasons, flagged, spans)


# ---------------------------------------------------------------------------- posing


def _rows(have: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Row of each of ``want`` in the increasing ``have`` (-1: absent)."""
    have = np.asarray(have)
    want = np.asarray(want)
    if not len(have):
        return np.full(len(want), -1)
    pos = np.searchsorted(have, want).clip(0, len(have) - 1)
    return np.where(have[pos] == want, pos, -1)


def _pose(model, fit, rows: np.ndarray, chunk: int = 64):
    """(vertices (F, V, 3) float32, kp65 (F, 65, 3) float64) of ``fit`` at ``rows``."""
    from body import forward, rest_state
    from body.joints import regress, regressor

    R = regressor(model, "kp65")
    rest = rest_state(model, np.asarray(fit.betas, float))
    V = np.empty((len(rows), model.num_vertices, 3), np.float32)
    P = np.empty((len(rows), R.shape[0], 3))
    for s in range(0, len(rows), chunk):
        i = rows[s:s + chunk]
        o = forward(model, None, fit.body_pose[i], fit.global_orient[i], fit.transl[i], rest=rest)
        V[s:s + chunk] = o.vertices
        P[s:s + chunk] = regress(R, o.vertices, o.joints)
    return V, P


_POSED: dict = {}  # id(fit) -> (fit, rows, kp65 (F, 65, 3)): what sequence_metrics posed


def _kp65_all(model, fit, chunk: int = 64) -> np.ndarray:
    """(F, 65, 3) KP65 keypoints of ``fit`` on all its frames (the sync's wearer); the ones
    :func:`sequence_metrics` posed when it posed every frame (the same numbers)."""
    hit = _POSED.get(id(fit))
    if hit is not None and hit[0] is fit and np.array_equal(hit[1], np.arange(fit.num_frames)):
        return hit[2]
    return _pose(model, fit, np.arange(fit.num_frames), chunk)[1]


# ---------------------------------------------------------------------------- per metric


def _marker_metrics(wearer, rows, values, units):
    res = np.asarray(wearer.marker_residual_m, float)[rows] * 1000.0
    seen = np.isfinite(res).any(axis=1)
    med = np.full(len(rows), np.nan)
    mx = np.full(len(rows), np.nan)
    with np.errstate(all="ignore"):
        med[seen] = np.nanmedian(res[seen], axis=1)
        mx[seen] = np.nanmax(res[seen], axis=1)
    values["wearer.marker_median_mm"] = med
    values["wearer.marker_max_mm"] = mx
    units["wearer.marker_median_mm"] = units["wearer.marker_max_mm"] = "mm"


def _median_rows(e: np.ndarray, need: int) -> np.ndarray:
    """(F,) median over axis 1 of e (F, n) where at least ``need`` values are finite."""
    out = np.full(len(e), np.nan)
    ok = np.isfinite(e).sum(1) >= need
    if ok.any():
        out[ok] = np.nanmedian(e[ok], axis=1)
    return out


def _limb_errors(err: np.ndarray, err_flip: np.ndarray) -> np.ndarray:
    """(F, 65) per-keypoint errors with each limb (``constants.LIMBS``) read directly or
    mirrored, whichever fits better in the frame (a detector that swapped the legs or the hands
    in a view is not a fit error); NaN where not detected."""
    out = np.array(err, float)
    for group in K.LIMBS.values():
        for limb in group:
            idx = list(limb)
            need = min(K.MIN_LIMB_POINTS, len(idx))
            a = _median_rows(err[:, idx], need)
            b = _median_rows(err_flip[:, idx], need)
            use = np.isfinite(a) & (b < a)
            out[np.ix_(use, idx)] = err_flip[np.ix_(use, idx)]
    return out


def _group_error(e: np.ndarray, group: str, statistic: str) -> np.ndarray:
    """(F,) one view's error of a group from per-keypoint errors e (F, 65): the largest limb
    median (``"limb"``) or the group's median (``"median"``)."""
    parts = (K.GROUPS[group],) if statistic == "median" else K.LIMBS[group]
    M = np.stack([_median_rows(e[:, list(p)], min(K.MIN_LIMB_POINTS, len(p))) for p in parts], 1)
    out = np.full(len(e), np.nan)
    ok = np.isfinite(M).any(1)
    out[ok] = np.nanmax(M[ok], axis=1)
    return out


def _views_error(E: np.ndarray, group: str) -> np.ndarray:
    """(F,) cross-view error of a group from per-view keypoint errors E (C, F, 65): for each
    unit (a keypoint of the body or face; a whole hand, by its median) the second largest
    error over the views that see it (at least ``MIN_VIEWS``), then the largest unit. A fit
    error moves a keypoint in most views, a detection error in one."""
    if group == "hands":
        units = [np.stack([_median_rows(E[c][:, list(h)], K.MIN_LIMB_POINTS)
                           for c in range(len(E))], 0) for h in K.LIMBS["hands"]]
    else:
        units = [E[:, :, k] for k in K.GROUPS[group]]
    cols = []
    for U in units:  # (C, F)
        n = np.isfinite(U).sum(0)
        m = np.full(U.shape[1], np.nan)
        ok = n >= K.MIN_VIEWS
        if ok.any():  # the second largest: seen off in two views at least
            srt = np.sort(np.where(np.isfinite(U[:, ok]), U[:, ok], -np.inf), axis=0)
            m[ok] = srt[-2]
        cols.append(m)
    M = np.stack(cols, 1)
    out = np.full(M.shape[0], np.nan)
    ok = np.isfinite(M).any(1)
    out[ok] = np.nanmax(M[ok], axis=1)
    return out


def _reprojection(person: str, pidx: int, P3: np.ndarray, frames, keypoints, cams, opts,
                  values, units):
    from calib import project

    krows = _rows(np.asarray(keypoints.frames), frames)
    have = krows >= 0
    flip = list(S.KP65_FLIP)
    E = []
    for cam in cams:
        try:
            c = keypoints.camera(cam.name)
        except KeyError:
            continue
        det = np.full((len(frames), P3.shape[1], 3), np.nan)
        det[have] = np.asarray(keypoints.kp[c][krows[have], pidx], float)
        ok = det[..., 2] >= opts.min_conf
        uv = project(cam, P3)
        err = np.where(ok, np.linalg.norm(uv - det[..., :2], axis=-1), np.nan)
        err_flip = np.where(ok[:, flip], np.linalg.norm(uv - det[:, flip, :2], axis=-1), np.nan)
        e = _limb_errors(err, err_flip)
        E.append(e)
        for g in GROUP_NAMES:
            n = f"{person}.reproj_{g}_px.{cam.name}"
            values[n] = _group_error(e, g, opts.reproj_statistic)
            units[n] = "px"
    if not E:
        return
    E = np.stack(E, 0)
    for g in GROUP_NAMES:
        n = f"{person}.reproj_views_{g}_px"
        values[n] = _views_error(E, g)
        units[n] = "px"


def _sync_people(model, fits, keypoints, marker_track=None):
    """For each (fit, person index): (``at(t0, s)`` -> kp65 (n, 65, 3) at video frames
    ``t0 + s`` (t0 fit frames), usable detection frames, person index).

    A fit on every video frame is read as it is. The wearer's fit on a stride, with
    ``marker_track`` (``marker_track(frames float (n,)) -> (n, M, 3)`` the capture resampled on
    the video clock, NaN = gap): each keypoint moves from its fitted
    position at t0 as its nearest marker (within ``SYNC_MARKER_RADIUS_M``) moved between t0
    and t0 + s: the capture's own rate (100 Hz and more) resolves the shift even when the fit
    has a stride. Else a cubic spline through the fit's frames."""
    from scipy.interpolate import CubicSpline

    kf = np.asarray(keypoints.frames)
    shifts = np.asarray(K.SYNC_SHIFTS)
    out = []
    for fit, pidx in fits:
        wf = np.asarray(fit.frames)
        if len(wf) < 4:
            continue
        P = _kp65_all(model, fit)
        valid = np.asarray(fit.valid, bool)
        full_rate = bool(np.all(np.diff(wf) == 1))
        if marker_track is not None and pidx == 0 and not full_rate:
            def at(t0, s, P=P, wf=wf):
                t0 = np.asarray(t0)
                base = P[_rows(wf, t0)]  # (n, 65, 3)
                m0 = marker_track(t0.astype(float))
                m1 = marker_track((t0 + s).astype(float))
                d = np.linalg.norm(base[:, :, None] - m0[:, None], axis=-1)  # (n, 65, M)
                d = np.where(np.isfinite(d), d, np.inf)
                near = np.argmin(d, axis=-1)
                close = np.take_along_axis(d, near[..., None], -1)[..., 0] <= K.SYNC_MARKER_RADIUS_M
                idx = np.arange(len(t0))[:, None]
                move = m1[idx, near] - m0[idx, near]
                move[~close] = np.nan
                return base + move
            use = np.isin(kf, wf)
        elif full_rate:
            def at(t0, s, P=P, wf=wf):
                return P[_rows(wf, np.asarray(t0) + s)]
            use = (kf + shifts.min() >= wf[0]) & (kf + shifts.max() <= wf[-1])
        else:
            spline = CubicSpline(wf, P, axis=0)

            def at(t0, s, spline=spline):
                return spline(np.asarray(t0) + s)
            use = (kf + shifts.min() >= wf[0]) & (kf + shifts.max() <= wf[-1])
        vi = np.searchsorted(wf, kf).clip(0, len(wf) - 1)  # the fit frames around are valid
        use &= valid[vi] & valid[(vi - 1).clip(0)]
        out.append((at, use, pidx))
    return out


def _paired_z(d: np.ndarray, unit: np.ndarray) -> float:
    """How many standard errors the mean of ``d`` (per detection, the error at shift 0 minus
    the error at the best shift) lies above 0, with the person-frames ``unit`` as the samples:
    the detections of one frame share its pose, so they are not independent of each other.
    +inf when every person-frame gains the same, 0 with fewer than 3 person-frames."""
    u, inv = np.unique(unit, return_inverse=True)
    if len(u) < 3:
        return 0.0
    g = np.bincount(inv, weights=d) / np.bincount(inv)
    sd = float(g.std(ddof=1))
    if sd == 0.0:
        return float("inf") if g.mean() > 0 else 0.0
    return float(g.mean() / (sd / np.sqrt(len(u))))


def _sync_rise(cost: dict[int, float], best: int) -> float:
    """How much a view's mean cost rises (relative) from the chosen shift ``best`` to the shift
    ``SYNC_SENSE_FRAMES`` away on each side (the farthest tried up to there), the smaller side:
    whether the view could tell its offset from one that many frames away. Detections that do
    not follow the motion (a view reading somebody else, or nobody) leave the cost flat."""
    rise = []
    for side in (-1, 1):
        near = [s for s in cost if 0 < side * (s - best) <= K.SYNC_SENSE_FRAMES]
        if near:
            far = max(near, key=lambda s: side * (s - best))
            rise.append(cost[far] / max(cost[best], 1e-9) - 1.0)
    return min(rise, default=0.0)


def _sync(model, fits, keypoints, cams, opts, seq, marker_track=None):
    """Per view the best time shift of the detections against the fits (the wearer first; see
    the module doc) and the cost of each shift. fits: [(BodyFit, person index)]."""
    from calib import project

    kf = np.asarray(keypoints.frames)
    shifts = [int(s) for s in K.SYNC_SHIFTS]
    pts = list(K.BODY + K.HANDS)
    offsets, costs, points, unmeasured, zs, rises, why = {}, {}, {}, [], {}, {}, {}
    people = _sync_people(model, fits, keypoints, marker_track)
    seq["sync_from"] = "markers" if marker_track is not None else "fit"
    for cam in cams:
        try:
            c = keypoints.camera(cam.name)
        except KeyError:
            continue
        err = {s: [] for s in shifts}
        unit = []  # the person-frame of each informative detection
        for at, use, pidx in people:
            det = np.asarray(keypoints.kp[c][:, pidx][:, pts], float)  # (Fk, n, 3)
            # the detector's own confidences: the cross-view check zeroes exactly the
            # keypoints a view out of sync gets wrong (its pixels are kept)
            conf = np.asarray(keypoints.conf_raw[c][:, pidx][:, pts], float)
            ok = (conf >= opts.min_conf) & np.isfinite(det[..., :2]).all(-1) & use[:, None]
            fr = np.flatnonzero(ok.any(1))
            if not len(fr):
                continue
            U = {s: project(cam, at(kf[fr], s)[:, pts].reshape(-1, 3)).reshape(len(fr), len(pts), 2)
                 for s in shifts}
            with np.errstate(invalid="ignore"):
                motion = np.max([np.linalg.norm(U[s] - U[0], axis=-1) for s in shifts], axis=0)
            known = np.all([np.isfinite(U[s]).all(-1) for s in shifts], axis=0)
            inf = ok[fr] & known & (np.nan_to_num(motion) >= K.SYNC_MIN_MOTION_PX)
            unit.append(np.broadcast_to(pidx * (int(kf.max()) + 1) + kf[fr][:, None], inf.shape)[inf])
            for s in shifts:
                err[s].append(np.minimum(np.linalg.norm(U[s] - det[fr, :, :2], axis=-1)[inf],
                                         K.SYNC_CAP_PX))
        e = {s: np.concatenate(v) if v else np.zeros(0) for s, v in err.items()}
        points[cam.name] = int(len(e[0]))
        if len(e[0]) < K.SYNC_MIN_POINTS:
            why[cam.name] = (f"{len(e[0])} detections that move with the shift (needs "
                             f"{K.SYNC_MIN_POINTS})")
            unmeasured.append(cam.name)
            continue
        cost = {s: float(e[s].mean()) for s in shifts}
        costs[cam.name] = {str(k): round(v, 3) for k, v in cost.items()}
        if min(cost.values()) > K.SYNC_MAX_COST_PX:  # most detections a miss at every shift
            why[cam.name] = (f"the best shift costs {min(cost.values()):.1f} px (more than "
                             f"{K.SYNC_MAX_COST_PX:.0f})")
            unmeasured.append(cam.name)
            continue
        best = min(cost, key=cost.get)
        if best in (min(shifts), max(shifts)):  # no minimum inside the range: a trend, not a shift
            why[cam.name] = f"no minimum inside {min(shifts)}..{max(shifts)} frames"
            unmeasured.append(cam.name)
            continue
        z = _paired_z(e[0] - e[best], np.concatenate(unit)) if best != 0 else 0.0
        zs[cam.name] = round(min(z, 999.0), 2)  # (JSON has no infinity)
        if z < K.SYNC_MIN_Z:
            best = 0
        rise = _sync_rise(cost, best)
        rises[cam.name] = round(rise, 3)
        if rise < K.SYNC_MIN_RISE:  # a cost that hardly moves with the shift cannot say "in sync"
            why[cam.name] = (f"flat: the cost rises {100 * rise:.0f} % "
                             f"{K.SYNC_SENSE_FRAMES} frames away (needs "
                             f"{100 * K.SYNC_MIN_RISE:.0f} %)")
            unmeasured.append(cam.name)
            continue
        offsets[cam.name] = int(best)
    seq["sync_offset_frames"] = offsets
    seq["sync_z"] = zs
    seq["sync_cost"] = costs
    seq["sync_points"] = points
    seq["sync_not_measurable"] = unmeasured
    seq["sync_rise"] = rises
    seq["sync_not_measurable_why"] = why
    return offsets


def _bbox(V, pad=0.0):
    return V.min(0) - pad, V.max(0) + pad


def _in_box(P, box):
    lo, hi = box
    return np.all((P >= lo) & (P <= hi), axis=1)


class _Surface:
    """Exact distances to one posed full mesh (libigl's AABB tree, what
    ``geometry.nearest_surface`` builds on every call), the tree built once on first use and
    kept for the frame's other queries against the same mesh.

    With ``anchors`` (points lying on the mesh, e.g. the proxy's) a query builds its tree
    over only the faces that can hold a nearest point: a point's distance to the surface is at
    most its distance ``b`` to the nearest anchor, so only faces whose bounding box meets the
    query points' boxes grown by their ``b`` (``cap``: by at most ``cap``, for a distance
    clipped there) can be nearer; the distances are the same as over the whole mesh (up to
    ``cap``)."""

    def __init__(self, V, faces, anchors=None):
        self.V = np.ascontiguousarray(V, dtype=np.float64)
        self.F = faces
        self.tree = None
        self.anchors = anchors
        self._kd = None
        self._fbox = None

    def distance(self, P: np.ndarray, cap: float | None = None) -> np.ndarray:
        import igl

        P = np.ascontiguousarray(P, np.float64)
        if self.anchors is None or self.tree is not None:
            if self.tree is None:
                self.tree = igl.AABB()
                self.tree.init(self.V, self.F)
            d2, _, _ = self.tree.squared_distance(self.V, self.F, P)
            return np.sqrt(np.maximum(np.asarray(d2), 0.0))
        from scipy.spatial import cKDTree

        if self._kd is None:
            self._kd = cKDTree(self.anchors)
            T = self.V[self.F]  # (T, 3, 3)
            self._fbox = (T.min(1), T.max(1))
        b = self._kd.query(P)[0] * (1 + 1e-9) + 1e-9
        if cap is not None:
            b = np.minimum(b, cap)
        lo, hi = (P - b[:, None]).min(0), (P + b[:, None]).max(0)
        near = np.all((self._fbox[0] <= hi) & (self._fbox[1] >= lo), axis=1)
        if not near.any():
            return np.full(len(P), np.inf)
        sub = np.ascontiguousarray(self.F[near])
        tree = igl.AABB()
        tree.init(self.V, sub)
        d2, _, _ = tree.squared_distance(self.V, sub, P)
        return np.sqrt(np.maximum(np.asarray(d2), 0.0))


class _Winding:
    """libigl's fast winding number against one posed proxy mesh, its hierarchy built once
    and kept for the frame's queries (``geometry.winding_number`` builds it on every call;
    the numbers are the same: each query point is evaluated on its own), and the exact
    distance to that mesh (an AABB tree, built on first use)."""

    def __init__(self, P, faces):
        import igl

        self.P = np.ascontiguousarray(P, np.float64)
        self.F = np.ascontiguousarray(faces, np.int64)
        self.bvh = igl.FastWindingNumberBVH()
        self.bvh.init(self.P, self.F)
        self.tree = None

    def __call__(self, Q) -> np.ndarray:
        Q = np.ascontiguousarray(Q, np.float64)
        return np.asarray(self.bvh.winding_number(Q)) if len(Q) else np.zeros(0)

    def distance(self, Q) -> np.ndarray:
        import igl

        if self.tree is None:
            self.tree = igl.AABB()
            self.tree.init(self.P, self.F)
        d2, _, _ = self.tree.squared_distance(self.P, self.F, np.ascontiguousarray(Q, np.float64))
        return np.sqrt(np.maximum(np.asarray(d2), 0.0))


GRID_BLOCK = 3  # cells per side of a block of the volume grid tested as one where it can be


def _grid_inside(W: _Winding, G: np.ndarray, n, want: np.ndarray) -> np.ndarray:
    """(N,) bool: the cells ``want`` (N,) bool of the grid ``G`` (N, 3) (``n`` cells per
    axis, ``indexing="ij"``) inside the mesh of ``W`` (winding number > 0.5); False elsewhere.

    Blocks of ``GRID_BLOCK``^3 cells whose wanted cells lie in a ball that the surface does
    not meet (exact distance from the ball's centre to the mesh larger than its radius) are
    on one side of the surface (the winding number is constant off the surface): one cell
    tested stands for the block. The other blocks test every cell. The same decisions as
    testing every cell wherever the fast winding number is on the right side of 0.5 off the
    surface (its error there is far smaller)."""
    out = np.zeros(len(G), bool)
    idx = np.flatnonzero(want)
    if not len(idx):
        return out
    n = tuple(int(x) for x in n)
    ijk = np.unravel_index(idx, n)
    nb_axis = tuple(-(-x // GRID_BLOCK) for x in n)
    bid = np.ravel_multi_index(tuple(a // GRID_BLOCK for a in ijk), nb_axis)
    _, blk = np.unique(bid, return_inverse=True)
    blk = blk.reshape(-1)
    nb = int(blk.max()) + 1
    X = G[idx]
    lo = np.full((nb, 3), np.inf)
    hi = np.full((nb, 3), -np.inf)
    np.minimum.at(lo, blk, X)
    np.maximum.at(hi, blk, X)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo, axis=1) / 2
    clear = W.distance(centre) > radius * (1 + 1e-9) + 1e-9
    first = np.full(nb, len(idx))
    np.minimum.at(first, blk, np.arange(len(idx)))
    test = ~clear[blk]  # every cell of a block the surface may cross
    test[first[clear]] = True  # one cell of the others
    w = W(X[test]) > 0.5
    res = np.zeros(len(idx), bool)
    res[test] = w
    rep = np.zeros(nb, bool)
    rep[clear] = res[first[clear]]
    res[clear[blk]] = rep[blk[clear[blk]]]
    out[idx] = res
    return out


def _pair_frame(VA, VB, faces, proxy, need_near: bool, posed=None):
    """Deepest interpenetration (m), penetrating volume (m^3) and (when ``need_near``) the
    closest distance (m, clipped at NEAR_M; 0 when penetrating) of two posed meshes VA, VB
    (V, 3) of one model.

    Subsampled where exactness is not needed: the inside test (winding number) is done with
    the proxy points of one body (``proxy.points``: surface points riding on the full mesh)
    against the other's proxy mesh; the depth of the points found inside is exact (nearest
    point of the other's full mesh). The volume counts the cells of a grid over the bounding
    box of the penetrating points inside both proxies (:func:`_grid_inside`: blocks of cells
    away from a surface tested by one cell); the closest distance is that of the proxy points
    to the other full mesh (both ways). One winding-number hierarchy per proxy mesh and
    frame serves all its queries. ``posed``: ((PA, PB), (WA, WB)) the proxy points and their
    :class:`_Winding` when the caller has them (the self-penetration's)."""
    if posed is None:
        PA, PB = proxy.points(VA), proxy.points(VB)
        wind: dict = {}
    else:
        (PA, PB), (WA, WB) = posed
        wind = {0: WA, 1: WB}
    pf = proxy.faces
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    SA, SB = _Surface(VA, faces, PA), _Surface(VB, faces, PB)
    pen, inside_pts = 0.0, []
    boxA, boxB = _bbox(VA), _bbox(VB)
    overlap = np.all(boxA[0] <= boxB[1]) and np.all(boxB[0] <= boxA[1])

    def winding(k):  # the proxy mesh of A (0) or B (1), its hierarchy built on first use
        if k not in wind:
            wind[k] = _Winding((PA, PB)[k], pf)
        return wind[k]

    if overlap:
        for X, (k, W, box) in ((PA, (1, SB, boxB)), (PB, (0, SA, boxA))):
            cand = np.flatnonzero(_in_box(X, box))
            if not len(cand):
                continue
            ins = cand[winding(k)(X[cand]) > 0.5]
            if len(ins):
                d = W.distance(X[ins])
                pen = max(pen, float(d.max()))
                inside_pts.append(X[ins])
    vol = 0.0
    if inside_pts:
        P = np.concatenate(inside_pts)
        lo, hi = P.min(0) - 2 * K.VOLUME_CELL_M, P.max(0) + 2 * K.VOLUME_CELL_M
        lo = np.maximum(lo, np.maximum(boxA[0], boxB[0]))
        hi = np.minimum(hi, np.minimum(boxA[1], boxB[1]))
        ext = np.maximum(hi - lo, 0.0)
        cell = K.VOLUME_CELL_M
        n = np.ceil(ext / cell).astype(int) + 1
        if n.prod() > K.VOLUME_MAX_CELLS:
            cell = float((np.prod(ext + cell) / K.VOLUME_MAX_CELLS) ** (1 / 3)) * 1.01
            n = np.ceil(ext / cell).astype(int) + 1
        g = [lo[k] + cell * (np.arange(n[k]) + 0.5) for k in range(3)]
        G = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
        inA = _grid_inside(winding(0), G, n, np.ones(len(G), bool))
        if inA.any():
            inB = _grid_inside(winding(1), G, n, inA)
            vol = float(inB.sum()) * cell ** 3
    near = np.nan
    if need_near:
        if pen > 0:
            near = 0.0
        else:
            near = K.NEAR_M
            for X, (W, box) in ((PA, (SB, boxB)), (PB, (SA, boxA))):
                cand = _in_box(X, (box[0] - K.NEAR_M, box[1] + K.NEAR_M))
                if cand.any():
                    d = W.distance(X[cand], cap=K.NEAR_M)
                    near = min(near, float(d.min()))
    return pen, vol, near


def _contact_gap(VA, VB, faces, sel):
    from geometry import facet_distances

    return max(float(facet_distances(VA, faces, a, VB, faces, b).a_to_b.min()) for a, b in sel)


_PER_MODEL: dict = {}  # (model content digest, what) -> built once per process (one model kept)


def _model_digest(model) -> str:
    """What a model's proxy is made of: its name, template and faces (every
    stage loads the model anew: a new object, the same content)."""
    import hashlib

    h = hashlib.sha1(str(getattr(model, "name", "")).encode())
    for a in (model.v_template, model.faces):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _per_model(model, what, build):
    """``build()``, once per model content and ``what`` in this process: the engine runs the
    qa stage of every sequence in one process, each loading the model anew (a new object, the
    same content). Only the latest model's are kept (a session has one)."""
    digest = _model_digest(model)
    if any(k[0] != digest for k in _PER_MODEL):
        _PER_MODEL.clear()
    key = (digest, what)
    if key not in _PER_MODEL:
        _PER_MODEL[key] = build()
    return _PER_MODEL[key]


def _proxy(model, ProxyMesh):
    """The model's ``ProxyMesh`` of ``K.PROXY_VERTICES`` (``igl.qslim``: ~0.7 s), once per
    model content in this process."""
    return _per_model(model, ProxyMesh, lambda: ProxyMesh.from_model(model, K.PROXY_VERTICES))


def qa_region_map(model):
    """``body.regions.region_map(model)`` (~0.1 s), once per model content in this process."""
    from body.regions import region_map

    return _per_model(model, "region_map", lambda: region_map(model))


def _foot_vertices(model) -> list[np.ndarray]:
    rm = qa_region_map(model)
    faces = np.asarray(model.faces)
    out = []
    for side in ("l", "r"):
        f = np.concatenate([rm.faces_of(f"{side}_{r}") for r in K.FOOT_REGIONS])
        out.append(np.unique(faces[f]))
    return out


def _person_metrics(person, fit, rows, V, P3, frames, fps, ground, feet, values, units):
    F = len(rows)
    step = np.diff(frames).astype(float)
    # not valid
    values[f"{person}.not_valid"] = (~np.asarray(fit.valid, bool)[rows]).astype(float)
    units[f"{person}.not_valid"] = ""
    # ground and foot skate
    gp = np.full(F, np.nan)
    sk = np.full(F, np.nan)
    if ground is not None:
        n = np.asarray(ground[0], float).reshape(3)
        n = n / np.linalg.norm(n)
        off = float(ground[1])
        h = V @ n.astype(np.float32) - np.float32(off)  # (F, V) height above the plane
        gp = np.maximum(0.0, -h.min(axis=1)).astype(float) * 1000.0
        for i in range(1, F):
            dt = step[i - 1] / fps
            best = np.nan
            for ids in feet:
                on = ids[(h[i, ids] < K.FOOT_CONTACT_M) & (h[i - 1, ids] < K.FOOT_CONTACT_M)]
                if len(on) < 3:
                    continue
                d = (V[i, on] - V[i - 1, on]).astype(float)
                d -= np.outer(d @ n, n)
                v = float(np.median(np.linalg.norm(d, axis=1))) / dt
                best = v if not best >= v else best
            sk[i] = best
    values[f"{person}.ground_penetration_mm"] = gp
    values[f"{person}.foot_skate_m_s"] = sk
    units[f"{person}.ground_penetration_mm"] = "mm"
    units[f"{person}.foot_skate_m_s"] = "m/s"
    # jerk over the body keypoints, on a time step of at least JERK_DT_S
    jk = np.full(F, np.nan)
    X = P3[:, list(K.FACE + K.BODY)]
    fs = float(np.median(step)) if len(step) else 1.0
    k = max(1, int(math.ceil(K.JERK_DT_S * fps / fs - 1e-9)))
    for i in range(2 * k, F - k):
        w = frames[[i - 2 * k, i - k, i, i + k]]
        d = np.diff(w)
        if not np.all(d == d[0]):
            continue
        dt = d[0] / fps
        d3 = X[i + k] - 3 * X[i] + 3 * X[i - k] - X[i - 2 * k]
        jk[i] = float(np.linalg.norm(d3, axis=1).max()) / dt ** 3
    values[f"{person}.jerk_m_s3"] = jk
    units[f"{person}.jerk_m_s3"] = "m/s3"
    # self-penetration on the proxy: filled by the frames' geometry pass (_geometry)
    values[f"{person}.self_penetration_mm"] = np.zeros(F)
    units[f"{person}.self_penetration_mm"] = "mm"


# ---------------------------------------------------------------------------- per-frame geometry

_GEOM: dict | None = None  # a worker process's static part of the geometry pass
PARALLEL_MIN_FRAMES = 48   # per worker: fewer frames run in one process (a worker's start
                           # costs ~1-2 CPU-s of imports, about 10 frames of this pass)


def _geometry_frames(g: dict, rows, verts, frames) -> list[tuple]:
    """Per frame: (row, self-penetration m per person, deepest interpenetration m, volume m^3,
    closest distance m, contact gap m; NaN = not measured). ``g`` the static part (proxy,
    faces, contact, sel, lo, hi); ``verts`` one (len(rows), V, 3) array per person and
    ``frames`` (len(rows),) the rows' frame numbers."""
    from fitting.collision import self_penetration

    proxy = g["proxy"]
    out = []
    for k, i in enumerate(rows):
        # each posed proxy's winding-number hierarchy, built once for both passes
        P = [proxy.points(V[k].astype(float)) for V in verts]
        W = [_Winding(p, proxy.faces) for p in P]
        sp = [self_penetration(proxy, p, winding=w) for p, w in zip(P, W, strict=True)]
        pen = vol = near = gap = np.nan
        if len(verts) == 2:
            f = int(frames[k])
            a, b = (V[k].astype(float) for V in verts)
            contact, lo, hi = g["contact"], g["lo"], g["hi"]
            outside = contact is not None and not (contact.has_contact and lo <= f <= hi)
            pen, vol, near = _pair_frame(a, b, g["faces"], g["proxy"], outside, (P, W))
            if g["sel"] and contact.active(f):
                gap = _contact_gap(a, b, g["faces"], g["sel"])
        out.append((int(i), sp, pen, vol, near, gap))
    return out


def _geometry_init(static: dict) -> None:
    """Worker initializer: the static part of the pass, sent once per worker."""
    global _GEOM
    _GEOM = static


def _geometry_chunk(rows, verts, frames) -> list[tuple]:
    return _geometry_frames(_GEOM, rows, verts, frames)


def _geometry(geom: dict, F: int, workers: int, progress) -> list[tuple]:
    """:func:`_geometry_frames` over the ``F`` frames, in frame order: in ``workers`` worker
    processes when more than one and every worker gets ``PARALLEL_MIN_FRAMES`` (frames
    interleaved over chunks; each frame's numbers are the same either way).

    The workers are spawned (``pipeline.procs.process_pool``: they die with this process and
    are killed when the pass fails or is interrupted), never forked: a fork of a process with
    threads and OpenMP pools, carrying the engine's SIGTERM handler, could hang in the child or
    outlive ``Pool.terminate`` (a CI run hung on it). Each chunk carries its own frames'
    vertices; the proxy, faces and contact go once per worker."""
    verts, frames = geom["verts"], np.asarray(geom["frames"])
    static = {k: v for k, v in geom.items() if k not in ("verts", "frames")}
    workers = max(1, min(int(workers), F // max(1, PARALLEL_MIN_FRAMES)))
    n_chunks = min(F, max(1, 4 * workers))
    chunks = [np.arange(F)[k::n_chunks] for k in range(n_chunks)]

    def show(it):
        return it if progress is None else progress(it, total=len(chunks),
                                                    desc="qa geometry (chunks)")

    if workers > 1:
        import concurrent.futures as cf

        from pipeline.procs import process_pool

        with process_pool(workers, initializer=_geometry_init, initargs=(static,)) as pool:
            futs = [pool.submit(_geometry_chunk, rows, [V[rows] for V in verts], frames[rows])
                    for rows in chunks]
            res = [r for fut in show(cf.as_completed(futs)) for r in fut.result()]
    else:
        res = [r for rows in show(chunks)
               for r in _geometry_frames(static, rows, [V[rows] for V in verts], frames[rows])]
    return sorted(res, key=lambda r: r[0])


SHARE_CHUNKS = 10  # chunks of the pass given to a pool that this process can take back


class _SharedGeometry:
    """The per-frame geometry pass (:func:`_geometry_frames`) shared between a pool and this
    process: submitted to ``pool`` in ``SHARE_CHUNKS`` runs of consecutive frames as soon as
    the bodies are posed; :meth:`result`, called when this process has computed its other
    metrics, takes back the chunks the pool has not started, from the last one on (a pool
    works through its queue from the first), computes them here, then waits for the rest.
    Each frame's numbers are the same wherever it runs. A pool's task that failed raises
    here."""

    def __init__(self, pool, geom: dict):
        self.static = {k: v for k, v in geom.items() if k not in ("verts", "frames")}
        self.verts, self.frames = geom["verts"], np.asarray(geom["frames"])
        F = len(self.frames)
        self.parts = [r for r in np.array_split(np.arange(F), min(F, SHARE_CHUNKS)) if len(r)]
        self.futures = [pool.submit(_geometry_frames, self.static, rows,
                                    [V[rows] for V in self.verts], self.frames[rows])
                        for rows in self.parts]

    def result(self) -> list[tuple]:
        out = []
        for k in reversed(range(len(self.parts))):
            if not self.futures[k].cancel():  # started (or done) in the pool: so are those before
                break
            rows = self.parts[k]
            out += _geometry_frames(self.static, rows, [V[rows] for V in self.verts],
                                    self.frames[rows])
        for f in self.futures:
            if not f.cancelled():
                out += f.result()
        return sorted(out, key=lambda r: r[0])


# ---------------------------------------------------------------------------- the sequence


def capture_repairs(changed: np.ndarray, rate_hz: float, first_frame: int, frames: np.ndarray,
                    clock) -> np.ndarray:
    """(F,) per fit frame, how many of the wearer's markers had a capture sample repaired by
    the cleaning step (un-swapped, or removed as a ghost, spike or swap) among the samples the
    frame is interpolated from. changed : (Fs, M) bool per capture sample and marker
    (``artifacts.capture.Markers.repaired``); rate_hz, first_frame : the capture's; frames :
    video frames (or capture frames on a marker-only sequence); clock :
    ``fitting.mocap.VideoClock``."""
    from fitting.mocap import frame_times

    changed = np.asarray(changed, bool)
    rate = clock.rate_hz or float(rate_hz)
    t_src = (int(first_frame) + np.arange(len(changed))) / rate
    frames = np.asarray(frames, dtype=int)
    if not len(frames):
        return np.zeros(0)
    t = frame_times(int(frames.max()) + 1, clock.fps, clock.sync_offset_s)[frames]
    # the two samples around each frame time (what the linear resampling reads)
    hi = np.clip(np.searchsorted(t_src, t), 0, len(t_src) - 1)
    lo = np.clip(hi - 1, 0, len(t_src) - 1)
    return (changed[lo] | changed[hi]).sum(axis=1).astype(float)


def marker_track(markers, clock):
    """``track(frames float (n,)) -> (n, M, 3)``: the capture linearly resampled at (fractional)
    video frames on ``clock`` (``fitting.mocap.VideoClock``), NaN where a marker is not seen."""
    from fitting.mocap import resample

    rate = clock.rate_hz or markers.rate_hz
    t_src = (markers.first_frame + np.arange(len(markers.xyz))) / rate

    def track(frames):
        t = np.asarray(frames, float) / clock.fps - clock.sync_offset_s
        obs, vis = resample(t_src, markers.xyz, t)
        return np.where(vis[..., None], obs, np.nan)
    return track


def qa_frames(wearer, partner) -> np.ndarray:
    """(F,) int64 the QA frames (:func:`sequence_metrics`): the partner's frames that the
    wearer's fit also has (all of them without a wearer), else the wearer's frames."""
    if partner is not None:
        frames = np.asarray(partner.frames)
        if wearer is not None:
            frames = frames[_rows(np.asarray(wearer.frames), frames) >= 0]
    else:
        frames = np.asarray(wearer.frames)
    return frames.astype(np.int64)


def sequence_metrics(model, wearer, partner, keypoints, cams, contact, ground, fps: float,
                     opts: QAOptions = QAOptions(), progress=None,
                     repaired: np.ndarray | None = None, marker_track=None,
                     workers: int = 1, pool=None) -> QAMetrics:
    """Every per-frame metric of a sequence (module doc), with the thresholds they are flagged
    against.

    model : ``body.BodyModel``; wearer, partner : ``artifacts.BodyFit`` or None (at least one);
    keypoints : ``artifacts.Keypoints2D`` or None (no reprojection, no sync); cams : list of
    ``calib.Camera`` (their order is the metric order); contact : a
    ``fitting.contact_signature.ContactAnnotation`` or None; ground : ``(normal (3,), offset)``
    or None; fps : video rate; progress : ``ctx.progress``-like wrapper or None;
    repaired : (F_w,) on the wearer's fit frames, markers repaired per frame
    (:func:`capture_repairs`), giving ``wearer.markers_repaired``; marker_track :
    ``marker_track(video frames float (n,)) -> (n, M, 3)`` the wearer's cleaned capture on the
    video clock (NaN = gap), which the sync check follows between fit frames; workers : the
    per-frame geometry (self-penetration, interpenetration, contact) in this many spawned
    processes (1: in this one; the numbers are the same); pool : an executor (e.g. a process
    pool's, ``pipeline.procs.process_pool``) given the per-frame geometry in chunks as soon as
    the bodies are posed, while this process computes the other metrics; this process then
    takes back the chunks the pool has not started (:class:`_SharedGeometry`); not used when
    ``workers`` would run the pass in several processes (the numbers are the same). QA
    frames: the partner's frames that the wearer's fit also has (all of them without a
    wearer), else the wearer's frames."""
    from fitting.collision import ProxyMesh

    if wearer is None and partner is None:
        raise ValueError("sequence_metrics: no fit (wearer and partner are both None)")
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps!r}")
    frames = qa_frames(wearer, partner)
    F = len(frames)
    values: dict[str, np.ndarray] = {}
    units: dict[str, str] = {}
    seq: dict = {"frames": int(F), "fps": float(fps)}
    fits = [(n, f) for n, f in zip(PEOPLE, (wearer, partner), strict=True) if f is not None]
    _POSED.clear()
    proxy = _proxy(model, ProxyMesh)
    feet = _foot_vertices(model) if ground is not None else []
    verts, people, posed = [], [], []
    seq["people"] = []
    for person, fit in fits:
        rows = _rows(np.asarray(fit.frames), frames)
        V, P3 = _pose(model, fit, rows)
        _POSED[id(fit)] = (fit, rows, P3)
        verts.append(V)
        people.append(person)
        posed.append((rows, V, P3))
    # per frame geometry: self-penetration of each, and between the two (given to ``pool``
    # now, when there is one)
    geom = {"verts": verts, "proxy": proxy, "faces": np.asarray(model.faces), "frames": frames,
            "contact": contact, "sel": [], "lo": None, "hi": None}
    if len(verts) == 2:
        if contact is not None and contact.has_contact:
            from fitting.contact_signature import select_facets

            geom["sel"] = select_facets(contact, qa_region_map(model), "all")
        if contact is not None:
            geom["lo"] = contact.interval[0] - opts.contact_margin_frames
            geom["hi"] = contact.interval[1] + opts.contact_margin_frames
    pending = None
    if pool is not None and min(int(workers), F // PARALLEL_MIN_FRAMES) <= 1:
        # (enough frames for several workers: :func:`_geometry`'s own processes, below)
        pending = _SharedGeometry(pool, geom)
    for (person, fit), (rows, V, P3) in zip(fits, posed, strict=True):
        if person == "wearer" and fit.has_markers:
            _marker_metrics(fit, rows, values, units)
            if repaired is not None:
                values["wearer.markers_repaired"] = np.asarray(repaired, float)[rows]
                units["wearer.markers_repaired"] = "markers"
        if keypoints is not None:
            _reprojection(person, PEOPLE.index(person), P3, frames, keypoints, cams, opts,
                          values, units)
        _person_metrics(person, fit, rows, V, P3, frames, float(fps), ground, feet, values,
                        units)
        seq["people"].append({"role": person, "frames": int(F),
                              "not_valid": int((~np.asarray(fit.valid, bool)[rows]).sum())})
    # sync: the wearer (the marker fit does not depend on the videos) and the partner (its
    # fit takes the view under test in, which pulls toward no shift: the test stays cautious)
    if keypoints is not None:
        sync_fits = [(f, PEOPLE.index(n)) for n, f in fits]
        offs = _sync(model, sync_fits, keypoints, cams, opts, seq, marker_track)
        for cam, s in offs.items():
            values[f"sync_offset_frames.{cam}"] = np.full(F, float(s))
            units[f"sync_offset_frames.{cam}"] = "frames"
    _POSED.clear()
    pen = np.full(F, np.nan)
    vol = np.full(F, np.nan)
    gap = np.full(F, np.nan)
    unexp = np.full(F, np.nan)
    if len(verts) == 2:
        if contact is not None:
            seq["contact"] = {"interval": [int(x) for x in contact.interval],
                              "has_contact": bool(contact.has_contact),
                              "margin_frames": int(opts.contact_margin_frames)}
    res = (pending.result() if pending is not None
           else _geometry(geom, F, max(1, int(workers)), progress))
    for i, sp, p, v, near, g in res:
        for person, d in zip(people, sp, strict=True):
            values[f"{person}.self_penetration_mm"][i] = d * 1000.0
        if len(verts) == 2:
            pen[i], vol[i] = p * 1000.0, v * 1e6
            if np.isfinite(near):
                unexp[i] = near * 1000.0
            if np.isfinite(g):
                gap[i] = g * 1000.0
    for n, v, u in (("penetration_mm", pen, "mm"), ("penetration_volume_cm3", vol, "cm3"),
                    ("contact_gap_mm", gap, "mm"), ("unexpected_contact_mm", unexp, "mm")):
        values[n] = v
        units[n] = u
    thresholds = {n: _threshold(n, opts) for n in values
                  if threshold_name(n) is not None or n.endswith(".not_valid")}
    return QAMetrics(frames, values, units, thresholds, seq, verts, people)


def body_proxy(model):
    """The model's QA proxy (``fitting.collision.ProxyMesh`` of ``constants.PROXY_VERTICES``
    vertices riding on the full mesh), the one the metrics use (built once per model object)."""
    from fitting.collision import ProxyMesh

    return _proxy(model, ProxyMesh)
