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

A stage output that is JSON (summaries, file lists) is a :class:`JsonArtifact`: the same
``KIND``/``VERSION``/``FILE`` (the json name without ``.json``), ``to_json()`` and
``from_json(JsonFields)``; ``save(writer)`` writes ``<FILE>.json`` with ``artifact_kind`` and
``artifact_version`` beside the content, ``load(artifact | folder | json path)`` checks them and
reads every field through :class:`JsonFields` (type, presence, finiteness), whose errors name
the file and the dotted field (``export.json: files[3]: ...``).
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

    @classmethod
    def exists_in(cls, source: Any) -> bool:
        """Whether the artifact (engine artifact or folder) holds this class's file (an
        optional output, e.g. the partner fit's refined keypoints)."""
        folder = getattr(source, "dir", None) if not isinstance(source, (str, Path)) else source
        return folder is not None and (Path(folder) / cls.file_name()).is_file()


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


# ------------------------------------------------------------------------ JSON artifacts

_JSON_TYPE_NAMES = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
                    list: "a list", dict: "an object"}


class JsonFields:
    """Typed access to one JSON object of an artifact file; every error names the file and the
    dotted field. ``get(name, type)``: ``int`` rejects bools and fractions, ``float`` accepts
    integers and (``finite=True``) rejects NaN/inf, ``optional`` accepts absent and null
    (-> ``default``)."""

    def __init__(self, data: Any, file: str | Path, prefix: str = "", folder: Path | None = None):
        self.file, self.prefix, self.folder = file, prefix, folder
        if not isinstance(data, dict):
            raise ArtifactError(file, prefix or "<content>",
                                f"expected an object, got {type(data).__name__}")
        self.data = data

    def name(self, key: str | int) -> str:
        if isinstance(key, int):
            return f"{self.prefix}[{key}]"
        return f"{self.prefix}.{key}" if self.prefix else key

    def check(self, value: Any, typ: type, field: str, finite: bool = True) -> Any:
        if isinstance(value, np.generic):  # an in-memory object being validated
            value = value.item()
        ok = (isinstance(value, typ) and not (typ in (int, float) and isinstance(value, bool)))
        if typ is float and isinstance(value, int) and not isinstance(value, bool):
            value, ok = float(value), True
        if typ is int and isinstance(value, float) and value.is_integer():
            value, ok = int(value), True
        if not ok:
            raise ArtifactError(self.file, field, f"expected {_JSON_TYPE_NAMES.get(typ, typ)}, "
                                f"got {type(value).__name__} {value!r:.60}")
        if typ is float and finite and not np.isfinite(value):
            raise ArtifactError(self.file, field, f"non-finite value {value}")
        return value

    def get(self, key: str, typ: type, optional: bool = False, default: Any = None,
            finite: bool = True) -> Any:
        field = self.name(key)
        if key not in self.data or self.data[key] is None:
            if optional:
                return default
            raise ArtifactError(self.file, field, "missing" if key not in self.data else
                                f"null, expected {_JSON_TYPE_NAMES.get(typ, typ)}")
        return self.check(self.data[key], typ, field, finite)

    def sub(self, key: str, optional: bool = False) -> JsonFields | None:
        """The object at ``key`` as JsonFields (None when optional and absent/null)."""
        v = self.get(key, dict, optional=optional)
        return None if v is None else JsonFields(v, self.file, self.name(key), self.folder)

    def items(self, key: str, typ: type, finite: bool = True, optional: bool = False,
              nullable: bool = False) -> list | None:
        """A list whose items are all ``typ`` (``nullable``: or null)."""
        v = self.get(key, list, optional=optional)
        if v is None:
            return None
        return [None if (x is None and nullable) else
                self.check(x, typ, f"{self.name(key)}[{i}]", finite) for i, x in enumerate(v)]

    def mapping(self, key: str, typ: type, finite: bool = True, optional: bool = False,
                nullable: bool = False) -> dict | None:
        """An object whose values are all ``typ`` (``nullable``: or null); keys are strings."""
        v = self.get(key, dict, optional=optional)
        if v is None:
            return None
        return {str(k): (None if (x is None and nullable) else
                         self.check(x, typ, f"{self.name(key)}.{k}", finite))
                for k, x in v.items()}

    def objects(self, key: str, optional: bool = False) -> list[JsonFields] | None:
        """A list of objects, each as JsonFields."""
        v = self.get(key, list, optional=optional)
        if v is None:
            return None
        return [JsonFields(x, self.file, f"{self.name(key)}[{i}]", self.folder)
                for i, x in enumerate(v)]

    def error(self, key: str | int, msg: str, frame: int | None = None) -> ArtifactError:
        return ArtifactError(self.file, self.name(key), msg, frame)


