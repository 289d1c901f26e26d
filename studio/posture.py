"""Named pieces of a body pose, built from the model's own geometry (no per-bone axis tables):
relaxed standing arms, elbow/knee hinge axes, palms, fists, spine bends, idle motion.

All poses are ``(J, 3)`` local axis-angle (``body.lbs`` convention); "body frame" is the
model's frame at ``global_orient = I`` (``studio.kin``: left +x, forward -y, up +z).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from body.lbs import forward
from studio.kin import FWD, LEFT, UP, Dof, Person, rotate_about_joint

SIDES = ("L", "R")


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class Hand:
    """Geometry of one hand at pose 0 (body frame). palm_offset: (3,) palm-centre surface point
    relative to the wrist joint; normal: (3,) palm normal (out of the palm); knuckle_offset:
    (3,) front of the fist relative to the wrist; curl_axes: {joint: (3,) axis} finger flexion."""

    side: str
    wrist: int
    palm_offset: np.ndarray
    normal: np.ndarray
    knuckle_offset: np.ndarray
    curl_axes: dict


@dataclass(frozen=True)
class Anatomy:
    """Per-person geometric facts used to build motions (body frame, pose 0)."""

    joints0: np.ndarray  # (J, 3)
    hands: dict  # side -> Hand
    elbow_axis: dict  # side -> (3,) local hinge axis (positive = flex)
    elbow_flex0: float  # radians of flexion at pose 0
    knee_axis: np.ndarray
    height: float
    hand_vertices: dict  # side -> (n,) vertex ids of the hand
    foot_vertices: dict  # side -> (n,) vertex ids of the foot
    instep_offset: dict  # side -> (3,) instep point relative to the foot joint
    pose0_vertices: np.ndarray  # (V, 3) mesh at pose 0


def anatomy(person: Person) -> Anatomy:
    m = person.model
    J0 = person.rest_joints()
    V0 = forward(m, person.betas, np.zeros((1, m.num_joints, 3)), np.eye(3)[None],
                 np.zeros((1, 3)), rest=person.rest).vertices[0]
    dom = np.asarray(m.weights.argmax(axis=1)).ravel()
    bone = [m.joint_names[d] for d in dom]

    def verts(prefixes, side):
        return np.array([i for i, b in enumerate(bone) if b.startswith(prefixes) and b.endswith("." + side)])
    n = person.j
    hands, elbow_axis, hand_v, foot_v, instep = {}, {}, {}, {}, {}
    for s in SIDES:
        w = J0[n(f"wrist.{s}")]
        a = J0[n(f"finger2-1.{s}")] - J0[n(f"finger5-1.{s}")]
        b = J0[n(f"finger3-1.{s}")] - w
        normal = _unit(np.cross(a, b) if s == "R" else np.cross(b, a))
        hv = verts(("wrist", "finger", "metacarpal"), s)
        hand_v[s] = hv
        centre = w + 0.55 * b
        # palm surface: the hand vertex furthest along the palm normal near the palm centre
        near = hv[np.linalg.norm(V0[hv] - centre, axis=1) < 0.035]
        palm = V0[near[np.argmax((V0[near] - centre) @ normal)]]
        knuck = J0[n(f"finger3-1.{s}")] + 0.02 * _unit(b)
        curl = {}
        for f in range(1, 6):
            for seg in range(1, 4):
                j = n(f"finger{f}-{seg}.{s}")
                child = n(f"finger{f}-{seg + 1}.{s}") if seg < 3 else None
                d = (J0[child] - J0[j]) if child is not None else (J0[j] - J0[m.parents[j]])
                curl[j] = _unit(np.cross(d, normal))
        hands[s] = Hand(s, n(f"wrist.{s}"), palm - w, normal, knuck - w, curl)
        u = J0[n(f"lowerarm01.{s}")] - J0[n(f"upperarm01.{s}")]
        f_ = J0[n(f"wrist.{s}")] - J0[n(f"lowerarm01.{s}")]
        elbow_axis[s] = _unit(np.cross(u, f_))
        fv = verts(("foot", "toe"), s)
        foot_v[s] = fv
        fj = J0[n(f"foot.{s}")]
        top = fv[np.argmax(V0[fv, 2] - 2.0 * np.abs((V0[fv] - fj) @ FWD - 0.07))]
        instep[s] = V0[top] - fj
    u = J0[n("lowerarm01.L")] - J0[n("upperarm01.L")]
    f_ = J0[n("wrist.L")] - J0[n("lowerarm01.L")]
    flex0 = float(np.arccos(np.clip(_unit(u) @ _unit(f_), -1, 1)))
    return Anatomy(J0, hands, elbow_axis, flex0, LEFT.copy(), float(V0[:, 2].max() - V0[:, 2].min()),
                   hand_v, foot_v, instep, V0)


# --------------------------------------------------------------------------------- postures
def arm_directions(person: Person, an: Anatomy, pose: np.ndarray, side: str,
                   upper_dir, elbow_flex: float) -> np.ndarray:
    """Point the upper arm of ``side`` along ``upper_dir`` (body frame) with ``elbow_flex``
    radians of flexion (minimal rotation from pose 0, so the arm's twist stays natural)."""
    n = person.j
    p = pose.copy()
    ua, la = n(f"upperarm01.{side}"), n(f"lowerarm01.{side}")
    p[la] = (elbow_flex - an.elbow_flex0) * an.elbow_axis[side]
    t, _ = person.fk(p[None], np.eye(3)[None], np.zeros((1, 3)))
    cur = _unit(t[0, la] - t[0, ua])
    want = _unit(upper_dir)
    ax = np.cross(cur, want)
    ang = np.arctan2(np.linalg.norm(ax), cur @ want)
    if np.linalg.norm(ax) > 1e-9:
        p = rotate_about_joint(person, p, ua, _unit(ax) * ang)
    return p


def standing(person: Person, an: Anatomy, rng: np.random.Generator) -> np.ndarray:
    """Relaxed standing: arms hanging a little away from the body, elbows slightly bent."""
    pose = np.zeros((person.model.num_joints, 3))
    for s, sgn in (("L", 1.0), ("R", -1.0)):
        d = -UP + LEFT * sgn * rng.uniform(0.2, 0.28) - FWD * rng.uniform(0.0, 0.08)
        pose = arm_directions(person, an, pose, s, d, rng.uniform(0.2, 0.4))
    return pose


def fist(person: Person, an: Anatomy, pose: np.ndarray, side: str, amount: float = 1.0) -> np.ndarray:
    """Curl the fingers of ``side`` (amount 1 = closed fist, 0.5 = a grip)."""
    p = pose.copy()
    for j, ax in an.hands[side].curl_axes.items():
        name = person.model.joint_names[j]
        ang = (0.6 if name.startswith("finger1") else 1.25) * amount
        p[j] = ax * ang
    return p


def bend(person: Person, pose: np.ndarray, joints: tuple[str, ...], rotvec_body) -> np.ndarray:
    """Distribute a rotation (body-frame axis-angle (3,)) evenly over a chain of joints
    (e.g. the spine), each rotating about its own head."""
    p = pose.copy()
    r = np.asarray(rotvec_body, float) / len(joints)
    for name in joints:
        p = rotate_about_joint(person, p, person.j(name), r)
    return p


SPINE = ("spine05", "spine03", "spine01")
NECK = ("neck01", "head")


def arm_dofs(person: Person, an: Anatomy, side: str, clavicle: bool = True, wrist: bool = True,
             weight: float = 0.02, twist_max: float = 1.2) -> list[Dof]:
    """IK unknowns of an arm: clavicle (stiff), shoulder (ball), elbow (hinge), forearm twist
    (up to ``twist_max`` radians), wrist (ball, stiff), thumb (two joints, stiff)."""
    n = person.j
    d = []
    if clavicle:
        d.append(Dof(n(f"clavicle.{side}"), weight=weight * 8, limits=(0, 0.35)))
    d.append(Dof(n(f"upperarm01.{side}"), weight=weight, limits=(0, 2.6)))
    d.append(Dof(n(f"lowerarm01.{side}"), kind="hinge", axis=tuple(an.elbow_axis[side]),
                 limits=(0.05 - an.elbow_flex0, 2.4 - an.elbow_flex0), weight=weight))
    d.append(Dof(n(f"lowerarm02.{side}"), weight=weight * 4, limits=(0, twist_max)))
    if wrist:
        d.append(Dof(n(f"wrist.{side}"), weight=weight * 6, limits=(0, 0.9)))
        # the thumb may move out of the way (it is what pokes into the other person)
        for seg in (1, 2):
            d.append(Dof(n(f"finger1-{seg}.{side}"), weight=weight * 4, limits=(0, 0.8)))
    return d


def leg_dofs(person: Person, an: Anatomy, side: str, weight: float = 0.02) -> list[Dof]:
    """IK unknowns of a leg: hip (ball), knee (hinge about the body's left axis), ankle."""
    n = person.j
    return [Dof(n(f"upperleg01.{side}"), weight=weight, limits=(0, 1.8)),
            Dof(n(f"lowerleg01.{side}"), kind="hinge", axis=tuple(an.knee_axis), limits=(0.0, 2.2),
                weight=weight),
            Dof(n(f"foot.{side}"), weight=weight * 4, limits=(0, 0.8))]


def idle(person: Person, pose: np.ndarray, u: np.ndarray, rng: np.random.Generator,
         amp: float = 1.0) -> np.ndarray:
    """Small living motion over time (breathing, sway, head): pose (J, 3) -> (N, J, 3) for
    sample times u (N,) seconds."""
    out = np.repeat(pose[None], len(u), 0)
    for name, scale in (("spine03", 0.025), ("spine01", 0.02), ("neck01", 0.04), ("head", 0.05)):
        j = person.j(name)
        for ax in range(3):
            fr = rng.uniform(0.15, 0.6, 2)
            ph = rng.uniform(0, 2 * np.pi, 2)
            out[:, j, ax] += amp * scale * (np.sin(2 * np.pi * fr[0] * u + ph[0])
                                            + 0.5 * np.sin(2 * np.pi * fr[1] * u + ph[1])) / 1.5
    return out
