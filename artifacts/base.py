"""Conventions shared by every typed artifact (one frozen dataclass per artifact kind).

A typed artifact is a frozen dataclass whose attributes are the arrays of one npz file of a
stage's artifact folder. The class owns that file's layout:

- ``KIND`` (str), ``VERSION`` (int), ``FILE`` (the npz name without ``.npz``) and ``FIELDS``
  (one :class:`FieldSpec` per attribute: dtype kind, shape in axis letters, optional, finite);
- ``obj.save(writer)`` validates, then writes ``<FILE>.npz`` through
  ``writer.save_arrays(FILE, **arrays)`` (the engine's ``ctx.out``) with two extra scalars,
  ``artifact_kind`` and ``artifact_version``;
- ``Cls.load(source)``: ``source`` is anything with ``.arrays(name)`` (the engine's artifact)
  or a folder ``Path`` (or the npz path itself); checks kind, version, every field's presence,
  dtype kind, shape consistency (one size per axis letter over all fields: every per-frame
  array has the same F) and the class's unit/plausibility checks (:meth:`TypedArtifact._check`);
- ``obj.validate(file)`` runs the same checks on an in-memory object.

Every problem raises :class:`ArtifactError` (an ``InputError``: ``<file>: <field> [frame N]:
what is wrong``) naming the npz file and the field. Readers use fields by name only.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from formats.errors import InputError

# constants
ROTATION_TOL = 1e-6  # |R^T R - I| and |det R - 1| of a stored rotation matrix
MAX_TRANSL_M = 100.0  # a translation beyond this is not metres (mm, or garbage)
KIND_KEY = "artifact_kind"
VERSION_KEY = "artifact_version"
DTYPE_KINDS = {"f": "float", "i": "signed int", "u": "unsigned int", "b": "bool", "U": "str"}


class ArtifactError(InputError):
    """A typed artifact's file (or in-memory object) is not what its class says:
    ``<file>: <field> [frame N]: what is wrong``."""


@dataclass(frozen=True)
class FieldSpec:
    """One array of a typed artifact.

    name : attribute and npz key; kind : accepted numpy dtype kinds (``"f"``, ``"iu"``,
    ``"b"``, ``"U"``); shape : axis letters / digits separated by spaces (``"F M 3"``; ``""``
    for a scalar), a letter has one size over all fields of the artifact; optional : may be
    absent (attribute None); finite : every value must be finite (else NaN is allowed)."""

    name: str
    kind: str
    shape: str
    optional: bool = False
    finite: bool = False
    doc: str = ""


class TypedArtifact:
    """Base of the typed artifacts (subclasses are ``@dataclass(frozen=True, eq=False)``)."""

    KIND: ClassVar[str]
    VERSION: ClassVar[int]
    FILE: ClassVar[str]
    FIELDS: ClassVar[tuple[FieldSpec, ...]]

    def __post_init__(self):
        for f in self.FIELDS:
            v = getattr(self, f.name)
            if v is not None and not isinstance(v, np.ndarray):
                object.__setattr__(self, f.name, np.asarray(v))

    # ---------------------------------------------------------------- files

    @classmethod
    def file_name(cls) -> str:
        return f"{cls.FILE}.npz"

    def arrays(self) -> dict[str, np.ndarray]:
        """The npz content: every present field plus ``artifact_kind``/``artifact_version``."""
        out = {f.name: np.asarray(getattr(self, f.name)) for f in self.FIELDS
               if getattr(self, f.name) is not None}
        out[KIND_KEY] = np.array(self.KIND)
        out[VERSION_KEY] = np.array(self.VERSION, dtype=np.int64)
        return out

    def save(self, writer) -> Path:
        """Validate, then write ``<FILE>.npz`` through ``writer.save_arrays``."""
        self.validate(Path(getattr(writer, "dir", ".")) / self.file_name())
        return writer.save_arrays(self.FILE, **self.arrays())

    @classmethod
    def load(cls, source: Any):
        """From an engine artifact (``.arrays(name)``), its folder, or the npz path."""
        if isinstance(source, (str, Path)):
            p = Path(source)
            file = p if p.suffix == ".npz" else p / cls.file_name()
            if not file.is_file():
                raise ArtifactError(file, cls.FILE, f"no {cls.file_name()} ({cls.KIND} artifact)")
            with np.load(file, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        else:
            folder = getattr(source, "dir", None)
            file = Path(folder) / cls.file_name() if folder is not None else Path(cls.file_name())
            try:
                arrays = source.arrays(cls.FILE)
            except (FileNotFoundError, KeyError) as e:
                raise ArtifactError(file, cls.FILE, f"no {cls.file_name()} ({cls.KIND} artifact): "
                                    f"{e}") from None
        return cls.from_arrays(arrays, file)

    @classmethod
    def from_arrays(cls, arrays: dict, file: str | Path = "<memory>"):
        """Check kind and version, build, validate."""
        if KIND_KEY not in arrays:
            raise ArtifactError(file, KIND_KEY, f"missing (expected {cls.KIND!r}: not a typed "
                                "artifact, or written before typed artifacts)")
        kind = str(np.asarray(arrays[KIND_KEY]))
        if kind != cls.KIND:
            raise ArtifactError(file, KIND_KEY, f"is {kind!r}, expected {cls.KIND!r}")
        if VERSION_KEY not in arrays:
            raise ArtifactError(file, VERSION_KEY, "missing")
        try:
            version = int(np.asarray(arrays[VERSION_KEY]))
        except (TypeError, ValueError):
            raise ArtifactError(file, VERSION_KEY, f"not an integer: {arrays[VERSION_KEY]!r}") from None
        if version != cls.VERSION:
            raise ArtifactError(file, VERSION_KEY, f"is {version}, this code reads version "
                                f"{cls.VERSION} of {cls.KIND!r} (recompute the stage)")
        values = {}
        for f in cls.FIELDS:
            if f.name not in arrays:
                if not f.optional:
                    raise ArtifactError(file, f.name, "missing")
                values[f.name] = None
            else:
                values[f.name] = np.asarray(arrays[f.name])
        names = {f.name for f in fields(cls) if f.init}
        obj = cls(**{k: v for k, v in values.items() if k in names})
        obj.validate(file)
        return obj

    # ---------------------------------------------------------------- checks

    def validate(self, file: str | Path = "<memory>") -> None:
        """Presence, dtype kind, shape consistency, finiteness, then the class's own checks."""
        sizes: dict[str, tuple[int, str]] = {}
        for f in self.FIELDS:
            v = getattr(self, f.name)
            if v is None:
                if not f.optional:
                    raise ArtifactError(file, f.name, "missing")
                continue
            a = np.asarray(v)
            if a.dtype.kind not in f.kind:
                want = " or ".join(DTYPE_KINDS.get(k, k) for k in f.kind)
                raise ArtifactError(file, f.name, f"dtype {a.dtype} is not {want}")
            dims = f.shape.split()
            if a.ndim != len(dims):
                raise ArtifactError(file, f.name, f"expected shape ({f.shape}), got {a.shape}")
            for d, n in zip(dims, a.shape, strict=True):
                if d.isdigit():
                    if int(d) != n:
                        raise ArtifactError(file, f.name, f"expected shape ({f.shape}), got {a.shape}")
                    continue
                seen = sizes.setdefault(d, (n, f.name))
                if seen[0] != n:
                    raise ArtifactError(file, f.name, f"expected shape ({f.shape}) with {d} = "
                                        f"{seen[0]} (as {seen[1]}), got {a.shape}")
            if f.finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                frame = first_frame(~np.isfinite(a)) if dims and dims[0] == "F" else None
                raise ArtifactError(file, f.name, "non-finite values", frame)
        self._check(Path(file) if not isinstance(file, Path) else file)

    def _check(self, file: Path) -> None:
        """Units and plausibility of the class (overridden)."""


