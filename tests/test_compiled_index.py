"""fitting.compiled's function index: a second build of the same CasADi function loads its
library without generating the C source; a changed function, a stale or corrupt entry does not
reuse a wrong library."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from fitting import compiled


def _graph(k: float = 1.0):
    x = ca.SX.sym("x", 2)
    p = ca.SX.sym("p", 2)
    return x, p, ca.vertcat(k * x[0] * p[0], ca.sin(x[1]) + p[1] * x[0] ** 2)


@pytest.fixture
def opts(tmp_path):
    o = compiled.CompileOptions(mode="compiled", cache_dir=tmp_path)
    if compiled.find_compiler(o) is None:
        pytest.skip("no C compiler")
    return o


def _no_source(monkeypatch):
    def fail(*a, **k):
        raise AssertionError("the C source was generated")
    monkeypatch.setattr(compiled, "_generate_source", fail)


def test_second_build_loads_through_the_index(opts, monkeypatch):
    f1 = compiled.build("idx", *_graph(), opts)
    index = list(opts.cache_dir.glob("idx_*.fn"))
    assert len(index) == 1 and index[0].read_text() == f1.library.name
    _no_source(monkeypatch)
    f2 = compiled.build("idx", *_graph(), opts)  # a new SX graph, the same function
    assert f2.compiled and f2.library == f1.library
    x, p = np.array([0.3, -0.7]), np.array([2.0, 0.5])
    r1, j1 = (a.copy() for a in f1(x, p))
    r2, j2 = f2(x, p)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(j1, j2)
    np.testing.assert_array_equal(f1.rows, f2.rows)
    np.testing.assert_array_equal(f1.cols, f2.cols)


def test_another_function_or_flags_do_not_hit_the_index(opts, monkeypatch):
    f1 = compiled.build("idx", *_graph(1.0), opts)
    f2 = compiled.build("idx", *_graph(3.0), opts)  # another constant: another library
    assert f2.library != f1.library
    x, p = np.array([0.3, -0.7]), np.array([2.0, 0.5])
    assert f2(x, p)[0][0] == pytest.approx(3 * 0.3 * 2.0)
    k1 = compiled.function_key(f1.func, "gcc", ("-O1",))
    assert k1 is not None and k1 != compiled.function_key(f1.func, "gcc", ("-O2",))
    assert k1 != compiled.function_key(f1.func, "clang", ("-O1",))
    assert k1 != compiled.function_key(f2.func, "gcc", ("-O1",))


def test_stale_or_corrupt_entries_rebuild(opts):
    f1 = compiled.build("idx", *_graph(), opts)
    lib = f1.library
    index = next(opts.cache_dir.glob("idx_*.fn"))
    lib.unlink()  # the index names a library that is gone: built again, same name
    f2 = compiled.build("idx", *_graph(), opts)
    assert f2.library == lib and lib.exists()
    index.write_text("../elsewhere.so")  # an index outside the folder is not followed
    assert compiled._indexed_library(opts.cache_dir, "idx", index.stem.split("_", 1)[1]) is None
    f3 = compiled.build("idx", *_graph(), opts)
    assert f3.library == lib and index.read_text() == lib.name
    other = opts.cache_dir / "corrupt"  # a corrupt library behind a valid index: rebuilt
    other.mkdir()
    (other / lib.name).write_bytes(b"not a shared library")
    (other / index.name).write_text(lib.name)
    f4 = compiled.build("idx", *_graph(), compiled.CompileOptions(mode="compiled",
                                                                  cache_dir=other))
    assert f4.compiled and f4.library == other / lib.name
    assert f4.library.stat().st_size > 100
    x, p = np.array([0.3, -0.7]), np.array([2.0, 0.5])
    np.testing.assert_array_equal(f4(x, p)[0], f1(x, p)[0])


def test_native_tuning_keys_the_library_by_the_host_cpu(opts, monkeypatch, tmp_path):
    """-march=native is in the default flags; the host's resolved target joins the key (a
    cache shared with a machine of another CPU never hands it this library), and a compiler
    that rejects -march=native compiles without it."""
    assert compiled.NATIVE in compiled.CompileOptions().flags
    gcc = compiled.find_compiler(opts)
    target = compiled.native_target(gcc)
    flags, key = compiled.effective_flags(gcc, ("-O2", compiled.NATIVE))
    if target is None:  # this compiler rejects -march=native: dropped, key without it
        assert flags == ("-O2",) and key == "-O2"
    else:
        assert flags == ("-O2", compiled.NATIVE) and target in key and "/" not in target
    f1 = compiled.build("idx", *_graph(), opts)
    # the same function on a CPU the compiler resolves differently: another library
    monkeypatch.setattr(compiled, "native_target", lambda c: "-march=some-other-cpu -mno-avx")
    f2 = compiled.build("idx", *_graph(), opts)
    assert f2.compiled and f2.library != f1.library
    x, p = np.array([0.3, -0.7]), np.array([2.0, 0.5])
    np.testing.assert_allclose(f2(x, p)[0], f1(x, p)[0], rtol=1e-14)
    assert compiled.effective_flags(gcc, ("-O1",)) == (("-O1",), "-O1")  # untouched without it
    # a compiler that rejects -march=native (it exits 1): the flag is dropped, not fatal
    monkeypatch.undo()
    fake = tmp_path / "cc-no-native"
    fake.write_text("#!/bin/sh\nfor a in \"$@\"; do [ \"$a\" = -march=native ] && exit 1; done\n"
                    f"exec {gcc} \"$@\"\n")
    fake.chmod(0o755)
    assert compiled.native_target(str(fake)) is None
    assert compiled.effective_flags(str(fake), ("-O1", compiled.NATIVE)) == (("-O1",), "-O1")
    f3 = compiled.build("idx", *_graph(), compiled.CompileOptions(
        mode="compiled", cache_dir=tmp_path / "plain", compiler=str(fake),
        flags=("-O1", compiled.NATIVE)))
    assert f3.compiled
    np.testing.assert_allclose(f3(x, p)[0], f1(x, p)[0], rtol=1e-14)
