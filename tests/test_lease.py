"""Leases (``pipeline/lease.py``) and the store's ``locks="lease"`` backend, with separate
Python processes that share no lock table (the lease never uses ``flock``): a live owner
keeps it, a killed owner's lease is taken over after expiry + grace and not before, a paused
owner finds it lost, contenders for a stale lease get exactly one winner, a lost lease makes
the store's commit refuse, and the engine builds and reuses artifacts as with flock."""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import toy_registry

from pipeline.engine import Engine
from pipeline.lease import Lease, LeaseLost, default_grace, read_lease
from pipeline.store import Store, StoreError
from tests.test_engine_cli import cli, counts, wait_for_line

REPO = Path(__file__).resolve().parents[1]
TTL = 1.0
GRACE = default_grace(TTL)

# A lease in its own interpreter, driven by one JSON command per stdin line.
CHILD = r"""
import json, os, sys, time
from pathlib import Path
from pipeline.lease import Lease
args = json.loads(sys.argv[1])
skew = args.pop("skew", 0.0)
lease = Lease(Path(args.pop("path")), clock=lambda: time.time() + skew, **args)
def say(**kw):
    print(json.dumps(kw), flush=True)
say(pid=os.getpid())
for line in sys.stdin:
    cmd = json.loads(line)
    op = cmd["op"]
    if op == "acquire":
        while time.time() < cmd.get("at", 0.0):  # contenders start together
            pass
        ok = lease.acquire(wait=cmd.get("wait", True), timeout=cmd.get("timeout"))
        say(ok=ok, t=time.time(), token=lease.token)
    elif op == "release":
        lease.release()
        say(ok=True)
    elif op == "state":
        say(held=lease.held, lost=lease.lost, renewals=lease.renewals,
            last_renewal=lease.last_renewal, token=lease.token)
"""


class Child:
    """One process holding a :class:`Lease` on ``path``."""

    def __init__(self, path: Path, **kw):
        self.proc = subprocess.Popen(
            [sys.executable, "-c", CHILD, json.dumps({"path": str(path), **kw})],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": str(REPO)})
        self.pid = self.reply(20.0)["pid"]

    def send(self, op: str, **kw) -> None:
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()

    def reply(self, timeout: float = 20.0) -> dict:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        assert ready, f"no reply from lease process {self.proc.pid} in {timeout} s"
        line = self.proc.stdout.readline()
        assert line, f"lease process {self.proc.pid} exited ({self.proc.poll()})"
        return json.loads(line)

    def call(self, op: str, reply_s: float = 20.0, **kw) -> dict:
        self.send(op, **kw)
        return self.reply(reply_s)

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=10)


