"""From a registry and a recipe to a plan: the (stage, unit) nodes to run, in DAG order, each
with its artifact key.

Key of a node = sha256 of the canonical JSON of::

    {"stage": name, "version": Stage.version, "source": sha256 of the module source of func,
     "params": validated parameters, "recipe": the declared recipe fields (Stage.reads) and
     their values for the unit, "upstream": {stage: {unit: key}},
     "raw": {name: sha256 of the file or folder}}

Keys depend only on code, recipe and raw files, never on what is on disk, so ``status`` can
compare them with the stored manifests without running anything.
"""
from __future__ import annotations

import ast
import dataclasses
import hashlib
import inspect
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.hashing import FileHasher, UnhashableError, canonical, digest
from pipeline.spec import Registry, Stage, build_view_tree

GRANULARITIES = ("subject", "sequence", "session")
NodeId = tuple[str, str]  # (stage, unit)


class PlanError(ValueError):
    """The registry, the recipe or the command can't be turned into a plan; the message names
    the file and field where it can."""


@dataclass
class Node:
    """One (stage, unit) of the plan. ``upstream``: ``{stage: [units]}`` it reads.
    ``key`` is None when it could not be computed (``error`` says why)."""

    stage: Stage
    unit: str
    upstream: dict[str, list[str]]
    params: Any = None
    params_canon: Any = None
    raw: dict[str, Path] = field(default_factory=dict)
    raw_hashes: dict[str, str] = field(default_factory=dict)
    upstream_keys: dict[str, dict[str, str]] = field(default_factory=dict)
    recipe_view: dict = field(default_factory=dict)
    key: str | None = None
    error: str = ""

    @property
    def id(self) -> NodeId:
        return (self.stage.name, self.unit)

    def upstream_ids(self) -> list[NodeId]:
        return [(s, u) for s, us in self.upstream.items() for u in us]


@dataclass
class Plan:
    """Nodes in an order where every node comes after its upstream nodes."""

    nodes: list[Node]
    session: str

    def __post_init__(self):
        self.by_id = {n.id: n for n in self.nodes}

    def descendants(self, ids: set[NodeId]) -> set[NodeId]:
        """``ids`` and every node of the plan downstream of them."""
        out = set(ids)
        for n in self.nodes:  # topological order: one pass suffices
            if any(u in out for u in n.upstream_ids()):
                out.add(n.id)
        return out


def check_registry(reg: Registry) -> list[Stage]:
    """Validate the stage declarations; return the stages in a topological order (the
    registry's own order when it already is one)."""
    names = [s.name for s in reg.stages]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise PlanError(f"registry: stages declared twice: {sorted(dup)}")
    by = {s.name: s for s in reg.stages}
    for s in reg.stages:
        if s.per not in GRANULARITIES:
            raise PlanError(f"registry: stage {s.name}: per={s.per!r}, expected one of {GRANULARITIES}")
        for u in s.upstream:
            if u not in by:
                raise PlanError(f"registry: stage {s.name}: unknown upstream stage {u!r}")
        if s.implemented and s.func is None:
            raise PlanError(f"registry: stage {s.name}: implemented but has no func")
    order: list[Stage] = []
    state: dict[str, int] = {}

    def visit(name: str, path: tuple[str, ...]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            raise PlanError(f"registry: cycle through stages {' -> '.join(path + (name,))}")
        state[name] = 1
        for u in by[name].upstream:
            visit(u, path + (name,))
        state[name] = 2
        order.append(by[name])

    for s in reg.stages:
        visit(s.name, ())
    return order


_IMPORTS: dict[tuple, list[Path]] = {}  # (path, root, pkg, sha1 of the source) -> its imports


class ImportMemo:
    """The module names each source text imports, kept on disk between processes.

    ``memo_file``: JSON ``{sha1 of (package, source): [dotted names]}`` (``None``: in memory
    only). Parsing every module a registry's stages import (~140 files) was ~0.5 s of each
    cached rerun; a name list depends only on the source text and its package, so an entry
    never goes stale (the names are resolved to files again in every process: a module file
    added later is found). Processes may share the file (last writer wins, a lost entry
    only costs a parse); at most ``MAX_ENTRIES`` are kept, the oldest dropped first."""

    MAX_ENTRIES = 4096

    def __init__(self, memo_file: Path | None = None):
        self.memo_file = memo_file
        self._memo: dict[str, list[str]] = {}
        self._dirty = False
        if memo_file is not None and memo_file.is_file():
            try:
                data = json.loads(memo_file.read_text())
                if isinstance(data, dict):
                    self._memo = {k: v for k, v in data.items() if isinstance(v, list)
                                  and all(isinstance(n, str) for n in v)}
            except (OSError, ValueError):
                self._memo = {}  # a damaged memo only costs parsing the sources again

    @staticmethod
    def key(data: bytes, pkg: str) -> str:
        return hashlib.sha1(pkg.encode() + b"\0" + data).hexdigest()

    def names(self, data: bytes, path: Path, pkg: str) -> list[str]:
        """The dotted module names the source ``data`` (of ``path``, in package ``pkg``)
        imports, from the memo or parsed (SyntaxError propagates)."""
        k = self.key(data, pkg)
        hit = self._memo.get(k)
        if hit is None:
            hit = self._memo[k] = _import_names(data, path, pkg)
            self._dirty = True
        return hit

    def save(self) -> None:
        """Write the memo back (atomically) if anything was added."""
        if self.memo_file is None or not self._dirty:
            return
        keep = dict(list(self._memo.items())[-self.MAX_ENTRIES:])
        self.memo_file.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.memo_file.parent, prefix=".imports-")
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(keep, f)
            os.replace(tmp, self.memo_file)
        except OSError:
            Path(tmp).unlink(missing_ok=True)
        self._dirty = False


