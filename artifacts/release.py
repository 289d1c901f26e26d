"""Stage ``release``'s typed output: the session's release folder (the artifact folder itself:
the CHI3D layout, ``MANIFEST.sha256``, ``datasheet.json`` / ``datasheet.md``) and the re-read
pass over it (``verification.json``, this class's own file). ``evaluate`` reads
:class:`Release` only: ``Release.load(art).root`` once ``verified``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from artifacts.base import ArtifactError, JsonArtifact, JsonFields, check_relative

MANIFEST_FILE = "MANIFEST.sha256"
DATASHEET_FILE = "datasheet.json"
DATASHEET_MD = "datasheet.md"


@dataclass(frozen=True)
class DatasheetTotals:
    """The release's totals: sequences, frames, person-frames, of them not valid, the
    not-valid person-frames per reason, and of those the ones withheld for QA flags
    (``{"qa:<reason>": person-frames}``; empty in a datasheet written before)."""

    sequences: int
    frames: int
    person_frames: int
    person_frames_not_valid: int
    not_valid_by_reason: dict[str, int] = field(default_factory=dict)
    withheld: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_json(cls, f: JsonFields) -> DatasheetTotals:
        t = cls(f.get("sequences", int), f.get("frames", int), f.get("person_frames", int),
                f.get("person_frames_not_valid", int), f.mapping("not_valid_by_reason", int),
                f.mapping("withheld", int, optional=True) or {})
        if not 0 <= t.person_frames_not_valid <= t.person_frames:
            raise f.error("person_frames_not_valid", f"{t.person_frames_not_valid} outside "
                          f"0..{t.person_frames}")
        for r, n in t.withheld.items():
            if t.not_valid_by_reason.get(r) != n:
                raise f.error(f"withheld.{r}", f"{n} person-frames, not_valid_by_reason counts "
                              f"{t.not_valid_by_reason.get(r, 0)}")
        return t


@dataclass(frozen=True)
class Datasheet:
    """``datasheet.json``'s typed part: session, subjects, the released sequences (per sequence
    the datasheet's entry as written), the recipe's sequences not released, the totals and
    the QA summary (None: no QA ran)."""

    session: str
    subjects: tuple[str, ...]
    sequences: dict[str, dict]
    sequences_not_exported: tuple[str, ...]
    totals: DatasheetTotals
    qa: dict | None = None

    @classmethod
    def from_json(cls, f: JsonFields) -> Datasheet:
        seqs = f.get("sequences", dict)
        sub = f.sub("sequences")
        for k in seqs:
            s = sub.sub(k)
            s.get("frames", int)
            s.items("persons", str)
        out = cls(session=f.get("session", str), subjects=tuple(f.items("subjects", str)),
                  sequences={str(k): v for k, v in seqs.items()},
                  sequences_not_exported=tuple(f.items("sequences_not_exported", str)),
                  totals=DatasheetTotals.from_json(f.sub("totals")),
                  qa=f.get("qa", dict, optional=True))
        if out.totals.sequences != len(out.sequences):
            raise f.error("totals.sequences", f"{out.totals.sequences}, the datasheet lists "
                          f"{len(out.sequences)} sequences")
        return out


@dataclass(frozen=True)
class Release(JsonArtifact):
    """The verified release folder.

    ok : the re-read pass found every file readable through its reader and the manifest
    matching; files_checked; files : {relative path: the reader that checked it}; problems :
    what the pass found (empty when ok); manifest / datasheet / datasheet_md : the relative
    names of those files. On load: ``root`` (the release folder, when loaded from one),
    ``sheet`` (:class:`Datasheet`)."""

    KIND: ClassVar[str] = "release_verification"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "verification"

    ok: bool
    files_checked: int
    files: dict[str, str]
    problems: tuple[str, ...] = ()
    manifest: str = MANIFEST_FILE
    datasheet: str = DATASHEET_FILE
    datasheet_md: str = DATASHEET_MD
    root: Path | None = None
    sheet: Datasheet | None = None

    @classmethod
    def of(cls, result: dict) -> Release:
        """From ``stages.release.verify_release``'s result."""
        return cls(ok=bool(result["ok"]), files_checked=int(result["files_checked"]),
                   files=dict(result["files"]), problems=tuple(result["problems"]))

    @property
    def verified(self) -> bool:
        return self.ok and not self.problems

    def to_json(self) -> dict:
        return {"ok": bool(self.ok), "files_checked": int(self.files_checked),
                "files": dict(self.files), "problems": list(self.problems),
                "manifest": self.manifest, "datasheet": self.datasheet,
                "datasheet_md": self.datasheet_md}

    @classmethod
    def from_json(cls, f: JsonFields) -> Release:
        out = cls(ok=f.get("ok", bool), files_checked=f.get("files_checked", int),
                  files=f.mapping("files", str), problems=tuple(f.items("problems", str)),
                  manifest=f.get("manifest", str), datasheet=f.get("datasheet", str),
                  datasheet_md=f.get("datasheet_md", str), root=f.folder)
        for key in ("manifest", "datasheet", "datasheet_md"):
            check_relative(f, key, getattr(out, key), f.folder)
        return out

    def _check(self, file: Path, folder: Path | None) -> None:  # noqa: ARG002
        f = JsonFields({}, file)
        if self.ok and self.problems:
            raise f.error("ok", f"true with {len(self.problems)} problems")
        if not self.ok and not self.problems:
            raise f.error("problems", "empty, but ok is false")
        if self.files_checked != len(self.files):
            raise f.error("files_checked", f"{self.files_checked}, the file lists "
                          f"{len(self.files)} files")

    @classmethod
    def load(cls, source: Any) -> Release:
        import dataclasses

        out = super().load(source)
        if out.root is None:
            raise ArtifactError(cls.file_name(), "root", "the release folder is unknown")
        p = out.root / out.datasheet
        try:
            data = json.loads(p.read_text())
        except (OSError, ValueError) as e:
            raise ArtifactError(p, "datasheet", f"unreadable: {type(e).__name__}: {e}") from None
        return dataclasses.replace(out, sheet=Datasheet.from_json(JsonFields(data, p)))

    def require_verified(self) -> Path:
        """The release folder; ArtifactError naming the first problem when not verified."""
        if not self.verified or self.root is None:
            raise ArtifactError((self.root or Path(".")) / self.file_name(), "ok",
                                "the release did not pass its re-read pass: "
                                + ("; ".join(self.problems[:3]) or "unknown folder"))
        return self.root
