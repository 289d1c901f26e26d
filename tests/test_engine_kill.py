"""Kills and cleanup: runs killed mid-stage (``kill -9``, SIGTERM, SIGINT), killed compiles,
damaged upstream artifacts. Each asserts what is left afterwards: no process of the killed
run alive, no temporary folder, the next run recomputing what was lost.

Processes are found through ``/proc`` (Linux): every descendant of the killed process,
snapshotted while it runs, must be gone (or a zombie) within ``GONE_S`` seconds."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import toy_registry
import yaml

from pipeline.engine import Engine
from pipeline.store import CorruptArtifactError, Store

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
TOY = str(TESTS / "toy_registry.py")
GONE_S = 10.0
pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")


# -- processes -------------------------------------------------------------------------------
def _stat(pid: int) -> tuple[str, int] | None:
    """(state, ppid) of a process, None if it does not exist."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    state, ppid = text.rsplit(")", 1)[1].split()[:2]
    return state, int(ppid)


def alive(pid: int) -> bool:
    s = _stat(pid)
    return s is not None and s[0] not in ("Z", "X")


def cmdlines(pids) -> dict[int, str]:
    """Each pid's command line (for an assertion's message: which process was not expected)."""
    out = {}
    for p in pids:
        try:
            out[p] = Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode(
                errors="replace")[:300]
        except OSError:
            out[p] = "(gone)"
    return out