def _local_imports(path: Path, root: Path, pkg: str, memo: ImportMemo | None = None) -> list[Path]:
    """Source files under ``root`` that the module at ``path`` imports (absolute or relative),
    including the packages' ``__init__.py`` on the way. Pure AST: nothing is imported.
    Memoised per source text in this process: the stages of one registry share most of their
    modules (parsing them once per stage was most of a cached rerun's time); the parsed names
    also in ``memo`` across processes (:class:`ImportMemo`)."""
    data = path.read_bytes()
    key = (str(path), str(root), pkg, hashlib.sha1(data).digest())
    hit = _IMPORTS.get(key)
    if hit is None:
        names = (memo.names(data, path, pkg) if memo is not None
                 else _import_names(data, path, pkg))
        hit = _IMPORTS[key] = _resolve_names(names, root)
    return list(hit)


#: the fields of a statement that hold statements (an import can sit in any of them: a
#: function's body, an ``if``/``try``/``with``/``for`` branch, an ``except`` handler, a ``case``)
_STMT_FIELDS = ("body", "orelse", "finalbody", "handlers", "cases")


def _statements(tree: ast.AST):
    """Every statement of ``tree``, nested ones included, without visiting expressions (an
    import is a statement: ``ast.walk`` over every expression node was 4x the work)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for f in _STMT_FIELDS:
            sub = getattr(node, f, None)
            if isinstance(sub, list):
                todo.extend(x for x in sub if isinstance(x, ast.AST))


def _parse_imports(data: bytes, path: Path, root: Path, pkg: str) -> list[Path]:
    return _resolve_names(_import_names(data, path, pkg), root)


def _import_names(data: bytes, path: Path, pkg: str) -> list[str]:
    """The dotted names a module's source imports (``from a import b``: ``a`` and ``a.b``;
    relative imports made absolute within ``pkg``)."""
    tree = ast.parse(data, filename=str(path))
    names: list[str] = []
    for node in _statements(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1] if pkg else []
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names.append(mod)
            names += [f"{mod}.{a.name}" for a in node.names if a.name != "*"]
    return names


def _resolve_names(names: list[str], root: Path) -> list[Path]:
    """The source files under ``root`` that dotted ``names`` are (modules and the packages'
    ``__init__.py`` on the way)."""
    found: list[Path] = []
    for name in names:
        parts = [p for p in name.split(".") if p]
        for i in range(1, len(parts) + 1):
            d = root.joinpath(*parts[:i])
            for cand in (d.with_suffix(".py"), d / "__init__.py"):
                if cand.is_file():
                    found.append(cand)
    return found


_RESOLVED: dict[Path, Path] = {}


def _resolved(p: Path) -> Path:
    """``p.resolve()``, memoised in this process (a plan resolves the same few hundred module
    paths thousands of times)."""
    r = _RESOLVED.get(p)
    if r is None:
        r = _RESOLVED[p] = p.resolve()
    return r


def source_hash(stage: Stage, memo: ImportMemo | None = None) -> str:
    """sha256 over the source of the module defining ``stage.func`` and of every module of the
    same source tree that it imports, transitively ("" for placeholders). A change in a helper
    package the stage uses therefore invalidates the stage, with no version bump needed.
    A function whose source can't be found can't be keyed: PlanError. ``memo``: the parsed
    import names kept between processes (:class:`ImportMemo`)."""
    if stage.func is None:
        return ""
    try:
        src = inspect.getsourcefile(stage.func)
    except TypeError:
        src = None
    if src is None or not Path(src).is_file():
        raise PlanError(f"stage {stage.name}: can't find the source of {stage.func!r} to hash it")
    modname = getattr(stage.func, "__module__", "") or ""
    start = Path(src).resolve()
    depth = max(len(modname.split(".")) - 1, 0) if start.name != "__init__.py" else len(modname.split("."))
    root = start.parents[depth] if modname else start.parent
    seen: dict[Path, None] = {}
    todo = [start]
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen[f] = None
        rel = f.relative_to(root).with_suffix("")
        parts = list(rel.parts)
        pkg = ".".join(parts[:-1] if parts[-1] != "__init__" else parts[:-1])
        try:
            todo += [_resolved(p) for p in _local_imports(f, root, pkg, memo)]
        except SyntaxError as e:
            raise PlanError(f"stage {stage.name}: {f}: can't parse to hash it: {e}") from None
    h = hashlib.sha256()
    for f in sorted(seen):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def validate_params(stage: Stage, raw: dict, where: str) -> tuple[Any, Any]:
    """Validate the recipe section of a stage with its ``params`` class.

    Returns ``(params object, canonical form for the key)``. Raises PlanError naming
    ``where`` (``<recipe>: stages.<name>``) and the parameter.
    """
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise PlanError(f"{where}: expected a mapping of parameters, got {type(raw).__name__}")
    cls = stage.params
    if not stage.implemented:
        return raw, _canon(raw, where)
    if cls is None:
        if raw:
            raise PlanError(f"{where}: stage {stage.name} takes no parameters, got {sorted(raw)}")
        return None, None
    if dataclasses.is_dataclass(cls):
        known = [f.name for f in dataclasses.fields(cls) if f.init]
    elif hasattr(cls, "model_fields"):
        known = list(cls.model_fields)
    else:
        known = None
    unknown = [f"{where}.{k}: unknown parameter (known: {', '.join(known)})"
               for k in raw if known is not None and k not in known]
    try:  # the known keys' problems too: every problem, one line each
        obj = _construct(cls, {k: v for k, v in raw.items() if known is None or k in known}, where)
    except PlanError as e:
        raise PlanError("\n".join([*unknown, str(e)])) from None
    if unknown:
        raise PlanError("\n".join(unknown))
    return obj, _canon(obj, where)


def _canon(obj: Any, where: str) -> Any:
    try:
        return canonical(obj, where)
    except UnhashableError as e:
        raise PlanError(str(e)) from None


def _construct(cls: type, raw: dict, where: str) -> Any:
    import pydantic

    try:
        if hasattr(cls, "model_validate"):
            return cls.model_validate(raw)
        try:
            adapter = pydantic.TypeAdapter(cls)
        except (pydantic.PydanticSchemaGenerationError, NameError, TypeError):
            adapter = None  # types pydantic can't check: fall back to the constructor
        if adapter is not None:
            return adapter.validate_python(raw)
        return cls(**raw)
    except pydantic.ValidationError as e:
        lines = []
        for err in e.errors():
            loc = ".".join(str(p) for p in err["loc"])
            got = err.get("input")
            got_s = "" if isinstance(got, (dict, list)) else f", got {got!r}"
            lines.append(f"{where}.{loc}: {err['msg']}{got_s}")
        raise PlanError("\n".join(lines)) from None
    except (TypeError, ValueError) as e:
        raise PlanError(f"{where}: {e}") from None


def recipe_view_tree(reg: Registry, recipe: Any, stage: Stage, unit: str) -> dict:
    """The canonical nested dict of the recipe fields ``stage`` declares (``Stage.reads``) for
    ``unit``; it enters the key and becomes the stage's ``ctx.recipe``. PlanError for a name the
    registry does not know or a value that can't be hashed."""
    if not stage.reads:
        return {}
    if reg.recipe_view is None:
        raise PlanError(f"stage {stage.name}: declares reads {list(stage.reads)} but the registry "
                        "has no recipe_view")
    values = {}
    for name in stage.reads:
        try:
            values[name] = _canon(reg.recipe_view(recipe, unit, name),
                                  f"stage {stage.name}: recipe field {name}")
        except KeyError as e:
            raise PlanError(f"stage {stage.name}: Stage.reads names {name!r}, which the registry "
                            f"does not know for unit {unit} ({e.args[0] if e.args else e})") from None
    try:
        return build_view_tree(values)
    except ValueError as e:
        raise PlanError(f"stage {stage.name}: {e}") from None


