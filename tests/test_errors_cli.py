"""Issue #26 "Errors": bad data inside a stage ends the CLI with exit code 2 and one line naming
file, field and frame (serial and Dask), a bug keeps exit 1 and its traceback; the Makefile hands
every user variable to the commands verbatim, never through the shell."""
from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import toy_registry

from formats.errors import InputError
from pipeline import cli
from pipeline.engine import is_input_error

REPO = Path(__file__).resolve().parents[1]

# The toy domain whose ``detect`` reads its numbers like a format reader: a word that is not a
# number is bad data (formats.errors.InputError naming file, field and frame).
BAD_DATA_REGISTRY = '''
import dataclasses, sys
from pathlib import Path
sys.path[:0] = [{repo!r}, {tests!r}]
import toy_registry as T
from formats.errors import InputError


def run_detect(ctx):
    words = Path(ctx.raw["values"]).read_text().split()
    ctx.out.save_json("partial", {{"half": True}})  # half-written when the bad value comes
    for i, w in enumerate(words):
        try:
            float(w)
        except ValueError:
            raise InputError(ctx.raw["values"], "values", f"not a number: {{w!r}}", frame=i) from None
    T.run_detect(ctx)


STAGES = tuple(dataclasses.replace(s, func=run_detect) if s.name == "detect" else s
               for s in T.STAGES)


def registry():
    return dataclasses.replace(T.registry(), stages=STAGES)
'''


def _bad_data(tmp: Path, n_seq: int = 2) -> tuple[Path, Path]:
    """A toy recipe whose sequence g/x has a bad value at frame 1, and its registry file."""
    recipe = toy_registry.write_toy(tmp, n_seq=n_seq)
    (tmp / "x.txt").write_text("1 abc 3\n")
    reg = tmp / "bad_registry.py"
    reg.write_text(BAD_DATA_REGISTRY.format(repo=str(REPO), tests=str(REPO / "tests")))
    return recipe, reg


def _cli(recipe: Path, reg: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", *args, "--recipe", str(recipe),
                           "--registry", str(reg), "--outputs", str(recipe.parent / "outputs")],
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True,
                          text=True, timeout=120)


def test_input_error_is_bad_data_by_convention_and_pickles():
    e = InputError("data/x.c3d", "POINT:DATA", "NaN coordinates", frame=7)
    assert is_input_error(e) and not is_input_error(ValueError("x"))
    assert not is_input_error(RuntimeError("a bug"))
    back = pickle.loads(pickle.dumps(e))  # through a worker pool or a Dask result
    assert type(back) is InputError and str(back) == str(e) == \
        "data/x.c3d: POINT:DATA [frame 7]: NaN coordinates"
    assert (back.file, back.field, back.frame) == ("data/x.c3d", "POINT:DATA", 7)


def test_bad_data_in_a_stage_exits_2_with_one_line_and_no_artifact(tmp_path):
    recipe, reg = _bad_data(tmp_path)
    r = _cli(recipe, reg, "sequence", "g/x", "g/y")
    want = f"{tmp_path / 'x.txt'}: values [frame 1]: not a number: 'abc'"
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert f"error: {want}" in r.stderr.splitlines()
    assert any(ln.split()[:2] == ["detect", "g/x"] and ln.endswith(want)
               for ln in r.stderr.splitlines()), r.stderr  # the failures table
    assert "full tracebacks" not in r.stderr
    unit = tmp_path / "outputs" / "toy" / "g" / "x"
    assert not (unit / "detect").exists() and not list(unit.glob(".tmp-*"))
    assert not list(unit.rglob("manifest.json"))  # fit, report: skipped, nothing complete
    assert (tmp_path / "outputs" / "toy" / "g" / "y" / "report" / "manifest.json").exists()
    assert not (tmp_path / "outputs" / "toy" / ".failures").exists()


def test_a_bug_keeps_exit_1_and_its_traceback_even_beside_bad_data(tmp_path):
    recipe, reg = _bad_data(tmp_path)
    recipe.write_text(recipe.read_text().replace("stages: {}", "stages: {fit: {peek: true}}"))
    r = _cli(recipe, reg, "sequence", "g/x", "g/y")  # g/x: bad data; g/y: an UndeclaredRead bug
    assert r.returncode == 1, r.stderr
    assert "Traceback" in r.stderr and "UndeclaredRead" in r.stderr
    assert "not a number: 'abc'" in r.stderr
    assert "full tracebacks:" in r.stderr


