"""pipeline/ knows nothing of the domain: it imports none of the domain packages."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOMAIN = {"stages", "body", "calib", "formats", "fitting", "studio", "recipes", "detect", "bench"}


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every import in a file (also inside functions)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module":
            arg = node.args[0] if node.args else None
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                out.add(arg.value.split(".")[0])
    return out


def test_pipeline_sources_import_no_domain_package():
    files = sorted((REPO / "pipeline").rglob("*.py"))
    assert len(files) >= 5
    bad = {f.name: sorted(imported_modules(f) & DOMAIN) for f in files}
    assert {k: v for k, v in bad.items() if v} == {}


def test_the_checker_sees_imports(tmp_path):
    p = tmp_path / "probe.py"
    p.write_text("import os\nfrom body.lbs import x\ndef f():\n    import calib.camera\n"
                 "importlib.import_module('studio.render')\n")
    assert imported_modules(p) >= {"os", "body", "calib", "studio"}


def test_importing_the_engine_loads_no_domain_package():
    code = ("import sys, pipeline.cli, pipeline.engine, pipeline.plan, pipeline.store;"
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({sorted(DOMAIN)!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
