"""A release whose every stage is cached starts no Dask cluster (a cached `make demo` spent
~20 s starting one only to check hits); one with something to compute, or --force, does."""
from __future__ import annotations

from pathlib import Path

import pytest
import toy_registry

import pipeline.cli as cli

TOY = str(Path(toy_registry.__file__).resolve())


def _args(folder: Path, *extra: str) -> list[str]:
    return ["release", "--recipe", str(folder / "toy.yaml"), "--registry", TOY,
            "--outputs", str(folder / "outputs"), *extra]


@pytest.fixture
def dask_calls(monkeypatch):
    calls = []

    def fake(eng, plan, args, log):  # stands in for the cluster: run serially, note the call
        calls.append(args.force)
        return eng.run(plan, force=args.force)

    monkeypatch.setattr(cli, "_run_dask", fake)
    monkeypatch.delenv("PIPELINE_EXECUTOR", raising=False)
    return calls


def test_cached_release_starts_no_cluster(tmp_path, dask_calls):
    toy_registry.write_toy(tmp_path, n_seq=1)
    logs: list[str] = []
    assert cli.main(_args(tmp_path), log=logs.append) == 0  # computes: the cluster runs it
    assert len(dask_calls) == 1
    n_counts = len((tmp_path / "counts.txt").read_text().splitlines())
    logs.clear()
    assert cli.main(_args(tmp_path), log=logs.append) == 0  # all cached: no cluster
    assert len(dask_calls) == 1
    assert any("every stage is cached" in ln for ln in logs)
    assert any(ln.startswith("release: 0 computed") for ln in logs), logs
    assert len((tmp_path / "counts.txt").read_text().splitlines()) == n_counts  # nothing ran


def test_stale_or_forced_release_uses_the_cluster(tmp_path, dask_calls):
    toy_registry.write_toy(tmp_path, n_seq=1)
    assert cli.main(_args(tmp_path), log=lambda _m: None) == 0
    assert cli.main(_args(tmp_path, "--force", "detect"), log=lambda _m: None) == 0
    assert dask_calls[-1] == ["detect"]
    (tmp_path / "x.txt").write_text("7 8\n")  # a raw input changed: something to compute
    assert cli.main(_args(tmp_path), log=lambda _m: None) == 0
    assert len(dask_calls) == 3
