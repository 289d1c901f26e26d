"""The contract between the engine and the stages that plug into it.

The engine (this package) knows nothing of bodies, cameras or recipes' contents: a domain
package (``stages``) hands it a :class:`Registry` of :class:`Stage` declarations plus a few
callables that interpret the recipe. The engine only connects names, hashes, caches, locks.

A stage function receives a :class:`StageContext` and writes its outputs through
``ctx.out`` into a temporary folder that the engine renames into place when the function
returns. The function should be a thin adapter: unpack artifacts, call a pure function that
never opens files, save the result.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Protocol

Granularity = Literal["subject", "sequence", "session"]


@dataclass(frozen=True)
class Stage:
    """One node of the DAG.

    name : artifact name, also the recipe section ``stages.<name>`` that holds its parameters.
    func : ``func(ctx: StageContext) -> None``; writes outputs through ``ctx.out``.
    per : granularity of one unit of work (a subject, a sequence, the session).
    upstream : names of stages whose artifacts this one reads.
    version : bump when the stage's behaviour changes in a way the source hash can't see
        (the engine hashes the source of ``func``'s module and of the local modules it
        imports, transitively).
    params : a class (frozen dataclass or pydantic model) that validates the recipe section;
        unknown keys are errors. ``None``: the stage takes no parameters.
    raw_inputs : ``raw_inputs(recipe, unit) -> {name: Path}``: raw files read from the recipe;
        their content hashes enter the key. ``None``: no raw inputs.
    implemented : False for a planned stage that does not exist yet (the CLI says so plainly).
    """

    name: str
    func: Callable[["StageContext"], None] | None
    per: Granularity
    upstream: tuple[str, ...] = ()
    version: str = "1"
    params: type | None = None
    raw_inputs: Callable[[Any, str], dict[str, Path]] | None = None
    implemented: bool = True
    doc: str = ""


@dataclass(frozen=True)
class Registry:
    """What the domain package hands the engine (found by name: ``stages.registry()``).

    load_recipe(path) -> recipe object (opaque to the engine); raises with file and field.
    session_name(recipe) -> str: folder name under ``outputs/``.
    units(recipe, per) -> list[str]: the units of a granularity (subject ids, sequence ids
        ``"<group>/<action>"``, or ``["session"]``).
    upstream_units(recipe, stage, unit, upstream) -> list[str]: which units of an upstream stage
        a unit reads (e.g. a sequence reads the shape_fit of the two subjects in it).
    stage_params(recipe, stage) -> dict: the raw recipe section for a stage (may be empty).
    prepare(recipe_path) -> None, optional: called before the recipe is loaded by the commands
        that run stages (``demo``, ``sequence``, ``release``; not ``status``), e.g. to generate
        the synthetic demo data when it is missing. Must be idempotent and cheap when there is
        nothing to do.
    """

    stages: tuple[Stage, ...]
    load_recipe: Callable[[Path], Any]
    session_name: Callable[[Any], str]
    units: Callable[[Any, Granularity], list[str]]
    upstream_units: Callable[[Any, str, str, str], list[str]]
    stage_params: Callable[[Any, str], dict]
    prepare: Callable[[Path], None] | None = None


class Artifact(Protocol):
    """A completed, read-only artifact of one stage for one unit."""

    dir: Path
    key: str
    unit: str

    def arrays(self, name: str) -> dict: ...  # the arrays of ``<name>.npz`` (read-only)

    def json(self, name: str) -> Any: ...  # the content of ``<name>.json``

    def path(self, filename: str) -> Path: ...  # any other file in the artifact folder


class ArtifactWriter(Protocol):
    """Writes into the temporary folder of the artifact being built."""

    dir: Path

    def save_arrays(self, name: str, **arrays) -> Path: ...  # ``<name>.npz``

    def save_json(self, name: str, obj: Any) -> Path: ...  # ``<name>.json``

    def path(self, filename: str) -> Path: ...  # a path to write any other file to


@dataclass
class StageContext:
    """Everything a stage function gets.

    inputs : ``{upstream_stage: Artifact}`` when the upstream stage has the same granularity
        (it maps to this very unit), else ``{upstream_stage: {unit: Artifact}}`` in the order
        ``upstream_units`` gives (a sequence reading a per-subject stage gets
        ``{markers_on: ..., partner: ...}``), even when that dict has a single entry.
    raw : the raw input files of this unit, ``{name: Path}``.
    progress : ``progress(iterable, total=None, desc="")`` wraps per-frame loops in a bar
        that is quiet when stderr is not a terminal.
    """

    stage: str
    unit: str
    recipe: Any
    params: Any
    inputs: dict[str, Any]
    raw: dict[str, Path]
    out: ArtifactWriter
    progress: Callable[..., Any]
    log: Callable[[str], None]
    extras: dict[str, Any] = field(default_factory=dict)
