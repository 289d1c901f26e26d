"""The on-disk artifact store: ``<root>/<unit>/<stage>/`` folders with a ``manifest.json``.

``root`` is ``outputs/<session>``. A unit may contain one ``/`` (sequences are
``"<group>/<action>"``), which nests the folder.

Life of an artifact:

1. the engine takes the artifact's lock (``<root>/<unit>/.<stage>.lock``, ``fcntl.flock``;
   the kernel drops it when the holder dies, even by ``kill -9``);
2. leftovers of earlier crashes (``.tmp-<stage>-*``, ``.trash-<stage>-*``) are removed;
3. the stage writes into a fresh ``<root>/<unit>/.tmp-<stage>-<pid>-<rand>/``;
4. the engine writes ``manifest.json`` last (with each file's size in ``files`` and its
   sha256 in ``sha256``), fsyncs it, and renames the folder to ``<stage>`` (an old artifact
   is first renamed to ``.trash-...``, then deleted).

So a folder named ``<stage>`` always had a complete manifest when it was renamed; a killed
stage leaves only a ``.tmp-`` folder, which never looks complete.

Lock backends (``Store(root, locks=...)``, else the ``PIPELINE_LOCKS`` environment variable,
else ``"flock"``): ``"flock"`` as above, for one machine; ``"lease"`` for workers on several
hosts sharing the folder (a cluster on NFS/Lustre, where ``flock`` may be local to each
client): the lock is a :class:`pipeline.lease.Lease` file ``<root>/<unit>/.<stage>.lease``
renewed while the build runs (ttl ``lease_ttl_s``, else ``PIPELINE_LEASE_TTL_S``, else 60 s).
A killed owner's lease blocks others until it expires (ttl + grace) instead of at once. If the
lease was lost meanwhile (the owner paused longer than the ttl and another process took it
over), :meth:`Store.commit` refuses: it removes the temporary folder and raises
:class:`pipeline.lease.LeaseLost`, leaving the new holder's artifact alone. Every process
working on one ``outputs`` folder must use the same backend (the flock backend's cleanup
does respect live leases, see below).

Leftovers of killed runs: every time the engine considers a node, hit or not, it removes the
``.tmp-``/``.trash-`` folders of that (unit, stage) that nobody is building
(:meth:`Store.clean_stale_leftovers`): it takes the artifact's lock without waiting; if it
gets it, no live process is building there (a builder holds the lock from step 1 to 4), so
they are a killed run's; if not, it leaves them to their builder. With leases, "gets it"
means no live lease exists (none, or an expired one it took over); with flock, a live lease
file also counts as held.

Corruption: on read, an entry whose manifest is unreadable or whose files are missing or of
the wrong size is *corrupt* (:meth:`Store.entry`): the engine warns, deletes it and
recomputes. A change that keeps the size is found by content: before a node is built from
an upstream artifact the engine compares the upstream files with the manifest's sha256
(:meth:`Store.verify`), and a file that can't be read inside a stage raises
:class:`CorruptArtifactError` naming stage, unit and file; either way the upstream node is
rebuilt first. Manifests written before ``sha256`` existed are checked by size only.
"""
from __future__ import annotations

import fcntl
import json
import math
import os
import secrets
import shutil
import time
import zipfile
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from pipeline.hashing import sha256_file
from pipeline.lease import Lease, LeaseError, LeaseLost, is_live

MANIFEST = "manifest.json"
LOCKS = ("flock", "lease")  # the lock backends (see the module docstring)


class StoreError(ValueError):
    """A unit or stage name that can't be turned into a folder, or a bad lock setting."""


class CorruptArtifactError(RuntimeError):
    """A file of a completed artifact can't be read (its content was damaged after commit).
    ``stage``, ``unit``, ``file``: which one; the message names them and the folder."""

    def __init__(self, dir: Path, stage: str, unit: str, file: str, problem: str):
        self.dir, self.stage, self.unit, self.file, self.problem = Path(dir), stage, unit, file, problem
        super().__init__(f"{stage} [{unit}]: {dir / file}: corrupt artifact file ({problem})")


file_sha256 = sha256_file  # one file hash for keys and manifests (pipeline.hashing)


def _check_part(kind: str, name: str) -> None:
    parts = name.split("/")
    if (not name or name.startswith("/") or "\0" in name
            or any(p in ("", ".", "..") or p.startswith(".") for p in parts)):
        raise StoreError(f"{kind} {name!r} can't be used as a folder name")


