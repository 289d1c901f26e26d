"""The bench's generated studio sessions, cached by the version of the code that generates them.

``ensure(recipe)`` makes the data of a studio preset recipe (``recipes/bench.yaml``,
``recipes/markers.yaml``) exist *as the studio's current code generates them*:

- the data folder already holds a session of this version (its stamp ``.bench_version`` says
  ``version_key(preset)``, or its ``gt/session.json`` names the preset's plan and
  ``studio.session.source_hash()``): kept;
- else the cache holds one (``$MOCAP_STUDIO_CACHE``, default ``~/.cache/mocap_studio``, a
  folder ``<preset>-<version_key>``, outside the checkout so that a fresh clone of the same
  code reuses it): copied into the data folder;
- else the data folder is generated afresh (``studio.ensure_generated``; a session from an
  older version is removed first, the studio itself would keep it) and copied into the cache.

The version (``version_key``): the preset's plan and :func:`code_hash`, the content of the
source files the studio's code imports (``studio/`` and, followed through every ``import`` of
the repository's own modules, e.g. ``body/lbs.py``, ``calib/camera.py``), not of whole
packages: the studio's own ``source_hash`` also covers modules it never imports (the QA
overlays in ``drawing/``, the rig refinement in ``calib/``), and any edit of those made a fresh
clone regenerate the bench session (37 minutes on 2 cores). One process at a time makes a
preset's data (a lock file in the cache folder): two bench runs never generate into the same
folder.

Generation is what a fresh clone's ``make bench`` pays first; a second clone of the same
studio code does not.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import uuid
from pathlib import Path


def cache_root() -> Path:
    return Path(os.environ.get("MOCAP_STUDIO_CACHE") or Path.home() / ".cache" / "mocap_studio")


def _data_dir(recipe: Path) -> tuple[str, Path]:
    import yaml

    from studio import recipe_files

    raw = yaml.safe_load(recipe.read_text()) or {}
    session = str(raw.get("session", ""))
    if not session.startswith("studio_"):
        raise ValueError(f"{recipe}: session {session!r} is not a studio preset")
    files = recipe_files(raw, recipe.resolve().parent)
    return session.removeprefix("studio_"), Path(os.path.commonpath([str(f) for f in files]))


STAMP = ".bench_version"  # in a data or cache folder: the version_key it was made with
REPO = Path(__file__).resolve().parents[2]


def _module_file(root: Path, name: str) -> Path | None:
    p = root.joinpath(*name.split("."))
    if (p / "__init__.py").is_file():
        return p / "__init__.py"
    return p.with_suffix(".py") if p.with_suffix(".py").is_file() else None


def code_files(root: Path = REPO, package: str = "studio") -> list[Path]:
    """The ``.py`` files of ``package`` under ``root`` and of every module of ``root`` they
    import, transitively (``import a.b``, ``from a.b import c`` (``a/b/c.py`` when it is a
    module), relative imports; imports inside functions count), sorted. A module is a file of
    ``root``: third-party imports are not followed."""
    import ast

    root = Path(root)
    todo = sorted((root / package).rglob("*.py"))
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        parts = list(f.relative_to(root).with_suffix("").parts)
        pkg = parts[:-1]  # the package a relative import starts from
        for node in ast.walk(ast.parse(f.read_bytes(), str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = pkg[:len(pkg) - node.level + 1] if node.level else []
                mod = ".".join(base + ([node.module] if node.module else []))
                names = [mod] + [f"{mod}.{a.name}" if mod else a.name for a in node.names]
            else:
                continue
            for name in names:
                bits = name.split(".")
                for i in range(1, len(bits) + 1):  # a.b.c imports a and a.b first
                    m = _module_file(root, ".".join(bits[:i]))
                    if m is not None and m not in seen:
                        todo.append(m)
    return sorted(seen)


def code_hash(root: Path = REPO, package: str = "studio") -> str:
    """16 hex of the paths and contents of :func:`code_files`."""
    h = hashlib.sha256()
    for f in code_files(root, package):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def version_key(preset: str) -> str:
    """16 hex of the preset's plan and :func:`code_hash`: what decides the data."""
    from studio import plan as PL
    from studio.session import plan_dict

    plan = plan_dict(PL.make_plan(PL.PRESETS[preset].seed, preset=preset))
    h = hashlib.sha256(json.dumps(plan, sort_keys=True).encode() + code_hash().encode())
    return h.hexdigest()[:16]


def _complete(data: Path, preset: str) -> dict | None:
    """``gt/session.json`` of a complete session of the preset's plan in ``data``, else None."""
    from studio import plan as PL
    from studio.session import plan_dict

    try:
        meta = json.loads((data / "gt" / "session.json").read_text())
    except (OSError, ValueError):
        return None
    want = plan_dict(PL.make_plan(PL.PRESETS[preset].seed, preset=preset))
    return meta if meta.get("plan") == want else None


def _current(data: Path, preset: str) -> bool:
    """The folder holds a complete session of the preset's plan made by this version (its
    stamp), or by exactly this studio source (``gt/session.json``; then it is stamped)."""
    from studio.session import source_hash

    meta = _complete(data, preset)
    if meta is None:
        return False
    key = version_key(preset)
    try:
        if (data / STAMP).read_text().strip() == key:
            return True
    except OSError:
        pass
    if meta.get("studio_source") == source_hash():
        (data / STAMP).write_text(key + "\n")
        return True
    return False


def _copy(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` through a temporary sibling renamed into place."""
    tmp = dst.parent / f".{dst.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        shutil.copytree(src, tmp)
        if dst.exists():
            shutil.rmtree(dst)
        os.rename(tmp, dst)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def ensure(recipe: str | Path) -> Path:
    """Make the recipe's studio data current (see the module doc); returns the recipe path.
    Holds the preset's lock file in the cache folder meanwhile (another bench process waits)."""
    import fcntl

    recipe = Path(recipe)
    preset, _ = _data_dir(recipe)
    cache_root().mkdir(parents=True, exist_ok=True)
    with open(cache_root() / f".{preset}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return _ensure(recipe)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _ensure(recipe: Path) -> Path:
    from studio import ensure_generated

    preset, data = _data_dir(recipe)
    key = version_key(preset)
    cached = cache_root() / f"{preset}-{key}"
    for d in (data, cached):  # copies a killed run left half-made (SIGTERM skips finally);
        for tmp in d.parent.glob(f".{d.name}.tmp-*"):  # safe: we hold the preset's lock
            shutil.rmtree(tmp, ignore_errors=True)
    if not _current(data, preset):
        if _current(cached, preset):
            print(f"[bench] {data}: copied from the studio cache {cached}", file=sys.stderr)
            data.parent.mkdir(parents=True, exist_ok=True)
            _copy(cached, data)
        elif data.exists():  # generated by other studio code: the studio would keep it
            print(f"[bench] {data}: generated by other studio code; regenerating", file=sys.stderr)
            shutil.rmtree(data)
    fresh = not _current(data, preset)
    ensure_generated(recipe)  # generates what is missing; adds the CHI3D truth if needed
    if fresh and _complete(data, preset) is not None:  # generated now, by this code
        (data / STAMP).write_text(key + "\n")
    if _current(data, preset) and not _current(cached, preset):
        cached.parent.mkdir(parents=True, exist_ok=True)
        _copy(data, cached)
    return recipe