def descendants(pid: int) -> list[int]:
    """Every live process under ``pid`` (children, grandchildren, ...)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            s = _stat(int(d.name))
            if s is not None and s[0] not in ("Z", "X"):
                children.setdefault(s[1], []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for k in children.get(todo.pop(), []):
            out.append(k)
            todo.append(k)
    return out


def wait_gone(pids: list[int], timeout: float = GONE_S) -> list[int]:
    """Poll until none of ``pids`` is alive; returns those still alive at the timeout."""
    t_end = time.monotonic() + timeout
    while (left := [p for p in pids if alive(p)]) and time.monotonic() < t_end:
        time.sleep(0.05)
    return left


def wait_until(cond, proc: subprocess.Popen | None, what: str, timeout: float = 20.0) -> None:
    t_end = time.monotonic() + timeout
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"exited ({proc.returncode}) before {what}")
        assert time.monotonic() < t_end, f"no {what} in {timeout} s"
        time.sleep(0.03)


def env(*paths: Path) -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(str(p) for p in (REPO, *paths))}


def kill_leftover(pids: list[int]) -> None:
    for p in pids:  # only the processes this test started, should an assertion fail
        try:
            os.kill(p, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


# -- the toy pipeline in a subprocess -------------------------------------------------------
def cli(folder: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "pipeline", *args, "--recipe", str(folder / "toy.yaml"),
            "--registry", TOY, "--outputs", str(folder / "outputs")]


def counts(folder: Path) -> list[str]:
    p = folder / "counts.txt"
    return p.read_text().splitlines() if p.exists() else []


def start(folder: Path, *args: str) -> subprocess.Popen:
    """The CLI in the background, stderr to ``folder/stderr.txt`` (a pipe would be held open
    by any process that outlives it)."""
    with open(folder / "stderr.txt", "w") as err:
        return subprocess.Popen(cli(folder, *args), env=env(), stdout=subprocess.DEVNULL,
                                stderr=err)


def set_detect(folder: Path, **kw) -> None:
    r = yaml.safe_load((folder / "toy.yaml").read_text())
    r["stages"]["detect"] = kw
    (folder / "toy.yaml").write_text(yaml.safe_dump(r))


def unit_dir(folder: Path, unit: str = "g/x") -> Path:
    return folder / "outputs" / "toy" / unit


def test_kill_9_of_a_stage_with_a_worker_pool_leaves_no_worker_or_tracker(tmp_path):
    toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 30.0, "pool_workers": 2}}, n_seq=1)
    proc = start(tmp_path, "sequence", "g/x")
    wait_until(lambda: "pool detect g/x" in counts(tmp_path), proc, "worker pool")
    kids = descendants(proc.pid)
    try:
        cmds = [Path(f"/proc/{k}/cmdline").read_bytes() for k in kids]
        assert sum(b"spawn_main" in c for c in cmds) == 2, cmds  # the two workers
        assert sum(b"resource_tracker" in c for c in cmds) == 1, cmds
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        assert wait_gone(kids) == []
    finally:
        kill_leftover([proc.pid, *kids])


@pytest.mark.parametrize("sig, code, pool", [(signal.SIGTERM, 143, 2), (signal.SIGINT, 130, 0)])
def test_signal_mid_stage_removes_the_temp_folder_ends_children_and_exits_128_plus_signum(
        tmp_path, sig, code, pool):
    toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 30.0, "pool_workers": pool}}, n_seq=1)
    proc = start(tmp_path, "sequence", "g/x")
    ud = unit_dir(tmp_path)
    wait_until(lambda: list(ud.glob(".tmp-detect-*/partial.json"))
               and (not pool or "pool detect g/x" in counts(tmp_path)), proc, "detect mid-stage")
    kids = descendants(proc.pid)
    try:
        assert len(kids) == (3 if pool else 0), cmdlines(kids)
        t0 = time.monotonic()
        os.kill(proc.pid, sig)
        proc.wait(timeout=20)
        err = (tmp_path / "stderr.txt").read_text()
        assert proc.returncode == code, err
        assert time.monotonic() - t0 < 10  # did not wait for the 30 s tasks
        assert wait_gone(kids) == []
    finally:
        kill_leftover([proc.pid, *kids])
    name = signal.Signals(sig).name
    line = next(ln for ln in err.splitlines() if "interrupted" in ln)
    assert line.split()[1:3] == ["detect", "g/x"] and f"by {name}" in line, err
    assert "Traceback" not in err, err
    assert not list(ud.glob(".tmp-*")) and not (ud / "detect").exists()
    assert "end detect g/x" not in counts(tmp_path)
    # the handlers are the stage's only: the next run computes it, finding the lock free
    set_detect(tmp_path, sleep_s=0.0)
    again = subprocess.run(cli(tmp_path, "sequence", "g/x"), env=env(), capture_output=True,
                           text=True, timeout=60)
    assert again.returncode == 0, again.stderr
    assert "waiting" not in again.stderr
    assert counts(tmp_path).count("end detect g/x") == 1
    assert (ud / "detect" / "manifest.json").exists()


def test_a_killed_force_runs_temp_folder_is_removed_by_the_next_run_although_it_is_a_hit(tmp_path):
    toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 1.0}}, n_seq=1)
    first = subprocess.run(cli(tmp_path, "sequence", "g/x"), env=env(), capture_output=True,
                           text=True, timeout=60)
    assert first.returncode == 0, first.stderr
    ud = unit_dir(tmp_path)
    manifest = (ud / "detect" / "manifest.json").read_text()
    proc = start(tmp_path, "sequence", "g/x", "--force", "detect")
    wait_until(lambda: list(ud.glob(".tmp-detect-*/partial.json")), proc, "forced detect")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    left = list(ud.glob(".tmp-detect-*"))
    assert len(left) == 1
    again = subprocess.run(cli(tmp_path, "sequence", "g/x"), env=env(), capture_output=True,
                           text=True, timeout=60)
    assert again.returncode == 0, again.stderr
    detect_line = next(ln for ln in again.stderr.splitlines() if ln.split()[1:3] == ["detect", "g/x"])
    assert detect_line.split()[3] == "hit", again.stderr
    assert not list(ud.glob(".tmp-*")) and not list(ud.glob(".trash-*"))
    assert left[0].name in again.stderr  # it says what it removed
    assert (ud / "detect" / "manifest.json").read_text() == manifest  # the hit was kept


def test_leftovers_of_a_live_build_are_not_touched(tmp_path):
    """The cleanup takes the artifact's lock without waiting: a folder someone is building in
    (lock held) stays."""
    store = Store(tmp_path / "s")
    tmp = store.begin("g/x", "detect")
    with store.lock("g/x", "detect"):
        other = Store(store.root)  # same process, another open file: flock still conflicts
        assert other.clean_stale_leftovers("g/x", "detect") == []
        assert tmp.dir.exists()
    assert store.clean_stale_leftovers("g/x", "detect") == [tmp.dir]
    assert not tmp.dir.exists()


# -- compiles ----------------------------------------------------------------------------------
FAKE_CC = """#!/bin/sh
# a "compiler" that writes part of its output, starts a child and sleeps; asked what it makes
# of -march=native (preprocessing only, fitting.compiled.native_target) it answers at once
for a in "$@"; do [ "$a" = "-E" ] && exit 0; done
out=""; prev=""
for a in "$@"; do [ "$prev" = "-o" ] && out="$a"; prev="$a"; done
echo partial > "$out"
sleep 60 &
echo "$$ $!" > "{pids}.part" && mv "{pids}.part" "{pids}"
wait
"""

BUILD = """
import sys
from pathlib import Path
import casadi as ca
from fitting import compiled
x = ca.SX.sym("x", 2); p = ca.SX.sym("p", 2)
opts = compiled.CompileOptions(mode="compiled", cache_dir=Path(sys.argv[1]), compiler=sys.argv[2])
compiled.build("killme", x, p, x * p + x[0] ** 2, opts)
"""


def fake_compiler(tmp_path: Path) -> tuple[Path, Path]:
    pids = tmp_path / "cc.pids"
    cc = tmp_path / "fakecc"
    cc.write_text(FAKE_CC.format(pids=pids))
    cc.chmod(0o755)
    return cc, pids


def leftovers(cache: Path) -> list[str]:
    return sorted(p.name for p in cache.iterdir() if p.name.startswith("."))


def test_killed_compile_leaves_no_compiler_and_the_next_build_removes_its_temp_files(tmp_path):
    cache = tmp_path / "cache"
    cc, pids = fake_compiler(tmp_path)
    proc = subprocess.Popen([sys.executable, "-c", BUILD, str(cache), str(cc)], env=env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_until(pids.exists, proc, "the compiler")
    kids = descendants(proc.pid)
    try:
        assert {int(p) for p in pids.read_text().split()} <= set(kids)  # sh and its sleep
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        assert wait_gone(kids) == []
    finally:
        kill_leftover([proc.pid, *kids])
    left = leftovers(cache)
    assert any(n.startswith(f".gen-{proc.pid}-") for n in left), left
    assert any(n.endswith(f".so.{proc.pid}.tmp") for n in left), left

    from fitting import compiled

    if shutil.which("gcc") is None:
        pytest.skip("no C compiler for the next build")
    import casadi as ca

    x, p = ca.SX.sym("x", 2), ca.SX.sym("p", 2)
    logs: list[str] = []
    f = compiled.build("killme", x, p, x * p + x[0] ** 2,
                       compiled.CompileOptions(mode="compiled", cache_dir=cache), log=logs.append)
    assert f.compiled
    assert leftovers(cache) == []
    assert any("removed 2 leftover(s)" in ln for ln in logs), logs
    r, _ = f(np.array([2.0, 3.0]), np.array([5.0, 7.0]))
    assert r.tolist() == [2.0 * 5 + 4, 3.0 * 7 + 4]


def test_leftovers_of_a_running_compile_are_kept(tmp_path):
    from fitting import compiled

    live = tmp_path / f".gen-{os.getppid()}-abc"  # our parent (pytest's runner) is alive
    live.mkdir()
    (tmp_path / f".f_x.so.{os.getppid()}.tmp").write_text("")
    dead = subprocess.Popen(["true"])
    dead.wait()
    (tmp_path / f".gen-{dead.pid}-abc").mkdir()
    (tmp_path / f".f_x.so.{dead.pid}.tmp").write_text("")
    old = tmp_path / ".gen-legacy1"
    old.mkdir()
    os.utime(old, (time.time() - 2 * compiled.STALE_LEGACY_S,) * 2)
    (tmp_path / ".gen-legacy2").mkdir()  # recent: might be a running older build
    gone = compiled.clean_stale(tmp_path)
    assert sorted(p.name for p in gone) == sorted([f".gen-{dead.pid}-abc", f".f_x.so.{dead.pid}.tmp",
                                                    ".gen-legacy1"])
    assert leftovers(tmp_path) == sorted([live.name, f".f_x.so.{os.getppid()}.tmp", ".gen-legacy2"])


class _Stop(BaseException):
    pass


def test_compile_interrupted_by_an_exception_kills_the_compiler_at_once(tmp_path):
    """What the engine's SIGTERM handler does to a compile: the exception raised in the main
    thread kills the compiler's process group and removes the temporary files."""
    import casadi as ca

    from fitting import compiled

    cache = tmp_path / "cache"
    cc, pids = fake_compiler(tmp_path)

    def raise_stop(*_):
        raise _Stop()

    def poke():
        t_end = time.monotonic() + 20
        while not pids.exists() and time.monotonic() < t_end:
            time.sleep(0.03)
        signal.pthread_kill(threading.main_thread().ident, signal.SIGUSR1)

    prev = signal.signal(signal.SIGUSR1, raise_stop)
    t = threading.Thread(target=poke)
    t.start()
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p", 2)
    t0 = time.monotonic()
    try:
        with pytest.raises(_Stop):
            compiled.build("stopme", x, p, x * p, compiled.CompileOptions(
                mode="compiled", cache_dir=cache, compiler=str(cc)))
    finally:
        signal.signal(signal.SIGUSR1, prev)
        t.join()
    assert time.monotonic() - t0 < 15
    cc_pids = [int(q) for q in pids.read_text().split()]
    try:
        assert wait_gone(cc_pids) == []
    finally:
        kill_leftover(cc_pids)
    assert leftovers(cache) == []


