"""evaluate.session: where a release is, its verification and the benchmark table; a missing
release or evaluation is said plainly with exit code 1."""
from __future__ import annotations

import json

from evaluate.session import summary


def _recipe(tmp_path, truth=True):
    p = tmp_path / "r.yaml"
    p.write_text("session: lab\n" + ("stages:\n  evaluate:\n    truth: gt\n" if truth else ""))
    return p


def test_missing_release_and_evaluation_are_said(tmp_path):
    rc, text = summary(_recipe(tmp_path), tmp_path / "out")
    assert rc == 1 and "No release" in text and "No evaluation" in text
    rc, text = summary(_recipe(tmp_path, truth=False), tmp_path / "out")
    assert rc == 1 and "No evaluation" not in text


def test_release_and_table_are_shown_and_json_copied(tmp_path):
    root = tmp_path / "out" / "lab" / "session"
    rel, ev = root / "release", root / "evaluate"
    rel.mkdir(parents=True), ev.mkdir(parents=True)
    (rel / "manifest.json").write_text("{}")
    (rel / "verification.json").write_text(json.dumps({"ok": False, "files_checked": 7}))
    (rel / "datasheet.json").write_text(json.dumps({"totals": {"frames": 12}}))
    (ev / "evaluation.json").write_text(json.dumps({"overall": {"all": {"mpjpe": 3.5}}}))
    (ev / "evaluation.md").write_text("| sequence | MPJPE |\n| s | 3.5 |\n")
    rc, text = summary(_recipe(tmp_path), tmp_path / "out")
    assert rc == 0 and "NOT verified: 7 files" in text and "frames 12" in text
    assert "| s | 3.5 |" in text
    assert json.loads((tmp_path / "out" / "lab" / "evaluation.json").read_text())["overall"]
