"""What a session contains, decided before anything is computed: subjects, sequences (action,
who wears the markers, number of frames, text), file layout and the recipe.

The plan depends only on the seed and the options, so the committed preset recipes
(``recipes/demo.yaml``, ``recipes/bench.yaml``) can be checked against it without generating
any data.

Layout of a generated session folder ``<out>``::

    recipe.yaml                                   the capture recipe (paths relative to <out>)
    scans/<subject>.ply                           one scan per subject
    <group>/camera_parameters/<camera>/<action>.json    CHI3D camera JSON
    <group>/videos/<camera>/<action>.mp4
    <group>/videos/<camera>/clean_plate.mp4       the empty room (``lab`` plans only; as labs
                                                  record one; constants.CLEAN_PLATE_FRAMES frames;
                                                  listed in gt/session.json "clean_plates")
    <group>/mocap/<action>.c3d                    markers of the subject wearing them
    <group>/interaction_contact_signature.json    contact annotations, keyed by action
    gt/...                                        ground truth (never read by the pipeline)
    previews/<group>_<action>_contact.png         contact sheet of the four views

A marker-only session (preset ``markers``, :class:`MarkerSessionPlan`)::

    recipe.yaml
    <group>/mocap/<subject>_static.c3d            static trial (standing), per subject
    <group>/mocap/<action>.c3d                    movement trials (group = subject minus "a")
    gt/...                                        ground truth (``studio.session.generate_markers``)
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from studio import constants as C

#: The paper's eight interaction classes: scenario name -> CHI3D action name (without take).
SCENARIOS = {
    "grab": "Grab",
    "handshake": "Handshake",
    "hit": "Hit",
    "holding_hands": "HoldingHands",
    "hug": "Hug",
    "kick": "Kick",
    "posing": "Posing",
    "push": "Push",
}
#: Accepted spellings on the command line.
_ALIASES = {"holding-hands": "holding_hands", "holdinghands": "holding_hands"}


@dataclass(frozen=True)
class Preset:
    """A named session configuration (the committed recipes). kind: ``interaction`` (two
    people, cameras, videos: :class:`SessionPlan`) or ``markers`` (marker capture only, one
    subject per trial: :class:`MarkerSessionPlan`; frames unused, scenarios: the motions of
    the movement trials, two per subject in order)."""

    name: str
    seed: int
    frames: int
    scenarios: tuple[str, ...]
    kind: str = "interaction"
    #: the realistic studio (:func:`realistic`) rather than the kind one
    realistic: bool = False


PRESETS = {
    "demo": Preset("demo", seed=3, frames=100, scenarios=("handshake", "push"), realistic=True),
    "bench": Preset("bench", seed=11, frames=120, scenarios=tuple(SCENARIOS), realistic=True),
    "markers": Preset("markers", seed=23, frames=0, scenarios=("kick", "grab", "hit", "push"),
                      kind="markers"),
}
DEFAULT_SCENARIOS = ("handshake", "hug", "push", "kick")
DEFAULT_FRAMES = 100


@dataclass(frozen=True)
class SequencePlan:
    """One sequence. index: position in the session (seeds its randomness); scenario: key of
    SCENARIOS; action: CHI3D action name with take (``"Hug 1"``); markers_on / partner:
    subject ids; frames: video frames; text: one sentence describing the motion."""

    index: int
    scenario: str
    group: str
    action: str
    markers_on: str
    partner: str
    frames: int
    text: str
    actor: int = 0

    @property
    def seq_id(self) -> str:
        return f"{self.group}/{self.action}"


@dataclass(frozen=True)
class SessionPlan:
    """A whole session. subjects: the two subject ids, in the order of person 0 / person 1 of
    the generator (the colours of constants.CLOTHING)."""

    session: str
    seed: int
    group: str
    subjects: tuple[str, str]
    cameras: tuple[str, ...]
    sequences: tuple[SequencePlan, ...]
    preset: str | None = None
    sync_offset_s: float = C.SYNC_OFFSET_S
    fps: float = C.VIDEO_FPS
    mocap_hz: float = C.MOCAP_HZ
    #: realistic marker capture (``studio.mocap.capture``: hand placement, soft tissue,
    #: labelling faults, extra points and analogs; first frame kept 0 so the recipe's sync
    #: offset stays valid). ``plan_dict`` omits it (and every option below) when off.
    marker_realism: bool = False
    #: The realistic studio (``studio.lab``; all on in the demo and bench presets, all off in
    #: the kind studio of the unit tests that need exactness):
    #: lab: a furnished lab room instead of floor and sky, a second camera rig on tripods, a
    #: bystander (an operator) behind the subjects in some views, and a clean plate per camera;
    lab: bool = False
    #: camera_look: clothing patterns, skin tones and hair; per camera gain and white balance,
    #: vignetting, sensor noise, compression (a JPEG pass before the MP4 writer) and motion blur;
    camera_look: bool = False
    #: calib_error: the recipe's calibration is the truth perturbed (constants.CALIB_ERROR_PX
    #: of reprojection error); the true cameras are in gt/;
    calib_error: bool = False
    #: desync_frames: the last camera records this fraction of a frame late (0: in sync).
    desync_frames: float = 0.0

    @property
    def kind(self) -> bool:
        """The kind studio: nothing realistic, every pixel and number exact."""
        return not (self.marker_realism or self.lab or self.camera_look or self.calib_error
                    or self.desync_frames)


@dataclass(frozen=True)
class TrialPlan:
    """One marker-only trial of the ``markers`` preset. kind: ``static`` (standing, for the
    shape fit) or ``motion``; name: the C3D's stem (``m01a_static``, ``Kick 1``); group: the
    subject's folder; scenario: the studio scenario whose wearer track is the motion (the
    other role is played by ``partner``, never captured nor written); samples: mocap samples
    (the C3D's frames); first_frame: the C3D's 0-based first frame; frames: the never-rendered
    check timeline's frames (constants.MARKERS_CHECK_FPS) of a motion trial."""

    index: int
    kind: str
    subject: str
    group: str
    name: str
    samples: int
    first_frame: int
    scenario: str | None = None
    partner: str | None = None
    frames: int = 0

    @property
    def seq_id(self) -> str:
        return f"{self.group}/{self.name}"


@dataclass(frozen=True)
class MarkerSessionPlan:
    """The ``markers`` preset: subjects (ids, sexes: person i of ``studio.subjects
    .make_subjects``), trials (a static and two motion trials per subject), marker capture at
    ``mocap_hz`` with ``studio.mocap.capture``."""

    session: str
    seed: int
    subjects: tuple[str, ...]
    sexes: tuple[str, ...]
    trials: tuple[TrialPlan, ...]
    preset: str | None = None
    mocap_hz: float = C.MARKERS_HZ
    fps: float = C.MARKERS_CHECK_FPS
    sync_offset_s: float = -C.MARKERS_LEAD_S

    @property
    def motion_trials(self) -> tuple[TrialPlan, ...]:
        return tuple(t for t in self.trials if t.kind == "motion")

    def static_of(self, subject: str) -> tuple[TrialPlan, ...]:
        return tuple(t for t in self.trials if t.kind == "static" and t.subject == subject)


def parse_scenarios(text: str | None) -> tuple[str, ...]:
    """``"hug,handshake"`` -> ("hug", "handshake"); raises ValueError on an unknown name."""
    if not text:
        return DEFAULT_SCENARIOS
    out = []
    for s in text.split(","):
        k = s.strip().lower().replace(" ", "_")
        k = _ALIASES.get(k, k)
        if k not in SCENARIOS:
            raise ValueError(f"--scenarios: unknown scenario {s!r} (known: {', '.join(SCENARIOS)})")
        out.append(k)
    return tuple(out)


# Colour words of the two people (match constants.CLOTHING).
_WHO = ("the person in blue", "the person in red")
_TEXT = {
    "grab": ["{a} reaches out and grabs {b} by the {limb}.",
             "{a} grabs the {limb} of {b}, who pulls back a little."],
    "handshake": ["{a} and {b} step towards each other and shake hands.",
                  "{a} shakes hands with {b}, holding the grip for a moment."],
    "hit": ["{a} punches {b} on the {part} and {b} flinches.",
            "{a} swings a fist at {b} and hits the {part}."],
    "holding_hands": ["{a} and {b} stand side by side and hold hands.",
                      "{a} takes the hand of {b} and they hold hands, swinging their arms."],
    "hug": ["{a} and {b} hug each other, arms around each other's back.",
            "{a} wraps both arms around {b}, who hugs back."],
    "kick": ["{a} kicks {b} on the {leg} with the right foot.",
             "{a} lifts a leg and kicks {b} lightly on the {leg}."],
    "posing": ["{a} rests a hand on the shoulder of {b} and they pose for a photo.",
               "{a} and {b} pose side by side, {a} with a hand on the shoulder of {b}."],
    "push": ["{a} pushes {b} in the chest with both hands and {b} steps back.",
             "{a} shoves {b} with both hands; {b} is pushed backwards."],
}


def sentence(scenario: str, actor: int, rng: np.random.Generator) -> str:
    """One sentence for a scenario; actor: 0 or 1, the person who initiates."""
    a, b = _WHO[actor], _WHO[1 - actor]
    t = _TEXT[scenario][int(rng.integers(len(_TEXT[scenario])))]
    s = t.format(a=a, b=b, limb="upper arm", part="shoulder", leg="thigh")
    return s[0].upper() + s[1:]


#: The options of the realistic studio and their values when on (:func:`realistic`).
REALISM = {"marker_realism": True, "lab": True, "camera_look": True, "calib_error": True,
           "desync_frames": C.DESYNC_FRAMES}


def realistic(plan: SessionPlan, on: bool = True) -> SessionPlan:
    """The plan with every option of the realistic studio on (REALISM), or all off (the kind
    studio)."""
    import dataclasses

    return dataclasses.replace(plan, **(REALISM if on else {k: type(v)() for k, v in REALISM.items()}))


def make_plan(seed: int, frames: int | None = None, scenarios: tuple[str, ...] | None = None,
              preset: str | None = None, realism: bool | None = None) -> SessionPlan:
    """The plan of a session. A preset gives defaults for seed-independent options; explicit
    ``frames`` / ``scenarios`` override it. realism: the realistic studio (:func:`realistic`);
    None: the preset's (the demo and bench presets are realistic), else the kind studio."""
    p = PRESETS[preset] if preset else None
    if p is not None and p.kind == "markers":
        if frames:
            raise ValueError(f"--frames: the {preset!r} preset has no video frames")
        return make_marker_plan(seed, scenarios or p.scenarios, preset)
    frames = frames or (p.frames if p else DEFAULT_FRAMES)
    scenarios = scenarios or (p.scenarios if p else DEFAULT_SCENARIOS)
    if frames < 10:
        raise ValueError(f"--frames: need at least 10 frames, got {frames}")
    group = "s01"
    subjects = (f"{group}a", f"{group}b")
    takes: dict[str, int] = {}
    seqs = []
    for i, sc in enumerate(scenarios):
        rng = np.random.default_rng([seed, 1000 + i])
        takes[sc] = takes.get(sc, 0) + 1
        wearer = i % 2  # as in CHI3D, who wears the markers alternates between sequences
        actor = int(rng.integers(2))
        seqs.append(SequencePlan(index=i, scenario=sc, group=group,
                                 action=f"{SCENARIOS[sc]} {takes[sc]}",
                                 markers_on=subjects[wearer], partner=subjects[1 - wearer],
                                 frames=int(frames), text=sentence(sc, actor, rng), actor=actor))
    session = f"studio_{preset}" if preset else f"studio_seed{seed}"
    plan = SessionPlan(session=session, seed=int(seed), group=group, subjects=subjects,
                       cameras=C.CAMERA_NAMES, sequences=tuple(seqs), preset=preset)
    if realism is None:
        realism = bool(p.realistic) if p is not None else False
    return realistic(plan) if realism else plan


def make_marker_plan(seed: int, scenarios: tuple[str, ...], preset: str | None = "markers",
                     n_subjects: int = 2, trial_s: tuple[float, float] = C.MARKERS_TRIAL_S,
                     static_s: float = C.STATIC_S) -> MarkerSessionPlan:
    """The plan of a marker-only session: ``n_subjects`` subjects ``m01a``, ``m02a``... (sexes
    as ``studio.subjects.make_subjects`` draws them: person 0 male, 1 female), each with a
    static trial (``static_s`` seconds) and ``len(scenarios) // n_subjects`` motion trials
    (scenarios in order; lengths drawn from ``trial_s`` seconds), every first frame drawn from
    constants.FIRST_FRAME_RANGE. The other role of a motion's scenario is played by the other
    subject (by a hidden ``<subject>_partner`` with one subject), never captured."""
    if n_subjects > 2:
        raise ValueError("the studio draws at most 2 subjects")
    per = max(1, len(scenarios) // n_subjects)
    hz = C.MARKERS_HZ
    subjects = tuple(f"m{i + 1:02d}a" for i in range(n_subjects))
    trials = []
    for i, sid in enumerate(subjects):
        rng = np.random.default_rng([seed, 3000 + i])
        group = sid[:-1]
        trials.append(TrialPlan(len(trials), "static", sid, group, f"{sid}_static",
                                int(round(static_s * hz)), int(rng.integers(*C.FIRST_FRAME_RANGE))))
        takes: dict[str, int] = {}
        for sc in scenarios[i * per:(i + 1) * per]:
            takes[sc] = takes.get(sc, 0) + 1
            secs = float(rng.uniform(*trial_s))
            frames = int(round(secs * C.MARKERS_CHECK_FPS)) + 1
            samples = _timeline_samples(frames)
            trials.append(TrialPlan(len(trials), "motion", sid, group, f"{SCENARIOS[sc]} {takes[sc]}",
                                    samples, int(rng.integers(*C.FIRST_FRAME_RANGE)), sc,
                                    subjects[(i + 1) % n_subjects] if n_subjects > 1 else f"{sid}_partner",
                                    frames))
    session = f"studio_{preset}" if preset else f"studio_markers_seed{seed}"
    return MarkerSessionPlan(session, int(seed), subjects, tuple("male" if i == 0 else "female"
                                                                 for i in range(n_subjects)),
                             tuple(trials), preset)


def _timeline_samples(frames: int) -> int:
    """Mocap samples of the master timeline of a motion trial (``studio.motion.make_timeline``)."""
    step = int(round(C.MARKERS_HZ / C.MARKERS_CHECK_FPS))
    m0 = int(round(C.MARKERS_LEAD_S * C.MARKERS_HZ))
    return m0 + step * (frames - 1) + 1 + int(round(C.MOCAP_TAIL_S * C.MARKERS_HZ))


# ------------------------------------------------------------------------------------ layout
def scan_path(subject: str) -> Path:
    return Path("scans") / f"{subject}.ply"


def camera_path(seq: SequencePlan, cam: str) -> Path:
    return Path(seq.group) / "camera_parameters" / cam / f"{seq.action}.json"


def video_path(seq: SequencePlan, cam: str) -> Path:
    return Path(seq.group) / "videos" / cam / f"{seq.action}.mp4"


def clean_plate_path(group: str, cam: str) -> Path:
    """The clean plate of a camera (the empty room), beside that camera's videos: the same for
    every sequence of the group (the room and the cameras do not move)."""
    return Path(group) / "videos" / cam / "clean_plate.mp4"


def c3d_path(seq: SequencePlan) -> Path:
    return Path(seq.group) / "mocap" / f"{seq.action}.c3d"


def contact_path(seq: SequencePlan) -> Path:
    return Path(seq.group) / "interaction_contact_signature.json"


def gt_path(seq: SequencePlan) -> Path:
    return Path("gt") / seq.group / f"{seq.action}.npz"


def preview_path(seq: SequencePlan) -> Path:
    return Path("previews") / f"{seq.group}_{seq.action.replace(' ', '_')}_contact.png"


def trial_c3d_path(t: TrialPlan) -> Path:
    return Path(t.group) / "mocap" / f"{t.name}.c3d"


def trial_gt_path(t: TrialPlan) -> Path:
    return Path("gt") / t.group / f"{t.name}.npz"


def marker_recipe_dict(plan: MarkerSessionPlan, prefix: str = "") -> dict:
    """The recipe of a marker-only session (the new recipe schema: no cameras, static trials
    per subject, sequences without partner, videos or calibration; ``fps: null``: the C3D's
    own rate). ``frames: null``: the whole static trial."""

    def p(x: Path) -> str:
        return prefix + x.as_posix()

    return {
        "session": plan.session,
        "cameras": [],
        "subjects": {s: {"markerset": "plug-in-gait", "sex": sex,
                         "static": [{"c3d": p(trial_c3d_path(t)), "frames": None}
                                    for t in plan.static_of(s)]}
                     for s, sex in zip(plan.subjects, plan.sexes, strict=True)},
        "sequences": {t.seq_id: {"markers_on": t.subject, "c3d": p(trial_c3d_path(t)), "fps": None}
                      for t in plan.motion_trials},
        "body_model": {"kind": "anny"},
        "ground_plane": {"normal": [0.0, 0.0, 1.0], "offset": 0.0},
        "stages": {},
    }


def recipe_dict(plan: SessionPlan | MarkerSessionPlan, prefix: str = "") -> dict:
    """The recipe (plain dict, YAML-ready) with every path ``prefix + relative path``."""
    if isinstance(plan, MarkerSessionPlan):
        return marker_recipe_dict(plan, prefix)

    def p(x: Path) -> str:
        return prefix + x.as_posix()

    def plates(seq: SequencePlan) -> dict:  # the lab's clean plates (a kind plan has none)
        return {"clean_plates": {c: p(clean_plate_path(seq.group, c)) for c in plan.cameras}} \
            if plan.lab else {}

    return {
        "session": plan.session,
        "cameras": list(plan.cameras),
        "subjects": {s: {"scan": p(scan_path(s)), "markerset": "plug-in-gait"}
                     for s in plan.subjects},
        "sequences": {
            seq.seq_id: {
                "markers_on": seq.markers_on,
                "partner": seq.partner,
                "c3d": p(c3d_path(seq)),
                "videos": {c: p(video_path(seq, c)) for c in plan.cameras},
                "calibration": {c: p(camera_path(seq, c)) for c in plan.cameras},
                "contact": p(contact_path(seq)),
                "text": seq.text,
                "fps": plan.fps,
                "mocap": {"sync_offset_s": plan.sync_offset_s},
                **plates(seq),
            }
            for seq in plan.sequences
        },
        "body_model": {"kind": "anny"},
        "ground_plane": {"normal": [0.0, 0.0, 1.0], "offset": 0.0},
        "stages": {},
    }
