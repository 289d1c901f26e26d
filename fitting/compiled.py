"""One CasADi function ``f(x, p) -> (residuals, Jacobian nonzeros)``, compiled to C once and cached.

The LM loop (``fitting/lm.py``) calls this function a few times per frame, so its evaluation
cost is the fitting speed. What DESIGN.md measured and this module follows:

- The Jacobian is emitted sparse and read through the function's buffer interface into a
  preallocated nonzero vector; the caller scatters it with the sparsity triplets. Never
  ``DM.full()`` (13 ms on a 1,738 x 159 Jacobian, more than the whole solve).
- Observations, masks and model arrays are *parameters* ``p``: the symbolic graph depends only
  on the model topology and the term set, so one compiled library serves every frame,
  sequence and subject.
- Compiled with ``gcc -O2 -march=native``. Measured on the real-capture marker graph (39
  markers, 117 residuals x 69 unknowns, 4.7 MB of C; one evaluation, best of 5 x 2,000, a
  noisy 2-core VM): ``-O1`` 0.14-0.23 ms, 27 s to compile; ``-O2`` / ``-O3`` 0.18-0.23 /
  0.14-0.18 ms, 47 / 54 s; ``-O1 -march=native`` 0.07-0.09 ms, 21 s; ``-O2 -march=native``
  0.044-0.051 ms, 28 s (results within 1e-15 of ``-O1``'s: contracted multiply-adds).
  A library built for one CPU may not run on another (a cluster's older node would die of an
  illegal instruction), so the host's resolved target (:func:`native_target`: what the
  compiler turns ``-march=native`` into) is part of every key; a compiler that rejects
  ``-march=native`` compiles without it. The library is cached on disk under ``assets/cache/casadi/`` keyed by a hash of the
  generated C source, the compiler and its flags, like any artifact (write to a temporary
  file, then ``os.replace``). Beside each library a small ``<name>_<key>.fn`` index names it
  under a hash of the CasADi function serialized (:func:`function_key`): a later build of the
  same function loads the library without generating its C first (~0.6 s of the marker
  graph's ~0.9 s set-up). No compiler: the interpreted function is used instead (same
  results, ~2x slower).
- The compiler dies with us: it runs under a small guard process that leads a new process
  group and reads a pipe only we hold; when we die (even by ``kill -9``) the pipe closes and
  the guard kills the whole group (gcc, cc1, as, ld). An exception while waiting (SIGTERM
  turned into an exception by the engine, Ctrl-C) kills the group at once. A killed build's
  leftovers in the cache folder, ``.gen-<pid>-*`` work folders and ``.<lib>.so.<pid>.tmp``
  outputs of a process that is gone, are removed by the next build (:func:`clean_stale`).

Shapes: ``x (n,) float64``, ``p (q,) float64``, residuals ``r (m,)``, Jacobian nonzeros
``(nnz,)`` in CasADi's column-major order with triplets ``rows (nnz,)``, ``cols (nnz,)``.
"""
from __future__ import annotations

import functools
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import casadi as ca
import numpy as np

from pipeline.procs import pid_alive

# constants
DEFAULT_CACHE = Path(__file__).resolve().parents[1] / "assets" / "cache" / "casadi"
CACHE_ENV = "CASADI_CACHE_DIR"  # overrides the cache folder when set
KEY_CHARS = 20
NATIVE = "-march=native"  # tune for the host CPU (the resolved target joins the cache key)
GEN_PREFIX = ".gen-"     # work folders: .gen-<pid>-<random>
STALE_LEGACY_S = 3600.0  # a .gen-* folder without a pid (older code) is stale after this long

# Run as ``python -c _GUARD compiler args...`` in a new session (process group): starts the
# compiler in the group, and kills the group when stdin (a pipe only our process holds)
# reaches EOF, i.e. when we die; exits with the compiler's return code otherwise.
_GUARD = """
import os, signal, subprocess, sys, threading
child = subprocess.Popen(sys.argv[1:], stdin=subprocess.DEVNULL)
def watch():
    while os.read(0, 65536):
        pass
    os.killpg(0, signal.SIGKILL)
threading.Thread(target=watch, daemon=True).start()
code = child.wait()
os._exit(code if code >= 0 else 128 - code)
"""