def json_default(o: Any) -> Any:
    """``json.dump`` fallback: numpy scalars/arrays, paths, sets."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, (set, frozenset)):
        return sorted(o)
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def strict_json(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, inf; numpy ones too) replaced by ``None``, numpy
    values and paths converted: what strict JSON can hold (``null`` = no value)."""
    if isinstance(obj, float) or (hasattr(obj, "dtype") and getattr(obj, "shape", None) == ()):
        v = obj.item() if hasattr(obj, "item") else obj
        return None if isinstance(v, float) and not math.isfinite(v) else v
    if isinstance(obj, dict):
        return {k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if hasattr(obj, "tolist") or isinstance(obj, (set, frozenset, os.PathLike)):
        return strict_json(json_default(obj))
    return obj


@dataclass(frozen=True)
class StoredArtifact:
    """A completed, read-only artifact (implements ``pipeline.spec.Artifact``)."""

    dir: Path
    key: str
    unit: str
    stage: str
    manifest: dict

    def arrays(self, name: str) -> dict:
        """The arrays of ``<name>.npz`` as a dict of read-only numpy arrays.
        CorruptArtifactError if the file can't be read."""
        import numpy as np

        p = self.path(f"{name}.npz")
        try:
            with np.load(p, allow_pickle=False) as z:
                out = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, zlib.error, ValueError, EOFError, OSError, KeyError) as e:
            raise CorruptArtifactError(self.dir, self.stage, self.unit, p.name,
                                       f"{type(e).__name__}: {e}") from e
        for a in out.values():
            a.flags.writeable = False
        return out

    def json(self, name: str) -> Any:
        """The content of ``<name>.json``. CorruptArtifactError if it can't be read."""
        p = self.path(f"{name}.json")
        try:
            return json.loads(p.read_text())
        except (OSError, ValueError) as e:  # JSONDecodeError, UnicodeDecodeError
            raise CorruptArtifactError(self.dir, self.stage, self.unit, p.name,
                                       f"{type(e).__name__}: {e}") from e

    def path(self, filename: str) -> Path:
        """Path of a file of this artifact; FileNotFoundError naming the artifact if absent."""
        p = self.dir / filename
        if not p.exists():
            raise FileNotFoundError(f"{self.stage} [{self.unit}]: no file {filename!r} in {self.dir}")
        return p


@dataclass(frozen=True)
class Writer:
    """Writes into the temporary folder of the artifact being built
    (implements ``pipeline.spec.ArtifactWriter``)."""

    dir: Path

    def path(self, filename: str) -> Path:
        """A path inside the artifact to write any other file to (parent folders created)."""
        p = (self.dir / filename).resolve()
        if self.dir.resolve() not in p.parents:
            raise StoreError(f"{filename!r} is outside the artifact folder")
        if p.name == MANIFEST:
            raise StoreError(f"{MANIFEST} is written by the engine")
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def save_arrays(self, name: str, **arrays) -> Path:
        """Write ``<name>.npz`` (uncompressed, no pickles)."""
        import numpy as np

        p = self.path(f"{name}.npz")
        with open(p, "wb") as f:
            np.savez(f, **arrays)
        return p

    def save_json(self, name: str, obj: Any) -> Path:
        """Write ``<name>.json``: strict JSON (numpy values converted, NaN and inf written as
        ``null``: a bare ``NaN`` is not JSON and breaks other readers)."""
        p = self.path(f"{name}.json")
        p.write_text(json.dumps(strict_json(obj), indent=1, allow_nan=False, default=json_default))
        return p


@dataclass(frozen=True)
class Entry:
    """What is on disk for one (unit, stage): ``state`` is ``complete``, ``absent`` or
    ``corrupt`` (``problem`` says why)."""

    state: str
    manifest: dict | None = None
    problem: str = ""


