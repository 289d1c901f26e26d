"""``FitSummary``: the headline figures of a body fit (stages marker_fit and partner_fit,
``summary.json``), which the export republishes in ``figures.json`` and the datasheet.

The fits' ``report.json`` stays a free report for people; what other stages take from a fit
goes through this class (``FitSummary.load(art)``), never through report keys.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from artifacts.base import JsonArtifact, JsonFields

# constants
FIT_KINDS = ("marker_fit", "partner_fit")


@dataclass(frozen=True, eq=False)
class FitSummary(JsonArtifact):
    """fit : ``marker_fit`` or ``partner_fit``; subject : the fitted subject's id;
    frames / frames_valid : fitted frames and those that are ground truth;
    frames_not_valid : {reason: count} (every reason, zeros included);
    warnings : sentences for a person; figures : the fit's other headline figures (residuals
    or reprojection in mm/px, penetration, speed: plain JSON numbers and objects, copied as
    they are into the export's ``figures.json``)."""

    KIND: ClassVar[str] = "fit_summary"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "summary"

    fit: str
    subject: str
    frames: int
    frames_valid: int
    frames_not_valid: dict[str, int]
    warnings: tuple[str, ...] = ()
    figures: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_report(cls, fit: str, report: dict, keys) -> FitSummary:
        """From a fit's report: the counts and warnings, plus ``keys`` as figures."""
        return cls(fit=fit, subject=str(report.get("subject", "")),
                   frames=int(report["frames"]), frames_valid=int(report["frames_valid"]),
                   frames_not_valid={str(k): int(v) for k, v in
                                     (report.get("frames_not_valid") or {}).items()},
                   warnings=tuple(str(w) for w in report.get("warnings") or ()),
                   figures={k: report[k] for k in keys if k in report})

    def to_json(self) -> dict:
        return {"fit": self.fit, "subject": self.subject, "frames": int(self.frames),
                "frames_valid": int(self.frames_valid),
                "frames_not_valid": {k: int(v) for k, v in self.frames_not_valid.items()},
                "warnings": list(self.warnings), "figures": dict(self.figures)}

    def published(self) -> dict:
        """What the export writes for this fit (figures.json): the counts, warnings, figures."""
        return {"subject": self.subject, "frames": self.frames, "frames_valid": self.frames_valid,
                "frames_not_valid": dict(self.frames_not_valid), **self.figures,
                "warnings": list(self.warnings)}

    @classmethod
    def from_json(cls, f: JsonFields) -> FitSummary:
        return cls(fit=f.get("fit", str), subject=f.get("subject", str),
                   frames=f.get("frames", int), frames_valid=f.get("frames_valid", int),
                   frames_not_valid=f.mapping("frames_not_valid", int),
                   warnings=tuple(f.items("warnings", str)), figures=f.get("figures", dict))

    def _check(self, file: Path, folder: Path | None) -> None:  # noqa: ARG002 - no files
        f = JsonFields(self.to_json(), file)
        if self.fit not in FIT_KINDS:
            raise f.error("fit", f"{self.fit!r} is not one of {FIT_KINDS}")
        if not 0 <= self.frames_valid <= self.frames:
            raise f.error("frames_valid", f"{self.frames_valid} outside 0..{self.frames}")
        if self.frames_valid + sum(self.frames_not_valid.values()) != self.frames:
            raise f.error("frames_not_valid", f"{self.frames_valid} valid + "
                          f"{sum(self.frames_not_valid.values())} not valid != {self.frames} frames")
