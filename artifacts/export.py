"""Stage ``export``'s typed outputs: what one sequence's export wrote (``export.json``,
:class:`SequenceExport`: frames, persons, every file it wrote by relative name, which release
files are absent and why, frames not valid per reason, cameras, contact) and the fitting
figures the release's datasheet lists (``figures.json``, :class:`SequenceFigures`).
``release`` reads these classes only (and the files they list through their readers).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from artifacts.base import JsonArtifact, JsonFields, check_relative, read_json_file
from formats.release import QA_REASON_PREFIX


def _num(d, *keys):
    """``d[k0][k1]...`` as a float, None when any level is missing or not a number."""
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return float(d) if isinstance(d, (int, float)) and not isinstance(d, bool) else None


@dataclass(frozen=True)
class SequenceFigures(JsonArtifact):
    """The fitting figures of one sequence: a pick of the marker fit's, the partner fit's and
    the conversion's report (None: that stage did not run for the sequence) and each
    subject's shape source."""

    KIND: ClassVar[str] = "sequence_figures"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "figures"

    sequence: str
    subjects: tuple[str, ...]
    marker_fit: dict | None = None
    partner_fit: dict | None = None
    convert: dict | None = None
    shape_source: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"sequence": self.sequence, "subjects": list(self.subjects),
                "marker_fit": self.marker_fit, "partner_fit": self.partner_fit,
                "convert": self.convert, "shape_source": dict(self.shape_source)}

    @classmethod
    def from_json(cls, f: JsonFields) -> SequenceFigures:
        conv = f.sub("convert", optional=True)
        if conv is not None:
            for p in conv.objects("per_person", optional=True) or []:
                p.get("v2s_median_mm", float, optional=True)
                p.get("subject", str)
        return cls(sequence=f.get("sequence", str), subjects=tuple(f.items("subjects", str)),
                   marker_fit=f.get("marker_fit", dict, optional=True),
                   partner_fit=f.get("partner_fit", dict, optional=True),
                   convert=None if conv is None else conv.data,
                   shape_source=f.mapping("shape_source", str))

    def marker_residual_median_mm(self) -> float | None:
        return _num(self.marker_fit, "residual_mm", "median")

    def partner_reprojection_median_px(self) -> float | None:
        return _num(self.partner_fit, "reprojection_px", "median")

    def v2s_median_mm(self) -> list[float | None]:
        """Per converted person, the SMPL-X surface's median distance to the fit (mm)."""
        return [_num(p, "v2s_median_mm") for p in (self.convert or {}).get("per_person") or []]

    def datasheet(self) -> dict:
        """The datasheet's ``figures`` entry of the sequence."""
        return {"marker_fit": self.marker_fit, "partner_fit": self.partner_fit,
                "convert": self.convert, "shape_source": dict(self.shape_source)}


@dataclass(frozen=True)
class ContactNote:
    """How the export wrote the sequence's contact signature: source file, model family,
    the annotated frames as given (``fr_id``, ``start_fr``, ``end_fr``: the recipe's video
    frames), pairs per family, and the free-form notes (mapping, warnings)."""

    source: str
    family: str
    fr_id: int
    start_fr: int | None
    end_fr: int | None
    pairs: dict[str, int]
    notes: dict = field(default_factory=dict)

    @property
    def event(self) -> bool:
        """Whether the signature has any contact pair."""
        return any(self.pairs.values())

    def to_json(self) -> dict:
        return {**self.notes, "source": self.source, "family": self.family,
                "original_frames": {"fr_id": int(self.fr_id), "start_fr": self.start_fr,
                                    "end_fr": self.end_fr},
                "pairs": {k: int(v) for k, v in self.pairs.items()}}

    @classmethod
    def from_json(cls, f: JsonFields) -> ContactNote:
        o = f.sub("original_frames")
        known = {"source", "family", "original_frames", "pairs"}
        return cls(source=f.get("source", str), family=f.get("family", str),
                   fr_id=o.get("fr_id", int), start_fr=o.get("start_fr", int, optional=True),
                   end_fr=o.get("end_fr", int, optional=True), pairs=f.mapping("pairs", int),
                   notes={k: v for k, v in f.data.items() if k not in known})