def closure(reg: Registry, recipe: Any, targets: list[NodeId]) -> dict[NodeId, dict[str, list[str]]]:
    """Every node needed for ``targets``: ``{(stage, unit): {upstream stage: [units]}}``."""
    by = {s.name: s for s in reg.stages}
    found: dict[NodeId, dict[str, list[str]]] = {}
    todo = list(targets)
    while todo:
        nid = todo.pop()
        if nid in found:
            continue
        stage, unit = nid
        ups: dict[str, list[str]] = {}
        for up in by[stage].upstream:
            if by[up].per == by[stage].per:
                units = [unit]
            else:
                units = list(reg.upstream_units(recipe, stage, unit, up))
            units = [u for u in units if applies(reg, recipe, up, u)]
            if not units and by[up].per == by[stage].per:
                continue  # e.g. no keypoints for a marker-only sequence: not an input at all
            ups[up] = units
            todo.extend((up, u) for u in units)
        found[nid] = ups
    return found


def targets_for(reg: Registry, recipe: Any, command: str, sequences: list[str] | None = None
                ) -> list[NodeId]:
    """The target nodes of a command. ``sequence``/``demo``: every per-sequence stage of the
    given sequences (their per-subject upstreams follow by closure); ``release``/``status``:
    every stage of every unit."""
    if command in ("release", "status"):
        return [(s.name, u) for s in reg.stages for u in reg.units(recipe, s.per)
                if applies(reg, recipe, s.name, u)]
    seqs = sequences if sequences is not None else list(reg.units(recipe, "sequence"))
    return [(s.name, q) for q in seqs for s in reg.stages
            if s.per == "sequence" and applies(reg, recipe, s.name, q)]


