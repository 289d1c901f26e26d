"""Leases: exclusive locks that hold across hosts sharing a filesystem (NFS, Lustre, ...),
where ``fcntl.flock`` may be local to each client.

A lease is a small JSON file ``{owner, host, pid, token, ttl, acquired, expires}``:

* **create** — write a private file ``<lease>.<token>.new`` next to it, then
  ``os.link(new, lease)``: ``link`` fails if the lease exists and is atomic on NFS too (unlike
  ``O_EXCL`` on old NFS). Success is judged by the private file's link count reaching 2 (an
  NFS ``link`` retransmitted after a lost reply can answer EEXIST although it worked);
* **renew** — a background thread, every ``renew_s`` (ttl/3): re-read the lease (a fresh
  ``open``: close-to-open consistency; ``os.stat`` alone may be served from the attribute
  cache) and, while it still holds our token, rewrite it with a new ``expires`` (private file
  + ``os.replace``). A token that is not ours any more sets :attr:`Lease.lost`;
* **release** — rename the lease to a private name, read it, delete it if the token is ours,
  else put it back (``link``): we never delete someone else's lease;
* **take over** — a lease whose ``expires`` (the writer's wall clock) plus ``grace_s`` (for
  clock skew between hosts) is past by our clock is stale. One contender at a time (the one
  that creates the gate file ``<lease>.takeover``, also by ``link``; a gate older than its
  ttl + grace is broken the same way) re-reads the lease, renames it to a private
  ``<lease>.stale-<our token>`` if it is still stale (put back if the rename caught a
  renewal), and then every contender tries ``link`` again: the first one wins. Without the
  gate, a slow contender could rename away the lease another had just created.

``clock`` is the wall clock (``time.time``): hosts must be NTP-synchronised to well within
``grace_s``. docs/ARCHITECTURE.md ("Locks across hosts") discusses the failure modes.
"""
from __future__ import annotations

import errno
import json
import os
import random
import secrets
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["Lease", "LeaseError", "LeaseHeld", "LeaseLost", "read_lease", "is_live",
           "default_grace"]


class LeaseError(RuntimeError):
    """A lease file that can't be used (unreadable content, no hard links on the filesystem)."""


class LeaseHeld(LeaseError):
    """Another owner holds the lease. ``holder``: its content (None if unknown)."""

    def __init__(self, path: Path, holder: dict | None, what: str = "held by another owner"):
        self.path, self.holder = Path(path), holder
        who = _describe(holder)
        super().__init__(f"{path}: lease {what}{f' ({who})' if who else ''}")


class LeaseLost(LeaseHeld):
    """Our lease was taken over (or removed) while we held it: ``holder`` is what the file
    holds now (None: no lease)."""

    def __init__(self, path: Path, holder: dict | None, what: str = "lost"):
        super().__init__(path, holder, what)


def _describe(holder: dict | None) -> str:
    if not holder:
        return ""
    if "corrupt" in holder:
        return f"unreadable: {holder['corrupt']}"
    return f"owner {holder.get('owner')}, expires {holder.get('expires')}"


def default_grace(ttl_s: float) -> float:
    """Extra seconds past ``expires`` before a lease counts as stale: covers clock skew
    between NTP-synchronised hosts (ttl/4, at most 5 s)."""
    return min(5.0, ttl_s / 4.0)


_RETRY_ERRNOS = {errno.ESTALE, errno.EIO, errno.EAGAIN}


def read_lease(path: Path) -> dict | None:
    """The content of the lease file at ``path`` read through a fresh ``open`` (so NFS
    revalidates it), or None if there is none. An unreadable file raises
    :class:`LeaseError` naming it."""
    path = Path(path)
    for attempt in range(3):
        try:
            with open(path, "rb") as f:
                text = f.read()
            break
        except FileNotFoundError:
            return None
        except OSError as e:
            if e.errno not in _RETRY_ERRNOS or attempt == 2:
                raise
            time.sleep(0.01)
    try:
        info = json.loads(text)
    except ValueError as e:
        raise LeaseError(f"{path}: unreadable lease file ({e})") from e
    need = {"token": str, "expires": (int, float), "owner": str}
    for field, kind in need.items():
        if not isinstance(info, dict) or not isinstance(info.get(field), kind):
            raise LeaseError(f"{path}: lease file lacks field {field!r}")
    return info


