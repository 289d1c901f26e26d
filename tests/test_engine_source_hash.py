"""The key follows the code a stage runs: its module and the local modules it imports."""
import importlib
import sys
import textwrap

from pipeline.plan import source_hash
from pipeline.spec import Stage


def _write(root, rel, text):
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(textwrap.dedent(text))
    return p


def _stage_from(root, modname):
    sys.path.insert(0, str(root))
    try:
        for m in [m for m in sys.modules if m.split(".")[0] in ("tstages", "thelp", "tother")]:
            del sys.modules[m]
        mod = importlib.import_module(modname)
        return Stage(name="s", func=mod.run, per="sequence")
    finally:
        sys.path.remove(str(root))


def test_source_hash_follows_transitive_local_imports(tmp_path):
    _write(tmp_path, "tstages/__init__.py", "")
    _write(tmp_path, "tstages/s.py", """
        from thelp import util
        from . import sibling
        import json

        def run(ctx):
            return util.f() + sibling.g()
    """)
    _write(tmp_path, "tstages/sibling.py", "def g():\n    return 1\n")
    _write(tmp_path, "thelp/__init__.py", "")
    _write(tmp_path, "thelp/util.py", "from thelp.deep import h\n\ndef f():\n    return h()\n")
    _write(tmp_path, "thelp/deep.py", "def h():\n    return 2\n")
    _write(tmp_path, "tother/__init__.py", "X = 1\n")
    h0 = source_hash(_stage_from(tmp_path, "tstages.s"))
    assert h0 == source_hash(_stage_from(tmp_path, "tstages.s"))  # deterministic

    # a module the stage does not import changes nothing
    _write(tmp_path, "tother/__init__.py", "X = 2\n")
    assert source_hash(_stage_from(tmp_path, "tstages.s")) == h0

    # a change two imports deep changes the key; so does a relative sibling
    _write(tmp_path, "thelp/deep.py", "def h():\n    return 3\n")
    h1 = source_hash(_stage_from(tmp_path, "tstages.s"))
    assert h1 != h0
    _write(tmp_path, "tstages/sibling.py", "def g():\n    return 5\n")
    assert source_hash(_stage_from(tmp_path, "tstages.s")) != h1
