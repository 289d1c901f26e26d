"""Stage ``qa``'s typed outputs: the per-frame metrics and flags (``qa.npz``, :class:`QAMetrics`)
and what the later stages read of a sequence's QA (``flags.json``, :class:`QAResult`: the
summary, the flagged spans and each flagged frame's reasons, the thresholds, and the relative
names of the files the stage drew: ``report.html``, ``qa.png``, the overlays, the video, the
scene). ``release`` (the datasheet's QA section) and ``qa_index`` read :class:`QAResult` only.

Axes: ``F`` QA frames (video frame indices in ``frames``), ``N`` metrics (``names``), ``R``
reasons that can flag (``reasons``: metric names).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from artifacts.base import (
    ArtifactError,
    FieldSpec,
    JsonArtifact,
    JsonFields,
    TypedArtifact,
    check_relative,
    first_frame,
)

# constants
RATE_TOL = 1e-9  # flagged_rate == flagged_frames / frames within this


@dataclass(frozen=True, eq=False)
class QAMetrics(TypedArtifact):
    """frames : (F,) video frames, increasing; names : (N,) metric names (unique); values :
    (F, N) NaN = not applicable; reasons : (R,) the metrics that can flag (unique); flagged :
    (F, R) bool."""

    KIND: ClassVar[str] = "qa_metrics"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "qa"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("frames", "iu", "F"),
        FieldSpec("names", "U", "N"),
        FieldSpec("values", "f", "F N", doc="NaN = not applicable"),
        FieldSpec("reasons", "U", "R"),
        FieldSpec("flagged", "b", "F R"),
    )

    frames: np.ndarray
    names: np.ndarray
    values: np.ndarray
    reasons: np.ndarray
    flagged: np.ndarray

    @property
    def any(self) -> np.ndarray:
        """(F,) bool: frames flagged by at least one reason."""
        fl = np.asarray(self.flagged, bool)
        return fl.any(axis=1) if fl.shape[1] else np.zeros(len(fl), bool)

    def metric(self, name: str) -> np.ndarray:
        """(F,) values of one metric (KeyError naming the known ones)."""
        names = [str(n) for n in self.names]
        if name not in names:
            raise KeyError(f"no metric {name!r} (known: {', '.join(names)})")
        return np.asarray(self.values)[:, names.index(name)]

    def flagged_by(self, frames, which) -> np.ndarray:
        """(len(frames),) whether each video frame is flagged by a reason ``r`` with
        ``which(r)``; False for frames QA did not measure."""
        fr = np.asarray(self.frames)
        frames = np.asarray(frames)
        cols = [i for i, r in enumerate(self.reasons) if which(str(r))]
        rows = np.searchsorted(fr, frames)
        ok = (rows < len(fr)) & (fr[np.minimum(rows, max(len(fr) - 1, 0))] == frames) if len(fr) \
            else np.zeros(len(frames), bool)
        out = np.zeros(len(frames), bool)
        if cols and ok.any():
            out[ok] = np.asarray(self.flagged)[rows[ok]][:, cols].any(axis=1)
        return out

    def _check(self, file: Path) -> None:
        fr = np.asarray(self.frames)
        if np.any(fr < 0):
            raise ArtifactError(file, "frames", "negative video frame index", first_frame(fr < 0))
        if len(fr) > 1 and np.any(np.diff(fr) <= 0):
            raise ArtifactError(file, "frames", "not increasing", int(np.argmax(np.diff(fr) <= 0)) + 1)
        for n in ("names", "reasons"):
            v = [str(x) for x in getattr(self, n)]
            if len(set(v)) != len(v):
                raise ArtifactError(file, n, f"duplicate names {sorted({x for x in v if v.count(x) > 1})}")
        inf = np.isinf(np.asarray(self.values, float))
        if inf.any():
            raise ArtifactError(file, "values", "infinite value (NaN is 'not applicable')",
                                first_frame(inf))


@dataclass(frozen=True)
class QASummary:
    """What a reviewer sorts by: frames measured, frames flagged and their share, the number
    of spans, frames per reason, frames not valid per person, each camera's estimated sync
    offset in frames (0 = in sync), the people measured, the metrics' wall time."""

    frames: int
    flagged_frames: int
    flagged_rate: float
    spans: int
    per_reason: dict[str, int] = field(default_factory=dict)
    not_valid: dict[str, int] = field(default_factory=dict)
    sync_offset_frames: dict[str, int] = field(default_factory=dict)
    people: tuple[str, ...] = ()
    metrics_s: float = 0.0

    @property
    def out_of_sync(self) -> dict[str, int]:
        """The cameras with a non-zero offset."""
        return {c: v for c, v in self.sync_offset_frames.items() if v}

    def to_json(self) -> dict:
        return {"frames": int(self.frames), "flagged_frames": int(self.flagged_frames),
                "flagged_rate": float(self.flagged_rate), "spans": int(self.spans),
                "per_reason": {k: int(v) for k, v in self.per_reason.items()},
                "not_valid": {k: int(v) for k, v in self.not_valid.items()},
                "sync_offset_frames": {k: int(v) for k, v in self.sync_offset_frames.items()},
                "people": list(self.people), "metrics_s": float(self.metrics_s)}

    @classmethod
    def from_json(cls, f: JsonFields) -> QASummary:
        return cls(frames=f.get("frames", int), flagged_frames=f.get("flagged_frames", int),
                   flagged_rate=f.get("flagged_rate", float), spans=f.get("spans", int),
                   per_reason=f.mapping("per_reason", int), not_valid=f.mapping("not_valid", int),
                   sync_offset_frames=f.mapping("sync_offset_frames", int),
                   people=tuple(f.items("people", str)), metrics_s=f.get("metrics_s", float))


