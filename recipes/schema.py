"""Schema of a capture-session recipe (YAML), validated with pydantic.

A recipe names the people (subjects), the cameras, the sequences with their raw files, the
ground plane, the body model, and the parameters of each stage (``stages.<stage>``; validated
by the stage's own options class, unknown keys are errors). Relative paths resolve against
the recipe's folder. Every error names the recipe file and the field, e.g.
``recipes/s03.yaml: sequences.s03/Hug 1.c3d: file not found``.

Sequence ids are ``"<group>/<action>"``: the group is the CHI3D subject folder (``s02``), the
action has a space and a take number (``"Grab 4"``). The session name, subject ids, groups and
actions become folder and file names, so each must fit the file system's ``NAME_MAX`` (of the
recipe's folder) with :data:`NAME_RESERVE` bytes to spare.

:func:`load_recipe` reports every problem at once (schema errors of every field, unknown
subjects and cameras, missing files, unknown stages, names too long), one line each, and hands
the part it could still check (``RecipeError.recipe``) to the engine's later checks.
"""
from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

# Numbers a capture can have: finite, and positive where a rate or a length is meant.
Finite = Annotated[float, Field(allow_inf_nan=False)]
Rate = Annotated[float, Field(gt=0, le=100_000, allow_inf_nan=False)]


# Bytes the pipeline adds to a name in the longest file name it makes of it (the release's
# ``<action>.json`` written through ``<action>.json.tmp``: 9), with room to spare.
NAME_RESERVE = 16
NAME_MAX_DEFAULT = 255  # when the file system does not say (os.pathconf)
_PLACEHOLDER = {"session": "invalid-session", "subjects": {}, "sequences": {}}


class RecipeError(ValueError):
    """A recipe that can't be used; the message names the file and the field, one line per
    problem (``problems``, the same lines).

    ``recipe`` : None, or the part of the recipe that could still be checked (fields with schema
        errors fall back to their defaults; a subject or sequence that can't be kept is left
        out) so that the engine's checks (stage options, raw files, videos) report their
        problems in the same run. Only for checking: a recipe with problems never runs.
    """

    def __init__(self, message: str | list[str], recipe: "Session | None" = None):
        lines = [message] if isinstance(message, str) else list(message)
        self.problems = [ln for m in lines for ln in str(m).splitlines() if ln.strip()]
        self.recipe = recipe
        super().__init__("\n".join(self.problems))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StaticTrial(_Strict):
    """A capture of the subject used only to place the markers and fit the shape (a static
    pose or a range-of-motion trial). ``frames``: ``[first, last]`` in the C3D's own frame
    numbers (1-based and inclusive, as Vicon Nexus shows them), or null for the whole file."""

    c3d: Path
    frames: tuple[int, int] | None = None

    @field_validator("frames")
    @classmethod
    def _range(cls, v):
        if v is not None and not 1 <= v[0] <= v[1]:
            raise ValueError(f"expected [first, last] with 1 <= first <= last, got {list(v)}")
        return v


#: a subject's ``markerset`` is a file when it ends in one of these (``markerset/2`` YAML or
#: JSON of landmarks, or ``markerset/1`` JSON: ``body.landmarks.load_markerset``), else one of
#: the built-in sets (``body.markers.BUILTIN_NAMES``)
MARKERSET_SUFFIXES = (".json", ".yaml", ".yml")
BUILTIN_MARKERSETS = ("plug-in-gait", "cmu", "plug-in-gait-lower")


def markerset_is_file(markerset: str) -> bool:
    """Whether a subject's ``markerset`` names a file (see ``MARKERSET_SUFFIXES``)."""
    return str(markerset).lower().endswith(MARKERSET_SUFFIXES)


