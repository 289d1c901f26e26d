"""The realistic marker studio run through the stage chain, shared by the ``marker_fit`` and
``shape_fit`` cases: ``recipes/markers.yaml`` (``studio`` preset ``markers``: two subjects
with a static trial each and two movement trials, Plug-in Gait on placements slid 1.5-2.5 cm
from the template with 8-25 mm skin offsets, soft tissue, label swaps, ghosts, spikes, extra
points and analog channels, non-zero first frames; no video, no scan) through ``shape_fit``
(shape and placement from the markers) -> ``marker_fit`` -> ``marker_loo``, with the engine,
into ``bench/work/markers_chain/outputs`` (cached: the second case reuses the first's run)."""
from __future__ import annotations

import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "markers.yaml"
WORK = REPO / "bench" / "work" / "markers_chain"


def run_chain(until: str = "marker_loo"):
    """Generate the preset's data if needed, run the chain; returns ``(recipe, outputs, gt)``
    with ``outputs`` the session's folder and ``gt`` the studio's ground truth."""
    import yaml

    from pipeline.cli import main
    from recipes import load_recipe
    from studio import ensure_generated

    ensure_generated(RECIPE)
    rec = yaml.safe_load(RECIPE.read_text())

    def absolute(p):
        return str((RECIPE.parent / p).resolve())

    for s in rec["subjects"].values():
        for t in s.get("static", []):
            t["c3d"] = absolute(t["c3d"])
    for q in rec["sequences"].values():
        q["c3d"] = absolute(q["c3d"])
    WORK.mkdir(parents=True, exist_ok=True)
    path = WORK / "recipe.yaml"
    path.write_text(yaml.safe_dump(rec, sort_keys=False))
    recipe = load_recipe(path)
    logs: list[str] = []
    rc = main(["sequence", *recipe.sequences, "--recipe", str(path), "--outputs",
               str(WORK / "outputs"), "--until", until], log=logs.append)
    (WORK / "engine.log").write_text("\n".join(logs))
    if rc != 0:
        raise RuntimeError("engine failed on the markers preset:\n" + "\n".join(logs[-30:]))
    gt = Path(next(iter(recipe.sequences.values())).c3d).parents[2] / "gt"
    return recipe, WORK / "outputs" / recipe.session, gt


def report_json(path: Path) -> dict:
    return json.loads(path.read_text())