@pytest.fixture
def children():
    made: list[Child] = []

    def make(path: Path, **kw) -> Child:
        made.append(Child(path, **kw))
        return made[-1]

    yield make
    for c in made:  # only the processes this test started
        if c.proc.poll() is None:
            try:
                os.kill(c.proc.pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        c.kill()


def lease_dir_names(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir())


# -- the lease between processes ------------------------------------------------------------
@pytest.mark.parametrize("b", [{}, {"skew": 0.8 * GRACE}, {"ttl_s": 0.5}],
                         ids=["same-clock", "b-clock-ahead-within-grace", "b-short-ttl"])
def test_a_renewing_holder_keeps_the_lease_from_another_process_for_over_two_ttl(tmp_path, children, b):
    path = tmp_path / "unit.lease"
    a = children(path, ttl_s=TTL, owner="A")
    b = children(path, owner="B", **b)
    assert a.call("acquire", wait=False)["ok"]
    t0 = time.time()
    got = b.call("acquire", wait=True, timeout=2.5 * TTL)
    assert got["ok"] is False and got["t"] - t0 >= 2.5 * TTL - 0.05
    st = a.call("state")
    assert st["held"] and not st["lost"] and st["renewals"] >= 5
    assert read_lease(path)["owner"] == "A"
    a.call("release")
    assert not path.exists()
    assert b.call("acquire", wait=False)["ok"]  # free again


def test_a_killed_holders_lease_is_taken_over_after_expiry_plus_grace_and_not_before(tmp_path, children):
    path = tmp_path / "unit.lease"
    a = children(path, ttl_s=TTL, owner="A")
    b = children(path, ttl_s=TTL, owner="B")
    assert a.call("acquire", wait=False)["ok"]
    b.send("acquire", wait=True, timeout=15.0)
    time.sleep(0.6 * TTL)  # A renews meanwhile
    a.kill()
    last = read_lease(path)  # what the dead owner last wrote
    last_renewal = last["expires"] - last["ttl"]
    got = b.reply(15.0)
    assert got["ok"]
    waited = got["t"] - last_renewal
    assert waited >= TTL + GRACE, waited  # not before expiry + grace
    assert waited < TTL + GRACE + 1.0, waited  # and soon after
    now = read_lease(path)
    assert now["owner"] == "B" and now["token"] == got["token"]
    assert lease_dir_names(path) == ["unit.lease"]  # no private files left behind


def test_a_paused_owner_finds_its_lease_lost_and_its_release_leaves_the_new_holders(tmp_path, children):
    path = tmp_path / "unit.lease"
    a = children(path, ttl_s=TTL, owner="A")
    b = children(path, ttl_s=TTL, owner="B")
    assert a.call("acquire", wait=False)["ok"]
    os.kill(a.pid, signal.SIGSTOP)  # a GC pause, a suspended VM, an NFS hang...
    try:
        got = b.call("acquire", wait=True, timeout=10.0)
    finally:
        os.kill(a.pid, signal.SIGCONT)
    assert got["ok"]
    time.sleep(TTL / 3 + 0.2)  # A's renewal thread runs again
    st = a.call("state")
    assert st["lost"] and not st["held"]
    a.call("release")  # a non-owner's release
    assert read_lease(path)["token"] == got["token"]
    assert b.call("state")["held"]


def test_a_clock_ahead_by_more_than_ttl_plus_grace_breaks_a_live_lease_and_the_owner_notices(
        tmp_path, children):
    """The clock-skew assumption made visible: a host whose clock runs ttl + grace ahead
    sees every lease as stale. The owner finds out at its next renewal."""
    path = tmp_path / "unit.lease"
    a = children(path, ttl_s=TTL, owner="A")
    b = children(path, ttl_s=TTL, owner="B", skew=TTL + GRACE + 0.5)
    assert a.call("acquire", wait=False)["ok"]
    assert b.call("acquire", wait=False)["ok"]
    time.sleep(TTL / 3 + 0.2)
    assert a.call("state")["lost"]
    a.call("release")
    assert read_lease(path)["owner"] == "B"


def test_two_processes_contending_for_a_stale_lease_have_exactly_one_winner(tmp_path, children):
    path = tmp_path / "unit.lease"
    procs = [children(path, ttl_s=TTL, owner=n) for n in ("B", "C")]
    for rnd in range(6):
        path.write_text(json.dumps({"owner": "dead", "token": f"dead{rnd}", "ttl": TTL,
                                    "acquired": time.time() - 100, "expires": time.time() - 99}))
        at = time.time() + 0.15
        for p in procs:
            p.send("acquire", wait=False, at=at)
        got = [p.reply() for p in procs]
        winners = [p for p, g in zip(procs, got, strict=True) if g["ok"]]
        assert len(winners) == 1, (rnd, got)
        assert read_lease(path)["token"] == got[procs.index(winners[0])]["token"]
        winners[0].call("release")
        assert lease_dir_names(path) == []


def test_threads_contending_for_a_stale_lease_have_exactly_one_winner(tmp_path):
    path = tmp_path / "unit.lease"
    for rnd in range(40):
        path.write_text(json.dumps({"owner": "dead", "token": f"dead{rnd}", "ttl": TTL,
                                    "acquired": 0.0, "expires": 1.0}))
        leases = [Lease(path, ttl_s=TTL) for _ in range(6)]
        barrier = threading.Barrier(len(leases))
        won = [False] * len(leases)

        def go(i: int, leases=leases, barrier=barrier, won=won) -> None:
            barrier.wait()
            won[i] = leases[i].acquire(wait=False)

        threads = [threading.Thread(target=go, args=(i,)) for i in range(len(leases))]
        [t.start() for t in threads]
        [t.join() for t in threads]
        assert sum(won) == 1, (rnd, won)
        winner = leases[won.index(True)]
        assert read_lease(path)["token"] == winner.token
        winner.release()
        assert lease_dir_names(path) == []


def test_release_by_a_non_owner_does_not_remove_the_lease(tmp_path):
    path = tmp_path / "unit.lease"
    with Lease(path, ttl_s=TTL) as a:
        other = Lease(path, ttl_s=TTL)
        assert other.acquire(wait=False) is False
        other.release()
        Lease(path, ttl_s=TTL).release()
        assert read_lease(path)["token"] == a.token and a.held
    assert not path.exists()


def test_an_unreadable_lease_file_blocks_until_ttl_plus_grace_after_its_mtime(tmp_path):
    path = tmp_path / "unit.lease"
    path.write_text("{not json")
    assert Lease(path, ttl_s=TTL).acquire(wait=False) is False
    assert path.read_text() == "{not json"
    old = time.time() - TTL - GRACE - 1
    os.utime(path, (old, old))
    lease = Lease(path, ttl_s=TTL)
    assert lease.acquire(wait=False)
    assert read_lease(path)["token"] == lease.token
    lease.release()


# -- the store's lease backend --------------------------------------------------------------
def test_a_lease_lost_while_building_makes_commit_refuse_and_removes_the_temp_folder(tmp_path, children):
    store = Store(tmp_path / "s", locks="lease", lease_ttl_s=TTL)
    with store.lock("g/x", "detect"):
        w = store.begin("g/x", "detect")
        w.save_json("report", {"v": 1})
        store.commit(w, "g/x", "detect", {"key": "k1"})
    before = (store.dir("g/x", "detect") / "manifest.json").read_text()
    # a host whose clock is far ahead takes the lease over while we build
    thief = children(store.lease_path("g/x", "detect"), ttl_s=TTL, owner="thief", skew=30.0)
    with store.lock("g/x", "detect"):
        w = store.begin("g/x", "detect")
        w.save_json("report", {"v": 2})
        assert thief.call("acquire", wait=False)["ok"]
        with pytest.raises(LeaseLost, match=r"detect \[g/x\] lost while building.*thief"):
            store.commit(w, "g/x", "detect", {"key": "k2"})
        assert not w.dir.exists()
    # the older artifact stands untouched, nothing half-written, the thief's lease too
    assert (store.dir("g/x", "detect") / "manifest.json").read_text() == before
    assert store.entry("g/x", "detect").state == "complete"
    unit = store.dir("g/x", "detect").parent
    assert not list(unit.glob(".tmp-*")) and not list(unit.glob(".trash-*"))
    assert read_lease(store.lease_path("g/x", "detect"))["owner"] == "thief"


def test_cleanup_with_leases_spares_a_live_holders_temp_folder_and_removes_a_dead_ones(tmp_path):
    store = Store(tmp_path / "s", locks="lease", lease_ttl_s=TTL)
    tmp = store.begin("g/x", "detect")
    with store.lock("g/x", "detect"):
        other = Store(store.root, locks="lease", lease_ttl_s=TTL)
        assert other.clean_stale_leftovers("g/x", "detect") == []
        # a flock-locked run sharing the folder respects the live lease too
        assert Store(store.root, locks="flock").clean_stale_leftovers("g/x", "detect") == []
        assert tmp.dir.exists()
    lease = store.lease_path("g/x", "detect")
    old_private = lease.with_name(lease.name + ".new-0123abcd")  # a kill mid-acquire left it
    old_private.write_text("{}")
    os.utime(old_private, (time.time() - 11 * TTL,) * 2)
    fresh_private = lease.with_name(lease.name + ".stale-4567cdef")  # in use right now
    fresh_private.write_text("{}")
    lease.write_text(json.dumps({"owner": "dead", "token": "t", "ttl": TTL,
                                 "acquired": time.time() - 60, "expires": time.time() - 59}))
    assert sorted(store.clean_stale_leftovers("g/x", "detect")) == sorted([tmp.dir, old_private])
    assert not tmp.dir.exists() and not lease.exists() and fresh_private.exists()


def test_lock_backend_and_ttl_come_from_the_arguments_or_the_environment(tmp_path, monkeypatch):
    assert Store(tmp_path).locks == "flock"
    monkeypatch.setenv("PIPELINE_LOCKS", "lease")
    monkeypatch.setenv("PIPELINE_LEASE_TTL_S", "7.5")
    s = Store(tmp_path)
    assert (s.locks, s.lease_ttl_s) == ("lease", 7.5)
    assert Store(tmp_path, locks="flock").locks == "flock"
    with pytest.raises(StoreError, match=r"locks='nfs'.*flock, lease"):
        Store(tmp_path, locks="nfs")
    monkeypatch.setenv("PIPELINE_LOCKS", "posix")
    with pytest.raises(StoreError, match="PIPELINE_LOCKS='posix'"):
        Store(tmp_path)
    monkeypatch.setenv("PIPELINE_LOCKS", "lease")
    monkeypatch.setenv("PIPELINE_LEASE_TTL_S", "soon")
    with pytest.raises(StoreError, match="PIPELINE_LEASE_TTL_S='soon'"):
        Store(tmp_path)


def _run_toy(folder: Path, logs: list[str]):
    reg = toy_registry.registry()
    recipe = folder / "toy.yaml"
    eng = Engine(reg, reg.load_recipe(recipe), recipe, folder / "outputs", log=logs.append)
    rep = eng.run(eng.plan("release"))
    return eng, rep


def test_the_engine_with_leases_builds_and_reuses_artifacts_as_with_flock(tmp_path, monkeypatch):
    keys = {}
    for locks in ("flock", "lease"):
        folder = tmp_path / locks
        toy_registry.write_toy(folder)
        monkeypatch.setenv("PIPELINE_LOCKS", locks)
        logs: list[str] = []
        eng, first = _run_toy(folder, logs)
        assert eng.store.locks == locks
        assert first.count("computed") == 9 and not first.failed, logs
        _, second = _run_toy(folder, logs)
        assert second.count("hit") == 9 and second.count("computed") == 0
        out = folder / "outputs" / "toy"
        assert not list(out.rglob(".*.lease*"))  # every lease released, no private file left
        keys[locks] = {(m.parent.parent.relative_to(out).as_posix(), m.parent.name):
                       json.loads(m.read_text())["key"] for m in out.rglob("manifest.json")}
    assert keys["lease"] == keys["flock"] and len(keys["lease"]) == 9


def _lease_env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO), "PIPELINE_LOCKS": "lease",
            "PIPELINE_LEASE_TTL_S": str(TTL)}