def _read_or_corrupt(path: Path) -> dict | None:
    """read_lease, with an unreadable file returned as ``{"corrupt": why, "mtime": t}``."""
    try:
        return read_lease(path)
    except LeaseError as e:
        try:
            mtime = os.stat(path).st_mtime
        except FileNotFoundError:
            return None
        return {"corrupt": str(e), "mtime": mtime}


def is_live(path: Path, ttl_s: float = 60.0, now: float | None = None) -> bool:
    """Whether a lease file at ``path`` still excludes others at ``now`` (default: the wall
    clock): it exists and its ``expires`` plus the grace of its ttl is not past. An unreadable
    one counts as live for ``ttl_s`` plus grace after its mtime."""
    holder = _read_or_corrupt(Path(path))
    if holder is None:
        return False
    now = time.time() if now is None else now
    if "corrupt" in holder:
        return now <= holder["mtime"] + ttl_s + default_grace(ttl_s)
    ttl = float(holder.get("ttl", ttl_s))
    return now <= float(holder["expires"]) + default_grace(ttl)


def _write_json(path: Path, info: dict) -> None:
    # Not fsynced: a lease need not survive a crash of the file server, and on NFS close()
    # sends the data to the server before the link/rename that publishes it.
    with open(path, "w") as f:
        json.dump(info, f)