# ------------------------------------------------------------------------ check helpers


def first_frame(bad: np.ndarray) -> int | None:
    """Index along axis 0 of the first True in ``bad`` (None for a scalar / nothing bad)."""
    bad = np.asarray(bad)
    if bad.ndim == 0 or not bad.any():
        return None
    return int(np.argmax(bad.reshape(len(bad), -1).any(axis=1)))


def check_rotations(R: np.ndarray, file, field: str, tol: float = ROTATION_TOL) -> None:
    """(F, 3, 3) rotation matrices: orthonormal and det +1 within ``tol``."""
    R = np.asarray(R, dtype=float)
    err = np.abs(np.einsum("...ji,...jk->...ik", R, R) - np.eye(3)).max(axis=(-2, -1))
    det = np.abs(np.linalg.det(R) - 1.0)
    bad = (err > tol) | (det > tol)
    if bad.any():
        f = first_frame(bad)
        raise ArtifactError(file, field, f"not a rotation matrix (|R^T R - I| = "
                            f"{float(err.reshape(-1)[np.argmax(bad.reshape(-1))]):.2g}, "
                            f"det {float(np.linalg.det(R).reshape(-1)[np.argmax(bad.reshape(-1))]):.4g}; "
                            f"tolerance {tol:g})", f)


def check_metres(x: np.ndarray, file, field: str, max_abs: float = MAX_TRANSL_M,
                 per_frame: bool = True) -> None:
    """Values below ``max_abs`` metres (a value in mm is 1000 times too large); ``per_frame``:
    axis 0 is frames (the error names the first bad one)."""
    x = np.asarray(x, dtype=float)
    bad = np.abs(x) >= max_abs
    if bad.any():
        f = first_frame(bad) if per_frame else None
        raise ArtifactError(file, field, f"|value| {float(np.abs(x).max()):.4g} >= {max_abs:g}: "
                            "not metres (millimetres?)", f)


def check_range(x: np.ndarray, file, field: str, lo: float, hi: float, what: str = "",
                per_frame: bool = True) -> None:
    """Finite values of ``x`` within [lo, hi] (NaN ignored); ``per_frame`` as check_metres."""
    x = np.asarray(x, dtype=float)
    bad = np.isfinite(x) & ((x < lo) | (x > hi))
    if bad.any():
        raise ArtifactError(file, field, f"values outside [{lo:g}, {hi:g}]{what}: e.g. "
                            f"{float(x[bad].reshape(-1)[0]):.4g}", first_frame(bad) if per_frame else None)