class SubjectSpec(_Strict):
    """One person. ``scan``: mesh or point cloud (PLY/OBJ), or null (shape from markers).
    ``markerset``: a marker-set file (``.yaml``/``.yml``/``.json``: ``markerset/2`` markers by
    anatomical landmark, or ``markerset/1``) or a built-in name (``plug-in-gait``, ``cmu``,
    ``plug-in-gait-lower``).
    ``label_prefix``: the subject name the C3D files put before the marker labels
    (``Derrick`` for ``Derrick:LFHD``); needed when a file holds several prefixed subjects.
    ``marker_labels``: the lab's label of a marker set's marker where it differs
    (``{LFRM: LFRA}``: our LFRM is labelled LFRA in the C3D files). ``static``: static or range-of-motion trials for ``shape_fit``."""

    scan: Path | None = None
    markerset: str = "plug-in-gait"
    sex: Literal["female", "male", "unknown"] = "unknown"
    label_prefix: str | None = None
    marker_labels: dict[str, str] = Field(default_factory=dict)
    static: list[StaticTrial] = Field(default_factory=list)

    @field_validator("markerset")
    @classmethod
    def _markerset(cls, v):
        if not markerset_is_file(v) and v not in BUILTIN_MARKERSETS:
            raise ValueError(f"{v!r}: expected a built-in set ({', '.join(BUILTIN_MARKERSETS)}) "
                             f"or a marker-set file ending in {', '.join(MARKERSET_SUFFIXES)}")
        return v


class BodyModelSpec(_Strict):
    """``kind``: ``anny`` (default, built at setup) or ``smplx``/``smplh``/``smpl`` with
    ``path`` to the licensed file (or the env var ``SMPLX_MODEL_PATH``)."""

    kind: Literal["anny", "smplx", "smplh", "smpl"] = "anny"
    path: Path | None = None


class GroundPlaneSpec(_Strict):
    """The floor: points ``x`` with ``normal . x = offset`` (metres, world z-up)."""

    normal: tuple[Finite, Finite, Finite] = (0.0, 0.0, 1.0)
    offset: Finite = 0.0

    @field_validator("normal")
    @classmethod
    def _unit_normal(cls, v):
        n = sum(c * c for c in v) ** 0.5
        if not 0.99 < n < 1.01:
            raise ValueError(f"must be a unit vector, got length {n:.3g}")
        return v


class MocapSpec(_Strict):
    """Timing of the marker capture relative to the videos: mocap time 0 (the C3D's sample
    numbering, sample ``i`` at ``(first_frame + i) / rate``) is at ``sync_offset_s`` seconds of
    video time, so video frame ``f`` is at mocap time ``f / fps - sync_offset_s``.
    ``rate_hz`` overrides the C3D's own rate."""

    sync_offset_s: Annotated[float, Field(ge=-3600, le=3600, allow_inf_nan=False)] = 0.0
    rate_hz: Rate | None = None


#: Calibration file formats (``calib.io.CALIBRATION_FORMATS``; recipes import no calib).
CalibrationFormat = Literal["chi3d", "vicon", "qualisys", "pose2sim", "easymocap", "opencv"]