def _unlink(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


class Lease:
    """An exclusive lease on ``path`` (one lease file per protected thing), renewed by a
    background thread while held; a context manager (``with Lease(p): ...``).

    ttl_s : seconds a lease stays valid without renewal (a dead owner blocks others at most
        ``ttl_s + grace_s``).
    renew_s : renewal period (default ``ttl_s / 3``).
    owner : a label for people (default ``<host>:<pid>``); identity is the random ``token``.
    clock : wall-clock seconds (``time.time``); tests pass a skewed one.
    grace_s : clock-skew allowance (default :func:`default_grace`).
    poll_s : how often a waiting :meth:`acquire` looks again (default ttl/20, 0.02-0.5 s).
    """

    def __init__(self, path: Path, ttl_s: float = 60.0, renew_s: float | None = None,
                 owner: str | None = None, clock: Callable[[], float] = time.time,
                 grace_s: float | None = None, poll_s: float | None = None):
        if not ttl_s > 0:
            raise ValueError(f"{path}: lease ttl_s must be > 0, got {ttl_s!r}")
        self.path = Path(path)
        self.ttl_s = float(ttl_s)
        self.renew_s = float(renew_s) if renew_s is not None else self.ttl_s / 3.0
        if not 0 < self.renew_s < self.ttl_s:
            raise ValueError(f"{path}: lease renew_s must be in (0, ttl_s={ttl_s}), got {renew_s!r}")
        self.grace_s = default_grace(self.ttl_s) if grace_s is None else float(grace_s)
        self.poll_s = poll_s if poll_s is not None else min(0.5, max(0.02, self.ttl_s / 20.0))
        self.host = socket.gethostname()
        self.owner = owner or f"{self.host}:{os.getpid()}"
        self.clock = clock
        self.token = secrets.token_hex(16)
        self.renewals = 0           # successful renewals since acquire
        self.last_renewal: float | None = None  # clock() of the last write of our lease
        self.lost_to: dict | None = None  # what the file held when we found the lease lost
        self._held = False
        self._lost = False
        self._expires = 0.0
        self.acquired_info: dict | None = None  # the content we published at acquire
        self._mutex = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- state ----------------------------------------------------------------------------
    @property
    def held(self) -> bool:
        """We acquired the lease and have not released it or found it lost."""
        return self._held and not self.lost

    @property
    def lost(self) -> bool:
        """The lease is no longer ours: a renewal found another token (or none) in the file,
        or our own expiry passed without a renewal (we can't know who holds it now)."""
        return self._lost or (self._held and self.clock() > self._expires)

    def __repr__(self) -> str:
        state = "lost" if self.lost else "held" if self._held else "free"
        return f"Lease({str(self.path)!r}, owner={self.owner!r}, {state})"

    # -- acquire --------------------------------------------------------------------------
    def acquire(self, wait: bool = True, timeout: float | None = None,
                on_wait: Callable[[], None] | None = None) -> bool:
        """Take the lease. If a live lease of another owner exists: return False at once
        (``wait=False``), or call ``on_wait()`` once and poll until it is released or goes
        stale (taken over then), for at most ``timeout`` seconds (None: no limit). True when
        held; the renewal thread then runs until :meth:`release`."""
        if self._held:
            raise LeaseError(f"{self.path}: lease already acquired by this Lease object")
        t_end = None if timeout is None else time.monotonic() + timeout
        waited = False
        first = True
        while True:
            if self._attempt(first):
                self._start_renewing()
                return True
            if not wait or (t_end is not None and time.monotonic() >= t_end):
                return False
            if not waited:
                waited = True
                if on_wait is not None:
                    on_wait()
            first = False
            pause = self.poll_s * random.uniform(0.7, 1.3)
            if t_end is not None:
                pause = max(0.0, min(pause, t_end - time.monotonic()))
            time.sleep(pause)

    def _attempt(self, first: bool = True) -> bool:
        """One try to take the lease: create it, or take over a stale one. A later poll
        (``first=False``) reads before it writes anything: a live lease costs one open."""
        if not first:
            holder = _read_or_corrupt(self.path)
            if holder is not None and not self._stale(holder):
                return False
        for _ in range(20):  # each pass follows a change by another contender
            if self._link_new():
                return True
            holder = _read_or_corrupt(self.path)
            if holder is None:
                continue  # released between our link and our read
            if not self._stale(holder) or not self._take_over():
                return False
        return False

    def _stale(self, holder: dict) -> bool:
        if "corrupt" in holder:  # never written by us (we publish whole files): damaged
            return self.clock() > holder["mtime"] + self.ttl_s + self.grace_s
        return self.clock() > float(holder["expires"]) + self.grace_s

    def _info(self) -> dict[str, Any]:
        now = self.clock()
        return {"owner": self.owner, "host": self.host, "pid": os.getpid(), "token": self.token,
                "ttl": self.ttl_s, "acquired": now, "expires": now + self.ttl_s}

    def _private(self, tag: str) -> Path:
        return self.path.with_name(f"{self.path.name}.{tag}-{self.token}")

    def _create(self, target: Path, info: dict, tag: str) -> bool:
        """Publish ``info`` at ``target`` unless something is there: a private file, then
        ``link``; success when the private file's link count is 2 (NFS-safe)."""
        new = self._private(tag)
        _write_json(new, info)
        try:
            try:
                os.link(new, target)
            except FileExistsError:
                pass
            except OSError as e:
                if e.errno in (errno.EPERM, errno.EOPNOTSUPP, errno.EMLINK):
                    raise LeaseError(f"{target.parent}: can't create hard links here "
                                     f"({e.strerror}); leases need a filesystem with link(2)") from e
                raise
            return os.stat(new).st_nlink == 2
        finally:
            _unlink(new)

    def _link_new(self) -> bool:
        info = self._info()
        if not self._create(self.path, info, "new"):
            return False
        self._held, self._lost, self.lost_to = True, False, None
        self._expires = info["expires"]
        self.acquired_info = info
        self.renewals, self.last_renewal = 0, info["acquired"]
        return True

    def _grab(self, target: Path, tag: str) -> tuple[Path, dict | None] | None:
        """Rename ``target`` to a private name; None if there was nothing."""
        mine = self._private(tag)
        try:
            os.rename(target, mine)
        except FileNotFoundError:
            return None
        return mine, _read_or_corrupt(mine)

    def _put_back(self, mine: Path, target: Path) -> None:
        """Restore a file we grabbed but must not remove (unless a new one appeared since:
        then its owner lost it, and finds out at its next renewal)."""
        try:
            os.link(mine, target)
        except FileExistsError:
            pass
        finally:
            _unlink(mine)

    def _remove_if_stale(self, target: Path, tag: str) -> None:
        grabbed = self._grab(target, tag)
        if grabbed is None:
            return
        mine, holder = grabbed
        if holder is None or self._stale(holder):
            _unlink(mine)
        else:  # renewed between our read and our rename (its owner was late, not dead)
            self._put_back(mine, target)

    def _take_over(self) -> bool:
        """Remove the stale lease, serialised by a short-lived gate file ``<lease>.takeover``
        (created like a lease): one taker at a time re-reads the lease and removes it only
        if it is still stale, so no contender can ever remove a lease another contender has
        just created. False when another taker holds the gate (let it finish)."""
        gate = self.path.with_name(f"{self.path.name}.takeover")
        info = self._info()
        if not self._create(gate, info, "gate-new"):
            holder = _read_or_corrupt(gate)
            if holder is not None and not self._stale(holder):
                return False
            if holder is not None:
                self._remove_if_stale(gate, "gate-stale")  # a taker died mid-takeover
            if not self._create(gate, info, "gate-new"):
                return False
        try:
            holder = _read_or_corrupt(self.path)
            if holder is not None and self._stale(holder):
                self._remove_if_stale(self.path, "stale")
        finally:
            if (_read_or_corrupt(gate) or {}).get("token") == self.token:
                _unlink(gate)
        return True

    # -- renew ----------------------------------------------------------------------------
    def renew(self) -> None:
        """Check that the file still holds our token and extend ``expires`` by ttl.
        Raises :class:`LeaseLost` (and sets :attr:`lost`) when it does not."""
        with self._mutex:
            if not self._held:
                if self._lost:
                    raise LeaseLost(self.path, self.lost_to)
                raise LeaseError(f"{self.path}: renew() of a lease that is not held")
            holder = _read_or_corrupt(self.path)
            if holder is None or holder.get("token") != self.token:
                self._lost, self._held, self.lost_to = True, False, holder
                self._stop.set()
                raise LeaseLost(self.path, holder)
            info = {**self.acquired_info, "expires": self.clock() + self.ttl_s}
            new = self._private("new")
            _write_json(new, info)
            try:
                os.replace(new, self.path)
            except FileNotFoundError:
                # NFS: a retransmitted rename that had worked; check the outcome
                if (read_lease(self.path) or {}).get("expires") != info["expires"]:
                    raise
            self._expires = info["expires"]
            self.renewals += 1
            self.last_renewal = info["expires"] - self.ttl_s

    def _start_renewing(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._renew_loop, args=(self._stop,),
                                        name=f"lease-renew {self.path.name}", daemon=True)
        self._thread.start()

    def _renew_loop(self, stop: threading.Event) -> None:
        while not stop.wait(self.renew_s):
            try:
                self.renew()
            except LeaseLost:
                return
            except LeaseError:
                return  # released meanwhile
            except OSError:
                continue  # transient (NFS); `lost` turns True if our expiry passes

    # -- release --------------------------------------------------------------------------
    def release(self) -> None:
        """Give the lease up: remove the file if it still holds our token (never another
        owner's). A no-op if not held (never acquired, released, or lost)."""
        with self._mutex:
            self._stop.set()
            if not self._held:
                return
            self._held = False
            holder = _read_or_corrupt(self.path)
            if holder is None or holder.get("token") != self.token:
                self._lost, self.lost_to = True, holder  # taken over: leave it alone
            else:
                grabbed = self._grab(self.path, "release")
                if grabbed is not None:
                    mine, holder = grabbed
                    if holder is not None and holder.get("token") == self.token:
                        _unlink(mine)
                    else:  # taken over between our read and our rename
                        self._lost, self.lost_to = True, holder
                        self._put_back(mine, self.path)
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)

    def __enter__(self) -> "Lease":
        if not self.acquire():
            raise LeaseHeld(self.path, _read_or_corrupt(self.path))
        return self

    def __exit__(self, *exc) -> None:
        self.release()