def applies(reg: Registry, recipe: Any, stage: str, unit: str) -> bool:
    """Whether ``stage`` runs for ``unit`` (``Registry.applies``; every stage applies to every
    unit when the registry does not say)."""
    return True if reg.applies is None else bool(reg.applies(recipe, stage, unit))


def build_plan(reg: Registry, recipe: Any, recipe_path: Path, targets: list[NodeId],
               until: str | None = None, hasher: FileHasher | None = None,
               imports: ImportMemo | None = None) -> Plan:
    """Nodes for ``targets`` (restricted to ``until`` and its ancestors), ordered, keyed.

    Errors that concern one node (missing raw file, bad parameter) are recorded in
    ``node.error`` (and the key of it and its descendants left None) so that ``status`` can
    still show the rest; ``run`` refuses a plan with errors. ``hasher`` / ``imports``: the
    memos of raw file hashes and of the stage sources' imports kept between processes.
    """
    order = check_registry(reg)
    by = {s.name: s for s in order}
    if until is not None and until not in by:
        raise PlanError(f"--until {until}: no such stage (known: {', '.join(by)})")
    graph = closure(reg, recipe, targets)
    if until is not None:
        keep = {nid for nid in graph if nid[0] == until}
        if not keep:
            raise PlanError(f"--until {until}: that stage is not part of this run")
        todo = list(keep)
        while todo:
            for s, us in graph[todo.pop()].items():
                for u in us:
                    if (s, u) not in keep:
                        keep.add((s, u))
                        todo.append((s, u))
        graph = {k: v for k, v in graph.items() if k in keep}
    hasher = hasher or FileHasher()
    rank = {s.name: i for i, s in enumerate(order)}
    ids = sorted(graph, key=lambda nid: (rank[nid[0]], nid[1]))
    nodes: dict[NodeId, Node] = {}
    sources: dict[str, str] = {}
    params: dict[str, tuple[Any, Any, str]] = {}
    for nid in ids:
        st = by[nid[0]]
        node = Node(stage=st, unit=nid[1], upstream=graph[nid])
        nodes[nid] = node
        if st.name not in params:
            where = f"{recipe_path}: stages.{st.name}"
            try:
                params[st.name] = (*validate_params(st, reg.stage_params(recipe, st.name), where), "")
            except PlanError as e:
                params[st.name] = (None, None, str(e))
        node.params, node.params_canon, perr = params[st.name]
        if perr:
            node.error = perr
            continue
        bad_up = [u for u in node.upstream_ids() if nodes[u].key is None]
        if bad_up:
            node.error = f"upstream {bad_up[0][0]} [{bad_up[0][1]}] has no key"
            continue
        try:
            node.recipe_view = recipe_view_tree(reg, recipe, st, node.unit)
            node.raw = dict(st.raw_inputs(recipe, node.unit)) if st.raw_inputs else {}
            for name, p in node.raw.items():
                p = Path(p)
                if not p.exists():
                    raise PlanError(f"{p}: not found (raw input {name!r} of stage "
                                    f"{st.name}, unit {node.unit})")
                node.raw_hashes[name] = hasher(p)
            if st.name not in sources:
                sources[st.name] = source_hash(st, imports)
        except (PlanError, ValueError, OSError) as e:
            node.error = str(e)
            continue
        node.upstream_keys = {s: {u: nodes[(s, u)].key for u in us}
                              for s, us in node.upstream.items()}
        node.key = digest({
            "stage": st.name, "version": st.version, "source": sources[st.name],
            "params": node.params_canon, "recipe": node.recipe_view,
            "upstream": node.upstream_keys, "raw": node.raw_hashes,
        })
    hasher.save()
    if imports is not None:
        imports.save()
    return Plan([nodes[i] for i in ids], reg.session_name(recipe))
