"""The registry of stages handed to the engine (``python -m pipeline ... --registry stages``).

``PLANNED`` lists every stage in DAG order with its granularity and upstream stages as in
``docs/ARCHITECTURE.md``. When ``stages/<name>.py`` exists its ``STAGE`` is used (the module's
declaration is the truth for ``per``/``upstream``); otherwise the stage is a placeholder with
``implemented=False`` and the CLI says plainly that it is not implemented.

This module also interprets the recipe for the engine: which units exist, which units of an
upstream stage a unit reads, where a stage's parameters are, and ``prepare`` (generate the
synthetic demo session when ``recipes/demo.yaml`` or its data are missing).
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

from pipeline.spec import Granularity, Registry, Stage
from recipes import RecipeError, Session, load_recipe, missing_files
from recipes.schema import markerset_is_file

REPO = Path(__file__).resolve().parents[1]
DEMO_RECIPE = REPO / "recipes" / "demo.yaml"

# (name, per, upstream, what it makes) in DAG order.
PLANNED: tuple[tuple[str, Granularity, tuple[str, ...], str], ...] = (
    ("capture", "sequence", (), "the capture read, unit-checked and cleaned once; the camera rig"),
    ("shape_fit", "subject", ("capture",), "body shape and marker placement per subject"),
    ("keypoints", "sequence", ("capture",), "2D body and hand keypoints per camera and frame"),
    ("rig", "sequence", ("capture", "keypoints"),
     "the camera rig refined from the person's detections (bundle adjustment with a prior to "
     "the given calibration; sequences with refine_rig)"),
    ("marker_fit", "sequence", ("capture", "shape_fit", "keypoints", "rig"),
     "pose of the subject wearing markers"),
    ("marker_loo", "sequence", ("capture", "shape_fit", "marker_fit"),
     "leave-one-out check of the marker fit"),
    ("silhouettes", "sequence", ("capture", "rig", "marker_fit"),
     "people masks from the clean plates; the partner's with the wearer rendered out"),
    ("partner_fit", "sequence", ("capture", "shape_fit", "keypoints", "rig", "marker_fit",
                                 "silhouettes"),
     "pose of the unmarked partner (2D keypoints, contact, collisions, silhouettes)"),
    ("heldout", "sequence", ("keypoints", "rig", "partner_fit"),
     "a view left out of the fit: reprojection into it against its detections, and the "
     "triangulation baseline (markerless sequences)"),
    ("convert", "sequence", ("marker_fit", "partner_fit"), "SMPL-X parameters of both"),
    ("qa", "sequence", ("capture", "shape_fit", "keypoints", "rig", "marker_fit", "partner_fit",
                        "heldout"),
     "per-frame quality flags, overlays on the four views, plots, HTML report, 3D scene"),
    ("export", "sequence", ("capture", "shape_fit", "keypoints", "rig", "marker_fit",
                            "partner_fit", "convert", "qa"),
     "CHI3D-layout files; frames whose QA flags say the fit is wrong published not valid"),
    ("release", "session", ("export", "qa"),
     "the release folder: every sequence's export, SHA-256 manifest, datasheet, re-read"),
    ("qa_index", "session", ("qa",),
     "the session's QA index page: sequences sorted by how much is flagged"),
    ("evaluate", "session", ("release",),
     "the CHI3D benchmark of the release against the session's ground truth"),
)


def _stage(name: str, per: Granularity, upstream: tuple[str, ...], doc: str) -> Stage:
    """The module's STAGE if ``stages/<name>.py`` exists and defines one, else a placeholder
    (a module still being written, without ``STAGE``, counts as not implemented; a module
    that fails to import is an error)."""
    placeholder = Stage(name=name, func=None, per=per, upstream=upstream, implemented=False,
                        doc=doc)
    if importlib.util.find_spec(f"stages.{name}") is None:
        return placeholder
    mod = importlib.import_module(f"stages.{name}")
    st = getattr(mod, "STAGE", None)
    if st is None:
        print(f"[stages] stages/{name}.py defines no STAGE yet: {name} counts as not implemented",
              file=sys.stderr, flush=True)
        return placeholder
    if not isinstance(st, Stage):
        raise ImportError(f"stages/{name}.py: STAGE is a {type(st).__name__}, not a Stage")
    if st.name != name:
        raise ImportError(f"stages/{name}.py: STAGE.name is {st.name!r}, expected {name!r}")
    return st


def stages() -> tuple[Stage, ...]:
    """Every planned stage: implemented ones from their modules, the rest as placeholders."""
    return tuple(_stage(*p) for p in PLANNED)


def units(recipe: Session, per: Granularity) -> list[str]:
    """Subject ids, sequence ids (``"<group>/<action>"``) or ``["session"]``."""
    if per == "subject":
        return list(recipe.subjects)
    if per == "sequence":
        return list(recipe.sequences)
    return ["session"]


def make_upstream_units(all_stages: tuple[Stage, ...]):
    per = {s.name: s.per for s in all_stages}

    def upstream_units(recipe: Session, stage: str, unit: str, upstream: str) -> list[str]:
        """Which units of ``upstream`` the ``unit`` of ``stage`` reads: a sequence reads the
        per-subject artifacts of its ``markers_on`` subject, then its ``partner``; a subject
        reads the sequences it takes part in; the session reads every unit."""
        mine, theirs = per[stage], per[upstream]
        if mine == theirs:
            return [unit]
        if mine == "session":
            return units(recipe, theirs)
        if theirs == "session":
            return ["session"]
        if mine == "sequence":  # theirs == "subject": person 0 first (markerless: ``people``)
            return recipe.sequence(unit).persons
        if upstream == "capture":  # a subject reads the captures of the sequences it wears
            return [q for q, s in recipe.sequences.items() if s.markers_on == unit]
        return recipe.sequences_of(unit)  # a subject reading sequences

    return upstream_units


def _subject_fields(recipe: Session, sid: str | None) -> dict:
    if sid is None:  # a marker-only sequence has no partner
        return {"markerset": None, "sex": None, "label_prefix": None, "marker_labels": {}}
    sub = recipe.subjects[sid]
    return {"markerset": "file" if markerset_is_file(sub.markerset) else sub.markerset,
            "sex": sub.sex, "label_prefix": sub.label_prefix,
            "marker_labels": dict(sub.marker_labels)}


#: stages that need the videos (and for partner_fit the partner) of a sequence
VIDEO_STAGES = ("keypoints", "partner_fit", "heldout")
#: stages of the marker wearer: not in the DAG of a markerless sequence
MARKER_STAGES = ("capture", "marker_fit", "marker_loo")


def applies(recipe: Session, stage: str, unit: str) -> bool:
    """Whether ``stage`` runs for ``unit``: the video stages only on sequences recorded with
    video (``partner_fit`` also needs a partner, or a markerless sequence; ``heldout`` only on
    markerless sequences); ``rig`` only on sequences with ``refine_rig``; the
    marker stages (``capture``, ``marker_fit``, ``marker_loo``) not on a markerless sequence; ``evaluate`` only when the recipe names a
    ground-truth folder (``stages.evaluate.truth``); everything else always."""
    if stage == "evaluate":
        return bool((recipe.stages.get("evaluate") or {}).get("truth"))
    if unit not in recipe.sequences:
        return True
    seq = recipe.sequences[unit]
    if stage in MARKER_STAGES:
        return not seq.markerless
    if stage == "rig":  # the rig refined from the people: only when the recipe asks
        return seq.refine_rig and seq.has_video
    if stage == "silhouettes":  # the partner's outline (L_sil): a wearer and a partner on video
        return seq.has_video and not seq.markerless and seq.partner is not None
    if stage not in VIDEO_STAGES:
        return True
    if stage == "heldout":  # the honest figure where no markers give one (marker_loo does)
        return seq.has_video and seq.markerless
    return seq.has_video and (stage == "keypoints" or seq.markerless or seq.partner is not None)


def recipe_view(recipe: Session, unit: str, name: str):
    """The value of the recipe field ``name`` (an entry of a stage's ``Stage.reads``) for
    ``unit``, as plain data. Names (docs/ARCHITECTURE.md, "The recipe view"):

    - ``cameras``: camera ids in recipe order; ``body_model.kind``;
    - per sequence: ``sequence.<fps | mocap | mocap.sync_offset_s | mocap.rate_hz | markers_on |
      partner | markerless | people | text | keypoints_format | calibration_format |
      has_keypoints | has_video>`` (a markerless sequence: ``markers_on`` / ``partner`` are
      ``people[0]`` / ``people[1]``, the people's slots, and ``markerless`` is true),
      ``wearer.<markerset | sex | label_prefix | marker_labels>`` and ``partner_subject.<...>`` (the subjects
      of ``markers_on`` / ``partner``; all None without a partner);
    - per subject: ``subject.<markerset | sex | label_prefix | marker_labels | has_scan | marker_sequences |
      static_frames>`` (``static_frames``: each static trial's ``[first, last]`` or None);
    - ``ground_plane.<normal | offset>`` (or ``ground_plane``);
    - for the session: ``session.<name | subjects | sequences>``, ``sequences`` mapping each
      sequence id to its ``group``, ``action``, ``markers_on``, ``partner``, ``fps``, ``text``
      and ``has_video``.

    Files are never part of the view (they are raw inputs, keyed by content): a marker set
    given as a ``.json`` file reads as ``"file"``. KeyError for any other name."""
    parts = name.split(".")
    head, rest = parts[0], parts[1:]
    if name == "cameras":
        return list(recipe.cameras)
    if name == "body_model.kind":
        return recipe.body_model.kind
    if head == "ground_plane":
        tree = {"normal": list(recipe.ground_plane.normal), "offset": recipe.ground_plane.offset}
        return _pick(tree, rest, name)
    if head in ("sequence", "wearer", "partner_subject"):
        if unit not in recipe.sequences:
            raise KeyError(f"{name}: unit {unit!r} is not a sequence")
        seq = recipe.sequences[unit]
        persons = seq.persons
        if head == "sequence":
            # markerless: person 0 and 1 of ``people`` read as markers_on / partner (the roles
            # of the people's slots), with ``markerless`` saying nobody wears markers
            tree = {"fps": seq.fps, "markers_on": persons[0] if persons else None,
                    "partner": persons[1] if len(persons) > 1 else None,
                    "markerless": seq.markerless, "people": persons,
                    "text": seq.text, "keypoints_format": seq.keypoints_format,
                    "calibration_format": seq.calibration_format,
                    "has_keypoints": bool(seq.keypoints), "has_video": seq.has_video,
                    "mocap": {"sync_offset_s": seq.mocap.sync_offset_s,
                              "rate_hz": seq.mocap.rate_hz}}
        else:
            i = 0 if head == "wearer" else 1
            tree = _subject_fields(recipe, persons[i] if len(persons) > i else None)
        return _pick(tree, rest, name)
    if head == "session":
        tree = {"name": recipe.session, "subjects": list(recipe.subjects),
                "sequences": {q: {"group": q.split("/", 1)[0], "action": q.split("/", 1)[-1],
                                  "markers_on": (s.persons or [None])[0],
                                  "partner": s.persons[1] if len(s.persons) > 1 else None,
                                  "markerless": s.markerless,
                                  "fps": s.fps, "text": s.text, "has_video": s.has_video}
                              for q, s in recipe.sequences.items()}}
        return _pick(tree, rest, name)
    if head == "subject":
        if unit not in recipe.subjects:
            raise KeyError(f"{name}: unit {unit!r} is not a subject")
        sub = recipe.subjects[unit]
        tree = {**_subject_fields(recipe, unit), "has_scan": sub.scan is not None,
                "marker_sequences": [q for q in recipe.sequences_of(unit)
                                     if recipe.sequences[q].markers_on == unit],
                "static_frames": [list(t.frames) if t.frames is not None else None
                                  for t in sub.static]}
        return _pick(tree, rest, name)
    raise KeyError(name)


def _pick(tree: dict, rest: list[str], name: str):
    v = tree
    for p in rest:
        if not isinstance(v, dict) or p not in v:
            raise KeyError(name)
        v = v[p]
    return v


def view_for(recipe: Session, stage: str, unit: str):
    """The :class:`pipeline.spec.RecipeView` the engine hands ``stage`` for ``unit`` (for tests
    and tools that call a stage's ``run`` directly)."""
    from pipeline.plan import recipe_view_tree
    from pipeline.spec import RecipeView

    reg = registry()
    st = next(s for s in reg.stages if s.name == stage)
    return RecipeView(recipe_view_tree(reg, recipe, st, unit), stage)


def stage_params(recipe: Session, stage: str) -> dict:
    """The recipe's ``stages.<stage>`` section (empty when absent)."""
    return dict(recipe.stages.get(stage) or {})


def load(path: Path) -> Session:
    """``recipes.load_recipe`` plus: every ``stages.<name>`` section names a planned stage."""
    return load_recipe(path, stages=[p[0] for p in PLANNED])  # every problem in one RecipeError


def prepare(recipe_path: Path, demo_recipe: Path = DEMO_RECIPE, repo: Path = REPO) -> None:
    """Generate the synthetic demo session when ``recipe_path`` is the demo recipe
    (``recipes/demo.yaml``) and it or any file it names is missing, by running
    ``python -m studio --recipe-preset demo`` in ``repo``. Any other recipe: nothing to do.
    Raises RuntimeError if the studio fails or leaves files missing."""
    if Path(recipe_path).resolve() != Path(demo_recipe).resolve():
        return
    if not _demo_missing(demo_recipe):
        return
    if not (repo / "studio" / "__main__.py").is_file():
        print("[demo] the demo data is missing and the synthetic studio (python -m studio) is "
              "not written yet, so it can't be generated", file=sys.stderr, flush=True)
        return
    cmd = [sys.executable, "-m", "studio", "--recipe-preset", "demo"]
    print(f"[demo] generating the synthetic demo session: {' '.join(cmd[1:])}", file=sys.stderr,
          flush=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(repo)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    done = subprocess.run(cmd, cwd=repo, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"`{' '.join(cmd[1:])}` failed with exit code {done.returncode}")
    still = _demo_missing(demo_recipe)
    if still:
        raise RuntimeError(f"`{' '.join(cmd[1:])}` ran but left {still}")


def _demo_missing(demo_recipe: Path) -> str:
    """What is missing of the demo session ("" when complete)."""
    if not Path(demo_recipe).is_file():
        return f"{demo_recipe} missing"
    try:
        missing = missing_files(load_recipe(demo_recipe, check_files=False))
    except RecipeError as e:
        return f"an unreadable recipe ({e})"
    return f"{len(missing)} files missing, e.g. {missing[0][1]}" if missing else ""


def check(recipe: Session, recipe_path: Path, sequences: list[str] | None = None) -> list[str]:
    """Problems of the recipe the schema cannot see, one message per problem naming the file and
    the field, found before any stage runs: each sequence's videos must be readable and run at
    the recipe's ``fps`` (``stages.common.check_videos``; videos of different lengths are cut to
    the shortest, with a warning, by the keypoints stage). Stage options are
    validated by the engine when it plans (every stage's, before anything runs)."""
    from stages import common

    errors: list[str] = []
    for q in sequences if sequences is not None else list(recipe.sequences):
        seq = recipe.sequences[q]
        if seq.videos:
            errors += [f"{recipe_path}: sequences.{q}.videos: {m}"
                       for m in common.check_videos([seq.videos[c] for c in recipe.cameras],
                                                    seq.fps)]
    return errors


def registry() -> Registry:
    """The registry the engine loads by name."""
    st = stages()
    return Registry(stages=st, load_recipe=load, session_name=lambda r: r.session, units=units,
                    upstream_units=make_upstream_units(st), stage_params=stage_params,
                    prepare=prepare, recipe_view=recipe_view, check=check, applies=applies)
