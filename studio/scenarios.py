"""The paper's eight interaction classes as contact scenarios: nominal motion of both people,
and the contacts that inverse kinematics then makes happen (``studio.motion``).

Pair frame: the actor ``a`` stands at ``(-s/2, 0)`` facing +x, the receiver ``b`` at
``(+s/2, 0)`` facing -x (side by side scenarios: both face +x, ``a`` at -y). The session
rotates and shifts the pair afterwards. ``u`` is normalised video time (0 = first video
frame, 1 = last); phase boundaries are fractions of it, so short sequences still contain the
whole interaction.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from studio import constants as C
from studio import posture as P
from studio.kin import FWD, LEFT, UP, Person, effector, heading_rotation, rotate_about_joint
from studio.motion import Anchor, Contact, Fixed, Shifted, Timeline, Track, anchor_at, pulse, ramp
from studio.posture import Anatomy


@dataclass
class Cast:
    """people / anatomy indexed by role: 0 = actor (initiates), 1 = receiver."""

    people: list[Person]
    an: list[Anatomy]
    tl: Timeline
    rng: np.random.Generator

    @property
    def span(self) -> float:
        """Seconds the whole interaction (u from 0 to 1) takes: the video's duration, but at
        least constants.MIN_SCENARIO_S so that short sequences keep human speeds (they then show
        the middle of the interaction)."""
        return max(self.tl.duration, C.MIN_SCENARIO_S)

    @property
    def u(self) -> np.ndarray:
        """(N,) normalised interaction time of each master sample (video middle at u = 0.5)."""
        return 0.5 + (self.tl.t - self.tl.duration / 2) / self.span

    def frame_of(self, u: float) -> int:
        """The video frame at normalised time u (clipped to the video)."""
        t = (u - 0.5) * self.span + self.tl.duration / 2
        return int(np.clip(round(t * self.tl.hz / self.tl.step), 0, self.tl.frames - 1))

    @property
    def N(self) -> int:
        return self.tl.n


@dataclass
class Scene:
    """nominal: tracks by role; contacts; movable: role pushed away on interpenetration;
    contact_hint: (u0, u1) where contact is planned (for the annotation frame search)."""

    nominal: list[Track]
    contacts: list[Contact]
    movable: int
    contact_hint: tuple[float, float]


def body_to_world(track: Track, i: int, point_body: np.ndarray, person: Person) -> np.ndarray:
    """A body-frame point (pose-independent, relative to the root joint's rest position) to
    world at master sample i."""
    h0 = person.rest.joints[0, 0]
    return track.R[i] @ (np.asarray(point_body) - h0) + h0 + track.T[i]


def place(person: Person, xy, heading_xy, N: int, pose: np.ndarray) -> Track:
    """A person standing with the root joint above ``xy`` (2,), facing ``heading_xy`` (2,)."""
    h0 = person.rest.joints[0, 0]
    R = heading_rotation(np.asarray(heading_xy, float))
    T = np.array([xy[0] - h0[0], xy[1] - h0[1], person.floor_z])
    # with a yaw R about the root, the root stays at h0 + T
    return Track(np.repeat(pose[None], N, 0) if pose.ndim == 2 else pose.copy(),
                 np.repeat(R[None], N, 0), np.repeat(T[None], N, 0))


def blend(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-sample blend of poses a, b ((J, 3) or (N, J, 3)) with weights w (N,)."""
    return a + w[:, None, None] * (b - a)


def living(cast: Cast, role: int, pose: np.ndarray, amp: float = 1.0) -> np.ndarray:
    """(N, J, 3) idle motion around ``pose`` (J, 3) or (N, J, 3)."""
    person = cast.people[role]
    base = pose if pose.ndim == 3 else np.repeat(pose[None], cast.N, 0)
    wig = P.idle(person, np.zeros_like(base[0]), cast.tl.t, cast.rng, amp)
    return base + wig


def palm(cast: Cast, role: int, side: str):
    h = cast.an[role].hands[side]
    return (h.wrist, h.palm_offset), h.normal


def hand_region(cast: Cast, role: int, side: str) -> np.ndarray:
    return cast.an[role].hand_vertices[side]


def with_fingers(cast: Cast, role: int, poses: np.ndarray, side: str, amount: float,
                 w: np.ndarray) -> np.ndarray:
    """Blend a finger curl of ``amount`` into poses (N, J, 3) with weight w (N,)."""
    person, an = cast.people[role], cast.an[role]
    curled = P.fist(person, an, np.zeros_like(poses[0]), side, amount)
    out = poses.copy()
    for j in an.hands[side].curl_axes:
        out[:, j] = poses[:, j] + w[:, None] * curled[j]
    return out


def flat_thumb(cast: Cast, role: int, poses: np.ndarray, side: str, w: np.ndarray) -> np.ndarray:
    """Lay the thumb of ``side`` into the palm's plane beside the index finger (a flat hand),
    blended in with weight w (N,): in its rest position the thumb stands off the palm, into
    whatever the palm holds."""
    person, an = cast.people[role], cast.an[role]
    J, n = an.joints0, person.j
    normal = an.hands[side].normal
    d = J[n(f"finger1-2.{side}")] - J[n(f"finger1-1.{side}")]
    d /= np.linalg.norm(d)
    index = J[n(f"finger2-1.{side}")] - J[n(f"wrist.{side}")]
    index /= np.linalg.norm(index)
    spread = d - (d @ normal) * normal - (d @ index) * index
    t = index + 0.35 * spread / max(np.linalg.norm(spread), 1e-9)
    t /= np.linalg.norm(t)
    ax = np.cross(d, t)
    rot = ax / np.linalg.norm(ax) * np.arccos(np.clip(d @ t, -1.0, 1.0))
    out = poses.copy()
    j = n(f"finger1-1.{side}")
    out[:, j] = poses[:, j] + w[:, None] * rot
    return out


def _shoulder_width(an: Anatomy, person: Person) -> float:
    return float(np.linalg.norm(an.joints0[person.j("upperarm01.L")] - an.joints0[person.j("upperarm01.R")]))


def _arm_len(an: Anatomy, person: Person, side: str = "R") -> float:
    J = an.joints0
    return float(np.linalg.norm(J[person.j(f"lowerarm01.{side}")] - J[person.j(f"upperarm01.{side}")])
                 + np.linalg.norm(J[person.j(f"wrist.{side}")] - J[person.j(f"lowerarm01.{side}")]))


def _floor_height(track: Track, person: Person, joint: int, an: Anatomy, i: int = 0) -> float:
    """World z of a joint at pose 0 placement (standing)."""
    return float(body_to_world(track, i, an.joints0[joint], person)[2])


# ------------------------------------------------------------------------------- scenarios
def handshake(cast: Cast) -> Scene:
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    reach = 0.5 * (_arm_len(aa, pa) + _arm_len(ab, pb))
    s = rng.uniform(1.45, 1.6) * reach
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    ta = place(pa, (-s / 2, 0), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    za = _floor_height(ta, pa, pa.j("lowerarm01.R"), aa)
    zb = _floor_height(tb, pb, pb.j("lowerarm01.R"), ab)
    zm = min(za, zb) + rng.uniform(-0.02, 0.04)
    w_a = pulse(u, 0.05, 0.35, 0.75, 0.95)
    w_b = pulse(u, 0.08, 0.36, 0.74, 0.93)
    # two shakes during the grip, whatever the sequence length
    shake = 0.015 * np.sin(2 * np.pi * 2 * (u - 0.4) / 0.3) * ramp(u, 0.38, 0.45) * (1 - ramp(u, 0.66, 0.72))
    M = np.stack([np.full(N, rng.uniform(-0.03, 0.03)), np.full(N, rng.uniform(-0.02, 0.02)),
                  zm + shake], 1)
    ta.pose = with_fingers(cast, 0, living(cast, 0, ta.pose[0]), "R", -0.15, w_a)
    tb.pose = with_fingers(cast, 1, living(cast, 1, tb.pose[0]), "R", -0.15, w_b)
    eff_a, n_a = palm(cast, 0, "R")
    eff_b, n_b = palm(cast, 1, "R")
    ca = Contact(0, P.arm_dofs(pa, aa, "R"), eff_a, Fixed(M, np.array([0.0, -1.0, 0.0])),
                 clearance=0.012, weight=w_a, region=hand_region(cast, 0, "R"), eff_normal=n_a,
                 name="hand.R->hand.R", refine=False)
    cb = Contact(1, P.arm_dofs(pb, ab, "R"), eff_b, Anchor(eff_a[0], eff_a[1], n_a),
                 clearance=0.0, weight=w_b, region=hand_region(cast, 1, "R"), eff_normal=n_b,
                 anchor_region=hand_region(cast, 0, "R"), name="hand.R->hand.R")
    return Scene([ta, tb], [ca, cb], movable=1, contact_hint=(0.4, 0.7))


def _front(person: Person, an: Anatomy, prefixes=("root", "pelvis", "spine", "breast", "clavicle")) -> float:
    """How far the torso surface reaches in front of the root joint (body frame, metres)."""
    m = person.model
    dom = np.asarray(m.weights.argmax(axis=1)).ravel()
    torso = np.array([m.joint_names[d].startswith(prefixes) for d in dom])
    V0 = an.pose0_vertices
    return float(((V0[torso] - an.joints0[0]) @ FWD).max())


def _anchor(cast: Cast, role: int, pose: np.ndarray, joint: str, start_body, direction) -> Anchor:
    p = cast.people[role]
    return anchor_at(p, pose, np.asarray(start_body, float), p.j(joint), np.asarray(direction, float))


def _joint0(cast: Cast, role: int, name: str) -> np.ndarray:
    return cast.an[role].joints0[cast.people[role].j(name)].copy()


def _region(cast: Cast, role: int, prefixes, side: str | None = None) -> np.ndarray:
    m = cast.people[role].model
    dom = np.asarray(m.weights.argmax(axis=1)).ravel()
    ok = [m.joint_names[d].startswith(prefixes) and (side is None or m.joint_names[d].endswith("." + side))
          for d in dom]
    return np.flatnonzero(ok)


def _pole_body(cast: Cast, role_of_frame: int, point_body) -> callable:
    """A pole target fixed in the body frame of person ``role_of_frame``."""
    person = cast.people[role_of_frame]
    pb = np.asarray(point_body, float)

    def fn(i, tracks):
        return body_to_world(tracks[role_of_frame], i, pb, person)

    return fn


def hug(cast: Cast) -> Scene:
    """Face to face, the taller person's arms go over the partner's shoulders, hands on their
    upper back; the shorter one's arms go under them, hands on the taller one's lower back.
    (The other way round, the shorter person's upper arms went through the taller one's
    shoulders.) The actor opens their arms and closes the hug first. The arms open sideways,
    the over-arms up and the under-arms down (opened forward, the hands went through the
    other's forearms before the hug)."""
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = _front(pa, aa) + _front(pb, ab) + rng.uniform(0.0, 0.02)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    hi = 0 if aa.height >= ab.height else 1  # the role whose arms go over
    w_lean = pulse(u, 0.05, 0.35, 0.78, 0.97)
    lean = [P.bend(p, P.bend(p, b, P.SPINE, LEFT * 0.12), P.NECK, UP * 0.5 + LEFT * 0.05)
            for p, b in zip(cast.people, base, strict=True)]
    # arms open first (wide, sideways: up for the arms that go over, down for the
    # others, so the opening hands pass above and below each other), then close around
    open_ = []
    for role in (0, 1):
        up = 0.4 if role == hi else -0.5
        o = lean[role]
        for side, sgn in (("L", 1.0), ("R", -1.0)):
            o = P.arm_directions(cast.people[role], cast.an[role], o, side,
                                 LEFT * sgn * 0.8 + UP * up, 0.7)
        open_.append(o)
    ta = place(pa, (-s / 2, 0), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    w = [pulse(u, 0.12, 0.4, 0.76, 0.95), pulse(u, 0.15, 0.42, 0.74, 0.93)]  # by role
    w_open = [pulse(u, 0.0, 0.25, 0.85, 1.0), pulse(u, 0.03, 0.28, 0.83, 1.0)]
    ta.pose = living(cast, 0, blend(blend(base[0], lean[0], w_lean), open_[0], w_open[0]), 0.5)
    tb.pose = living(cast, 1, blend(blend(base[1], lean[1], w_lean), open_[1], w_open[1]), 0.5)
    ta.pose = with_fingers(cast, 0, with_fingers(cast, 0, ta.pose, "L", -0.1, w[0]), "R", -0.1, w[0])
    contacts = []
    lo = 1 - hi
    ph, ah = cast.people[hi], cast.an[hi]
    pl, al = cast.people[lo], cast.an[lo]
    # over: hands on the partner's upper back (they face me: my left hand on their right side)
    half = 0.5 * _shoulder_width(al, pl)
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        start = _joint0(cast, lo, "spine01") + LEFT * (-sgn) * 0.08 + UP * 0.05
        anc = _anchor(cast, lo, lean[lo], "spine01", start, -FWD + UP * 0.3)
        eff, nrm = palm(cast, hi, side)
        elbow_pt = _joint0(cast, lo, "spine01") + LEFT * (-sgn) * (half + 0.1) + UP * 0.12
        poles = [(ph.j(f"lowerarm01.{side}"), np.zeros(3), _pole_body(cast, lo, elbow_pt), 0.3)]
        contacts.append(Contact(hi, P.arm_dofs(ph, ah, side), eff, anc, clearance=0.012, weight=w[hi],
                                region=hand_region(cast, hi, side), eff_normal=nrm, poles=poles,
                                name=f"hand.{side}->back"))
    # under: hands around the partner's waist
    half_h = 0.5 * _shoulder_width(ah, ph)
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        start = _joint0(cast, hi, "spine05") - LEFT * sgn * 0.04
        anc = _anchor(cast, hi, lean[hi], "spine05", start, -LEFT * sgn - FWD * 0.25)
        eff, nrm = palm(cast, lo, side)
        elbow_pt = _joint0(cast, hi, "spine05") - LEFT * sgn * (half_h + 0.1) + FWD * 0.05
        poles = [(pl.j(f"lowerarm01.{side}"), np.zeros(3), _pole_body(cast, hi, elbow_pt), 0.3)]
        contacts.append(Contact(lo, P.arm_dofs(pl, al, side), eff, anc, clearance=0.012, weight=w[lo],
                                region=hand_region(cast, lo, side), eff_normal=nrm, poles=poles,
                                name=f"hand.{side}->waist"))
    return Scene([ta, tb], contacts, movable=1, contact_hint=(0.42, 0.72))


def push(cast: Cast) -> Scene:
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = _front(pb, ab) + 0.62 * _arm_len(aa, pa) + rng.uniform(0.1, 0.16)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    ta = place(pa, (-s / 2, 0), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    w = pulse(u, 0.08, 0.33, 0.58, 0.8)
    recoil = ramp(u, 0.36, 0.6) * (1 - 0.6 * ramp(u, 0.7, 0.95))
    back = P.bend(pb, base[1], P.SPINE, -LEFT * 0.22)
    tb.pose = living(cast, 1, blend(base[1], back, recoil), 0.6)
    tb.T = tb.T + recoil[:, None] * np.array([rng.uniform(0.1, 0.16), 0.0, 0.0])
    fwd = P.bend(pa, base[0], P.SPINE, LEFT * 0.12)
    ta.pose = living(cast, 0, blend(base[0], fwd, w), 0.6)
    contacts = []
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        start = _joint0(cast, 1, "spine02") + LEFT * (-sgn) * 0.09 + UP * 0.08
        anc = _anchor(cast, 1, base[1], "spine02", start, FWD)
        eff, nrm = palm(cast, 0, side)
        contacts.append(Contact(0, P.arm_dofs(pa, aa, side), eff, anc, clearance=0.012, weight=w,
                                region=hand_region(cast, 0, side), eff_normal=nrm,
                                name=f"hand.{side}->chest"))
    return Scene([ta, tb], contacts, movable=1, contact_hint=(0.36, 0.56))


def hit(cast: Cast) -> Scene:
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = _front(pb, ab) + 0.75 * _arm_len(aa, pa) + rng.uniform(0.1, 0.15)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    guard = P.fist(pa, aa, P.arm_directions(pa, aa, base[0], "R", -UP + FWD * 0.3 - LEFT * 0.2, 1.9), "R")
    ta = place(pa, (-s / 2, 0), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    w_guard = pulse(u, 0.02, 0.2, 0.75, 0.95)
    ta.pose = living(cast, 0, blend(base[0], guard, w_guard), 0.6)
    w = pulse(u, 0.25, 0.42, 0.5, 0.68)
    flinch = ramp(u, 0.44, 0.56) * (1 - ramp(u, 0.7, 0.95))
    away = P.bend(pb, P.bend(pb, base[1], P.SPINE, -UP * 0.35 - LEFT * 0.12), P.NECK, -UP * 0.3)
    tb.pose = living(cast, 1, blend(base[1], away, flinch), 0.6)
    start = _joint0(cast, 1, "upperarm01.L") - UP * 0.03
    anc = _anchor(cast, 1, base[1], "upperarm01.L", start, FWD + LEFT * 0.5)
    h = cast.an[0].hands["R"]
    fwd_hand = h.knuckle_offset / np.linalg.norm(h.knuckle_offset)
    c = Contact(0, P.arm_dofs(pa, aa, "R"), (h.wrist, h.knuckle_offset + fwd_hand * 0.01), anc,
                clearance=0.01, weight=w, region=hand_region(cast, 0, "R"), eff_normal=fwd_hand,
                orient_weight=0.15, name="fist.R->shoulder.L")
    return Scene([ta, tb], [c], movable=1, contact_hint=(0.43, 0.5))


def kick(cast: Cast) -> Scene:
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    leg = float(aa.joints0[pa.j("upperleg01.R"), 2] - aa.joints0[pa.j("foot.R"), 2])
    s = 0.8 * leg + 0.5 * _front(pb, ab) + rng.uniform(0.05, 0.1)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    ta = place(pa, (-s / 2, 0.05), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    w = pulse(u, 0.15, 0.42, 0.5, 0.78)
    balance = P.bend(pa, base[0], P.SPINE, -LEFT * 0.15)
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        balance = P.arm_directions(pa, aa, balance, side, -UP + LEFT * sgn * 0.8 + FWD * 0.2, 0.5)
    ta.pose = living(cast, 0, blend(base[0], balance, pulse(u, 0.1, 0.4, 0.55, 0.85)), 0.5)
    flinch = ramp(u, 0.46, 0.6) * (1 - ramp(u, 0.75, 0.97))
    away = P.bend(pb, base[1], P.SPINE, LEFT * 0.2 - UP * 0.15)
    # the receiver swings the arm on the kicked side out and back (off the thigh, out of the
    # leg's way; hands raised in front were hit by a tall kicker's shin)
    guard = P.arm_directions(pb, ab, base[1], "L", -UP * 0.4 + LEFT * 0.9 - FWD * 0.35, 0.5)
    w_guard = pulse(u, 0.05, 0.3, 0.7, 0.95)
    tb.pose = living(cast, 1, blend(blend(base[1], guard, w_guard), away, flinch), 0.6)
    mid = 0.5 * (_joint0(cast, 1, "upperleg01.L") + _joint0(cast, 1, "lowerleg01.L"))
    # on the thigh as it is when the foot lands, the arm swung out of the way (found on the
    # standing pose, the ray could leave the body through the hanging hand: the foot then
    # aimed at a point in the air where that hand had been)
    anc = _anchor(cast, 1, guard, "upperleg01.L", mid, LEFT + FWD * 0.8)
    # the foot swings in aimed a few cm off the thigh and closes in at the end (aimed straight
    # at the contact, the big toe grazed the thigh on the way)
    off = 0.01 + 0.04 * (1 - ramp(u, 0.3, 0.42))
    c = Contact(0, P.leg_dofs(pa, aa, "R"), (pa.j("foot.R"), aa.instep_offset["R"]), anc,
                clearance=off, weight=w, region=aa.foot_vertices["R"], name="foot.R->thigh.L")
    return Scene([ta, tb], [c], movable=1, contact_hint=(0.43, 0.5))


def grab(cast: Cast) -> Scene:
    """The actor grabs the receiver's left upper arm from the front-outside; the receiver leans
    and turns away a little while held. (Grabbing the forearm made the actor's forearm run back
    over the receiver's hand: the upper arm keeps the two arms apart.)"""
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = _front(pb, ab) + 0.7 * _arm_len(aa, pa) + rng.uniform(0.1, 0.14)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    ta = place(pa, (-s / 2, 0), (1, 0), N, base[0])
    tb = place(pb, (s / 2, 0), (-1, 0), N, base[1])
    w = pulse(u, 0.12, 0.4, 0.72, 0.92)
    w_pull = ramp(u, 0.45, 0.65) * (1 - ramp(u, 0.8, 1.0))
    away = P.bend(pb, base[1], P.SPINE, -LEFT * 0.1 - UP * 0.12)
    tb.pose = living(cast, 1, blend(base[1], away, w_pull), 0.5)
    ta.pose = with_fingers(cast, 0, living(cast, 0, base[0], 0.5), "R", 0.0, w)
    mid = 0.45 * _joint0(cast, 1, "upperarm01.L") + 0.55 * _joint0(cast, 1, "lowerarm01.L")
    anc = _anchor(cast, 1, base[1], "upperarm02.L", mid, FWD + LEFT * 0.6)
    eff, nrm = palm(cast, 0, "R")
    c = Contact(0, P.arm_dofs(pa, aa, "R"), eff, anc, clearance=0.012, weight=w,
                region=hand_region(cast, 0, "R"), eff_normal=nrm,
                anchor_region=_region(cast, 1, ("upperarm",), "L"), name="hand.R->upperarm.L")
    return Scene([ta, tb], [c], movable=1, contact_hint=(0.42, 0.7))


# holding hands
HANDS_APART = 0.05  # m: how far above its place the lead's hand waits
RECEIVER_BELOW = 0.04  # m: the other palm below the lead's (its thumb clear of the lead's wrist)
WRIST_TILT_DEG = 55.0  # each hand leans this far from vertical toward the partner
WRIST_POLE_WEIGHT = 0.5
HOLD_SWING_M = 0.04  # amplitude of the hands' swing back and forth
FOREARM_TWIST_MAX = 1.8  # rad: the hold turns each palm about 90 degrees from hanging
HOLD_ORIENT_WEIGHT = 1.0  # the palms kept parallel (each facing the other hand)


def _swing_in(cast: Cast, role: int, track: Track, pose: np.ndarray, side: str, toward: float,
              fwd: float, flex: float) -> tuple[np.ndarray, np.ndarray]:
    """The arm of ``side`` swung in from the shoulder toward the partner (LEFT * toward) until
    its palm reaches the middle between the two (world y = 0): (the pose (J, 3), the palm's
    world point (3,)) at master sample 0."""
    person, h, best = cast.people[role], cast.an[role].hands[side], None
    for phi in np.deg2rad(np.arange(8.0, 70.0, 1.0)):
        d = -UP * np.cos(phi) + LEFT * toward * np.sin(phi) + FWD * fwd
        p = P.arm_directions(person, cast.an[role], pose, side, d, flex)
        pw = effector(person, p[None], track.R[:1], track.T[:1], h.wrist, h.palm_offset)[0]
        if best is None or abs(pw[1]) < best[0]:
            best = (abs(pw[1]), p, pw)
    return best[1], best[2]


def _palm_facing(cast: Cast, role: int, track: Track, pose: np.ndarray, side: str,
                 want: np.ndarray) -> np.ndarray:
    """``pose`` (J, 3) with the forearm of ``side`` turned (pronation / supination: a rotation
    about the forearm's axis at lowerarm02, 3-degree search within +-120) so that the palm
    faces the world direction ``want`` (3,) at master sample 0, as nearly as it can."""
    person, h = cast.people[role], cast.an[role].hands[side]
    tw = person.j(f"lowerarm02.{side}")
    t, _ = person.fk(pose[None], np.eye(3)[None], np.zeros((1, 3)))
    axis = t[0, h.wrist] - t[0, tw]
    axis /= np.linalg.norm(axis)
    poses = np.stack([rotate_about_joint(person, pose, tw, axis * a)
                      for a in np.deg2rad(np.arange(-120.0, 121.0, 3.0))])
    K = len(poses)
    _, G = person.fk(poses, np.repeat(track.R[:1], K, 0), np.repeat(track.T[:1], K, 0))
    return poses[int(np.argmax(G[:, h.wrist] @ h.normal @ want))]


def holding_hands(cast: Cast) -> Scene:
    """Side by side, two hands meet between them and hold, swinging a little. The shorter
    person leads (whether actor or receiver: seen from the text, the one who takes the other's
    hand takes the hand that waits for it): its hand comes first, waits above its place, lies
    in front. With the taller one leading, the short one's hand, held up almost level, went
    under the tall one's fingers."""
    tall = [float(np.ptp(a.pose0_vertices[:, 2])) for a in cast.an]
    if tall[0] <= tall[1]:
        return _holding_hands(cast)
    scene = _holding_hands(Cast(cast.people[::-1], cast.an[::-1], cast.tl, cast.rng))
    return Scene(scene.nominal[::-1], [_swap_roles(c) for c in scene.contacts], 1 - scene.movable,
                 scene.contact_hint)


def _swap_roles(c: Contact) -> Contact:
    """A contact of a scene built with the roles swapped, for the roles as they are."""
    poles = [(j, off, (lambda i, tracks, f=fn: f(i, tracks[::-1])), w) for j, off, fn, w in c.poles]
    return replace(c, who=1 - c.who, poles=poles)


def _holding_hands(cast: Cast) -> Scene:
    """Holding hands with role 0 leading: its left and the other's right hand meet between
    them, palm on palm. The lead's palm faces back, the other's forward (each forearm turned
    about 90 degrees from hanging; not turned, the hands met edge on and the wrists went
    through each other), swinging a little. The near arms hang close to the body before and
    after (hanging a little away from it, the two hands started a few cm apart). Each arm
    swings in from the shoulder, a little forward, until its hand reaches the middle (the
    nominal pose, so the hand travels along the arm's arc); the hands meet halfway between
    those two palms, each elbow held where the swing put it and each wrist on its own side above
    its palm, so the hands cross like an X, palms kept parallel. Both thumbs lie flat along the
    palm, and the other's palm sits RECEIVER_BELOW lower than the lead's (its thumb points at
    the lead's wrist). The lead's hand arrives first and waits above its place while the other
    hand comes in below it, then comes down onto it; they part the same way."""
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = 0.5 * (_shoulder_width(aa, pa) + _shoulder_width(ab, pb)) + rng.uniform(0.3, 0.36)
    side, toward = ("L", "R"), (1.0, -1.0)  # by role: the hand between them, the partner's side
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    for r in (0, 1):
        d = -UP + LEFT * toward[r] * rng.uniform(0.05, 0.1) - FWD * rng.uniform(0.0, 0.05)
        base[r] = P.arm_directions(cast.people[r], cast.an[r], base[r], side[r], d, rng.uniform(0.2, 0.4))
    tracks = [place(pa, (0, -s / 2), (1, 0), N, base[0]), place(pb, (0, s / 2), (1, 0), N, base[1])]
    fwd_w, left_w = tracks[0].R[0] @ FWD, tracks[0].R[0] @ LEFT  # the pair's world axes
    faces = (-fwd_w, fwd_w)  # by role: where the palm faces in the hold
    hold, palms = [], []
    for r in (0, 1):
        p = _swing_in(cast, r, tracks[r], base[r], side[r], toward[r], 0.15, 0.35)[0]
        hold.append(_palm_facing(cast, r, tracks[r], p, side[r], faces[r]))
        h = cast.an[r].hands[side[r]]
        palms.append(effector(cast.people[r], hold[r][None], tracks[r].R[:1], tracks[r].T[:1],
                              h.wrist, h.palm_offset)[0])
    # the lead's hand comes first and goes last: the other hand takes it once it is there and
    # lets go before it leaves (both moving at once, the hands went through each other)
    w = [pulse(u, 0.03, 0.25, 0.84, 0.98), pulse(u, 0.18, 0.36, 0.76, 0.9)]
    for r in (0, 1):
        nom = living(cast, r, blend(base[r], hold[r], w[r]), 0.6)
        tracks[r].pose = flat_thumb(cast, r, with_fingers(cast, r, nom, side[r], -0.15, w[r]), side[r], w[r])
    swing = HOLD_SWING_M * np.sin(2 * np.pi * 0.9 * u * cast.span + rng.uniform(0, 6)) * ramp(u, 0.35, 0.45)
    mid = 0.5 * (palms[0] + palms[1])
    M = mid[None] + swing[:, None] * fwd_w[None]
    M[:, 1] = 0.0
    # the lead's hand waits above its place while the other comes and goes (in front of it,
    # its forearm swept through the other hand); the other's target stays put
    above = (HANDS_APART * ((1 - ramp(u, 0.3, 0.4)) + ramp(u, 0.72, 0.8)))[:, None] * UP[None]
    eff_a, n_a = palm(cast, 0, "L")
    eff_b, n_b = palm(cast, 1, "R")
    clear_a = 0.012

    def poles(r, palm_at):
        """The elbow where the swing put it; the wrist on its own side above the palm (the
        hand leaning WRIST_TILT_DEG toward the partner), off the palm by the hand's thickness."""
        person, h = cast.people[r], cast.an[r].hands[side[r]]
        t, _ = person.fk(hold[r][None], np.eye(3)[None], np.zeros((1, 3)))
        elbow = person.j(f"lowerarm01.{side[r]}")
        depth = float(h.palm_offset @ h.normal)
        length = float(np.linalg.norm(h.palm_offset - depth * h.normal))
        tilt = np.deg2rad(WRIST_TILT_DEG)
        back = length * (UP * np.cos(tilt) - left_w * toward[r] * np.sin(tilt)) - depth * faces[r]
        return [(elbow, np.zeros(3), _pole_body(cast, r, t[0, elbow]), 0.6),
                (h.wrist, np.zeros(3), lambda i, _tracks: palm_at[i] + back, WRIST_POLE_WEIGHT)]

    ca = Contact(0, P.arm_dofs(pa, aa, "L", twist_max=FOREARM_TWIST_MAX), eff_a, Fixed(M + above, fwd_w),
                 clearance=clear_a, weight=w[0], region=hand_region(cast, 0, "L"), eff_normal=n_a,
                 orient_weight=HOLD_ORIENT_WEIGHT, poles=poles(0, M + above + clear_a * fwd_w),
                 name="hand.L->hand.R")
    cb = Contact(1, P.arm_dofs(pb, ab, "R", twist_max=FOREARM_TWIST_MAX), eff_b,
                 Shifted(Anchor(eff_a[0], eff_a[1], n_a), -above - RECEIVER_BELOW * UP),
                 clearance=0.0, weight=w[1], region=hand_region(cast, 1, "R"), eff_normal=n_b,
                 orient_weight=HOLD_ORIENT_WEIGHT, poles=poles(1, M),
                 anchor_region=hand_region(cast, 0, "L"), name="hand.R->hand.L")
    return Scene(tracks, [ca, cb], movable=1, contact_hint=(0.4, 0.75))


def posing(cast: Cast) -> Scene:
    """Side by side for a photo, the actor rests the left hand on top of the receiver's near
    (right) shoulder, elbow out behind them; the receiver holds the hands together in front.
    (An arm across the shoulders to the far one, with the receiver's arm around the actor's
    waist, put the crossing arms through the other's neck and back.)"""
    rng, u, N = cast.rng, cast.u, cast.N
    (pa, pb), (aa, ab) = cast.people, cast.an
    s = 0.5 * (_shoulder_width(aa, pa) + _shoulder_width(ab, pb)) + rng.uniform(0.26, 0.32)
    base = [P.standing(p, a, rng) for p, a in zip(cast.people, cast.an, strict=True)]
    ta = place(pa, (0, -s / 2), (1, 0), N, base[0])
    tb = place(pb, (0, s / 2), (1, 0), N, base[1])
    w_a = pulse(u, 0.06, 0.36, 0.8, 0.97)
    lean = P.bend(pa, base[0], P.SPINE, -FWD * 0.08)
    ta.pose = living(cast, 0, blend(base[0], lean, w_a), 0.4)
    # the receiver poses with the hands together in front (a hanging near arm was in the way
    # of the actor's hand going up to the shoulder)
    front = base[1]
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        front = P.arm_directions(pb, ab, front, side, -UP + FWD * 0.5 - LEFT * sgn * 0.05, 1.1)
    tb.pose = living(cast, 1, front, 0.4)
    # on the outer top of the shoulder, the elbow out behind: the fingers lie forward over the
    # shoulder, away from the partner's neck
    shoulder = _joint0(cast, 1, "upperarm01.R") - LEFT * 0.03
    anc_a = _anchor(cast, 1, base[1], "clavicle.R", shoulder, UP)
    eff, nrm = palm(cast, 0, "L")
    elbow = _joint0(cast, 1, "upperarm01.R") - LEFT * 0.06 - FWD * 0.2 - UP * 0.1
    # the hand comes down onto the shoulder from above and lifts off before it goes (sliding
    # along the partner's upper arm grazed it)
    above = 0.012 + 0.06 * (1 - ramp(u, 0.26, 0.42)) + 0.06 * ramp(u, 0.8, 0.88)
    ca = Contact(0, P.arm_dofs(pa, aa, "L"), eff, anc_a, clearance=above, weight=w_a,
                 region=hand_region(cast, 0, "L"), eff_normal=nrm,
                 anchor_region=_region(cast, 1, ("clavicle", "shoulder", "upperarm"), "R"),
                 poles=[(pa.j("lowerarm01.L"), np.zeros(3), _pole_body(cast, 1, elbow), 0.3)],
                 name="hand.L->shoulder.R")
    return Scene([ta, tb], [ca], movable=1, contact_hint=(0.42, 0.75))


SCENES = {
    "grab": grab,
    "handshake": handshake,
    "hit": hit,
    "holding_hands": holding_hands,
    "hug": hug,
    "kick": kick,
    "posing": posing,
    "push": push,
}
