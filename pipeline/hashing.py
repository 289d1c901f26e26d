"""Content hashes for artifact keys: canonical JSON of parameters, sha256 of files and folders.

Everything that enters a key goes through :func:`canonical`, which turns it into plain JSON
with sorted keys. Arrays are hashed together with their dtype and shape (two arrays with the
same bytes but different shapes get different keys). A value that can't be hashed is an
error (:class:`UnhashableError`), never a hash that could collide.

File hashes are sha256 of the bytes. :class:`FileHasher` remembers them between runs in a
small JSON file keyed on ``(path, size, mtime_ns, ctime_ns, inode)`` so that an unchanged
multi-gigabyte video is not re-read on every run; any change to the file's metadata (a
write, a copy over it, a touch) makes it re-read the bytes.
"""
from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import os
import tempfile
from pathlib import Path, PurePath
from typing import Any

CHUNK = 1 << 20  # bytes read at a time when hashing a file


class UnhashableError(TypeError):
    """A value that can't enter a key (the message names where it was found)."""


def canonical(obj: Any, where: str = "value") -> Any:
    """Plain-JSON form of ``obj`` for hashing: dicts with str keys (sorted on dump), lists,
    str, int, float, bool, None. Paths become strings, tuples lists, dataclasses and pydantic
    models dicts, numpy arrays ``{"__ndarray__": sha256, "dtype", "shape"}``.

    Raises UnhashableError naming ``where`` (e.g. ``stages.fit.weights``) for anything else.
    """
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        if obj != obj or obj in (float("inf"), float("-inf")):
            return {"__float__": repr(obj)}  # JSON has no NaN/inf
        return obj
    if isinstance(obj, enum.Enum):
        return canonical(obj.value, where)
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if not isinstance(k, (str, int, float, bool)) and k is not None:
                raise UnhashableError(f"{where}: key {k!r} of type {type(k).__name__} can't be hashed")
            out[str(k)] = canonical(v, f"{where}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        return [canonical(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, (set, frozenset)):
        items = [canonical(v, f"{where}{{}}") for v in obj]
        return sorted(items, key=lambda x: json.dumps(x, sort_keys=True))
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return canonical({f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}, where)
    if hasattr(obj, "model_dump") and callable(obj.model_dump):  # pydantic model
        return canonical(obj.model_dump(mode="python"), where)
    mod = type(obj).__module__
    if mod == "numpy":
        import numpy as np

        if isinstance(obj, np.ndarray):
            if obj.dtype.hasobject:
                raise UnhashableError(f"{where}: object arrays can't be hashed")
            a = np.ascontiguousarray(obj)
            return {"__ndarray__": hashlib.sha256(a.tobytes()).hexdigest(),
                    "dtype": a.dtype.str, "shape": list(a.shape)}
        if isinstance(obj, np.generic):
            return canonical(obj.item(), where)
    raise UnhashableError(f"{where}: a {type(obj).__name__} can't be hashed into a key")


def dumps(obj: Any) -> str:
    """Canonical JSON text of ``obj`` (sorted keys, no spaces)."""
    return json.dumps(canonical(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def digest(obj: Any) -> str:
    """sha256 hex of the canonical JSON of ``obj``."""
    return hashlib.sha256(dumps(obj).encode()).hexdigest()


def sha256_file(path: Path) -> str:
    """sha256 hex of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _stat_key(st: os.stat_result) -> str:
    return f"{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}:{st.st_ino}"


class FileHasher:
    """sha256 of files and folders with a persistent stat-keyed memo.

    ``memo_file``: JSON file holding ``{abs path: [stat key, sha256]}``; ``None`` keeps the
    memo in memory only. Not shared between threads; processes may share the file (last
    writer wins, a lost entry only costs a re-read).
    """

    def __init__(self, memo_file: Path | None = None):
        self.memo_file = memo_file
        self._memo: dict[str, list[str]] = {}
        self._dirty = False
        if memo_file is not None and memo_file.is_file():
            try:
                data = json.loads(memo_file.read_text())
                if isinstance(data, dict):
                    self._memo = {k: v for k, v in data.items()
                                  if isinstance(v, list) and len(v) == 2}
            except (OSError, ValueError):
                self._memo = {}  # a damaged memo only costs re-reading the files

    def file(self, path: Path) -> str:
        """sha256 of one file, from the memo when its stat is unchanged."""
        path = Path(path).resolve()
        st = path.stat()
        sk = _stat_key(st)
        hit = self._memo.get(str(path))
        if hit is not None and hit[0] == sk:
            return hit[1]
        h = sha256_file(path)
        self._memo[str(path)] = [sk, h]
        self._dirty = True
        return h

    def __call__(self, path: Path) -> str:
        """sha256 of a file, or of a folder: the sorted relative paths and file hashes of
        everything under it (hidden files included, symlinks followed)."""
        path = Path(path)
        if path.is_dir():
            h = hashlib.sha256(b"dir\0")
            for p in sorted(q for q in path.rglob("*") if q.is_file()):
                h.update(p.relative_to(path).as_posix().encode() + b"\0")
                h.update(self.file(p).encode() + b"\0")
            return h.hexdigest()
        return self.file(path)

    def save(self) -> None:
        """Write the memo back (atomically) if anything was added."""
        if self.memo_file is None or not self._dirty:
            return
        self.memo_file.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.memo_file.parent, prefix=".filehashes-")
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(self._memo, f)
            os.replace(tmp, self.memo_file)
        except OSError:
            Path(tmp).unlink(missing_ok=True)
        self._dirty = False
