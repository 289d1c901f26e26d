"""Child processes that die with their parent, for stages that start worker pools.

A worker blocked on its task queue does not notice its parent die: the queue's pipe stays
open (the workers hold both of its ends), so after ``kill -9`` of a stage its workers and the
multiprocessing resource tracker (which exits only when every holder of its pipe is gone)
would live on. Two pieces fix that:

- :func:`die_with_parent`, called in the child: on Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)``
  (the kernel kills the child when the thread that started it ends), plus everywhere a
  daemon watchdog thread polling ``os.getppid()`` every ``WATCHDOG_POLL_S`` (a child is
  re-parented when its parent dies). If the parent is already gone when it is called, the
  child kills itself at once.
- :func:`process_pool`: a ``concurrent.futures.ProcessPoolExecutor`` whose workers run
  :func:`die_with_parent` before the caller's initializer, and which, when the ``with``
  block is left by an exception (a failed task, or SIGTERM/SIGINT turned into an exception by
  the engine), kills its workers instead of waiting for the running tasks to finish. Once the
  workers are gone the resource tracker sees the end of its pipe and exits too.

The start method is ``spawn`` (forking a process with threads is unsafe), so the pool's
initializer and tasks must be importable module-level callables. Workers are started by the
thread that calls ``submit``; the death signal follows that thread, so keep a pool in the
thread that created it (the ``with`` block) and let that thread outlive the pool.

Signals: :func:`signals_raise` (used by the engine around a stage) turns SIGTERM and SIGINT
into :class:`Interrupted` raised in the main thread, a ``SystemExit`` whose code is
``128 + signum`` (143, 130): ``except Exception`` in a stage does not swallow it, every
``finally``/``with`` on the way out runs (temporary folder, pools, locks), and the process
exits with that code without a traceback.
"""
from __future__ import annotations

import concurrent.futures as cf
import ctypes
import ctypes.util
import functools
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator

# constants
WATCHDOG_POLL_S = 0.5     # how often the fallback watchdog looks at os.getppid()
PR_SET_PDEATHSIG = 1      # <linux/prctl.h>
END_TIMEOUT_S = 5.0       # how long end_pool waits for a killed worker to be reaped


def set_parent_death_signal(sig: int = signal.SIGKILL) -> bool:
    """Linux: ask the kernel to send ``sig`` to this process when its parent (the thread that
    started it) ends. Returns False where that is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int, poll_s: float) -> None:
    while True:
        time.sleep(poll_s)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGKILL)


def die_with_parent(parent_pid: int | None = None, poll_s: float = WATCHDOG_POLL_S) -> None:
    """Make this (child) process die by SIGKILL when its parent dies.

    parent_pid : the pid the parent had when it started us (default: ``os.getppid()`` now).
        Passing it closes the race of a parent that died before this call: we die at once.
    """
    parent_pid = os.getppid() if parent_pid is None else int(parent_pid)
    set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before the death signal was armed
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch_parent, args=(parent_pid, poll_s), daemon=True,
                     name="die-with-parent").start()


def worker_init(parent_pid: int, then: Callable[..., Any] | None = None, *args: Any) -> None:
    """Pool initializer: :func:`die_with_parent` (``parent_pid``), then ``then(*args)``."""
    die_with_parent(parent_pid)
    if then is not None:
        then(*args)


def end_pool(pool: cf.ProcessPoolExecutor, timeout: float = END_TIMEOUT_S) -> None:
    """Kill the workers of ``pool`` now (running tasks are lost, pending ones cancelled) and
    reap them, so neither they nor the pool's threads outlive the call."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        try:
            p.kill()
        except (OSError, ValueError, AttributeError):
            pass
    for p in procs:
        try:
            p.join(timeout)
        except (OSError, ValueError, AssertionError):
            pass
    pool.shutdown(wait=True)  # the manager thread sees the dead workers and ends


@contextmanager
def process_pool(max_workers: int, initializer: Callable[..., Any] | None = None,
                 initargs: tuple = (), start_method: str = "spawn"
                 ) -> Iterator[cf.ProcessPoolExecutor]:
    """``with process_pool(n, initializer=f) as pool:`` a ProcessPoolExecutor of ``n`` workers
    that die with this process. Leaving the block normally waits for the tasks like the
    plain executor; leaving it by an exception (``BaseException``: also SystemExit and
    KeyboardInterrupt) kills the workers first (:func:`end_pool`)."""
    init = functools.partial(worker_init, os.getpid(), initializer, *initargs)
    pool = cf.ProcessPoolExecutor(max_workers=max_workers, mp_context=mp.get_context(start_method),
                                  initializer=init)
    try:
        yield pool
    except BaseException:
        end_pool(pool)
        raise
    pool.shutdown(wait=True)


def end_children(timeout: float = END_TIMEOUT_S) -> list[int]:
    """Kill the ``multiprocessing`` children of this process still alive (a safety net after
    an interrupted stage); returns their pids."""
    kids = mp.active_children()
    for p in kids:
        p.kill()
    for p in kids:
        p.join(timeout)
    return [p.pid for p in kids]


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (zombies count as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Interrupted(SystemExit):
    """SIGTERM or SIGINT arrived while a stage was running. ``code`` = 128 + ``signum``."""

    def __init__(self, signum: int):
        super().__init__(128 + int(signum))
        self.signum = int(signum)

    @property
    def signal_name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"


@contextmanager
def signals_raise(signums: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[None]:
    """Inside the block, the signals ``signums`` raise :class:`Interrupted` in the main thread;
    the previous handlers are restored on the way out. Outside the main thread (where Python
    can't set handlers) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        raise Interrupted(signum)

    previous = {}
    try:
        for s in signums:
            previous[s] = signal.signal(s, handler)
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)
