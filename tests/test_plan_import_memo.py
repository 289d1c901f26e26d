"""Keying many stages parses each shared module once per source text (a cached rerun spent
most of its seconds re-parsing the same modules for every stage), and an edited module is
parsed again: its new imports count."""
import importlib
import sys
import textwrap

import pipeline.plan as P
from pipeline.spec import Stage


def _write(root, rel, text):
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(textwrap.dedent(text))


def _stage(root, modname):
    sys.path.insert(0, str(root))
    try:
        for m in [m for m in sys.modules if m.split(".")[0] in ("mstages", "mhelp")]:
            del sys.modules[m]
        return Stage(name=modname, func=importlib.import_module(modname).run, per="sequence")
    finally:
        sys.path.remove(str(root))


def test_shared_modules_parsed_once_and_again_when_edited(tmp_path, monkeypatch):
    _write(tmp_path, "mstages/__init__.py", "")
    for s in ("a", "b"):
        _write(tmp_path, f"mstages/{s}.py", "from mhelp import util\n\ndef run(ctx):\n    return 1\n")
    _write(tmp_path, "mhelp/__init__.py", "")
    _write(tmp_path, "mhelp/util.py", "X = 1\n")
    _write(tmp_path, "mhelp/extra.py", "Y = 1\n")
    parsed = []
    real = P._parse_imports
    monkeypatch.setattr(P, "_parse_imports", lambda data, path, *a: parsed.append(path.name)
                        or real(data, path, *a))
    monkeypatch.setattr(P, "_IMPORTS", {})
    ha = P.source_hash(_stage(tmp_path, "mstages.a"))
    P.source_hash(_stage(tmp_path, "mstages.b"))
    assert parsed.count("util.py") == 1 and parsed.count("__init__.py") == 1  # shared by a and b
    # util now imports extra: parsed again, and extra enters the key
    _write(tmp_path, "mhelp/util.py", "from mhelp import extra\nX = 1\n")
    h2 = P.source_hash(_stage(tmp_path, "mstages.a"))
    assert parsed.count("util.py") == 2 and "extra.py" in parsed and h2 != ha
    _write(tmp_path, "mhelp/extra.py", "Y = 2\n")
    assert P.source_hash(_stage(tmp_path, "mstages.a")) != h2


def test_imports_found_wherever_a_statement_can_hold_them():
    """The key follows an import in any statement body (a function, a method, if / else,
    try / except / else / finally, with, for / else, while, match), as ``ast.walk`` over every
    node finds them, and ignores the text ``import`` in strings and comments."""
    import ast

    src = textwrap.dedent('''
        import a0
        def f():
            import a1
            class C:
                from a2 import b
                def m(self):
                    import a3
        if X:
            import a4
        else:
            from . import a5
        try:
            import a6
        except ImportError:
            import a7
        else:
            import a8
        finally:
            import a9
        with ctx():
            import a10
        for i in y:
            pass
        else:
            import a11
        while False:
            import a12
        match v:
            case 1:
                import a13
        s = "import nothing"  # import nothing either
        async def g():
            async with z:
                import a14
    ''')
    tree = ast.parse(src)
    walk = sorted(ast.dump(n) for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)))
    mine = sorted(ast.dump(n) for n in P._statements(tree)
                  if isinstance(n, (ast.Import, ast.ImportFrom)))
    assert mine == walk and len(mine) == 15