# -- damaged artifacts -----------------------------------------------------------------------
class Toy:
    def __init__(self, folder: Path):
        self.recipe = toy_registry.write_toy(folder, n_seq=1)
        self.folder, self.outputs, self.logs = folder, folder / "outputs", []

    def run(self, **fit):
        r = yaml.safe_load(self.recipe.read_text())
        r["stages"]["fit"] = fit
        self.recipe.write_text(yaml.safe_dump(r))
        reg = toy_registry.registry()
        eng = Engine(reg, reg.load_recipe(self.recipe), self.recipe, self.outputs,
                     log=self.logs.append)
        return eng.run(eng.plan("sequence", ["g/x"]))

    def art(self, stage: str) -> Path:
        return self.outputs / "toy" / "g" / "x" / stage


def flip_npy_data_byte(npz: Path) -> None:
    """Change one byte of the first array's data inside an (uncompressed) npz: same size."""
    b = bytearray(npz.read_bytes())
    i = b.index(b"\x93NUMPY")
    data = i + 10 + int.from_bytes(b[i + 8:i + 10], "little")
    b[data] ^= 0xFF
    npz.write_bytes(bytes(b))


@pytest.mark.parametrize("hashed", [True, False])
def test_same_size_corruption_of_an_upstream_npz_is_reported_and_recomputed(tmp_path, hashed):
    """hashed: the manifest has sha256 (found before fit runs); False: an older manifest
    without them (found when fit can't read the file: CorruptArtifactError)."""
    toy = Toy(tmp_path)
    toy.run()
    npz = toy.art("detect") / "detections.npz"
    size = npz.stat().st_size
    m = json.loads((toy.art("detect") / "manifest.json").read_text())
    assert set(m["sha256"]) == set(m["files"]) == {"detections.npz", "partial.json"}
    if not hashed:
        del m["sha256"]
        (toy.art("detect") / "manifest.json").write_text(json.dumps(m))
    flip_npy_data_byte(npz)
    assert npz.stat().st_size == size
    toy.logs.clear()
    rep = toy.run(weight=2.0)  # fit must be rebuilt, from detect
    assert not rep.failed, [o.detail for o in rep.outcomes.values()]
    warn = [ln for ln in toy.logs if ln.startswith("WARNING")]
    assert len(warn) == 1, toy.logs
    assert warn[0].startswith(f"WARNING: {toy.art('detect')}: corrupt artifact (detections.npz: ")
    assert warn[0].endswith("; recomputing detect [g/x]")
    # hashed: found by content before fit starts; else fit fails on it once and is retried
    assert ("content changed (sha256" in warn[0]) == hashed
    assert ("BadZipFile" in warn[0]) == (not hashed)
    assert counts(tmp_path).count("start fit g/x") == (2 if hashed else 3)
    ends = [ln for ln in counts(tmp_path) if ln.startswith("end ")]
    assert ends.count("end detect g/x") == 2 and ends.count("end fit g/x") == 2
    assert ends.count("end scale a") == 1  # the rest was not touched
    fit = np.load(toy.art("fit") / "fit.npz")
    assert fit["total"][0] == pytest.approx(2 * (1 + 2) + (1 + 2 + 3) + (10 + 20))
    assert np.load(npz)["values"].tolist() == [1.0, 2.0]