@dataclass(frozen=True)
class QASpan:
    """Flagged video frames ``start..end`` (inclusive), the reasons inside, the frame of the
    worst excess and each reason's worst value (None: not a number)."""

    start: int
    end: int
    reasons: tuple[str, ...]
    peak_frame: int
    worst: dict[str, float | None] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"start": int(self.start), "end": int(self.end), "reasons": list(self.reasons),
                "peak_frame": int(self.peak_frame),
                "worst": {k: (None if v is None or not np.isfinite(v) else float(v))
                          for k, v in self.worst.items()}}

    @classmethod
    def from_json(cls, f: JsonFields) -> QASpan:
        s = cls(start=f.get("start", int), end=f.get("end", int),
                reasons=tuple(f.items("reasons", str)), peak_frame=f.get("peak_frame", int),
                worst=f.mapping("worst", float, nullable=True, finite=False))
        if not s.start <= s.peak_frame <= s.end:
            raise f.error("peak_frame", f"{s.peak_frame} outside the span {s.start}..{s.end}",
                          s.peak_frame)
        return s


@dataclass(frozen=True)
class QAFiles:
    """Relative names (in the qa folder) of what the stage drew; None / empty: not drawn.
    overlays : {video frame: png}; span_frames / sample_frames : the frames chosen for an
    overlay (span starts, peaks and ends; a sample of the rest)."""

    report: str | None = None
    plot: str | None = None
    overlays: dict[int, str] = field(default_factory=dict)
    span_frames: tuple[int, ...] = ()
    sample_frames: tuple[int, ...] = ()
    video: str | None = None
    scene: str | None = None

    def to_json(self) -> dict:
        return {"report": self.report, "plot": self.plot,
                "overlays": {str(int(k)): v for k, v in sorted(self.overlays.items())},
                "span_frames": [int(x) for x in self.span_frames],
                "sample_frames": [int(x) for x in self.sample_frames],
                "video": self.video, "scene": self.scene}

    @classmethod
    def from_json(cls, f: JsonFields) -> QAFiles:
        ov = f.mapping("overlays", str)
        overlays = {}
        for k, v in ov.items():
            try:
                overlays[int(k)] = v
            except ValueError:
                raise f.error(f"overlays.{k}", "key is not a video frame index") from None
        out = cls(report=f.get("report", str, optional=True), plot=f.get("plot", str, optional=True),
                  overlays=overlays, span_frames=tuple(f.items("span_frames", int)),
                  sample_frames=tuple(f.items("sample_frames", int)),
                  video=f.get("video", str, optional=True), scene=f.get("scene", str, optional=True))
        for key in ("report", "plot", "video", "scene"):
            if getattr(out, key) is not None:
                check_relative(f, key, getattr(out, key), f.folder)
        for k, v in overlays.items():
            check_relative(f, f"overlays.{k}", v, f.folder)
        return out

    def thumbnail(self) -> str | None:
        """The first span frame's overlay, else the plot (relative names)."""
        for fr in self.span_frames[:1]:
            if fr in self.overlays:
                return self.overlays[fr]
        return self.plot


