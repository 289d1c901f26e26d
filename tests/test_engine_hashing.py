"""Keys: canonical JSON, array fingerprints, file/folder hashes and their memo; store names."""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipeline.hashing import FileHasher, UnhashableError, canonical, digest
from pipeline.store import Store, StoreError


def test_digest_ignores_key_order_but_not_values_or_types():
    assert digest({"a": 1, "b": [1, 2]}) == digest({"b": [1, 2], "a": 1})
    assert digest({"a": 1}) != digest({"a": 2})
    assert digest({"a": 1}) != digest({"a": "1"})
    assert digest({"a": 1.0}) != digest({"a": 1.5})
    assert digest((1, 2)) == digest([1, 2])
    assert digest(Path("/x/y")) == digest("/x/y")


def test_arrays_are_hashed_with_dtype_and_shape():
    a = np.arange(6, dtype=np.float64)
    assert digest(a) == digest(a.copy())
    assert digest(a) != digest(a.reshape(2, 3))  # same bytes, other shape
    assert digest(a) != digest(a.astype(np.float32))
    assert digest(a) != digest(a.view(np.int64))  # same bytes, other dtype
    assert digest(a[::2]) == digest(np.ascontiguousarray(a[::2]))
    assert canonical(np.float32(1.5)) == 1.5


def test_dataclasses_and_nan_are_canonical():
    @dataclass(frozen=True)
    class Opt:
        w: float = 1.0
        names: tuple = ("a",)

    assert canonical(Opt()) == {"w": 1.0, "names": ["a"]}
    assert digest(Opt(w=2.0)) != digest(Opt())
    assert digest(float("nan")) == digest(float("nan"))
    assert digest(float("nan")) != digest(float("inf"))


def test_unhashable_values_are_errors_that_say_where():
    with pytest.raises(UnhashableError, match=r"stages.fit.cb: a function can't be hashed"):
        canonical({"cb": lambda x: x}, "stages.fit")
    with pytest.raises(UnhashableError, match="object arrays"):
        canonical(np.array([object()]))


def test_file_and_folder_hashes_and_the_stat_memo(tmp_path):
    f = tmp_path / "a.bin"
    f.write_bytes(b"hello")
    memo = tmp_path / "memo.json"
    h = FileHasher(memo)
    assert h(f) == hashlib.sha256(b"hello").hexdigest()
    h.save()
    # a new hasher trusts the memo while the stat is unchanged ...
    h2 = FileHasher(memo)
    assert h2._memo[str(f.resolve())][1] == h(f)
    # ... and re-reads when the file changes, even to the same size
    f.write_bytes(b"world")
    assert FileHasher(memo)(f) == hashlib.sha256(b"world").hexdigest()
    d = tmp_path / "dir"
    (d / "sub").mkdir(parents=True)
    (d / "sub" / "x.txt").write_text("1")
    (d / "y.txt").write_text("2")
    hd = h(d)
    (d / "y.txt").write_text("3")
    assert h(d) != hd
    (d / "y.txt").write_text("2")
    assert h(d) == hd
    os.rename(d / "y.txt", d / "z.txt")  # a renamed file changes the folder hash
    assert h(d) != hd
    memo.write_text("{broken")
    assert FileHasher(memo)(f) == hashlib.sha256(b"world").hexdigest()


@pytest.mark.parametrize("unit", ["", "/abs", "a/../b", ".hidden", "g/.x", "a//b"])
def test_store_refuses_units_that_are_not_plain_folders(tmp_path, unit):
    with pytest.raises(StoreError):
        Store(tmp_path).dir(unit, "fit")
