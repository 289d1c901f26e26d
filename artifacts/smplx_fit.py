"""Stage ``convert``'s typed outputs: both people as SMPL-family parameters (``smplx.npz``),
the surface correspondence source <-> target it used (``correspondence.npz``) and its report
(``report.json``: the target, the surface distance per person, timings).

Axes: ``P`` persons (0 = the marker wearer, 1 = the partner), ``F`` frames (video frame indices
in ``frames``: marker_fit's frames that partner_fit also has), ``B`` body joints of the target
(21 for SMPL-X / SMPL+H, 23 for SMPL), ``S`` betas, ``E`` expression coefficients.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from artifacts.base import (
    ROTATION_TOL,
    ArtifactError,
    FieldSpec,
    JsonArtifact,
    JsonFields,
    TypedArtifact,
    check_metres,
    first_frame,
)

# constants
BARY_TOL = 1e-3  # barycentric coordinates: >= -tol, rows sum to 1 within tol

ROTATION_FIELDS = ("global_orient", "body_pose", "left_hand_pose", "right_hand_pose", "jaw_pose",
                   "leye_pose", "reye_pose")
V2S_FIELDS = ("v2s_mm", "v2s_median_mm", "v2s_p95_mm", "v2s_max_mm")


def _check_person_rotations(R, file, field: str) -> None:
    """(P, F, ..., 3, 3) rotation matrices; the error names the frame (axis 1) and person."""
    R = np.asarray(R, dtype=float)
    err = np.abs(np.einsum("...ji,...jk->...ik", R, R) - np.eye(3)).max(axis=(-2, -1))
    det = np.abs(np.linalg.det(R) - 1.0)
    bad = (err > ROTATION_TOL) | (det > ROTATION_TOL)
    if bad.any():
        bad_pf = bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=-1)
        p, f = (int(x[0]) for x in np.nonzero(bad_pf))
        raise ArtifactError(file, field, f"person {p}: not a rotation matrix (|R^T R - I| = "
                            f"{float(err[p, f].max()):.2g}, tolerance {ROTATION_TOL:g})", f)


@dataclass(frozen=True, eq=False)
class SMPLXFit(TypedArtifact):
    """Both people's SMPL-family parameters per frame (rotation matrices, smplx's arguments).

    transl : (P, F, 3) metres; global_orient : (P, F, 3, 3); body_pose : (P, F, B, 3, 3);
    left_hand_pose / right_hand_pose : (P, F, 15, 3, 3), jaw_pose / leye_pose / reye_pose :
    (P, F, 3, 3) (SMPL-X; absent for SMPL); betas : (P, S); expression : (P, E);
    frames : (F,) video frame indices, increasing; valid : (P, F) bool, the person-frame is
    ground truth (the fit's frame was valid; a frame not valid in the fit stays not valid);
    v2s_mm : (P, F) per frame mean distance of the target vertices to the fitted source
    surface, mm (NaN = not measured); v2s_median_mm / v2s_p95_mm / v2s_max_mm : (P, F) the
    per-frame median, 95th percentile and maximum (optional together); subjects : (P,) ids.
    """

    KIND: ClassVar[str] = "smplx_fit"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "smplx"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("transl", "f", "P F 3", finite=True, doc="metres"),
        FieldSpec("global_orient", "f", "P F 3 3", finite=True),
        FieldSpec("body_pose", "f", "P F B 3 3", finite=True),
        FieldSpec("left_hand_pose", "f", "P F 15 3 3", optional=True, finite=True),
        FieldSpec("right_hand_pose", "f", "P F 15 3 3", optional=True, finite=True),
        FieldSpec("jaw_pose", "f", "P F 3 3", optional=True, finite=True),
        FieldSpec("leye_pose", "f", "P F 3 3", optional=True, finite=True),
        FieldSpec("reye_pose", "f", "P F 3 3", optional=True, finite=True),
        FieldSpec("betas", "f", "P S", finite=True),
        FieldSpec("expression", "f", "P E", finite=True),
        FieldSpec("frames", "iu", "F"),
        FieldSpec("valid", "b", "P F"),
        FieldSpec("v2s_mm", "f", "P F", doc="mm, NaN = not measured"),
        FieldSpec("v2s_median_mm", "f", "P F", optional=True),
        FieldSpec("v2s_p95_mm", "f", "P F", optional=True),
        FieldSpec("v2s_max_mm", "f", "P F", optional=True),
        FieldSpec("subjects", "U", "P"),
    )

    transl: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    betas: np.ndarray
    expression: np.ndarray
    frames: np.ndarray
    valid: np.ndarray
    v2s_mm: np.ndarray
    subjects: np.ndarray
    left_hand_pose: np.ndarray | None = None
    right_hand_pose: np.ndarray | None = None
    jaw_pose: np.ndarray | None = None
    leye_pose: np.ndarray | None = None
    reye_pose: np.ndarray | None = None
    v2s_median_mm: np.ndarray | None = None
    v2s_p95_mm: np.ndarray | None = None
    v2s_max_mm: np.ndarray | None = None

    @property
    def num_persons(self) -> int:
        return int(np.asarray(self.transl).shape[0])

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    def params(self) -> dict[str, np.ndarray]:
        """The present SMPL-family parameters by smplx's argument names (``transl``,
        ``global_orient``, ``body_pose``, hands, jaw, eyes, ``betas``, ``expression``)."""
        names = ("transl", *ROTATION_FIELDS, "betas", "expression")
        return {n: np.asarray(getattr(self, n)) for n in names if getattr(self, n) is not None}

    def _check(self, file: Path) -> None:
        check_metres(np.moveaxis(np.asarray(self.transl), 1, 0), file, "transl")
        for n in ROTATION_FIELDS:
            if getattr(self, n) is not None:
                _check_person_rotations(getattr(self, n), file, n)
        fr = np.asarray(self.frames)
        if np.any(fr < 0):
            raise ArtifactError(file, "frames", "negative video frame index", first_frame(fr < 0))
        if len(fr) > 1 and np.any(np.diff(fr) <= 0):
            raise ArtifactError(file, "frames", "not increasing",
                                int(np.argmax(np.diff(fr) <= 0)) + 1)
        hands = [n for n in ("left_hand_pose", "right_hand_pose") if getattr(self, n) is not None]
        if len(hands) == 1:
            raise ArtifactError(file, ({"left_hand_pose", "right_hand_pose"} - set(hands)).pop(),
                                f"missing while {hands[0]} is present")
        extra = [n for n in V2S_FIELDS[1:] if getattr(self, n) is not None]
        if extra and len(extra) != len(V2S_FIELDS) - 1:
            missing = [n for n in V2S_FIELDS[1:] if n not in extra]
            raise ArtifactError(file, missing[0], f"missing while {', '.join(extra)} are present")
        for n in V2S_FIELDS:
            v = getattr(self, n)
            if v is not None and np.any(np.asarray(v)[np.isfinite(v)] < 0):
                bad = np.isfinite(v) & (np.asarray(v) < 0)
                raise ArtifactError(file, n, "negative distance", first_frame(bad.T))
        if len(set(map(str, self.subjects))) != len(self.subjects):
            raise ArtifactError(file, "subjects", f"duplicate subjects {list(map(str, self.subjects))}")


@dataclass(frozen=True, eq=False)
class SurfaceCorrespondence(TypedArtifact):
    """The surface correspondence source (fitted model) <-> target (SMPL family) that convert
    registered (``fitting.convert.Correspondence``'s arrays): each target vertex on a source
    face (``tgt_vert_face``, ``tgt_vert_bary``), each source vertex on a target face, the
    nearest target facet of each source facet (``src_face_tgt_face``) and back, both meshes'
    faces."""

    KIND: ClassVar[str] = "surface_correspondence"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "correspondence"
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = (
        FieldSpec("tgt_vert_face", "iu", "Vt"),
        FieldSpec("tgt_vert_bary", "f", "Vt 3", finite=True),
        FieldSpec("src_vert_face", "iu", "Vs"),
        FieldSpec("src_vert_bary", "f", "Vs 3", finite=True),
        FieldSpec("src_face_tgt_face", "iu", "Ts"),
        FieldSpec("tgt_face_src_face", "iu", "Tt"),
        FieldSpec("tgt_faces", "iu", "Tt 3"),
        FieldSpec("src_faces", "iu", "Ts 3"),
    )

    tgt_vert_face: np.ndarray
    tgt_vert_bary: np.ndarray
    src_vert_face: np.ndarray
    src_vert_bary: np.ndarray
    src_face_tgt_face: np.ndarray
    tgt_face_src_face: np.ndarray
    tgt_faces: np.ndarray
    src_faces: np.ndarray

    @classmethod
    def of(cls, corr) -> SurfaceCorrespondence:
        """From anything with the arrays' attributes (``fitting.convert.Correspondence``)."""
        return cls(**{f.name: np.asarray(getattr(corr, f.name)) for f in cls.FIELDS})

    def _check(self, file: Path) -> None:
        Ts, Tt = len(self.src_faces), len(self.tgt_faces)
        for n, hi in (("tgt_vert_face", Ts), ("src_vert_face", Tt), ("src_face_tgt_face", Tt),
                      ("tgt_face_src_face", Ts)):
            v = np.asarray(getattr(self, n))
            if np.any((v < 0) | (v >= hi)):
                i = int(np.argmax((v < 0) | (v >= hi)))
                raise ArtifactError(file, n, f"entry {i}: facet {int(v[i])} outside 0..{hi - 1}")
        for n in ("tgt_vert_bary", "src_vert_bary"):
            b = np.asarray(getattr(self, n), float)
            bad = (b.min(axis=1) < -BARY_TOL) | (np.abs(b.sum(axis=1) - 1) > BARY_TOL)
            if bad.any():
                i = int(np.argmax(bad))
                raise ArtifactError(file, n, f"vertex {i}: {b[i].tolist()} are not barycentric "
                                    f"coordinates (>= 0, sum 1 within {BARY_TOL:g})")


def _num(x) -> float | None:
    """A distance for JSON: None where not measured (NaN)."""
    return None if x is None or not np.isfinite(x) else float(x)


@dataclass(frozen=True)
class TargetInfo:
    """The SMPL-family model convert fitted: its file, sha256, kind (``smplx`` ...), vertex
    count, whether it is the stand-in built from Anny, and a sentence saying so."""

    path: str
    sha256: str
    kind: str
    n_vertices: int
    standin: bool
    description: str


@dataclass(frozen=True)
class PersonConversion:
    """One person's conversion: surface distance target -> source in mm (median over frames
    of the per-frame mean, median of the per-frame 95th percentile, the largest), frames,
    warm-start restarts."""

    subject: str
    v2s_median_mm: float | None
    v2s_p95_mm: float | None
    v2s_max_mm: float | None
    frames: int
    restarts: int = 0


@dataclass(frozen=True)
class ConversionReport(JsonArtifact):
    """convert's ``report.json``: target, correspondence cache key, per person figures,
    ``fps_per_core`` (person-frames per CPU-second of the conversion), ``cpu_s``,
    ``registration_cpu_s`` (0 when the correspondence came from the cache), warnings."""

    KIND: ClassVar[str] = "conversion_report"
    VERSION: ClassVar[int] = 1
    FILE: ClassVar[str] = "report"

    sequence: str
    target: TargetInfo
    correspondence_key: str
    registered_now: bool
    per_person: tuple[PersonConversion, ...]
    fps_per_core: float
    cpu_s: float
    registration_cpu_s: float
    warnings: tuple[str, ...] = ()

    def to_json(self) -> dict:
        t = self.target
        return {"sequence": self.sequence,
                "target": {"path": t.path, "sha256": t.sha256, "kind": t.kind,
                           "n_vertices": int(t.n_vertices), "standin": bool(t.standin),
                           "description": t.description},
                "correspondence": {"key": self.correspondence_key,
                                   "registered_now": bool(self.registered_now)},
                "per_person": [{"subject": p.subject, "v2s_median_mm": _num(p.v2s_median_mm),
                                "v2s_p95_mm": _num(p.v2s_p95_mm), "v2s_max_mm": _num(p.v2s_max_mm),
                                "frames": int(p.frames), "restarts": int(p.restarts)}
                               for p in self.per_person],
                "fps_per_core": float(self.fps_per_core), "cpu_s": float(self.cpu_s),
                "registration_cpu_s": float(self.registration_cpu_s),
                "warnings": list(self.warnings)}

    @classmethod
    def from_json(cls, f: JsonFields) -> ConversionReport:
        t = f.sub("target")
        c = f.sub("correspondence")
        people = []
        for p in f.objects("per_person"):
            people.append(PersonConversion(
                p.get("subject", str), p.get("v2s_median_mm", float, optional=True),
                p.get("v2s_p95_mm", float, optional=True), p.get("v2s_max_mm", float, optional=True),
                p.get("frames", int), p.get("restarts", int, optional=True, default=0)))
        return cls(sequence=f.get("sequence", str),
                   target=TargetInfo(t.get("path", str), t.get("sha256", str), t.get("kind", str),
                                     t.get("n_vertices", int), t.get("standin", bool),
                                     t.get("description", str)),
                   correspondence_key=c.get("key", str), registered_now=c.get("registered_now", bool),
                   per_person=tuple(people), fps_per_core=f.get("fps_per_core", float),
                   cpu_s=f.get("cpu_s", float), registration_cpu_s=f.get("registration_cpu_s", float),
                   warnings=tuple(f.items("warnings", str)))

    def _check(self, file: Path, folder: Path | None) -> None:  # noqa: ARG002
        f = JsonFields({}, file)
        for i, p in enumerate(self.per_person):
            for n in ("v2s_median_mm", "v2s_p95_mm", "v2s_max_mm"):
                v = getattr(p, n)
                if v is not None and v < 0:
                    raise f.error(f"per_person[{i}].{n}", f"negative distance {v}")
        if self.cpu_s < 0 or self.registration_cpu_s < 0 or self.fps_per_core < 0:
            raise f.error("cpu_s", "negative time or rate")

    def figures(self) -> dict:
        """What the release's datasheet shows of the conversion (target, per person, speed)."""
        j = self.to_json()
        return {k: j[k] for k in ("target", "per_person", "fps_per_core", "cpu_s", "warnings")}
