"""Stage ``evaluate`` (per session, after ``release``): the CHI3D benchmark of the release
against the session's ground truth, both in the CHI3D layout (``evaluate.evaluate_folders``);
the release folder comes from ``artifacts.Release`` (refused unless its re-read pass passed).

Applies only when the recipe sets ``stages.evaluate.truth``: a folder, relative to the recipe
file's folder (the studio writes its truth there: ``data/<preset>/gt``, ``studio.truth``). The
truth's files are raw inputs (one entry per CHI3D-layout file under it, keyed by content), so
a changed truth recomputes the figures. Writes

- ``evaluation.json``: the evaluator's figures (per sequence and over sequences: MPJPE,
  PA-MPJPE, pelvis translation error, MPVPE, PA-MPVPE over all and contact frames, the mesh
  the vertex metrics used, the contact-frame convention), plus per sequence
  ``frames_scored`` / ``frames_excluded`` (person-frames too): frames the release does not
  publish (``valid`` false) are excluded from the figures and counted here, never silently;
- ``evaluation.md``: the same figures as markdown tables (also logged).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from evaluate import constants as K
from pipeline.spec import Stage, StageContext
from stages import common

READS = ("body_model.kind",)

#: the sub-folders and files of a CHI3D subject folder the evaluator reads
TRUTH_PARTS = (K.JOINTS_DIR, K.ANNY_DIR, K.SMPLX_DIR, K.VERTICES_DIR, K.VALID_DIR, K.CAMERAS_DIR)
RAW_PREFIX = "truth:"


@dataclass(frozen=True)
class Options:
    """truth : the ground-truth folder in the CHI3D layout, relative to the recipe's folder."""

    truth: str = ""

    def __post_init__(self):
        object.__setattr__(self, "truth", str(self.truth or ""))


def truth_dir(recipe) -> Path:
    opts = Options(**dict(recipe.stages.get("evaluate") or {}))
    if not opts.truth:
        from formats.errors import InputError

        raise InputError(recipe.source or "<recipe>", "stages.evaluate.truth", "not set")
    p = Path(opts.truth)
    base = Path(recipe.source).resolve().parent if recipe.source else Path.cwd()
    return p if p.is_absolute() else (base / p).resolve()


def truth_inputs(root: Path) -> dict[str, Path]:
    """{``truth:<relative path>``: file} of every CHI3D-layout file under the truth folder
    (the files the evaluator may read; the studio's npz ground truth next to them is not)."""
    from formats.errors import InputError

    if not root.is_dir():
        raise InputError(root, "stages.evaluate.truth", "folder not found")
    out = {}
    for f in sorted(root.rglob("*")):
        rel = f.relative_to(root)
        if f.is_file() and (f.name == K.CONTACT_FILE or any(p in TRUTH_PARTS for p in rel.parts[:-1])):
            out[RAW_PREFIX + rel.as_posix()] = f
    if not any(k.split("/")[-2:-1] == [K.JOINTS_DIR] for k in out):
        raise InputError(root, K.JOINTS_DIR, "no joints3d_25/<action>.json under the truth folder")
    return out


def raw_inputs(recipe, unit: str) -> dict[str, Path]:  # noqa: ARG001 (one session unit)
    out = truth_inputs(truth_dir(recipe))
    if recipe.body_model.kind == "anny":
        out["body_model"] = common.body_model_file(recipe)
    return out


def _truth_root(raw: dict[str, Path]) -> Path:
    key = next(k for k in raw if k.startswith(RAW_PREFIX))
    rel = Path(key[len(RAW_PREFIX):])
    return Path(raw[key]).parents[len(rel.parts) - 1]


def exclusions(result: dict) -> dict:
    """Per sequence: frames scored and excluded (not valid in the truth or not published by
    the release), as frames and as person-frames."""
    out = {}
    for name, s in result["sequences"].items():
        out[name] = {"frames": s["frames"], "frames_scored": s["frames_scored"],
                     "frames_excluded": s["frames"] - s["frames_scored"],
                     "frames_not_published": s["frames_not_published"],
                     "frames_not_valid": s["frames_not_valid"],
                     "person_frames_scored": s["person_frames_scored"],
                     "person_frames_excluded": s["person_frames"] - s["person_frames_scored"]}
    return out


def run(ctx: StageContext) -> None:
    from artifacts import Release
    from evaluate import evaluate_folders, markdown

    release = Release.load(ctx.inputs["release"]).require_verified()
    truth = _truth_root(ctx.raw)
    result = evaluate_folders(release, truth, anny_model=ctx.raw.get("body_model"))
    result["scored"] = exclusions(result)
    table = markdown(result)
    lines = [f"{n}: {e['frames_scored']}/{e['frames']} frames scored, {e['frames_excluded']} "
             f"excluded ({e['frames_not_published']} not published, {e['frames_not_valid']} not "
             "valid in the truth)" for n, e in result["scored"].items()]
    ctx.out.save_json("evaluation", result)
    ctx.out.path("evaluation.md").write_text(table + "\n" + "\n".join(f"- {x}" for x in lines) + "\n")
    ctx.log(table)
    for x in lines:
        ctx.log(x)


STAGE = Stage(name="evaluate", func=run, per="session", upstream=("release",),
              params=Options, raw_inputs=raw_inputs, reads=READS, version="1",
              doc="the CHI3D benchmark of the release against the session's ground truth")