class SequenceSpec(_Strict):
    """One recording. ``markers_on`` and ``partner`` are subject ids; ``videos`` and
    ``calibration`` are keyed by camera id (a file holding that camera: CHI3D camera JSON,
    Vicon ``.xcp``, Qualisys ``.qca.txt``, Pose2Sim / anipose / caliscope ``.toml``, EasyMocap
    ``intri.yml`` (its ``extri.yml`` beside it) or OpenCV FileStorage; a file of several
    cameras may be given for each, the camera is found by its id: ``calib.io.read_camera``);
    ``calibration_format`` names the files' format (null: from the suffix); ``contact`` is a CHI3D
    ``interaction_contact_signature.json`` (keyed by action); ``keypoints`` optionally points
    at precomputed detections (OpenPose/COCO JSON folders keyed by camera); ``clean_plates``
    optionally names, per camera, a video of the empty room (the clean plate labs record with
    the cameras and lights as in the take; any subset of the cameras): the people's masks
    are subtracted from it (stage ``silhouettes``; a camera without one: OpenCV's MOG2).
    ``refine_rig: true`` refines the cameras from the people's detections before anything is
    fitted (stage ``rig``, options in ``stages.rig``; needs ``videos`` and ``calibration``).

    A marker-only sequence has just ``markers_on`` and ``c3d``: no ``partner``, ``videos`` or
    ``calibration``; it is fitted at the C3D's own rate (or ``mocap.rate_hz``) over its whole
    length. ``fps``: the video rate; null means the videos' own rate, or the capture's rate
    for a marker-only sequence.

    A markerless sequence names no marker wearer (``markers_on`` and ``c3d`` absent): its
    ``people`` (one or two subject ids, none of them wearing markers) are all found in the
    views and fitted from the video (``videos`` and ``calibration`` required; ``partner``
    not used: the second person is ``people[1]``). Anyone else in the views (an operator)
    is a bystander, rejected by the keypoints stage."""

    markers_on: str | None = None
    c3d: Path | None = None
    people: list[str] = Field(default_factory=list)
    partner: str | None = None
    videos: dict[str, Path] = Field(default_factory=dict)
    calibration: dict[str, Path] = Field(default_factory=dict)
    calibration_format: CalibrationFormat | None = None
    contact: Path | None = None
    text: str = ""
    fps: Rate | None = None
    mocap: MocapSpec = MocapSpec()
    keypoints: dict[str, Path] | None = None
    keypoints_format: Literal["openpose", "coco"] | None = None
    clean_plates: dict[str, Path] = Field(default_factory=dict)
    refine_rig: bool = False

    @property
    def has_video(self) -> bool:
        """Recorded with the cameras (videos given): the video stages apply."""
        return bool(self.videos)

    @property
    def markerless(self) -> bool:
        """No marker wearer: every person is fitted from the video (``people``)."""
        return self.markers_on is None

    @property
    def persons(self) -> list[str]:
        """The subject ids fitted, person 0 first: ``[markers_on, partner]`` (the partner when
        there is one), or a markerless sequence's ``people``."""
        if self.markerless:
            return list(self.people)
        return [self.markers_on] + ([self.partner] if self.partner is not None else [])


def _folder_name(kind: str, name: str) -> str:
    """Names that become folders under ``outputs/``: no '/', no leading '.', not empty."""
    if not name or "/" in name or name.startswith(".") or name != name.strip():
        raise ValueError(f"{kind} {name!r}: must be a non-empty name without '/', "
                         "leading '.' or surrounding spaces")
    return name


class Session(_Strict):
    """A whole capture session."""

    session: str
    cameras: list[str] = Field(default_factory=list)
    subjects: dict[str, SubjectSpec]
    sequences: dict[str, SequenceSpec]
    body_model: BodyModelSpec = BodyModelSpec()
    ground_plane: GroundPlaneSpec = GroundPlaneSpec()
    stages: dict[str, dict[str, Any]] = Field(default_factory=dict)
    source: Path | None = None  # the recipe file it was read from (set by load_recipe)

    @field_validator("session")
    @classmethod
    def _session_name(cls, v: str) -> str:
        return _folder_name("session", v)

    @field_validator("cameras")
    @classmethod
    def _camera_ids(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"camera ids repeat: {v}")
        return v

    @field_validator("subjects")
    @classmethod
    def _subject_ids(cls, v: dict[str, SubjectSpec]) -> dict[str, SubjectSpec]:
        for sid in v:
            _folder_name("subject id", sid)
        return v

    @field_validator("sequences")
    @classmethod
    def _seq_ids(cls, v: dict[str, SequenceSpec]) -> dict[str, SequenceSpec]:
        for sid in v:
            if sid.count("/") != 1:
                raise ValueError(f"sequence id {sid!r}: expected '<group>/<action>'")
            for part in sid.split("/"):
                _folder_name(f"sequence id {sid!r}: part", part)
        return v

    def sequence(self, seq_id: str) -> SequenceSpec:
        if seq_id not in self.sequences:
            raise RecipeError(
                f"{self.source}: sequences: no sequence {seq_id!r} (known: {sorted(self.sequences)})"
            )
        return self.sequences[seq_id]

    def sequences_of(self, subject: str) -> list[str]:
        """Ids of the sequences a subject takes part in (wearing markers or as partner)."""
        return [q for q, s in self.sequences.items() if subject in s.persons]