class Store:
    """The artifacts of one session under ``root`` (``outputs/<session>``)."""

    def __init__(self, root: Path, locks: str | None = None, lease_ttl_s: float | None = None):
        self.root = Path(root)
        if locks is None:
            env = os.environ.get("PIPELINE_LOCKS", "").strip()
            locks, where = (env or "flock"), ("PIPELINE_LOCKS=" if env else "locks=")
        else:
            where = "locks="
        if locks not in LOCKS:
            raise StoreError(f"{where}{locks!r}: the lock backend must be one of {', '.join(LOCKS)}")
        self.locks = locks
        if lease_ttl_s is None:
            env = os.environ.get("PIPELINE_LEASE_TTL_S", "").strip()
            try:
                lease_ttl_s = float(env) if env else 60.0
            except ValueError:
                lease_ttl_s = float("nan")
            where = f"PIPELINE_LEASE_TTL_S={env!r}"
        else:
            where = f"lease_ttl_s={lease_ttl_s!r}"
        if not (isinstance(lease_ttl_s, (int, float)) and lease_ttl_s > 0):
            raise StoreError(f"{where}: the lease time-to-live must be a number of seconds > 0")
        self.lease_ttl_s = float(lease_ttl_s)
        self._leases: dict[tuple[str, str], Lease] = {}  # held by lock(), checked by commit()

    def __getstate__(self) -> dict:  # a Store sent to another process holds no lease there
        return {**self.__dict__, "_leases": {}}

    def lease_path(self, unit: str, stage: str) -> Path:
        """The lease file of (unit, stage) (``locks="lease"``)."""
        return self.dir(unit, stage).parent / f".{stage}.lease"

    def _lease(self, unit: str, stage: str) -> Lease:
        return Lease(self.lease_path(unit, stage), ttl_s=self.lease_ttl_s)

    def dir(self, unit: str, stage: str) -> Path:
        _check_part("unit", unit)
        _check_part("stage", stage)
        if "/" in stage:
            raise StoreError(f"stage {stage!r} can't contain '/'")
        return self.root / unit / stage

    def entry(self, unit: str, stage: str) -> Entry:
        """Inspect the folder of (unit, stage) without changing anything."""
        d = self.dir(unit, stage)
        if not d.exists():
            return Entry("absent")
        mf = d / MANIFEST
        try:
            m = json.loads(mf.read_text())
        except FileNotFoundError:
            return Entry("corrupt", problem=f"no {MANIFEST}")
        except (OSError, ValueError) as e:
            return Entry("corrupt", problem=f"unreadable {MANIFEST}: {e}")
        if not isinstance(m, dict) or not isinstance(m.get("key"), str) \
                or not isinstance(m.get("files"), dict):
            return Entry("corrupt", problem=f"{MANIFEST} lacks key/files")
        if m.get("stage") != stage or m.get("unit") != unit:
            return Entry("corrupt", problem=f"{MANIFEST} names {m.get('stage')}/{m.get('unit')}")
        for name, size in m["files"].items():
            f = d / name
            try:
                actual = f.stat().st_size
            except OSError:
                return Entry("corrupt", m, f"missing file {name}")
            if actual != size:
                return Entry("corrupt", m, f"{name}: {actual} bytes, manifest says {size}")
        return Entry("complete", m)

    def open(self, unit: str, stage: str, manifest: dict) -> StoredArtifact:
        return StoredArtifact(self.dir(unit, stage), manifest["key"], unit, stage, manifest)

    def verify(self, unit: str, stage: str, manifest: dict) -> str:
        """Compare the artifact's files with the manifest's ``sha256``; returns "" when they
        match (or the manifest predates hashes), else what differs (``"<file>: ..."``)."""
        hashes = manifest.get("sha256")
        if not isinstance(hashes, dict):
            return ""
        d = self.dir(unit, stage)
        for name, want in sorted(hashes.items()):
            try:
                got = file_sha256(d / name)
            except OSError as e:
                return f"{name}: unreadable ({e})"
            if got != want:
                return f"{name}: content changed (sha256 {got[:12]}, manifest says {str(want)[:12]})"
        return ""

    @contextmanager
    def lock(self, unit: str, stage: str, on_wait: Callable[[], None] | None = None
             ) -> Iterator[None]:
        """Hold the exclusive lock of (unit, stage) for the ``with`` block. If another
        process holds it, call ``on_wait()`` once and block until it is released (with
        leases: or until its lease expires, then take it over). A lease is renewed in the
        background for the whole block."""
        d = self.dir(unit, stage)
        d.parent.mkdir(parents=True, exist_ok=True)
        if self.locks == "lease":
            lease = self._lease(unit, stage)
            lease.acquire(wait=True, on_wait=on_wait)
            self._leases[(unit, stage)] = lease
            try:
                yield
            finally:
                if self._leases.get((unit, stage)) is lease:
                    del self._leases[(unit, stage)]
                lease.release()
            return
        fd = os.open(d.parent / f".{stage}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if on_wait is not None:
                    on_wait()
                fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # closing drops the flock

    @contextmanager
    def try_lock(self, unit: str, stage: str) -> Iterator[bool]:
        """Take the lock of (unit, stage) if nobody holds it, without waiting: yields True
        (held for the block) or False (another process, or this one, holds it)."""
        d = self.dir(unit, stage)
        if not d.parent.is_dir():
            yield True  # no folder: nothing to build in or clean, nobody to race with
            return
        if self.locks == "lease":
            lease = self._lease(unit, stage)
            if not lease.acquire(wait=False):  # a live lease: someone is building
                yield False
                return
            try:
                yield True
            finally:
                lease.release()
            return
        fd = os.open(d.parent / f".{stage}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                yield False
                return
            # a worker of a lease-locked run may be building here: leave it alone too
            yield not is_live(self.lease_path(unit, stage), self.lease_ttl_s)
        finally:
            os.close(fd)

    def clean_stale_leftovers(self, unit: str, stage: str) -> list[Path]:
        """Remove the ``.tmp-<stage>-*``/``.trash-<stage>-*`` folders of killed runs when no
        live process is building (unit, stage) (its lock is free); needs no lock held, and
        leaves everything alone while someone holds the lock. Returns what was removed."""
        parent = self.dir(unit, stage).parent
        if not parent.is_dir() or not any(
                p.name.startswith((f".tmp-{stage}-", f".trash-{stage}-")) for p in parent.iterdir()):
            return []
        with self.try_lock(unit, stage) as free:
            return self.clean_leftovers(unit, stage) if free else []

    # The methods below must be called with the lock held.

    def clean_leftovers(self, unit: str, stage: str) -> list[Path]:
        """Remove ``.tmp-<stage>-*`` and ``.trash-<stage>-*`` left by killed runs, and the
        private files of lease operations a kill interrupted (``.<stage>.lease.<op>-<token>``,
        untouched for 10 ttl: in use, they live for milliseconds)."""
        parent = self.dir(unit, stage).parent
        gone = []
        if parent.is_dir():
            old = time.time() - 10 * self.lease_ttl_s
            for p in parent.iterdir():
                if p.name.startswith((f".tmp-{stage}-", f".trash-{stage}-")):
                    shutil.rmtree(p, ignore_errors=True)
                    gone.append(p)
                elif p.name.startswith(f".{stage}.lease.") and "-" in p.name:
                    try:
                        if p.lstat().st_mtime < old:
                            p.unlink()
                            gone.append(p)
                    except FileNotFoundError:
                        pass
        return gone

    def begin(self, unit: str, stage: str) -> Writer:
        """A fresh temporary folder for building (unit, stage)."""
        parent = self.dir(unit, stage).parent
        parent.mkdir(parents=True, exist_ok=True)
        tmp = parent / f".tmp-{stage}-{os.getpid()}-{secrets.token_hex(4)}"
        tmp.mkdir()
        return Writer(tmp)

    def abort(self, writer: Writer) -> None:
        shutil.rmtree(writer.dir, ignore_errors=True)

    def remove(self, unit: str, stage: str) -> None:
        """Delete the artifact folder of (unit, stage) if present."""
        d = self.dir(unit, stage)
        if d.exists():
            trash = d.parent / f".trash-{stage}-{os.getpid()}-{secrets.token_hex(4)}"
            os.rename(d, trash)
            shutil.rmtree(trash, ignore_errors=True)

    def commit(self, writer: Writer, unit: str, stage: str, manifest: dict) -> dict:
        """Write the manifest (with every file's size and sha256) into the temporary folder
        and rename it into place, replacing any older artifact. Returns the manifest written.

        With leases, when the lease of (unit, stage) held by :meth:`lock` is no longer ours
        (checked by re-reading the file, and renewed so the rename runs within a fresh ttl),
        it removes the temporary folder and raises :class:`pipeline.lease.LeaseLost`: the
        process that took the lease over owns the artifact now."""
        files, hashes = {}, {}
        for p in sorted(writer.dir.rglob("*")):
            if p.is_file():
                name = p.relative_to(writer.dir).as_posix()
                files[name] = p.stat().st_size
                hashes[name] = file_sha256(p)
        manifest = {**manifest, "stage": stage, "unit": unit, "files": files, "sha256": hashes}
        mf = writer.dir / MANIFEST
        with open(mf, "w") as f:
            json.dump(manifest, f, indent=1, default=json_default)
            f.flush()
            os.fsync(f.fileno())
        self._check_lease(writer, unit, stage)
        self.remove(unit, stage)
        os.rename(writer.dir, self.dir(unit, stage))
        dfd = os.open(self.dir(unit, stage).parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
        return manifest

    def _check_lease(self, writer: Writer, unit: str, stage: str) -> None:
        """Before commit: the lease held by :meth:`lock` must still be ours (renewed now, so
        the rename runs within a fresh ttl); else remove the temporary folder and raise
        :class:`LeaseLost`."""
        lease = self._leases.get((unit, stage))
        if lease is None:
            return
        err: BaseException | None = None
        for _ in range(3):
            try:
                lease.renew()
                return
            except LeaseError as e:
                err = e
                break
            except OSError as e:  # a file server hiccup: look again before giving the work up
                err = e
                time.sleep(0.2)
        shutil.rmtree(writer.dir, ignore_errors=True)
        holder = getattr(err, "holder", None)
        who = (f"now held by {holder.get('owner')}" if holder and "owner" in holder else
               "no lease there now" if isinstance(err, LeaseLost) else f"{type(err).__name__}: {err}")
        raise LeaseLost(lease.path, holder,
                        f"of {stage} [{unit}] lost while building ({who}): not committed, "
                        f"its temporary folder {writer.dir.name} was removed") from err