def read_json_file(source: Any, name: str) -> tuple[Any, Path, Path | None]:
    """``(content of <name>.json, its path, the artifact folder or None)`` from an engine
    artifact (``.json(name)``), its folder, or the json path; ArtifactError when absent or
    unreadable."""
    import json

    if isinstance(source, (str, Path)):
        p = Path(source)
        file = p if p.suffix == ".json" else p / f"{name}.json"
        if not file.is_file():
            raise ArtifactError(file, name, f"no {name}.json")
        try:
            return json.loads(file.read_text()), file, file.parent
        except (OSError, ValueError) as e:
            raise ArtifactError(file, name, f"unreadable: {type(e).__name__}: {e}") from None
    folder = getattr(source, "dir", None)
    file = Path(folder) / f"{name}.json" if folder is not None else Path(f"{name}.json")
    try:
        return source.json(name), file, None if folder is None else Path(folder)
    except FileNotFoundError as e:
        raise ArtifactError(file, name, f"no {name}.json: {e}") from None


def check_header(data: Any, file: Path, kind: str, version: int) -> None:
    """The ``artifact_kind`` / ``artifact_version`` of a JSON artifact file."""
    f = JsonFields(data, file)
    got = f.get(KIND_KEY, str, optional=True)
    if got is None:
        raise ArtifactError(file, KIND_KEY, f"missing (expected {kind!r}: not a typed artifact, "
                            "or written before typed artifacts)")
    if got != kind:
        raise ArtifactError(file, KIND_KEY, f"is {got!r}, expected {kind!r}")
    v = f.get(VERSION_KEY, int)
    if v != version:
        raise ArtifactError(file, VERSION_KEY, f"is {v}, this code reads version {version} of "
                            f"{kind!r} (recompute the stage)")


class JsonArtifact:
    """Base of the typed JSON outputs (subclasses are frozen dataclasses): ``to_json()`` is the
    content, ``from_json(JsonFields)`` reads and checks it (raising ArtifactError naming the
    file and field), ``_check(file, folder)`` adds cross-field and on-disk checks (``folder``:
    the artifact folder when known, e.g. that the files it lists exist)."""

    KIND: ClassVar[str]
    VERSION: ClassVar[int]
    FILE: ClassVar[str]

    @classmethod
    def file_name(cls) -> str:
        return f"{cls.FILE}.json"

    def to_json(self) -> dict:
        raise NotImplementedError

    @classmethod
    def from_json(cls, f: JsonFields):
        raise NotImplementedError

    def _check(self, file: Path, folder: Path | None) -> None:
        """Cross-field checks (overridden)."""

    def content(self) -> dict:
        return {KIND_KEY: self.KIND, VERSION_KEY: int(self.VERSION), **self.to_json()}

    def validate(self, file: str | Path = "<memory>", folder: Path | None = None) -> None:
        """Read our own content back through ``from_json`` (types, finiteness), then ``_check``."""
        file = Path(file)
        type(self).from_json(JsonFields(self.to_json(), file, folder=folder))
        self._check(file, folder)

    def save(self, writer) -> Path:
        folder = Path(getattr(writer, "dir", "."))
        self.validate(folder / self.file_name(), folder)
        return writer.save_json(self.FILE, self.content())

    @classmethod
    def load(cls, source: Any):
        data, file, folder = read_json_file(source, cls.FILE)
        check_header(data, file, cls.KIND, cls.VERSION)
        obj = cls.from_json(JsonFields(data, file, folder=folder))
        obj._check(file, folder)
        return obj


def check_relative(f: JsonFields, key: str | int, rel: str, folder: Path | None) -> None:
    """``rel`` is a relative path inside the artifact (no ``..``, not absolute) and, when the
    folder is known, a file there."""
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts or not rel:
        raise f.error(key, f"{rel!r} is not a relative path inside the artifact")
    if folder is not None and not (Path(folder) / p).is_file():
        raise f.error(key, f"{rel!r} is listed but not in {folder}")
