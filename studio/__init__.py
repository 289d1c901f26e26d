"""Synthetic capture studio (``python -m studio``): complete two-person sessions in the real
input formats, with exact ground truth kept apart in ``<out>/gt/``.

    from studio import ensure_generated
    ensure_generated("recipes/demo.yaml")   # generates data/demo if any file is missing

See ``studio.plan`` (session layout, presets), ``studio.session`` (what is written).
"""
from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

__all__ = ["ensure_generated", "preset_recipe", "recipe_files"]


def recipe_files(raw: dict, base: Path) -> list[Path]:
    """Every file a recipe (raw YAML dict) refers to, resolved against ``base``."""
    files = []
    for s in (raw.get("subjects") or {}).values():
        if s.get("scan"):
            files.append(s["scan"])
    for q in (raw.get("sequences") or {}).values():
        files.append(q["c3d"])
        files.extend(q["videos"].values())
        files.extend(q["calibration"].values())
        if q.get("contact"):
            files.append(q["contact"])
    return [(base / f).resolve() for f in files]


def _strip(raw: dict) -> dict:
    return {k: v for k, v in raw.items() if k != "stages"}


def preset_recipe(preset: str, recipe_dir: Path, data_dir: Path) -> dict:
    """The recipe of a preset session stored in ``data_dir``, with paths relative to
    ``recipe_dir`` (what ``recipes/<preset>.yaml`` holds)."""
    from studio import plan as PL

    p = PL.PRESETS[preset]
    prefix = os.path.relpath(Path(data_dir).resolve(), Path(recipe_dir).resolve()).replace(os.sep, "/")
    return PL.recipe_dict(PL.make_plan(p.seed, preset=preset), prefix=prefix + "/")


def ensure_generated(recipe_path: str | Path) -> Path:
    """Make sure the data of a studio preset recipe exist; generate them if any file is missing.

    The preset is named by the recipe's ``session`` (``studio_demo``, ``studio_bench``); the
    data folder is the common folder of the recipe's files (``data/demo``). Generation goes to
    a temporary sibling folder renamed into place at the end, so an interrupted run never
    leaves a half-written session that looks complete. Raises ``recipes.RecipeError`` if files
    are missing from a recipe that is not a studio preset, or if the committed recipe no longer
    matches what the studio would generate. Returns the recipe path.
    """
    import yaml

    from recipes import RecipeError
    from studio import plan as PL

    recipe_path = Path(recipe_path)
    if not recipe_path.is_file():
        raise RecipeError(f"{recipe_path}: recipe not found")
    raw = yaml.safe_load(recipe_path.read_text()) or {}
    base = recipe_path.resolve().parent
    files = recipe_files(raw, base)
    if files and all(f.exists() for f in files):
        return recipe_path
    session = str(raw.get("session", ""))
    preset = session.removeprefix("studio_") if session.startswith("studio_") else None
    if preset not in PL.PRESETS:
        missing = next(f for f in files if not f.exists()) if files else "sequences"
        raise RecipeError(f"{recipe_path}: {missing}: file not found (and session {session!r} "
                          f"is not a studio preset: {', '.join('studio_' + p for p in PL.PRESETS)})")
    data_dir = Path(os.path.commonpath([str(f) for f in files]))
    want = preset_recipe(preset, base, data_dir)
    if _strip(want) != _strip(raw):
        raise RecipeError(f"{recipe_path}: does not match the studio's {preset!r} preset any more; "
                          f"rewrite it: python -m studio --preset {preset} --out {data_dir} "
                          f"--write-recipe {recipe_path}")
    from studio.session import generate

    tmp = data_dir.parent / f".{data_dir.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        generate(tmp, PL.make_plan(PL.PRESETS[preset].seed, preset=preset))
        if data_dir.exists():
            old = data_dir.parent / f".{data_dir.name}.old-{uuid.uuid4().hex[:8]}"
            os.rename(data_dir, old)
            shutil.rmtree(old, ignore_errors=True)
        try:
            os.rename(tmp, data_dir)
        except OSError:
            if not all(f.exists() for f in files):  # nobody else finished it meanwhile
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return recipe_path
