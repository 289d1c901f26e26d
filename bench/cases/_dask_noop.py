"""A registry of trivial stages for ``bench/cases/dask.py`` (``dask.overhead_s_per_task``): one
per-subject ``base`` node read by ``N`` per-sequence ``noop`` nodes, each writing one tiny JSON.
Recipe: ``{session: noop, n: 200}``. Loaded by path (``--registry bench/cases/_dask_noop.py``)."""
from __future__ import annotations

from pathlib import Path

import yaml

from pipeline.spec import Registry, Stage, StageContext


def load_recipe(path: Path) -> dict:
    raw = yaml.safe_load(Path(path).read_text())
    return {"session": str(raw["session"]), "n": int(raw["n"])}


def run_base(ctx: StageContext) -> None:
    ctx.out.save_json("base", {"unit": ctx.unit})


def run_noop(ctx: StageContext) -> None:
    ctx.out.save_json("noop", {"unit": ctx.unit})


STAGES = (
    Stage("base", run_base, per="subject"),
    Stage("noop", run_noop, per="sequence", upstream=("base",)),
)


def units(r: dict, per: str) -> list[str]:
    return {"subject": ["a"], "sequence": [f"g/q{i:04d}" for i in range(r["n"])],
            "session": ["session"]}[per]


def upstream_units(r: dict, stage: str, unit: str, upstream: str) -> list[str]:  # noqa: ARG001
    return ["a"]  # every noop reads the one base


def stage_params(r: dict, stage: str) -> dict:  # noqa: ARG001
    return {}


def registry() -> Registry:
    return Registry(stages=STAGES, load_recipe=load_recipe, session_name=lambda r: r["session"],
                    units=units, upstream_units=upstream_units, stage_params=stage_params)
