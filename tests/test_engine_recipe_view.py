"""The recipe view: a stage declares the recipe fields it reads (``Stage.reads``), exactly those
enter its key, and it can read nothing else."""
from __future__ import annotations

import ast
import copy
import inspect
from pathlib import Path

import pytest
import toy_registry as toy
import yaml

from pipeline.engine import Engine
from pipeline.plan import PlanError, build_plan, targets_for
from pipeline.spec import RecipeView, Stage, UndeclaredRead, build_view_tree

REPO = Path(__file__).resolve().parents[1]


def _engine(recipe_path: Path, outputs: Path, reg=None) -> Engine:
    reg = reg or toy.registry()
    return Engine(reg, reg.load_recipe(recipe_path), recipe_path, outputs, log=lambda m: None)


def _statuses(report) -> dict:
    return {nid: o.status for nid, o in report.outcomes.items()}


def test_view_reads_only_declared_fields():
    v = RecipeView(build_view_tree({"sequence.fps": 50.0, "sequence.mocap": {"rate_hz": None},
                                    "cameras": ["a", "b"]}), "marker_fit")
    assert v.sequence.fps == 50.0 and v.cameras == ["a", "b"] and v.sequence.mocap.rate_hz is None
    with pytest.raises(UndeclaredRead, match=r"stage marker_fit reads recipe field 'sequence.c3d'"):
        v.sequence.c3d  # noqa: B018
    with pytest.raises(UndeclaredRead, match="'ground_plane'"):
        v.ground_plane  # noqa: B018
    with pytest.raises(AttributeError):
        v.cameras = []


def test_editing_a_declared_field_recomputes_exactly_the_stages_that_read_it(tmp_path):
    rp = toy.write_toy(tmp_path / "r")
    eng = _engine(rp, tmp_path / "out")
    first = eng.run(eng.plan("release"))
    assert not first.failed
    raw = yaml.safe_load(rp.read_text())
    seqs = list(raw["sequences"])
    raw["sequences"][seqs[0]]["gain"] = 3.0  # read by `fit` only
    rp.write_text(yaml.safe_dump(raw, sort_keys=False))
    eng = _engine(rp, tmp_path / "out")
    st = _statuses(eng.run(eng.plan("release")))
    computed = {nid for nid, s in st.items() if s == "computed"}
    assert computed == {("fit", seqs[0]), ("report", seqs[0]), ("summary", "session")}
    assert st[("detect", seqs[0])] == "hit" and st[("scale", "a")] == "hit"
    assert st[("fit", seqs[1])] == "hit"
    # the value reached the stage through the view
    eng2 = _engine(rp, tmp_path / "out")
    assert eng2.store.entry(seqs[0], "report").manifest["recipe_fields"] == {"counter": "counts.txt"}
    assert eng2.store.entry(seqs[0], "fit").manifest["recipe_fields"]["sequence"] == {"gain": 3.0}


def test_reading_an_undeclared_field_fails_the_stage(tmp_path):
    rp = toy.write_toy(tmp_path / "r", stages={"fit": {"peek": True}})
    eng = _engine(rp, tmp_path / "out")
    rep = eng.run(eng.plan("release"))
    fails = {nid: o.detail for nid, o in rep.outcomes.items() if o.status == "failed"}
    assert fails and all(nid[0] == "fit" for nid in fails)
    assert all("UndeclaredRead" in d and "'sequence.file'" in d for d in fails.values())
    assert not list((tmp_path / "out").rglob("fit/manifest.json"))  # nothing that looks complete


def test_a_read_the_registry_does_not_know_is_a_planning_error(tmp_path):
    import dataclasses

    rp = toy.write_toy(tmp_path / "r")
    reg = toy.registry()
    bad = tuple(dataclasses.replace(s, reads=s.reads + ("sequence.colour",)) if s.name == "fit" else s
                for s in reg.stages)
    reg = dataclasses.replace(reg, stages=bad)
    eng = _engine(rp, tmp_path / "out", reg)
    plan = eng.plan("release")
    problems = eng.check(plan)
    assert any("stage fit: Stage.reads names 'sequence.colour'" in p for p in problems)
    with pytest.raises(PlanError, match="sequence.colour"):
        eng.run(plan)
    assert not (tmp_path / "out" / "toy").exists() or not list((tmp_path / "out").rglob("manifest.json"))


# --------------------------------------------------------------------------- the real stages


