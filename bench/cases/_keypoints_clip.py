"""One sequence's clip of the keypoints case (``bench/cases/keypoints.py``, ``_clip``): the
stage at its defaults on the first ``frames`` frames, in a worker process of its own, so that
two sequences' clips run at once, one per core (a module-level function: the pool spawns)."""
from __future__ import annotations

from pathlib import Path


def clip_one(recipe_path: str, sid: str, frames: int):
    """(the clip's Keypoints2D, the stage's report) of sequence ``sid``."""
    from recipes import load_recipe
    from stages import view_for
    from stages.capture import capture_of
    from stages.keypoints import Options, compute, raw_inputs

    recipe = load_recipe(Path(recipe_path))
    o = Options(stride=1, start=0, stop=frames, workers=1)
    mk, cams, _ = capture_of(recipe, sid)
    c = compute(view_for(recipe, "keypoints", sid), raw_inputs(recipe, sid), o, unit=sid,
                recipe_path=Path(recipe_path), markers=mk, cams=cams)
    return c.keypoints, c.report
