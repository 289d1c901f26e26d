"""Keying many stages parses each shared module once per source text (a cached rerun spent
most of its seconds re-parsing the same modules for every stage), and an edited module is
parsed again: its new imports count. The parsed names are kept on disk between processes
(``ImportMemo``, ``outputs/<session>/.imports.json``): a new process parses nothing that did
not change, still finds a module file added since, and a damaged memo only costs parsing."""
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
    real = P._import_names
    monkeypatch.setattr(P, "_import_names", lambda data, path, *a: parsed.append(path.name)
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


def test_the_memo_on_disk_spares_the_next_process_the_parsing(tmp_path, monkeypatch):
    _write(tmp_path, "mstages/__init__.py", "")
    _write(tmp_path, "mstages/a.py", "from mhelp import util\n\n\ndef run(ctx):\n"
           "    from mhelp import later  # not there yet\n    return later.Z\n")
    _write(tmp_path, "mhelp/__init__.py", "")
    _write(tmp_path, "mhelp/util.py", "X = 1\n")
    parsed = []
    real = P._import_names
    monkeypatch.setattr(P, "_import_names", lambda data, path, *a: parsed.append(path.name)
                        or real(data, path, *a))
    memo_file = tmp_path / "store" / ".imports.json"
    monkeypatch.setattr(P, "_IMPORTS", {})
    memo = P.ImportMemo(memo_file)
    h1 = P.source_hash(_stage(tmp_path, "mstages.a"), memo)
    assert not memo_file.exists()  # written by save(), as build_plan does at its end
    memo.save()
    first = len(parsed)
    assert first == 3 and memo_file.is_file()  # a.py, mhelp/__init__.py and util.py
    # a new process (the in-process memo empty): nothing is parsed, the same key
    monkeypatch.setattr(P, "_IMPORTS", {})
    assert P.source_hash(_stage(tmp_path, "mstages.a"), P.ImportMemo(memo_file)) == h1
    assert len(parsed) == first
    # a module file the unchanged a.py names appears: found from the remembered names
    _write(tmp_path, "mhelp/later.py", "Z = 1\n")
    monkeypatch.setattr(P, "_IMPORTS", {})
    h2 = P.source_hash(_stage(tmp_path, "mstages.a"), P.ImportMemo(memo_file))
    assert h2 != h1 and parsed.count("later.py") == 1 and parsed.count("a.py") == 1
    # without any memo the same key: the memo never changes what is hashed
    monkeypatch.setattr(P, "_IMPORTS", {})
    assert P.source_hash(_stage(tmp_path, "mstages.a")) == h2
    # a damaged memo file is ignored, and replaced at the next save
    memo_file.write_text("{not json")
    monkeypatch.setattr(P, "_IMPORTS", {})
    damaged = P.ImportMemo(memo_file)
    assert P.source_hash(_stage(tmp_path, "mstages.a"), damaged) == h2
    damaged.save()
    import json

    assert len(json.loads(memo_file.read_text())) == 4  # later.py too now


def test_the_memo_keeps_the_newest_entries(tmp_path, monkeypatch):
    monkeypatch.setattr(P.ImportMemo, "MAX_ENTRIES", 3)
    memo = P.ImportMemo(tmp_path / ".imports.json")
    for i in range(5):
        memo.names(f"import m{i}\n".encode(), tmp_path / f"m{i}.py", "")
    memo.save()
    again = P.ImportMemo(tmp_path / ".imports.json")
    kept = [again._memo.get(P.ImportMemo.key(f"import m{i}\n".encode(), "")) for i in range(5)]
    assert kept == [None, None, ["m2"], ["m3"], ["m4"]]


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