def test_bad_data_on_dask_ends_with_exit_2_and_the_line_in_the_table(tmp_path):
    pytest.importorskip("distributed")
    recipe, reg = _bad_data(tmp_path, n_seq=1)
    log: list[str] = []
    code = cli.main(["release", "--recipe", str(recipe), "--registry", str(reg), "--outputs",
                     str(tmp_path / "outputs"), "--executor", "dask", "--workers", "1"],
                    log=log.append)
    text = "\n".join(log)
    assert code == 2, text
    want = f"{tmp_path / 'x.txt'}: values [frame 1]: not a number: 'abc'"
    table = text[text.index("1 FAILED:"):].splitlines()
    assert any(ln.split()[:2] == ["detect", "g/x"] and ln.rstrip().endswith(want) for ln in table), text
    assert "Traceback" not in text
    assert not (tmp_path / "outputs" / "toy" / "g" / "x" / "detect").exists()


# -- the Makefile ------------------------------------------------------------------------------

FAKE_PY = """#!/bin/sh
# stands in for .venv/bin/python: one record of its argv per call
for a in "$@"; do printf '%s\\n' "$a"; done >> "$ARGV_FILE"
printf '%s\\n' '--end--' >> "$ARGV_FILE"
"""


def _make(tmp: Path, target: str, **vars: str) -> tuple[subprocess.CompletedProcess, list[list[str]]]:
    fake = tmp / "fake_python"
    fake.write_text(FAKE_PY)
    fake.chmod(0o755)
    argv_file = tmp / "argv.txt"
    argv_file.unlink(missing_ok=True)
    # -o setup: the real setup (the venv) is not what is tested here
    r = subprocess.run(["make", "-s", "-C", str(REPO), "-o", "setup", target, f"PY={fake}",
                        *(f"{k}={v}" for k, v in vars.items())],
                       env={**os.environ, "ARGV_FILE": str(argv_file)}, cwd=tmp,
                       capture_output=True, text=True, timeout=60)
    calls: list[list[str]] = [[]]
    for ln in (argv_file.read_text().splitlines() if argv_file.exists() else []):
        if ln == "--end--":
            calls.append([])
        else:
            calls[-1].append(ln)
    return r, calls[:-1]


@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_make_passes_variables_verbatim_and_runs_nothing_they_contain(tmp_path):
    pwned = tmp_path / "pwned"
    seq = f"x`touch {pwned}`$(touch {pwned})$(shell touch {pwned}) $$HOME;*"
    r, calls = _make(tmp_path, "sequence", SEQ=seq, RECIPE="my recipe.yaml", STAGE="fit",
                     FORCE="shape_fit *")
    assert r.returncode == 0, r.stderr
    assert not pwned.exists()
    assert calls == [["-m", "pipeline", "sequence", seq, "--recipe", "my recipe.yaml",
                      "--until", "fit", "--force", "shape_fit", "--force", "*"]]


@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_make_targets_still_build_their_commands(tmp_path):
    pwned = tmp_path / "pwned"
    r, calls = _make(tmp_path, "release", WORKERS="2", CLUSTER=f"c.yaml;touch {pwned}")
    assert r.returncode == 0, r.stderr
    assert calls == [["-m", "pipeline", "release", "--recipe", "recipes/demo.yaml", "--cluster",
                      f"c.yaml;touch {pwned}", "--workers", "2"],
                     ["-m", "evaluate.session", "--recipe", "recipes/demo.yaml"]]
    r, calls = _make(tmp_path, "loo", SEQ="g/a 1", MARKERS="RELB,RWRA", STRIDE="4")
    assert calls == [["-m", "pipeline", "sequence", "g/a 1", "--recipe", "recipes/demo.yaml",
                      "--until", "marker_loo", "--set", "marker_loo.markers=[RELB,RWRA]",
                      "--set", "marker_loo.stride=4"]]
    r, calls = _make(tmp_path, "evaluate", PRED=f"p`touch {pwned}`", GT="g t")
    assert calls == [["-m", "evaluate", f"p`touch {pwned}`", "g t"]]
    r, calls = _make(tmp_path, "studio", OUT="o u t", SEED="5", FRAMES="10")
    assert calls == [["-m", "studio", "--out", "o u t", "--seed", "5", "--frames", "10"]]
    r, calls = _make(tmp_path, "sequence")
    assert r.returncode != 0 and calls == [] and "usage: make sequence" in r.stdout
    assert not pwned.exists()