@dataclass(frozen=True)
class CompileOptions:
    """How to turn a CasADi function into something fast.

    mode : ``auto`` compiles when a C compiler is found, else interprets; ``compiled`` raises
        when compiling is impossible; ``interpreted`` never compiles.
    cache_dir : where compiled libraries live; None: ``$CASADI_CACHE_DIR`` or
        ``assets/cache/casadi``.
    compiler, flags : the C compiler command and its optimisation flags (``-march=native``
        is dropped for a compiler that rejects it, and keys the library by the host's CPU).
    max_source_mb : in ``auto`` mode, generated C larger than this runs interpreted unless
        already compiled and cached (measured with ``-O1``: the 52-joint graph with 42 hand
        keypoints in 4 views is 14 MB of C, 250 s to compile, and only 1.6x faster than
        interpreted; the 22-joint marker graph is 1.4 MB, 10-15 s, and 2-3x faster).
    """

    mode: Literal["auto", "compiled", "interpreted"] = "auto"
    cache_dir: Path | None = None
    compiler: str = "gcc"
    flags: tuple[str, ...] = ("-O2", NATIVE)
    max_source_mb: float = 6.0


def cache_dir(opts: CompileOptions) -> Path:
    """The folder holding compiled libraries for these options."""
    if opts.cache_dir is not None:
        return Path(opts.cache_dir)
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else DEFAULT_CACHE


