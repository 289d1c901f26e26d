"""Shared fixtures.

``small_session``: a tiny complete studio session (two sequences of a few frames: a handshake
with the markers on one subject, a push with them on the other; scans, C3D, calibration,
videos, contact annotations, ground truth), generated once and cached on disk under
``assets/cache/test_session/<key>/``, the key being the hash of the studio's source and of the
packages it writes with (``studio.session.source_hash``). Returns the recipe path
(``recipe.yaml``; the ground truth is in ``gt/`` beside it).
"""
from __future__ import annotations

import os
import shutil
import sys
import uuid
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
os.environ.setdefault("ANNY_CACHE_DIR", str(REPO / "assets" / "cache" / "anny"))

SMALL_SESSION = {"seed": 7, "frames": 24, "scenarios": ("handshake", "push")}


def small_session_path() -> Path:
    """Where the cached small session lives (may not exist yet)."""
    from studio.session import source_hash

    return REPO / "assets" / "cache" / "test_session" / source_hash()


def _live_tmp(name: str) -> bool:
    """``.tmp-<pid>-<hex>`` of a process still running (another pytest building it now)."""
    from pipeline.procs import pid_alive

    parts = name.split("-")
    return (name.startswith(".tmp-") and len(parts) >= 3 and parts[1].isdigit()
            and pid_alive(int(parts[1])))


def build_small_session() -> Path:
    """Generate the small session into the cache if it is not there; returns the recipe path."""
    from studio import plan as PL
    from studio.session import generate

    final = small_session_path()
    recipe = final / "recipe.yaml"
    if recipe.exists():
        return recipe
    root = final.parent
    root.mkdir(parents=True, exist_ok=True)
    for old in root.iterdir():  # sessions of older studio versions, and dead builders' leftovers
        if old.name == final.name or _live_tmp(old.name):
            continue
        shutil.rmtree(old, ignore_errors=True)
    tmp = root / f".tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        plan = PL.make_plan(SMALL_SESSION["seed"], SMALL_SESSION["frames"], SMALL_SESSION["scenarios"])
        generate(tmp, plan)
        try:
            os.rename(tmp, final)
        except OSError:
            if not recipe.exists():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return recipe


@pytest.fixture(scope="session")
def small_session() -> Path:
    """Recipe path of the cached tiny studio session (see module doc)."""
    return build_small_session()


@pytest.fixture(scope="session")
def anny():
    """The exported Anny model, loaded once for the whole test session (skipped when it is not
    exported: ``make setup`` exports it)."""
    from body import load_model
    from formats.errors import InputError

    try:
        return load_model("anny")
    except InputError as e:
        pytest.skip(f"Anny not exported: {e}")


@pytest.fixture(scope="session")
def chromium_exe():
    """The headless Chromium the browser tests drive (qa.report.chromium_path): skipped when it
    is missing, failed instead when MOCAP_REQUIRE_BROWSER is set (``make test`` sets it)."""
    import os

    from qa.report import chromium_path

    exe = chromium_path()
    if exe is None:
        msg = ("chromium is not installed (/usr/bin/chromium missing): install it with "
               "`bash scripts/setup.sh --browser` (or `make browser`)")
        if os.environ.get("MOCAP_REQUIRE_BROWSER"):
            pytest.fail(msg + "; MOCAP_REQUIRE_BROWSER is set, so the browser tests must run")
        pytest.skip(msg)
    return exe
