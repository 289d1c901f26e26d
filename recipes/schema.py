"""Schema of a capture-session recipe (YAML), validated with pydantic.

A recipe names the people (subjects), the cameras, the sequences with their raw files, the
ground plane, the body model, and the parameters of each stage (``stages.<stage>``; validated
by the stage's own options class, unknown keys are errors). Relative paths resolve against
the recipe's folder. Every error names the recipe file and the field, e.g.
``recipes/s03.yaml: sequences.s03/Hug 1.c3d: file not found``.

Sequence ids are ``"<group>/<action>"``: the group is the CHI3D subject folder (``s02``), the
action has a space and a take number (``"Grab 4"``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator


class RecipeError(ValueError):
    """A recipe that can't be used; the message names the file and the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SubjectSpec(_Strict):
    """One person. ``scan``: mesh or point cloud (PLY/OBJ), or null (shape from markers).
    ``markerset``: a marker-set JSON path or a built-in name (``plug-in-gait``)."""

    scan: Path | None = None
    markerset: str = "plug-in-gait"
    sex: Literal["female", "male", "unknown"] = "unknown"


class BodyModelSpec(_Strict):
    """``kind``: ``anny`` (default, built at setup) or ``smplx``/``smplh``/``smpl`` with
    ``path`` to the licensed file (or the env var ``SMPLX_MODEL_PATH``)."""

    kind: Literal["anny", "smplx", "smplh", "smpl"] = "anny"
    path: Path | None = None


class GroundPlaneSpec(_Strict):
    """The floor: points ``x`` with ``normal . x = offset`` (metres, world z-up)."""

    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    offset: float = 0.0


class MocapSpec(_Strict):
    """Timing of the marker capture relative to the videos: the C3D's first frame is at
    ``sync_offset_s`` seconds of video time. ``rate_hz`` overrides the C3D's own rate."""

    sync_offset_s: float = 0.0
    rate_hz: float | None = None


class SequenceSpec(_Strict):
    """One recording. ``markers_on`` and ``partner`` are subject ids; ``videos`` and
    ``calibration`` are keyed by camera id; ``contact`` is a CHI3D
    ``interaction_contact_signature.json`` (keyed by action); ``keypoints`` optionally points
    at precomputed detections (OpenPose/COCO JSON folders keyed by camera)."""

    markers_on: str
    partner: str
    c3d: Path
    videos: dict[str, Path]
    calibration: dict[str, Path]
    contact: Path | None = None
    text: str = ""
    fps: float = 50.0
    mocap: MocapSpec = MocapSpec()
    keypoints: dict[str, Path] | None = None
    keypoints_format: Literal["openpose", "coco"] | None = None


class Session(_Strict):
    """A whole capture session."""

    session: str
    cameras: list[str]
    subjects: dict[str, SubjectSpec]
    sequences: dict[str, SequenceSpec]
    body_model: BodyModelSpec = BodyModelSpec()
    ground_plane: GroundPlaneSpec = GroundPlaneSpec()
    stages: dict[str, dict[str, Any]] = Field(default_factory=dict)
    source: Path | None = None  # the recipe file it was read from (set by load_recipe)

    @field_validator("sequences")
    @classmethod
    def _seq_ids(cls, v: dict[str, SequenceSpec]) -> dict[str, SequenceSpec]:
        for sid in v:
            if sid.count("/") != 1 or not all(sid.split("/")):
                raise ValueError(f"sequence id {sid!r}: expected '<group>/<action>'")
        return v

    def sequence(self, seq_id: str) -> SequenceSpec:
        if seq_id not in self.sequences:
            raise RecipeError(
                f"{self.source}: sequences: no sequence {seq_id!r} (known: {sorted(self.sequences)})"
            )
        return self.sequences[seq_id]


def _resolve_paths(obj: Any, base: Path) -> Any:
    """Return a copy of a parsed model with every relative Path made absolute against base."""
    if isinstance(obj, Path):
        return obj if obj.is_absolute() else (base / obj).resolve()
    if isinstance(obj, BaseModel):
        upd = {k: _resolve_paths(getattr(obj, k), base) for k in type(obj).model_fields}
        return obj.model_copy(update=upd)
    if isinstance(obj, dict):
        return {k: _resolve_paths(v, base) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_resolve_paths(v, base) for v in obj)
    return obj


def _check_refs(s: Session, src: Path) -> None:
    for sid, seq in s.sequences.items():
        for role in ("markers_on", "partner"):
            who = getattr(seq, role)
            if who not in s.subjects:
                raise RecipeError(f"{src}: sequences.{sid}.{role}: unknown subject {who!r}")
        for field_name in ("videos", "calibration"):
            cams = set(getattr(seq, field_name))
            if cams != set(s.cameras):
                raise RecipeError(
                    f"{src}: sequences.{sid}.{field_name}: cameras {sorted(cams)} "
                    f"do not match cameras {sorted(s.cameras)}"
                )


def load_recipe(path: str | Path) -> Session:
    """Read, validate and resolve a recipe. Raises RecipeError naming the file and field."""
    path = Path(path)
    if not path.is_file():
        raise RecipeError(f"{path}: recipe not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RecipeError(f"{path}: not valid YAML: {e}") from None
    if not isinstance(raw, dict):
        raise RecipeError(f"{path}: expected a mapping at the top level")
    try:
        s = Session.model_validate(raw)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        got = err.get("input")
        got_s = "" if isinstance(got, (dict, list)) else f", got {got!r}"
        raise RecipeError(f"{path}: {loc}: {err['msg']}{got_s}") from None
    _check_refs(s, path)
    s = _resolve_paths(s, path.resolve().parent)
    return s.model_copy(update={"source": path})