class ResidualFunction:
    """Evaluate ``f(x, p) -> (r, jnz)`` with minimal overhead.

    Attributes
    ----------
    name : str
    n_x, n_p, n_r : sizes of x, p and r.
    rows, cols : (nnz,) int64, the Jacobian sparsity triplets (nonzero order).
    compiled : bool, True when running generated C.
    library : Path | None, the shared library in use.

    ``__call__`` returns views of internal buffers that the next call overwrites: copy what
    you keep. The Jacobian ``J (n_r, n_x)`` is ``J[rows[k], cols[k]] = jnz[k]``.
    """

    def __init__(self, func: ca.Function, rows, cols, compiled: bool, library: Path | None):
        self.func = func
        self.name = func.name()
        self.n_x = func.size1_in(0)
        self.n_p = func.size1_in(1)
        self.n_r = func.size1_out(0)
        self.rows = np.asarray(rows, dtype=np.int64)
        self.cols = np.asarray(cols, dtype=np.int64)
        self.compiled = compiled
        self.library = library
        self._x = np.zeros(self.n_x)
        self._p = np.zeros(self.n_p)
        self._r = np.zeros(self.n_r)
        self._j = np.zeros(len(self.rows))
        self._flat = self.rows * self.n_x + self.cols
        buf, self._eval = func.buffer()
        buf.set_arg(0, memoryview(self._x))
        buf.set_arg(1, memoryview(self._p))
        buf.set_res(0, memoryview(self._r))
        buf.set_res(1, memoryview(self._j))
        self._buf = buf  # keeps the buffer (and our arrays' views) alive

    @property
    def nnz(self) -> int:
        return len(self.rows)

    def __call__(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x (n_x,), p (n_p,) -> (r (n_r,), jnz (nnz,)), views into internal buffers."""
        self._x[:] = x
        self._p[:] = p
        self._eval()
        return self._r, self._j

    def dense(self, x: np.ndarray, p: np.ndarray, out: np.ndarray | None = None):
        """x, p -> (r (n_r,) copy, J (n_r, n_x) dense); ``out`` is reused when given."""
        r, jnz = self(x, p)
        if out is None:
            out = np.zeros((self.n_r, self.n_x))
        else:
            out[...] = 0.0
        out.ravel()[self._flat] = jnz
        return r.copy(), out


def find_compiler(opts: CompileOptions) -> str | None:
    """Path of the C compiler, or None."""
    return shutil.which(opts.compiler)


_TARGET_TOKEN = re.compile(r"-march=\S+|-mtune=\S+|-m[a-z0-9][a-z0-9.-]*|--param=l[12]-\S+"
                           r"|-target-(?:cpu|feature) \S+")


@functools.lru_cache(maxsize=8)
def native_target(compiler: str) -> str | None:
    """What ``compiler`` makes of ``-march=native`` on this host: its CPU and feature options
    as it passes them to its back end (the ``cc1`` line of ``-v``; gcc: ``-march=icelake-client
    -mavx512f ...``; clang: ``-target-cpu ... -target-feature ...``), paths left out. None when the compiler rejects
    ``-march=native`` (or cannot be run). Asked once per process and compiler, under
    :func:`run_guarded` like a compile (killed with us, or at once on an exception): a Python
    guard's start-up and the compiler's, ~0.1 s."""
    with tempfile.TemporaryFile() as out:  # guarded as a compile is: it dies with us
        code = run_guarded([compiler, NATIVE, "-E", "-v", "-x", "c", os.devnull, "-o",
                            os.devnull], out)
        out.seek(0)
        text = out.read().decode(errors="replace")
    if code != 0:
        return None
    back_end = [ln for ln in text.splitlines() if re.search(r"(^|[/\s-])cc1(\s|$)", ln)]
    found = [t for ln in back_end for t in _TARGET_TOKEN.findall(ln)]
    return " ".join(found) if found else None


def effective_flags(compiler: str, flags: tuple[str, ...]) -> tuple[tuple[str, ...], str]:
    """(the flags to compile with, the text that keys the library): ``NATIVE`` is kept when
    the compiler accepts it, and then the host's resolved target joins the key, so a cache
    shared between machines never hands a library to a CPU it was not built for."""
    if NATIVE not in flags:
        return tuple(flags), " ".join(flags)
    target = native_target(compiler)
    if target is None:
        plain = tuple(f for f in flags if f != NATIVE)
        return plain, " ".join(plain)
    return tuple(flags), " ".join(flags) + " [" + target + "]"


def _generate_source(func: ca.Function, workdir: Path) -> str:
    cg = ca.CodeGenerator(f"{func.name()}.c", {"with_header": False, "casadi_real": "double"})
    cg.add(func)
    cg.generate(str(workdir) + os.sep)
    return (workdir / f"{func.name()}.c").read_text()


def run_guarded(cmd: list[str], out) -> int:
    """Run ``cmd`` (stdout and stderr to the open file ``out``) so that it and everything it
    starts die with this process (see the module docstring); on any exception while waiting
    (KeyboardInterrupt, SystemExit from a signal handler) kill them first. Returns the exit
    code."""
    proc = subprocess.Popen([sys.executable, "-c", _GUARD, *cmd], stdin=subprocess.PIPE,
                            stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        return proc.wait()
    except BaseException:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        proc.wait()
        raise
    finally:
        proc.stdin.close()


def _compile(src_path: Path, lib_path: Path, compiler: str, flags: tuple[str, ...]) -> None:
    tmp = lib_path.with_name(f".{lib_path.name}.{os.getpid()}.tmp")
    cmd = [compiler, *flags, "-shared", "-fPIC", "-o", str(tmp), str(src_path), "-lm"]
    log_path = src_path.with_name(f"{src_path.stem}.compiler.log")
    try:
        with open(log_path, "wb") as out:
            code = run_guarded(cmd, out)
        if code != 0:
            raise RuntimeError(f"compiling {src_path.name} failed: "
                               f"{log_path.read_text(errors='replace')[-2000:]}")
        os.replace(tmp, lib_path)
    finally:
        tmp.unlink(missing_ok=True)


def _pid_of(text: str) -> int | None:
    return int(text) if text.isdigit() else None


def clean_stale(folder: Path) -> list[Path]:
    """Remove what killed builds left in the cache ``folder``: ``.gen-<pid>-*`` work folders
    and ``.<lib>.so.<pid>.tmp`` files whose process no longer runs on this host (and
    ``.gen-*`` folders without a pid older than ``STALE_LEGACY_S``). Returns what went."""
    gone = []
    try:
        entries = list(Path(folder).iterdir())
    except FileNotFoundError:
        return gone
    now = time.time()
    for p in entries:
        name = p.name
        if name.startswith(GEN_PREFIX):
            head, sep, _ = name[len(GEN_PREFIX):].partition("-")
            pid = _pid_of(head) if sep else None
        elif name.startswith(".") and name.endswith(".tmp") and (".so." in name
                                                                 or ".fn." in name):
            pid = _pid_of(name[:-len(".tmp")].rsplit(".", 1)[-1])
            if pid is None:
                continue
        else:
            continue
        try:
            if pid is None:
                stale = now - p.stat().st_mtime > STALE_LEGACY_S
            else:
                stale = pid != os.getpid() and not pid_alive(pid)
            if not stale:
                continue
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink()
        except FileNotFoundError:  # another process cleaned it first
            continue
        gone.append(p)
    return gone


def library_key(source: str, compiler: str, flags: tuple[str, ...] | str) -> str:
    """Cache key of a compiled library: hash of the C source, compiler name, flags (or the key
    text of :func:`effective_flags`), CasADi."""
    h = hashlib.sha256()
    for part in (source, Path(compiler).name, _flag_text(flags), ca.__version__):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:KEY_CHARS]


def _flag_text(flags: tuple[str, ...] | str) -> str:
    return flags if isinstance(flags, str) else " ".join(flags)


def function_key(func: ca.Function, compiler: str, flags: tuple[str, ...] | str) -> str | None:
    """Key of a function's compiled library *before* generating its C: a hash of the function
    serialized (CasADi's exact description of the graph, ~0.2-0.3 s for the marker graph, where
    generating the C source takes ~0.6 s), its name, the compiler, the flags and CasADi's
    version. None when the function cannot be serialized (then only the source is the key)."""
    try:
        ser = func.serialize()
    except RuntimeError:
        return None
    h = hashlib.sha256()
    for part in (ser, func.name(), Path(compiler).name, _flag_text(flags), ca.__version__):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:KEY_CHARS]


def _index_path(folder: Path, name: str, fkey: str | None) -> Path:
    return folder / f"{name}_{fkey}.fn"


def _indexed_library(folder: Path, name: str, fkey: str | None) -> Path | None:
    """The library a previous build of the same function (``function_key``) compiled or
    loaded, when its index file and the library are both there; else None."""
    if fkey is None:
        return None
    try:
        lib = folder / _index_path(folder, name, fkey).read_text().strip()
    except (FileNotFoundError, UnicodeDecodeError):
        return None
    ok = lib.name.startswith(f"{name}_") and lib.suffix == ".so" and lib.parent == folder
    return lib if ok and lib.exists() else None


def _write_index(folder: Path, name: str, fkey: str | None, lib: Path) -> None:
    """Remember that the function ``fkey`` compiles to ``lib`` (written to a temporary file,
    then ``os.replace``: a reader sees the old index or the new one)."""
    if fkey is None:
        return
    path = _index_path(folder, name, fkey)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(lib.name)
        os.replace(tmp, path)
    except OSError:  # a read-only cache: the next build generates the source again
        tmp.unlink(missing_ok=True)


def build(
    name: str,
    x: ca.SX,
    p: ca.SX,
    r: ca.SX,
    opts: CompileOptions = CompileOptions(),
    log=None,
) -> ResidualFunction:
    """Make ``f(x, p) -> (r, dr/dx)`` and compile it (or load it from the cache).

    name : a C identifier (letters, digits, underscore).
    x : (n, 1) SX, the unknowns; p : (q, 1) SX, everything else (observations, masks, model).
    r : (m, 1) SX, the residual vector as a function of x and p.
    log : optional ``log(str)`` for "compiling ..." messages.
    """
    if not name.isidentifier():
        raise ValueError(f"function name {name!r} is not a C identifier")
    jac = ca.jacobian(r, x)
    rows, cols = jac.sparsity().get_triplet()
    func = ca.Function(name, [x, p], [r, jac], ["x", "p"], ["r", "jnz"])
    if opts.mode == "interpreted":
        return ResidualFunction(func, rows, cols, compiled=False, library=None)
    compiler = find_compiler(opts)
    if compiler is None:
        if opts.mode == "compiled":
            raise RuntimeError(f"no C compiler {opts.compiler!r} found to compile {name}")
        if log:
            log(f"{name}: no C compiler, using the interpreted function")
        return ResidualFunction(func, rows, cols, compiled=False, library=None)
    folder = cache_dir(opts)
    folder.mkdir(parents=True, exist_ok=True)
    gone = clean_stale(folder)
    if gone and log:
        log(f"{name}: removed {len(gone)} leftover(s) of killed builds from {folder}")
    flags, flag_key = effective_flags(compiler, opts.flags)
    fkey = function_key(func, compiler, flag_key)
    known = _indexed_library(folder, name, fkey)
    if known is not None:
        try:
            return ResidualFunction(ca.external(name, str(known)), rows, cols, compiled=True,
                                    library=known)
        except RuntimeError:  # a corrupt library: the full path below checks and rebuilds it
            pass
    with tempfile.TemporaryDirectory(dir=folder, prefix=f"{GEN_PREFIX}{os.getpid()}-") as tmpd:
        work = Path(tmpd)
        source = _generate_source(func, work)
        key = library_key(source, compiler, flag_key)
        lib = folder / f"{name}_{key}.so"
        too_big = len(source) > opts.max_source_mb * 1e6
        if not lib.exists() and opts.mode == "auto" and too_big:
            if log:
                log(f"{name}: {len(source) / 1e6:.1f} MB of C would take minutes to compile; "
                    f"running it interpreted (mode='compiled' forces compiling)")
            return ResidualFunction(func, rows, cols, compiled=False, library=None)
        if not lib.exists():
            if log:
                log(f"{name}: compiling {len(source) // 1024} kB of C with {opts.compiler} "
                    f"{' '.join(flags)} (once; cached in {folder})")
            _compile(work / f"{name}.c", lib, compiler, flags)
    try:
        ext = ca.external(name, str(lib))
    except RuntimeError:  # a corrupt cache entry: delete and rebuild once
        lib.unlink(missing_ok=True)
        _index_path(folder, name, fkey).unlink(missing_ok=True)
        return build(name, x, p, r, opts, log)
    _write_index(folder, name, fkey, lib)
    return ResidualFunction(ext, rows, cols, compiled=True, library=lib)