@dataclass(frozen=True)
class SequenceExport(JsonArtifact):
    """One sequence's export (``export.json``).

    sequence, group, action; persons : subject ids, person 0 = the marker wearer; model : the
    fitted model's name; frames : exported frames (F), first_frame / last_frame : their video
    frame indices; video_fps : the cut videos' rate (None: not filmed);
    person_frames_not_valid; not_valid_by_reason : per person ``{subject, <reason>: count}``;
    withhold : the QA reasons (``QAOptions`` threshold names) a flagged frame was withheld for
    (None: no QA was read, nothing withheld); withheld : ``{"qa:<reason>": person-frames}``
    the fit called valid but QA withheld (counted in ``person_frames_not_valid`` and
    ``not_valid_by_reason`` too);
    cameras : {camera: how its calibration was written}; contact : :class:`ContactNote` or
    None; absent : {what: why} of the release files the sequence does not have; files : every
    file written, relative to the artifact folder (``<group>/...``); valid_file / contact_file
    / text_file : the validity mask, contact signature and text annotation among them (None:
    not written). ``figures`` (:class:`SequenceFigures`) is loaded with it; ``folder`` is the
    artifact folder when loaded from one (:meth:`path`)."""

    KIND: ClassVar[str] = "sequence_export"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "export"

    sequence: str
    group: str
    action: str
    persons: tuple[str, ...]
    model: str
    frames: int
    first_frame: int
    last_frame: int
    video_fps: float | None
    person_frames_not_valid: int
    not_valid_by_reason: tuple[dict, ...]
    cameras: dict[str, dict]
    contact: ContactNote | None
    absent: dict[str, str]
    files: tuple[str, ...]
    valid_file: str
    contact_file: str | None = None
    text_file: str | None = None
    figures: SequenceFigures | None = None
    withhold: tuple[str, ...] | None = None
    withheld: dict[str, int] = field(default_factory=dict)
    folder: Path | None = None

    def to_json(self) -> dict:
        return {"sequence": self.sequence, "group": self.group, "action": self.action,
                "persons": list(self.persons), "model": self.model, "frames": int(self.frames),
                "first_frame": int(self.first_frame), "last_frame": int(self.last_frame),
                "video_fps": None if self.video_fps is None else float(self.video_fps),
                "person_frames_not_valid": int(self.person_frames_not_valid),
                "not_valid_by_reason": [dict(x) for x in self.not_valid_by_reason],
                "cameras": dict(self.cameras),
                "contact": None if self.contact is None else self.contact.to_json(),
                "absent": dict(self.absent), "files": list(self.files),
                "valid_file": self.valid_file, "contact_file": self.contact_file,
                "text_file": self.text_file,
                "withhold": None if self.withhold is None else list(self.withhold),
                "withheld": {k: int(v) for k, v in self.withheld.items()}}

    @classmethod
    def from_json(cls, f: JsonFields) -> SequenceExport:
        nv = []
        for p in f.objects("not_valid_by_reason"):
            nv.append({"subject": p.get("subject", str),
                       **{k: p.check(v, int, p.name(k)) for k, v in p.data.items()
                          if k != "subject"}})
        cams = {}
        for c in f.get("cameras", dict):
            cams[str(c)] = f.sub("cameras").get(c, dict)
        contact = f.sub("contact", optional=True)
        files = f.items("files", str)
        for i, rel in enumerate(files):
            check_relative(f, f"files[{i}]", rel, f.folder)
        out = cls(sequence=f.get("sequence", str), group=f.get("group", str),
                  action=f.get("action", str), persons=tuple(f.items("persons", str)),
                  model=f.get("model", str), frames=f.get("frames", int),
                  first_frame=f.get("first_frame", int), last_frame=f.get("last_frame", int),
                  video_fps=f.get("video_fps", float, optional=True),
                  person_frames_not_valid=f.get("person_frames_not_valid", int),
                  not_valid_by_reason=tuple(nv), cameras=cams,
                  contact=None if contact is None else ContactNote.from_json(contact),
                  absent=f.mapping("absent", str), files=tuple(files),
                  valid_file=f.get("valid_file", str),
                  contact_file=f.get("contact_file", str, optional=True),
                  text_file=f.get("text_file", str, optional=True),
                  withhold=None if f.data.get("withhold") is None
                  else tuple(f.items("withhold", str)),
                  withheld=f.mapping("withheld", int, optional=True) or {}, folder=f.folder)
        return out

    def _check(self, file: Path, folder: Path | None) -> None:  # noqa: ARG002
        f = JsonFields({}, file)
        if self.frames < 1:
            raise f.error("frames", f"{self.frames}: an export has at least one frame")
        if self.last_frame < self.first_frame:
            raise f.error("last_frame", f"{self.last_frame} < first_frame {self.first_frame}")
        if self.sequence != f"{self.group}/{self.action}":
            raise f.error("sequence", f"{self.sequence!r} is not group/action "
                          f"{self.group!r}/{self.action!r}")
        if not 0 <= self.person_frames_not_valid <= self.frames * len(self.persons):
            raise f.error("person_frames_not_valid", f"{self.person_frames_not_valid} outside "
                          f"0..{self.frames * len(self.persons)}")
        if len(self.not_valid_by_reason) != len(self.persons):
            raise f.error("not_valid_by_reason", f"{len(self.not_valid_by_reason)} entries for "
                          f"{len(self.persons)} persons")
        for i, rel in enumerate(self.files):
            if not rel.startswith(f"{self.group}/"):
                raise f.error(f"files[{i}]", f"{rel!r} is not under the group {self.group!r}/")
        for key in ("valid_file", "contact_file", "text_file"):
            v = getattr(self, key)
            if v is not None and v not in self.files:
                raise f.error(key, f"{v!r} is not among the files written")
        for k, n in self.withheld.items():
            if not k.startswith(QA_REASON_PREFIX):
                raise f.error(f"withheld.{k}", f"not a QA reason ({QA_REASON_PREFIX}<reason>)")
            if self.withhold is None or k[len(QA_REASON_PREFIX):] not in self.withhold:
                raise f.error(f"withheld.{k}", f"not among the reasons withheld "
                              f"({self.withhold})")
            counted = sum(int(p.get(k, 0)) for p in self.not_valid_by_reason)
            if n != counted:
                raise f.error(f"withheld.{k}", f"{n} person-frames, not_valid_by_reason counts "
                              f"{counted}")
        if self.video_fps is not None and not self.video_fps > 0:
            raise f.error("video_fps", f"{self.video_fps}: must be > 0")

    @classmethod
    def load(cls, source: Any) -> SequenceExport:
        import dataclasses

        out = super().load(source)
        folder = out.folder
        if folder is None:
            _, _, folder = read_json_file(source, cls.FILE)
        return dataclasses.replace(out, figures=SequenceFigures.load(source), folder=folder)

    def save(self, writer) -> Path:
        if self.figures is not None:
            self.figures.save(writer)
        return super().save(writer)

    def path(self, rel: str) -> Path:
        """The absolute path of one of ``files`` (the export loaded from its folder)."""
        if self.folder is None:
            raise ValueError("the export was not loaded from a folder")
        return Path(self.folder) / rel

    def paths(self) -> dict[str, Path]:
        """{relative name: absolute path} of every file written."""
        return {rel: self.path(rel) for rel in self.files}