def _resolve_paths(obj: Any, base: Path) -> Any:
    """Return a copy of a parsed model with every relative Path made absolute against base
    (and a marker-set given as a file path)."""
    if isinstance(obj, Path):
        return obj if obj.is_absolute() else (base / obj).resolve()
    if isinstance(obj, SubjectSpec) and markerset_is_file(obj.markerset):
        obj = obj.model_copy(update={"markerset": str(_resolve_paths(Path(obj.markerset), base))})
    if isinstance(obj, BaseModel):
        upd = {k: _resolve_paths(getattr(obj, k), base) for k in type(obj).model_fields}
        return obj.model_copy(update=upd)
    if isinstance(obj, dict):
        return {k: _resolve_paths(v, base) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_resolve_paths(v, base) for v in obj)
    return obj


def _ref_problems(s: Session, src: Path, tainted: dict[str, set[str]],
                  gone: set[str]) -> tuple[list[str], set[str]]:
    """The problems of references between fields (subjects, cameras), and the sequences that
    have one. ``tainted``: the fields of each sequence (``"*"``: all; key ``""``: top-level
    fields) whose schema errors were reported and dropped: checks that involve them would only
    repeat those errors, so they say nothing (the sequence still counts as bad). ``gone``:
    subject ids reported and dropped for their names."""
    out: list[str] = []
    bad: set[str] = set()
    top = tainted.get("", set())

    def problem(sid: str, fields: set[str], msg: str) -> None:
        bad.add(sid)
        t = tainted.get(sid, set())
        if not ("*" in t or t & fields or ("cameras" in fields and "cameras" in top)):
            out.append(f"{src}: {msg}")

    no_cameras_said = False
    for sid, seq in s.sequences.items():
        if seq.markerless:
            for m in _markerless_problems(seq):
                problem(sid, {"markers_on", "c3d", "people", "partner", "videos"},
                        f"sequences.{sid}.{m}")
        elif seq.people:
            problem(sid, {"markers_on", "people"}, f"sequences.{sid}.people: a sequence with a "
                    f"marker wearer (markers_on {seq.markers_on!r}) names its partner in partner, "
                    "not people (people is for markerless sequences: no markers_on, no c3d)")
        elif seq.c3d is None:
            problem(sid, {"markers_on", "c3d"}, f"sequences.{sid}.c3d: missing required field "
                    f"(markers_on {seq.markers_on!r} wears markers; a markerless sequence names "
                    "no markers_on and its people in people)")
        if seq.refine_rig and not (seq.videos and seq.calibration):
            problem(sid, {"refine_rig", "videos", "calibration"}, f"sequences.{sid}.refine_rig: "
                    "the rig is refined from the people seen in the videos: the sequence needs "
                    "videos and calibration")
        for who in seq.people:
            if who not in s.subjects and who not in gone:
                problem(sid, {"people"}, f"sequences.{sid}.people: unknown subject {who!r} "
                        f"(subjects: {', '.join(s.subjects)})")
        if seq.markers_on is not None and seq.markers_on == seq.partner:
            problem(sid, {"markers_on", "partner"}, f"sequences.{sid}.partner: the same subject "
                    f"as markers_on ({seq.partner!r})")
        for role in ("markers_on", "partner"):
            who = getattr(seq, role)
            if who is not None and who not in s.subjects:
                if who in gone:
                    bad.add(sid)
                else:
                    problem(sid, {role}, f"sequences.{sid}.{role}: unknown subject {who!r} "
                            f"(subjects: {', '.join(s.subjects)})")
        if seq.partner is not None and not seq.videos:
            problem(sid, {"partner", "videos"}, f"sequences.{sid}.partner: the partner is fitted "
                    "to the videos, and this sequence has none (videos)")
        for field_name in ("videos", "calibration"):
            cams = set(getattr(seq, field_name))
            if (cams or field_name == "calibration" and seq.videos) and cams != set(s.cameras):
                problem(sid, {field_name, "videos", "cameras"},
                        f"sequences.{sid}.{field_name}: cameras {sorted(cams)} "
                        f"do not match cameras {sorted(s.cameras)}")
        if seq.videos and not s.cameras:
            if no_cameras_said:
                bad.add(sid)
            else:
                problem(sid, {"videos", "cameras"}, f"cameras: a sequence has videos ({sid}) but "
                        "no camera is named")
                no_cameras_said = True
        if seq.keypoints is not None and not seq.videos:
            problem(sid, {"keypoints", "videos"}, f"sequences.{sid}.keypoints: keypoints need the "
                    "videos and calibration of the cameras")
        if seq.keypoints is not None:
            extra = set(seq.keypoints) - set(s.cameras)
            if extra:
                problem(sid, {"keypoints", "cameras"},
                        f"sequences.{sid}.keypoints: unknown cameras {sorted(extra)}")
            if seq.keypoints_format is None:
                problem(sid, {"keypoints", "keypoints_format"}, f"sequences.{sid}.keypoints_format: "
                        "required when keypoints are given (openpose or coco)")
        extra = set(seq.clean_plates) - set(s.cameras)
        if extra:
            problem(sid, {"clean_plates", "cameras"},
                    f"sequences.{sid}.clean_plates: unknown cameras {sorted(extra)}")
        if seq.clean_plates and not seq.videos:
            problem(sid, {"clean_plates", "videos"}, f"sequences.{sid}.clean_plates: clean "
                    "plates need the videos of the cameras (videos)")
    return out, bad


