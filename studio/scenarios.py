"""The paper's eight interaction classes as contact scenarios: nominal motion of both people,
and the contacts that inverse kinematics then makes happen (``studio.motion``).

Pair frame: the actor ``a`` stands at ``(-s/2, 0)`` facing +x, the receiver ``b`` at
``(+s/2, 0)`` facing -x (side by side scenarios: both face +x, ``a`` at -y). The session
rotates and shifts the pair afterwards. ``u`` is normalised video time (0 = first video
frame, 1 = last); phase boundaries are fractions of it, so short sequences still contain the
whole interaction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from studio import posture as P
from studio.kin import Person, heading_rotation
from studio.motion import Anchor, Contact, Fixed, Timeline, Track, pulse, ramp
from studio.posture import Anatomy


@dataclass
class Cast:
    """people / anatomy indexed by role: 0 = actor (initiates), 1 = receiver."""

    people: list[Person]
    an: list[Anatomy]
    tl: Timeline
    rng: np.random.Generator

    @property
    def u(self) -> np.ndarray:
        return self.tl.t / self.tl.duration

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
    shake = 0.025 * np.sin(2 * np.pi * 2.2 * cast.tl.t) * ramp(u, 0.38, 0.45) * (1 - ramp(u, 0.68, 0.74))
    M = np.stack([np.full(N, rng.uniform(-0.03, 0.03)), np.full(N, rng.uniform(-0.02, 0.02)),
                  zm + shake], 1)
    ta.pose = with_fingers(cast, 0, living(cast, 0, ta.pose[0]), "R", 0.1, w_a)
    tb.pose = with_fingers(cast, 1, living(cast, 1, tb.pose[0]), "R", 0.1, w_b)
    eff_a, n_a = palm(cast, 0, "R")
    eff_b, n_b = palm(cast, 1, "R")
    ca = Contact(0, P.arm_dofs(pa, aa, "R"), eff_a, Fixed(M, np.array([0.0, -1.0, 0.0])),
                 clearance=0.012, weight=w_a, region=hand_region(cast, 0, "R"), eff_normal=n_a,
                 name="hand.R->hand.R", refine=False)
    cb = Contact(1, P.arm_dofs(pb, ab, "R"), eff_b, Anchor(eff_a[0], eff_a[1], n_a),
                 clearance=0.0, weight=w_b, region=hand_region(cast, 1, "R"), eff_normal=n_b,
                 anchor_region=hand_region(cast, 0, "R"), name="hand.R->hand.R")
    return Scene([ta, tb], [ca, cb], movable=1, contact_hint=(0.4, 0.7))


SCENES = {"handshake": handshake}
