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
    reads : the recipe fields the stage reads, as dotted names the registry resolves for a unit
        (``"cameras"``, ``"sequence.fps"``, ``"sequence.mocap"`` for a whole sub-tree). Their
        values enter the key, and the stage's ``ctx.recipe`` is a :class:`RecipeView` of exactly
        them: reading anything else raises :class:`UndeclaredRead`. Files are not read through
        the view but through ``raw_inputs`` (keyed by content, not by path).
    implemented : False for a planned stage that does not exist yet (the CLI says so plainly).
    cores, memory_gb : what one unit of the stage needs on a worker. A distributed executor
        runs it only where that much is free (Dask resources ``cores`` / ``memory_gb``), and the
        stage gets ``ctx.cores`` (the cores granted) for its own worker pools, so a stage that
        starts processes never oversubscribes its worker.
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
    reads: tuple[str, ...] = ()
    cores: int = 1
    memory_gb: float = 2.0


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
    recipe_view(recipe, unit, name) -> value, optional: the value of the declared recipe field
        ``name`` (one entry of ``Stage.reads``) for ``unit``: plain data (str, numbers, bools,
        lists, dicts); raises ``KeyError`` for a name it does not know. Without it a stage may
        declare no ``reads``.
    check(recipe, recipe_path, units) -> list[str], optional: every problem of the recipe that
        the schema cannot see (e.g. input files that disagree with each other), one message per
        problem naming the file and the field, for the sequences ``units`` about to run (None:
        all). The CLI runs it before any stage and stops with exit code 2 on any message.
    applies(recipe, stage, unit) -> bool, optional: whether a stage runs for a unit at all (e.g.
        a video stage on a sequence recorded without video). A stage that does not apply is
        neither a target nor an input: its downstream stages' ``ctx.inputs`` lack it.
    """

    stages: tuple[Stage, ...]
    load_recipe: Callable[[Path], Any]
    session_name: Callable[[Any], str]
    units: Callable[[Any, Granularity], list[str]]
    upstream_units: Callable[[Any, str, str, str], list[str]]
    stage_params: Callable[[Any, str], dict]
    prepare: Callable[[Path], None] | None = None
    recipe_view: Callable[[Any, str, str], Any] | None = None
    check: Callable[[Any, Path, list[str] | None], list[str]] | None = None
    applies: Callable[[Any, str, str], bool] | None = None


class UndeclaredRead(LookupError):
    """A stage read a recipe field it did not declare in ``Stage.reads`` (the field would be
    missing from the artifact key, so an edit of it would reuse stale results)."""


class RecipeView:
    """The part of the recipe a stage declared (``Stage.reads``), as read-only attributes:
    ``view.sequence.fps``, ``view.cameras``. ``tree`` is the nested dict of declared values.
    A missing attribute is an :class:`UndeclaredRead` naming the stage and the field."""

    __slots__ = ("_tree", "_stage", "_prefix")

    def __init__(self, tree: dict, stage: str, prefix: str = ""):
        object.__setattr__(self, "_tree", tree)
        object.__setattr__(self, "_stage", stage)
        object.__setattr__(self, "_prefix", prefix)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        tree = object.__getattribute__(self, "_tree")
        stage = object.__getattribute__(self, "_stage")
        prefix = object.__getattribute__(self, "_prefix")
        full = f"{prefix}{name}"
        if name not in tree:
            raise UndeclaredRead(f"stage {stage} reads recipe field {full!r} but does not declare "
                                 f"it in Stage.reads (declared here: {sorted(tree) or 'nothing'})")
        v = tree[name]
        return RecipeView(v, stage, f"{full}.") if isinstance(v, dict) else v

    __getitem__ = __getattr__

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("the recipe view is read-only")

    def __contains__(self, name: str) -> bool:
        return name in object.__getattribute__(self, "_tree")

    def as_dict(self) -> dict:
        return object.__getattribute__(self, "_tree")

    def __repr__(self) -> str:
        return f"RecipeView({object.__getattribute__(self, '_tree')!r})"


def build_view_tree(values: dict[str, Any]) -> dict:
    """``{"sequence.fps": 50, "cameras": [...]}`` -> ``{"sequence": {"fps": 50}, "cameras":
    [...]}``. A name that is a prefix of another merges (``sequence.mocap`` and
    ``sequence.mocap.rate_hz`` give one sub-tree)."""
    tree: dict = {}
    for name in sorted(values, key=lambda n: n.count(".")):
        parts = name.split(".")
        node = tree
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise ValueError(f"recipe field {name!r}: {p!r} is a value, not a group")
            node = nxt
        v = values[name]
        if isinstance(v, dict) and isinstance(node.get(parts[-1]), dict):
            node[parts[-1]].update(v)
        else:
            node[parts[-1]] = v
    return tree


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
    recipe : a :class:`RecipeView` of the fields the stage declared in ``Stage.reads``.
    recipe_path : the recipe file, for error messages only (it is not part of the key).
    raw : the raw input files of this unit, ``{name: Path}``.
    progress : ``progress(iterable, total=None, desc="")`` wraps per-frame loops in a bar
        that is quiet when stderr is not a terminal.
    cores : the cores the executor granted this unit (0: the whole machine, as in a serial
        run); a stage that starts worker processes starts at most this many.
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
    recipe_path: Path | None = None
    cores: int = 0