def _real_recipe(tmp: Path, raw: dict | None = None) -> Path:
    """A two-sequence recipe of the real schema whose files are tiny placeholders (keys hash
    file contents; nothing is run)."""
    files = tmp / "files"
    files.mkdir(parents=True, exist_ok=True)
    for name in ("a.ply", "b.ply", "x.c3d", "y.c3d", "v.mp4", "cal.json", "contact.json", "m.npz"):
        (files / name).write_text(name)
    (files / "ms.json").write_text("{}")
    (files / "kp").mkdir(exist_ok=True)
    (files / "kp" / "000000_keypoints.json").write_text("{}")
    cams = ["c1", "c2", "c3"]

    def seq(wearer, partner, c3d):
        return {"markers_on": wearer, "partner": partner, "c3d": f"files/{c3d}",
                "videos": {c: "files/v.mp4" for c in cams},
                "calibration": {c: "files/cal.json" for c in cams},
                "contact": "files/contact.json", "text": "t", "fps": 50.0,
                "mocap": {"sync_offset_s": -0.1}}

    raw = raw or {"session": "view", "cameras": cams,
                  "subjects": {"sa": {"scan": "files/a.ply"}, "sb": {"scan": "files/b.ply"}},
                  "sequences": {"g/X 1": seq("sa", "sb", "x.c3d"), "g/Y 1": seq("sb", "sa", "y.c3d")},
                  "body_model": {"kind": "anny", "path": "files/m.npz"}}
    p = tmp / "r.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def _keys(recipe_path: Path) -> dict:
    import stages

    reg = stages.registry()
    recipe = reg.load_recipe(recipe_path)
    plan = build_plan(reg, recipe, recipe_path, targets_for(reg, recipe, "release"))
    errs = [n.error for n in plan.nodes if n.error and n.stage.implemented]
    assert not errs, errs
    return {n.id: n.key for n in plan.nodes if n.stage.implemented}, plan


def _markerless(seq: dict, people: list[str]) -> None:
    """Make a sequence markerless (nobody's markers: no markers_on, partner, c3d, mocap)."""
    for k in ("markers_on", "partner", "c3d", "mocap"):
        seq.pop(k, None)
    seq["people"] = people


EDITS = {  # a recipe edit for each field name a stage may declare
    "cameras": lambda r: r.__setitem__("cameras", r["cameras"][::-1]),
    "body_model.kind": lambda r: r["body_model"].__setitem__("kind", "smplx"),
    "sequence.fps": lambda r: r["sequences"]["g/X 1"].__setitem__("fps", 25.0),
    "sequence.mocap": lambda r: r["sequences"]["g/X 1"]["mocap"].__setitem__("sync_offset_s", 0.3),
    "sequence.mocap.sync_offset_s":
        lambda r: r["sequences"]["g/X 1"]["mocap"].__setitem__("sync_offset_s", 0.3),
    "sequence.mocap.rate_hz": lambda r: r["sequences"]["g/X 1"]["mocap"].__setitem__("rate_hz", 120.0),
    "sequence.markers_on": lambda r: r["sequences"]["g/X 1"].update(markers_on="sb", partner="sa"),
    "sequence.partner": lambda r: r["sequences"]["g/X 1"].update(markers_on="sb", partner="sa"),
    "sequence.has_keypoints": lambda r: r["sequences"]["g/X 1"].update(
        keypoints={c: "files/kp" for c in r["cameras"]}, keypoints_format="openpose"),
    "sequence.keypoints_format": lambda r: r["sequences"]["g/X 1"].update(
        keypoints={c: "files/kp" for c in r["cameras"]}, keypoints_format="coco"),
    "sequence.text": lambda r: r["sequences"]["g/X 1"].__setitem__("text", "another sentence"),
    "sequence.markerless": lambda r: _markerless(r["sequences"]["g/X 1"], ["sa", "sb"]),
    "sequence.people": lambda r: _markerless(r["sequences"]["g/X 1"], ["sb", "sa"]),
    "sequence.calibration_format":
        lambda r: r["sequences"]["g/X 1"].__setitem__("calibration_format", "chi3d"),
    "wearer.markerset": lambda r: r["subjects"]["sa"].__setitem__("markerset", "files/ms.json"),
    "partner_subject.markerset":
        lambda r: r["subjects"]["sb"].__setitem__("markerset", "files/ms.json"),
    "subject.markerset": lambda r: r["subjects"]["sa"].__setitem__("markerset", "files/ms.json"),
    "wearer.sex": lambda r: r["subjects"]["sa"].__setitem__("sex", "female"),
    "partner_subject.sex": lambda r: r["subjects"]["sb"].__setitem__("sex", "female"),
    "subject.sex": lambda r: r["subjects"]["sa"].__setitem__("sex", "female"),
    "subject.has_scan": lambda r: r["subjects"]["sa"].__setitem__("scan", None),
    "subject.marker_sequences": lambda r: r["sequences"]["g/X 1"].update(markers_on="sb", partner="sa"),
    "sequence.has_video": lambda r: [r["sequences"]["g/X 1"].pop(k) for k in
                                     ("videos", "calibration", "partner", "contact", "fps")],
    "wearer.label_prefix": lambda r: r["subjects"]["sa"].__setitem__("label_prefix", "A"),
    "subject.label_prefix": lambda r: r["subjects"]["sa"].__setitem__("label_prefix", "A"),
    "subject.marker_labels": lambda r: r["subjects"]["sa"].__setitem__("marker_labels",
                                                                       {"LFRM": "LFRA"}),
    "wearer.marker_labels": lambda r: r["subjects"]["sa"].__setitem__("marker_labels",
                                                                      {"LFRM": "LFRA"}),
    "subject.static_frames": lambda r: r["subjects"]["sa"].__setitem__(
        "static", [{"c3d": "files/x.c3d", "frames": [1, 2]}]),
    "ground_plane": lambda r: r.__setitem__("ground_plane", {"normal": [0, 0, 1], "offset": 0.02}),
    "ground_plane.offset": lambda r: r.__setitem__("ground_plane", {"normal": [0, 0, 1], "offset": 0.02}),
    "ground_plane.normal": lambda r: r.__setitem__("ground_plane", {"normal": [0, 1, 0], "offset": 0}),
    "session.name": lambda r: r.__setitem__("session", "another_session"),
    "session.subjects": lambda r: r["subjects"].__setitem__("sc", dict(r["subjects"]["sb"])),
    "session.sequences": lambda r: r["sequences"]["g/X 1"].__setitem__("text", "a third sentence"),
}