def test_two_concurrent_cli_runs_with_leases_compute_each_artifact_once(tmp_path):
    toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 1.5}}, n_seq=1)

    def start() -> subprocess.Popen:
        return subprocess.Popen(cli(tmp_path, "sequence", "g/x"), env=_lease_env(), text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    first = start()
    wait_for_line(tmp_path, "start detect g/x", first)
    procs = [first, start()]
    outs = [p.communicate(timeout=60) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    lines = counts(tmp_path)
    for node in ("scale a", "scale b", "detect g/x", "fit g/x", "report g/x"):
        assert lines.count(f"start {node}") == 1 and lines.count(f"end {node}") == 1, (node, lines)
    words = [[ln.split()[3] for ln in err.splitlines() if " detect " in ln] for _, err in outs]
    assert words == [["miss"], ["waiting", "hit"]], outs


def test_a_builder_paused_past_its_lease_loses_the_artifact_to_the_one_that_took_over(tmp_path):
    toy_registry.write_toy(tmp_path, {"detect": {"sleep_s": 1.5}}, n_seq=1)
    unit = tmp_path / "outputs" / "toy" / "g" / "x"
    a = subprocess.Popen(cli(tmp_path, "sequence", "g/x"), env=_lease_env(),
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_line(tmp_path, "start detect g/x", a)
        os.kill(a.pid, signal.SIGSTOP)
        b = subprocess.run(cli(tmp_path, "sequence", "g/x"), env=_lease_env(),
                           capture_output=True, text=True, timeout=60)
        assert b.returncode == 0, b.stderr
        assert "waiting" in b.stderr
        text_by_b = (unit / "detect" / "manifest.json").read_text()
        built_by_b = json.loads(text_by_b)
    finally:
        os.kill(a.pid, signal.SIGCONT)
        a_err = a.communicate(timeout=60)[1]
    # A wakes up, its lease is gone and so is its temporary folder: it does not commit
    assert (unit / "detect" / "manifest.json").read_text() == text_by_b
    assert built_by_b["host"]["pid"] != a.pid
    assert Store(tmp_path / "outputs" / "toy").entry("g/x", "detect").state == "complete"
    assert not list(unit.glob(".tmp-*")) and not list(unit.glob(".trash-*")), a_err
    lines = counts(tmp_path)
    assert lines.count("start detect g/x") == 2 and lines.count("end detect g/x") == 2, lines
    assert "lost while building" in a_err and "not committed" in a_err, a_err