def test_unreadable_artifact_file_names_stage_unit_and_file(tmp_path):
    toy = Toy(tmp_path)
    toy.run()
    store = Store(toy.outputs / "toy")
    flip_npy_data_byte(toy.art("detect") / "detections.npz")
    (toy.art("detect") / "partial.json").write_text("{nope")
    e = store.entry("g/x", "detect")
    assert e.state == "corrupt"  # the json is shorter now; the npz has the same size
    a = store.open("g/x", "detect", e.manifest)
    with pytest.raises(CorruptArtifactError, match=r"detect \[g/x\]: .*detections\.npz: corrupt "
                       r"artifact file \(BadZipFile"):
        a.arrays("detections")
    with pytest.raises(CorruptArtifactError, match=r"detect \[g/x\]: .*partial\.json"):
        a.json("partial")
    assert "detections.npz: content changed" in store.verify("g/x", "detect", e.manifest)


# -- the real detector pool ------------------------------------------------------------------
class SleepyFactory:
    """A detector factory whose build() records the worker's pid and then sleeps: the pool's
    workers are all busy when the driver is killed."""

    def __init__(self, folder: str):
        self.folder = folder

    def build(self):
        Path(self.folder, f"{os.getpid()}.pid").write_text("")
        time.sleep(60)


DRIVER = """
import sys
import numpy as np
from detect.hints import WearerHints
from detect.run import ArraySource, detect_sequence
from test_engine_kill import SleepyFactory
C, F = 1, 4
nan = lambda *s: np.full((C, F, *s), np.nan)
hints = WearerHints(nan(4), nan(2, 4), nan(2, 2), nan(65, 2), nan(3, 2))
src = ArraySource(np.zeros((C, F, 8, 8, 3), np.uint8), tuple(range(F)))
detect_sequence(src, SleepyFactory(sys.argv[1]), hints, np.arange(F), workers=2, chunk=2)
"""


def test_kill_9_of_detect_sequence_kills_its_pool_workers(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(DRIVER), str(tmp_path)],
                            env=env(TESTS), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_until(lambda: len(list(tmp_path.glob("*.pid"))) == 2, proc, "two busy workers", 60)
    kids = descendants(proc.pid)
    try:
        workers = {int(p.stem) for p in tmp_path.glob("*.pid")}
        assert workers <= set(kids) and len(kids) == 3, cmdlines(kids)  # + the resource tracker
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        assert wait_gone(kids) == []
    finally:
        kill_leftover([proc.pid, *kids])