@dataclass(frozen=True, eq=False)
class QAResult(JsonArtifact):
    """A sequence's QA: ``flags.json`` (this class's content) and ``qa.npz`` (``metrics``).

    summary : :class:`QASummary`; spans : the flagged spans; frame_reasons : {video frame:
    reasons} of every flagged frame; thresholds : {metric: threshold}; units : {metric: unit};
    files : :class:`QAFiles`. Checked together: the summary's frames, flagged frames, rate
    and span count agree with ``metrics``, every flagged frame lies in a span and its reasons
    are the flagged columns."""

    KIND: ClassVar[str] = "qa_result"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "flags"

    metrics: QAMetrics
    summary: QASummary
    spans: tuple[QASpan, ...]
    frame_reasons: dict[int, tuple[str, ...]]
    thresholds: dict[str, float]
    units: dict[str, str]
    files: QAFiles = field(default_factory=QAFiles)

    def to_json(self) -> dict:
        return {"summary": self.summary.to_json(), "spans": [s.to_json() for s in self.spans],
                "frames": {str(int(k)): list(v) for k, v in sorted(self.frame_reasons.items())},
                "thresholds": {k: float(v) for k, v in self.thresholds.items()},
                "units": dict(self.units), "files": self.files.to_json()}

    @classmethod
    def from_json(cls, f: JsonFields, metrics: QAMetrics | None = None) -> QAResult:
        fr = f.get("frames", dict)
        reasons = {}
        for k in fr:
            try:
                reasons[int(k)] = tuple(f.sub("frames").items(k, str))
            except ValueError:
                raise f.error(f"frames.{k}", "key is not a video frame index") from None
        return cls(metrics=metrics, summary=QASummary.from_json(f.sub("summary")),
                   spans=tuple(QASpan.from_json(s) for s in f.objects("spans")),
                   frame_reasons=reasons, thresholds=f.mapping("thresholds", float),
                   units=f.mapping("units", str), files=QAFiles.from_json(f.sub("files")))

    # ------------------------------------------------------------------ files
    def save(self, writer) -> Path:
        self.metrics.save(writer)
        return super().save(writer)

    @classmethod
    def load(cls, source: Any) -> QAResult:
        from artifacts.base import check_header, read_json_file

        metrics = QAMetrics.load(source)
        data, file, folder = read_json_file(source, cls.FILE)
        check_header(data, file, cls.KIND, cls.VERSION)
        obj = cls.from_json(JsonFields(data, file, folder=folder), metrics)
        obj._check(file, folder)
        return obj

    def validate(self, file: str | Path = "<memory>", folder: Path | None = None) -> None:
        self.metrics.validate(Path(file).with_name(QAMetrics.file_name()))
        type(self).from_json(JsonFields(self.to_json(), Path(file), folder=folder), self.metrics)
        self._check(Path(file), folder)

    def _check(self, file: Path, folder: Path | None) -> None:  # noqa: ARG002
        m, s = self.metrics, self.summary
        f = JsonFields({}, file)
        anyf = m.any
        F = len(m.frames)
        if s.frames != F:
            raise f.error("summary.frames", f"{s.frames}, qa.npz has {F} frames")
        if s.flagged_frames != int(anyf.sum()):
            raise f.error("summary.flagged_frames", f"{s.flagged_frames}, qa.npz flags "
                          f"{int(anyf.sum())} frames")
        if abs(s.flagged_rate - s.flagged_frames / max(F, 1)) > RATE_TOL:
            raise f.error("summary.flagged_rate", f"{s.flagged_rate} is not {s.flagged_frames}/{F}")
        if s.spans != len(self.spans):
            raise f.error("summary.spans", f"{s.spans}, the file lists {len(self.spans)} spans")
        names = [str(r) for r in m.reasons]
        frames = np.asarray(m.frames)
        for i, fr in enumerate(frames):
            want = tuple(r for r, x in zip(names, np.asarray(m.flagged)[i], strict=True) if x)
            got = self.frame_reasons.get(int(fr), ())
            if tuple(got) != want:
                raise f.error(f"frames.{int(fr)}", f"reasons {list(got)}, qa.npz flags "
                              f"{list(want)}", int(fr))
            if want and not any(sp.start <= fr <= sp.end for sp in self.spans):
                raise f.error("spans", "a flagged frame lies in no span", int(fr))
        extra = set(self.frame_reasons) - {int(x) for x in frames}
        if extra:
            raise f.error(f"frames.{min(extra)}", "not a QA frame", min(extra))

    # ------------------------------------------------------------------ facts
    def span_list(self) -> list[tuple[int, int, list[str]]]:
        """``[(start, end, reasons), ...]`` (the datasheet's form)."""
        return [(s.start, s.end, list(s.reasons)) for s in self.spans]