def _declared() -> dict[str, tuple[str, ...]]:
    import stages

    return {s.name: s.reads for s in stages.registry().stages if s.implemented}


def test_every_declared_field_of_the_real_stages_is_in_their_keys(tmp_path):
    """Each field a stage declares, edited alone, changes the key of every unit of a stage that
    reads a changed value, and of their descendants, and of nothing else."""
    import stages

    base = _real_recipe(tmp_path / "base")
    before, plan = _keys(base)
    raw0 = yaml.safe_load(base.read_text())
    names = sorted({n for r in _declared().values() for n in r})
    assert names, "no stage declares what it reads"
    reg = stages.registry()
    for name in names:
        assert name in EDITS, f"no edit in this test for the declared field {name!r}: add one"
        raw = copy.deepcopy(raw0)
        EDITS[name](raw)
        p = _real_recipe(tmp_path / name.replace(".", "_"), raw)
        # files of the edited recipe: same contents as the base ones
        after, plan2 = _keys(p)
        rec0, rec1 = reg.load_recipe(base), reg.load_recipe(p)
        seeds = set()
        for n in plan2.nodes:
            if not n.stage.implemented or n.id not in before:
                continue
            for f in n.stage.reads:
                try:
                    v0 = stages.recipe_view(rec0, n.unit, f)
                except KeyError:
                    v0 = KeyError
                if v0 != stages.recipe_view(rec1, n.unit, f):
                    seeds.add(n.id)
        # an edit of who wears the markers also rewires which subject artifacts a sequence reads
        # (and which raw files a subject's shape fit reads: raw inputs are keyed by content)
        rewired = {n.id for n in plan2.nodes if n.id in before
                   and (n.upstream != plan.by_id[n.id].upstream
                        or n.raw_hashes != plan.by_id[n.id].raw_hashes)}
        # (a sequence made marker-only loses its video stages: gone, not changed)
        expected = plan2.descendants(seeds | rewired) & set(before) & set(after)
        changed = {nid for nid in before if nid in after and before[nid] != after[nid]}
        assert seeds, f"editing {name} changed no declared value"
        assert changed == expected, (name, sorted(changed ^ expected))


def test_stage_code_reads_only_what_its_stage_declares():
    """Static check over each stage module: every ``ctx.recipe.<a>.<b>`` chain in the code is
    covered by the stage's ``reads`` (a prefix of it or an extension of it)."""
    import stages

    for st in stages.registry().stages:
        if not st.implemented:
            continue
        src = Path(inspect.getsourcefile(st.func))
        chains = set()
        for node in ast.walk(ast.parse(src.read_text())):
            if isinstance(node, ast.Attribute):
                parts = []
                cur = node
                while isinstance(cur, ast.Attribute):
                    parts.append(cur.attr)
                    cur = cur.value
                parts.reverse()
                if isinstance(cur, ast.Name) and cur.id == "ctx" and parts[:1] == ["recipe"]:
                    chains.add(".".join(parts[1:]))
        chains = {c for c in chains if c and not any(o != c and o.startswith(c + ".") for o in chains)}
        for c in chains:
            ok = any(c == r or c.startswith(r + ".") or r.startswith(c + ".") for r in st.reads)
            assert ok, f"{src.name}: reads ctx.recipe.{c}, not declared in {st.name}'s reads {st.reads}"


def test_stage_reads_names_are_known_to_the_registry(tmp_path):
    import stages

    p = _real_recipe(tmp_path)
    rec = stages.registry().load_recipe(p)
    for st in stages.registry().stages:
        unit = "sa" if st.per == "subject" else "g/X 1"
        for name in st.reads:
            stages.recipe_view(rec, unit, name)  # KeyError if unknown
    with pytest.raises(KeyError):
        stages.recipe_view(rec, "g/X 1", "sequence.c3d")  # files are raw inputs, not view fields
    with pytest.raises(KeyError):
        stages.recipe_view(rec, "sa", "sequence.fps")  # not a sequence unit


def test_stage_declaration_defaults_to_no_reads():
    assert Stage("x", None, per="sequence", implemented=False).reads == ()
