"""The package layering of docs/ARCHITECTURE.md's Packages table, enforced by AST.

The table is parsed here (so the doc and the test cannot diverge): each row names a folder and
the project packages it may import. Every ``.py`` file of each package is read by AST: imports
at any depth (also inside functions) and ``importlib.import_module("x")`` / ``__import__("x")``
with a constant. The pipeline also imports nothing of the domain at run time (subprocess check),
and ``body/`` has no import cycle between its modules.
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "ARCHITECTURE.md"
EVERYTHING = "everything"


def read_layering(doc: Path = DOC) -> dict[str, set[str] | None]:
    """{package: project packages it may import, None = everything} from the doc's Packages
    table (section ``## Packages``; column 1 the folder, column 3 the project packages)."""
    text = doc.read_text()
    m = re.search(r"^## Packages\n(.*?)(?=^## )", text, re.S | re.M)
    if m is None:
        raise AssertionError(f"{doc}: no '## Packages' section")
    rows = [r for r in m.group(1).splitlines() if r.startswith("|")]
    header = [c.strip() for c in rows[0].strip("|").split("|")]
    if header[:3] != ["folder", "what", "may import (project packages)"]:
        raise AssertionError(f"{doc}: Packages table header: unexpected columns {header}")
    out: dict[str, set[str] | None] = {}
    for r in rows[2:]:
        cells = [c.strip() for c in r.strip().strip("|").split("|")]
        folder = re.fullmatch(r"`(\w+)/`", cells[0])
        if folder is None:
            raise AssertionError(f"{doc}: Packages table: bad folder cell {cells[0]!r}")
        allowed = cells[2]
        if allowed == EVERYTHING:
            out[folder.group(1)] = None
        elif allowed == "none":
            out[folder.group(1)] = set()
        else:
            names = re.findall(r"`(\w+)`", allowed)
            if not names or re.sub(r"`\w+`|[,\s]", "", allowed):
                raise AssertionError(f"{doc}: Packages table, row {cells[0]}: cannot read {allowed!r}")
            out[folder.group(1)] = set(names)
    return out


LAYERS = read_layering()
PROJECT = set(LAYERS) | {p.name for p in REPO.iterdir() if (p / "__init__.py").is_file()}


def imports_of(path: Path) -> dict[str, int]:
    """Every absolute import of a file -> the line of its first occurrence (also inside
    functions; ``importlib.import_module``/``__import__`` with a constant string)."""
    out: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Call):
            f = node.func
            fname = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            arg = node.args[0] if node.args else None
            if fname in ("import_module", "__import__") and isinstance(arg, ast.Constant) \
                    and isinstance(arg.value, str) and not arg.value.startswith("."):
                names = [arg.value]
        for n in names:
            out.setdefault(n, node.lineno)
    return out


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every import in a file (also inside functions)."""
    return {n.split(".")[0] for n in imports_of(path)}


def violations(root: Path, package: str, allowed: set[str] | None) -> list[str]:
    """``file:line: imports X`` for each import of a project package outside ``allowed``."""
    if allowed is None:
        return []
    ok = allowed | {package}
    bad = []
    for f in sorted((root / package).rglob("*.py")):
        tops: dict[str, int] = {}
        for name, line in imports_of(f).items():
            tops.setdefault(name.split(".")[0], line)
        for top, line in sorted(tops.items()):
            if top in PROJECT and top not in ok:
                bad.append(f"{f.relative_to(root)}:{line}: imports {top}")
    return bad


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_package_imports_only_what_its_row_allows(package):
    if not (REPO / package).is_dir():
        pytest.skip(f"{package}/ does not exist yet")
    assert violations(REPO, package, LAYERS[package]) == []


def test_pipeline_sources_import_no_domain_package():
    assert LAYERS["pipeline"] == set(), f"{DOC}: the pipeline/ row must allow no project package"
    assert len(list((REPO / "pipeline").rglob("*.py"))) >= 5
    assert violations(REPO, "pipeline", set()) == []


def test_the_table_covers_every_package():
    assert {"pipeline", "formats", "body", "calib", "stages", "tests"} <= set(LAYERS)
    missing = sorted(p.name for p in REPO.iterdir() if (p / "__init__.py").is_file() and p.name not in LAYERS)
    assert missing == [], f"{DOC}: packages without a row in the Packages table: {missing}"
    for package, allowed in LAYERS.items():
        unknown = (allowed or set()) - set(LAYERS)
        assert not unknown, f"{DOC}: row {package}/ allows packages with no row: {sorted(unknown)}"


def test_the_checker_sees_imports(tmp_path):
    p = tmp_path / "probe.py"
    p.write_text("import os\nfrom body.lbs import x\ndef f():\n    import calib.camera\n"
                 "importlib.import_module('studio.render')\n__import__('fitting')\n"
                 "from . import sibling\n")
    assert imported_modules(p) == {"os", "body", "calib", "studio", "fitting"}


def test_the_checker_catches_a_forbidden_import(tmp_path):
    pkg = tmp_path / "formats"
    pkg.mkdir()
    (pkg / "ok.py").write_text("import numpy\nfrom formats.errors import InputError\n")
    (pkg / "bad.py").write_text("import numpy\n\n\ndef f():\n    from body.lbs import forward\n"
                                "    return importlib.import_module('calib.camera')\n")
    assert violations(tmp_path, "formats", LAYERS["formats"]) == [
        "formats/bad.py:5: imports body", "formats/bad.py:6: imports calib"]
    assert violations(tmp_path, "formats", {"body", "calib"}) == []
    assert violations(tmp_path, "formats", None) == []


def test_the_table_parser_rejects_an_unreadable_row(tmp_path):
    doc = tmp_path / "A.md"
    head = ("## Packages\n\n| folder | what | may import (project packages) | third-party |\n"
            "|---|---|---|---|\n")
    doc.write_text(head + "| `body/` | x | `formats`, `geometry` | numpy |\n\n## Next\n")
    assert read_layering(doc) == {"body": {"formats", "geometry"}}
    doc.write_text(head + "| `body/` | x | formats and geometry | numpy |\n\n## Next\n")
    with pytest.raises(AssertionError, match="row `body/`: cannot read"):
        read_layering(doc)


def module_graph(root: Path, package: str) -> dict[str, set[str]]:
    """{module: modules of the same package it imports} (``pkg`` = its ``__init__.py``;
    ``from pkg import name`` counts as importing ``pkg.name`` when that is a module, else
    ``pkg``; relative imports are resolved)."""
    files = {}
    for f in sorted((root / package).rglob("*.py")):
        parts = f.relative_to(root).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    graph: dict[str, set[str]] = {}
    for mod, f in files.items():
        here = mod if f.name == "__init__.py" else mod.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in files:  # a name inside a module -> the module
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    deps.add(t)
        graph[mod] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (as a path that returns to its start) or None: depth-first search."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state and (c := visit(d)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_body_modules_import_no_cycle():
    g = module_graph(REPO, "body")
    assert {"body", "body.model", "body.lbs", "body.loaders", "body.smplfamily"} <= set(g)
    assert find_cycle(g) is None
    # the data class imports no other module of body/, lbs only the data class and rotations
    assert g["body.model"] == set()
    assert g["body.lbs"] <= {"body.model", "body.rotations"}


def test_no_stage_hashes_the_test_asset_builder():
    """The engine keys a stage on the source of every module it imports (pipeline.plan's AST
    walk): the SMPL-X-from-Anny test-asset builder is not among them for any stage module, so
    editing it recomputes no stage."""
    from pipeline.plan import _local_imports

    stage_files = sorted((REPO / "stages").glob("*.py"))
    assert len(stage_files) >= 3
    seen: set[Path] = set()
    todo = [f.resolve() for f in stage_files]
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            rel = f.relative_to(REPO).with_suffix("").parts
            todo += [q.resolve() for q in _local_imports(f, REPO, ".".join(rel[:-1]))]
    hashed = {str(f.relative_to(REPO)) for f in seen}
    assert {"body/lbs.py", "body/loaders.py", "body/smplfamily.py"} <= hashed  # the walk works
    assert "body/smplx_from_anny.py" not in hashed


def test_the_cycle_finder_finds_a_cycle(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from pkg.a import x\n")
    (pkg / "a.py").write_text("def f():\n    from . import b\n")
    (pkg / "b.py").write_text("from pkg.c import y\n")
    (pkg / "c.py").write_text("import os\nfrom pkg.a import f\n")
    g = module_graph(tmp_path, "pkg")
    assert g == {"pkg": {"pkg.a"}, "pkg.a": {"pkg.b"}, "pkg.b": {"pkg.c"}, "pkg.c": {"pkg.a"}}
    assert find_cycle(g) == ["pkg.a", "pkg.b", "pkg.c", "pkg.a"]
    (pkg / "c.py").write_text("import os\n")
    assert find_cycle(module_graph(tmp_path, "pkg")) is None


def test_importing_the_engine_loads_no_domain_package():
    domain = sorted(PROJECT - {"pipeline"})
    code = ("import sys, pipeline.cli, pipeline.engine, pipeline.plan, pipeline.store;"
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({domain!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