def _markerless_problems(seq: SequenceSpec) -> list[str]:
    """What contradicts itself in a markerless sequence (no ``markers_on``), as
    ``"<field>: why"``."""
    out = []
    if seq.c3d is not None:
        out.append("c3d: a C3D is given but no subject wears the markers (markers_on); name "
                   "the wearer in markers_on, or drop c3d for a markerless sequence")
    if not seq.people:
        out.append("people: a sequence without a marker wearer (markers_on) names the people "
                   "fitted from the video in people (one or two subject ids)")
    elif len(seq.people) > 2:
        out.append(f"people: one or two people are fitted, got {len(seq.people)}")
    elif len(set(seq.people)) != len(seq.people):
        out.append(f"people: the same subject twice ({seq.people})")
    if seq.partner is not None:
        out.append("partner: a markerless sequence names everyone in people (the second "
                   f"person as people[1], not partner {seq.partner!r})")
    if not seq.videos:
        out.append("videos: a markerless sequence is fitted from the videos, and has none")
    return out


def name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of ``folder`` (or its nearest existing
    parent) allows: ``os.pathconf(folder, "PC_NAME_MAX")``, else 255."""
    folder = Path(folder).resolve()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return NAME_MAX_DEFAULT


def _name_problem(kind: str, name: Any, limit: int) -> str:
    """What is wrong with ``name`` as a folder or file name ("" when nothing)."""
    if not isinstance(name, str):
        return f"{kind} {name!r}: expected a string"
    try:
        _folder_name(kind, name)
    except ValueError as e:
        return str(e)
    n = len(name.encode("utf-8", "surrogateescape"))
    if n + NAME_RESERVE > limit:
        return (f"name too long: {kind} {name[:40]!r}... is {n} bytes; this file system allows "
                f"{limit} per file name (NAME_MAX) and the pipeline adds up to {NAME_RESERVE} "
                f"(e.g. '.json.tmp'), so at most {limit - NAME_RESERVE}")
    return ""


def _check_names(raw: dict, src: Path, limit: int) -> tuple[list[str], set[str]]:
    """The session name, subject ids and sequence ids of ``raw`` (edited in place: a bad one
    is left out, a bad session name replaced): one problem each, and the subject ids left out.
    Other layouts (not a string, not a mapping) are left to the schema."""
    out: list[str] = []
    sess = raw.get("session")
    if isinstance(sess, str):
        why = _name_problem("session", sess, limit)
        if why:
            out.append(f"{src}: session: {why}")
            raw["session"] = _PLACEHOLDER["session"]
    gone: set[str] = set()
    subjects = raw.get("subjects")
    if isinstance(subjects, dict):
        for sid in list(subjects):
            why = _name_problem("subject id", sid, limit)
            if why:
                out.append(f"{src}: subjects.{sid}: {why}")
                del subjects[sid]
                gone.add(sid)
    seqs = raw.get("sequences")
    if isinstance(seqs, dict):
        for sid in list(seqs):
            if not isinstance(sid, str) or sid.count("/") != 1:
                why = f"sequence id {sid!r}: expected '<group>/<action>'"
            else:
                group, action = sid.split("/")
                why = _name_problem("group", group, limit) or _name_problem("action", action, limit)
            if why:
                out.append(f"{src}: sequences.{sid}: {why}")
                del seqs[sid]
    return out, gone


def _drop(raw: Any, loc: tuple) -> None:
    """Remove the value at ``loc`` from ``raw`` (so its default applies), or the nearest
    enclosing value that exists; a required top-level field gets a placeholder."""
    if not loc:
        return
    if len(loc) == 1 and loc[0] in _PLACEHOLDER:
        raw[loc[0]] = copy.deepcopy(_PLACEHOLDER[loc[0]])
        return
    if len(loc) == 2 and loc[0] == "subjects" and isinstance(raw.get("subjects"), dict):
        raw["subjects"][loc[1]] = {}  # every subject field has a default: keep the subject
        return
    node = raw
    for k in loc[:-1]:
        try:
            node = node[k]
        except (KeyError, IndexError, TypeError):
            return _drop(raw, loc[:-1])
    key = loc[-1]
    if isinstance(node, dict) and key in node:
        del node[key]
    elif isinstance(node, list) and isinstance(key, int) and 0 <= key < len(node):
        del node[key]
    else:
        _drop(raw, loc[:-1])


def _validate(raw: dict, src: Path) -> tuple[list[str], Session | None, dict[str, set[str]]]:
    """The schema's problems of ``raw`` (every field, one line each), the Session of what is
    left once the bad values are dropped (None if nothing usable is left), and the fields
    dropped per sequence (see :func:`_ref_problems`)."""
    problems: list[str] = []
    tainted: dict[str, set[str]] = {}
    raw = copy.deepcopy(raw)
    for round_ in range(50):
        try:
            return problems, Session.model_validate(raw), tainted
        except ValidationError as e:
            if round_ == 0:
                problems = _describe(e, src).splitlines()
            def order(x):  # later list items first: the indices of the rest stay valid
                return [(0, k) if isinstance(k, int) else (1, str(k)) for k in x["loc"]]

            for err in sorted(e.errors(), key=order, reverse=True):
                loc = tuple(err["loc"])
                if loc[:1] == ("sequences",) and len(loc) > 1:
                    tainted.setdefault(str(loc[1]), set()).add(str(loc[2]) if len(loc) > 2 else "*")
                elif loc:
                    tainted.setdefault("", set()).add(str(loc[0]))
                missing = err["type"] == "missing" and not (len(loc) == 1 and loc[0] in _PLACEHOLDER)
                _drop(raw, loc[:-1] if missing else loc)
    return problems, None, tainted


def input_files(s: Session) -> list[tuple[str, Path]]:
    """Every file or folder the recipe names, as ``(field, path)``, e.g.
    ``("sequences.s02/Grab 4.videos.50591643", Path(...))``."""
    out: list[tuple[str, Path]] = []
    for sid, sub in s.subjects.items():
        if sub.scan is not None:
            out.append((f"subjects.{sid}.scan", sub.scan))
        if markerset_is_file(sub.markerset):
            out.append((f"subjects.{sid}.markerset", Path(sub.markerset)))
        for i, st in enumerate(sub.static):
            out.append((f"subjects.{sid}.static[{i}].c3d", st.c3d))
    if s.body_model.path is not None:
        out.append(("body_model.path", s.body_model.path))
    for q, seq in s.sequences.items():
        if seq.c3d is not None:
            out.append((f"sequences.{q}.c3d", seq.c3d))
        for cam, p in seq.videos.items():
            out.append((f"sequences.{q}.videos.{cam}", p))
        for cam, p in seq.calibration.items():
            out.append((f"sequences.{q}.calibration.{cam}", p))
        if seq.contact is not None:
            out.append((f"sequences.{q}.contact", seq.contact))
        for cam, p in (seq.keypoints or {}).items():
            out.append((f"sequences.{q}.keypoints.{cam}", p))
        for cam, p in seq.clean_plates.items():
            out.append((f"sequences.{q}.clean_plates.{cam}", p))
    return out


def missing_files(s: Session) -> list[tuple[str, Path]]:
    """The ``(field, path)`` of :func:`input_files` that do not exist."""
    return [(f, p) for f, p in input_files(s) if not p.exists()]


_MSG = {
    "extra_forbidden": "unknown key",
    "missing": "missing required field",
}


def _describe(e: ValidationError, path: Path) -> str:
    lines = []
    for err in e.errors():
        loc = ".".join(str(p) for p in err["loc"])
        msg = _MSG.get(err["type"], err["msg"])
        got = err.get("input")
        got_s = "" if err["type"] == "missing" or isinstance(got, (dict, list)) else f", got {got!r}"
        lines.append(f"{path}: {loc}: {msg}{got_s}")
    return "\n".join(lines)


def load_recipe(path: str | Path, check_files: bool = True, stages: list[str] | None = None,
                max_name: int | None = None) -> Session:
    """Read, validate and resolve a recipe (relative paths against the recipe's folder).

    check_files : also require every file the recipe names to exist.
    stages : the stage names a ``stages.<name>`` section may have (None: any).
    max_name : the file system's longest file name in bytes (default :func:`name_max` of the
        recipe's folder).
    Raises RecipeError naming the file and the field, one line for every problem found (the
    schema's, e.g. ``recipes/x.yaml: sequences.s02/Grab 4.fps: Input should be a valid number,
    got 'fast'``, names, references, missing files, unknown stages), with ``recipe`` the part
    of the recipe that can still be checked (see :class:`RecipeError`).
    """
    path = Path(path)
    if not path.is_file():
        raise RecipeError(f"{path}: recipe not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RecipeError(f"{path}: not valid YAML: {e}") from None
    if not isinstance(raw, dict):
        raise RecipeError(f"{path}: expected a mapping at the top level")
    raw = copy.deepcopy(raw)
    limit = max_name if max_name is not None else name_max(path.resolve().parent)
    problems, gone = _check_names(raw, path, limit)
    schema, s, tainted = _validate(raw, path)
    problems += schema
    if s is None:
        raise RecipeError(problems)
    refs, bad = _ref_problems(s, path, tainted, gone)
    problems += refs
    s = _resolve_paths(s, path.resolve().parent)
    s = s.model_copy(update={"source": path})
    if check_files:
        problems += [f"{path}: {f}: file not found: {p}" for f, p in missing_files(s)]
    if stages is not None:
        problems += [f"{path}: stages.{name}: unknown stage (known: {', '.join(stages)})"
                     for name in s.stages if name not in stages]
    if problems:
        keep = {q: v for q, v in s.sequences.items() if q not in bad}
        raise RecipeError(problems, recipe=s.model_copy(update={"sequences": keep}))
    return s
