"""Two-person motion synthesis: nominal tracks, contacts driven by inverse kinematics, contact
refinement on the true surfaces and separation of interpenetrating bodies.

Time: a master timeline at the mocap rate (``constants.MOCAP_HZ``) covers the mocap capture,
which starts ``-sync_offset_s`` before the first video frame; video frame ``i`` is master
sample ``m0 + i * step`` (``step = MOCAP_HZ / VIDEO_FPS``, an integer). Everything (IK, checks)
runs on the master timeline, so the marker samples and the video frames see the same bodies.

A :class:`Contact` makes person ``who`` put an effector point (a palm, a fist, an instep) on an
:class:`Anchor` of the other person (a point attached to one of their joint frames), blended in
and out by a weight profile. Synthesis is a few passes of: IK for every contact and sample,
skin both meshes, measure the true gap at each contact and shift the IK target along the
surface normal so the surfaces touch (by ``constants.CONTACT_PRESS_M``), and push the bodies
apart where other parts interpenetrate.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from body import forward
from geometry import VertexNormals, vertex_normals
from studio import constants as C
from studio.kin import Dof, Goal, Person, solve_ik


@dataclass(frozen=True)
class Timeline:
    """frames: video frames; n: master samples; m0: master index of video frame 0;
    step: master samples per video frame; hz: master (= mocap) rate; t: (n,) video time of each
    master sample, seconds (negative before the first video frame)."""

    frames: int
    n: int
    m0: int
    step: int
    hz: float

    @property
    def t(self) -> np.ndarray:
        return (np.arange(self.n) - self.m0) / self.hz

    @property
    def video_samples(self) -> np.ndarray:
        """(frames,) master indices of the video frames."""
        return self.m0 + self.step * np.arange(self.frames)

    @property
    def duration(self) -> float:
        """Video duration, seconds (first to last frame)."""
        return (self.frames - 1) * self.step / self.hz


def make_timeline(frames: int, fps: float = C.VIDEO_FPS, hz: float = C.MOCAP_HZ,
                  sync_offset_s: float = C.SYNC_OFFSET_S, tail_s: float = C.MOCAP_TAIL_S) -> Timeline:
    step = hz / fps
    m0 = -sync_offset_s * hz
    if abs(step - round(step)) > 1e-9 or abs(m0 - round(m0)) > 1e-6 or m0 < 0:
        raise ValueError(f"mocap rate {hz} Hz must be a multiple of {fps} fps and the sync offset "
                         f"{sync_offset_s} s a non-positive multiple of 1/{hz} s")
    step, m0 = int(round(step)), int(round(m0))
    n = m0 + step * (frames - 1) + 1 + int(round(tail_s * hz))
    return Timeline(frames, n, m0, step, hz)


def ramp(u: np.ndarray, a: float, b: float) -> np.ndarray:
    """Minimum-jerk step from 0 (u <= a) to 1 (u >= b)."""
    x = np.clip((np.asarray(u, float) - a) / max(b - a, 1e-9), 0, 1)
    return x ** 3 * (10 - 15 * x + 6 * x ** 2)


def pulse(u: np.ndarray, a: float, b: float, c: float, d: float) -> np.ndarray:
    """0 before a, up to 1 by b, 1 until c, down to 0 by d (minimum-jerk edges)."""
    return ramp(u, a, b) * (1 - ramp(u, c, d))


@dataclass
class Track:
    """Motion of one person on the master timeline: pose (N, J, 3) local axis-angle, R (N, 3, 3)
    global orientation, T (N, 3) translation (metres, world)."""

    pose: np.ndarray
    R: np.ndarray
    T: np.ndarray

    def copy(self) -> Track:
        return Track(self.pose.copy(), self.R.copy(), self.T.copy())


@dataclass(frozen=True)
class Anchor:
    """A point on a person's surface attached to a joint frame: offset (3,) and outward normal
    (3,) in that frame (world-aligned at pose 0)."""

    joint: int
    offset: np.ndarray
    normal: np.ndarray

    def world(self, person: Person, track: Track, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(len(idx), 3) points and unit normals at master samples idx."""
        t, G = person.fk(track.pose[idx], track.R[idx], track.T[idx])
        Gj = G[:, self.joint]
        return t[:, self.joint] + Gj @ self.offset, Gj @ self.normal


@dataclass(frozen=True)
class Fixed:
    """A target given in the world: points (N, 3) on the master timeline and one unit normal
    (3,) (the direction the effector surface is pressed against: it faces ``-normal``)."""

    points: np.ndarray
    normal: np.ndarray

    def world(self, person: Person, track: Track, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: ARG002
        return self.points[idx], np.broadcast_to(self.normal, (len(idx), 3))


@dataclass(frozen=True)
class Shifted:
    """A target moved by a world offset per master sample: ``base`` (an :class:`Anchor` or
    :class:`Fixed`) plus ``shift`` (N, 3) metres (e.g. a hand held in place while the hand it is
    anchored to moves away)."""

    base: Anchor | Fixed
    shift: np.ndarray

    def world(self, person: Person, track: Track, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, n = self.base.world(person, track, idx)
        return p + self.shift[idx], n


def anchor_at(person: Person, pose: np.ndarray, point_body: np.ndarray, joint: int,
              direction: np.ndarray | None = None) -> Anchor:
    """The anchor on ``person`` (posed by ``pose`` (J, 3) in the body frame) at the surface point
    nearest to ``point_body`` (3,), or where the ray from ``point_body`` along ``direction``
    leaves the body; attached to ``joint``."""
    out = forward(person.model, person.betas, pose[None], np.eye(3)[None], np.zeros((1, 3)),
                  rest=person.rest)
    V = out.vertices[0]
    N = vertex_normals(V, person.model.faces)
    p = np.asarray(point_body, float)
    if direction is None:
        k = int(np.argmin(np.linalg.norm(V - p, axis=1)))
    else:
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        rel = V - p
        along = rel @ d
        perp = np.linalg.norm(rel - along[:, None] * d, axis=1)
        ok = (along > 0) & (perp < 0.02) & (N @ d > 0.3)
        if not ok.any():
            ok = perp < np.sort(perp)[20]
        cand = np.flatnonzero(ok)
        k = int(cand[np.argmax(along[cand])])
    G = out.joint_rot[0, joint]
    return Anchor(joint, G.T @ (V[k] - out.joints[0, joint]), G.T @ N[k])


@dataclass
class Contact:
    """Person ``who`` puts ``effector`` (joint, offset (3,) in its frame) on ``anchor`` of the
    other person (an :class:`Anchor`, a :class:`Fixed` world target, or either moved by
    :class:`Shifted`), at ``clearance`` metres outside the anchor along its normal (the
    effector's own thickness; refined on the true surfaces; a float, or (N,) over the master
    timeline, e.g. to come in and leave from above). weight: (N,) in [0, 1] on the master
    timeline (1 = in contact). eff_normal: optional (3,) outward normal of the effector surface
    in its frame, turned to face the anchor (orient_weight). poles: extra goals
    ``(joint, offset, fn(i, tracks) -> (3,) world target at master sample i, weight)`` (e.g. an
    elbow kept outside the partner). region: (n,) vertex ids of the effector's body part (for gap
    measurement). name: for reports (``"hand.R->back"``)."""

    who: int
    dofs: list[Dof]
    effector: tuple[int, np.ndarray]
    anchor: Anchor | Fixed | Shifted
    clearance: float
    weight: np.ndarray
    region: np.ndarray
    eff_normal: np.ndarray | None = None
    orient_weight: float = 0.3
    poles: list = field(default_factory=list)
    name: str = ""
    anchor_region: np.ndarray | None = None
    refine: bool = True  # measure the true gap and correct the target (False: fixed target)
    chain_vertices: np.ndarray | None = None  # vertices moved by the IK joints (set by synthesize)
    vertex_bone: np.ndarray | None = None  # (V,) dominant bone of each vertex (set by synthesize)
    repel: dict = field(default_factory=dict)  # sample -> {key: (joint, offset, world target)}
    adjust: np.ndarray | None = None  # (N,) learned clearance corrections
    repel_gain: np.ndarray | None = None  # (N,) weight factor of the repulsion goals


def _solve_contacts(people: list[Person], tracks: list[Track], nominal: list[Track],
                    contacts: list[Contact], active: np.ndarray | None = None,
                    warm_pass: bool = False) -> None:
    """Run the IK of every contact over the timeline (in place on tracks), at the samples
    ``active`` (N,) bool (default all). warm_pass: start each sample from its own current
    solution (a later pass) instead of the previous sample's. Each contact's ``adjust`` and
    ``repel_gain`` are set (by :func:`_synthesize`)."""
    N = len(tracks[0].T)
    for c in contacts:
        me, other = c.who, 1 - c.who
        P, tr, nom = people[me], tracks[me], nominal[me]
        idx = np.flatnonzero(c.weight > 1e-4)
        if active is not None:
            idx = idx[active[idx]]
        if not len(idx):
            continue
        a_pt, a_n = c.anchor.world(people[other], tracks[other], idx)
        clear = np.broadcast_to(np.asarray(c.clearance, float), (N,))
        joint, off = c.effector
        t0, G0 = P.fk(nom.pose[idx], nom.R[idx], nom.T[idx])
        e_nom = t0[:, joint] + G0[:, joint] @ off
        prev = None
        for k, i in enumerate(idx):
            w = c.weight[i]
            tgt = a_pt[k] + a_n[k] * (clear[i] + c.adjust[i])
            goal = (1 - w) * e_nom[k] + w * tgt
            goals = [Goal(joint, tuple(off), tuple(goal), 1.0)]
            if c.eff_normal is not None and c.orient_weight > 0 and w > 0.05:
                # the point 5 cm out of the effector surface should lie 5 cm "into" the anchor
                en = c.eff_normal * 0.05
                goals.append(Goal(joint, tuple(off + en), tuple(goal - a_n[k] * 0.05),
                                  c.orient_weight * w))
            for pj, poff, fn, pw in c.poles:
                goals.append(Goal(pj, tuple(poff), tuple(fn(i, tracks)), pw * w))
            for bj, boff, banc in c.repel.get(i, {}).values():
                btarget = banc.world(people[other], tracks[other], np.array([i]))[0][0]
                goals.append(Goal(bj, tuple(boff), tuple(btarget), C.REPEL_WEIGHT * c.repel_gain[i]))
            start = tr.pose[i] if (prev is None or warm_pass) else _carry(tr.pose[i], prev, c.dofs)
            sol = solve_ik(P, start, tr.R[i], tr.T[i], goals, c.dofs, nominal=nom.pose[i],
                           iters=C.IK_ITERS)
            for d in c.dofs:
                tr.pose[i, d.joint] = sol[d.joint]
            prev = sol
        # per-sample solutions jitter a little (goals appear and vanish): smooth the solved
        # joints over time, as a real motion would be
        js = [d.joint for d in c.dofs]
        tr.pose[:, js] = gaussian_filter1d(tr.pose[:, js], C.IK_SMOOTH_SAMPLES, axis=0, mode="nearest")


def _carry(pose: np.ndarray, prev: np.ndarray, dofs: list[Dof]) -> np.ndarray:
    """Warm start: the previous sample's solution on the IK joints."""
    p = pose.copy()
    for d in dofs:
        p[d.joint] = prev[d.joint]
    return p


def skin_all(people: list[Person], tracks: list[Track], idx: np.ndarray) -> list[np.ndarray]:
    """Skinned vertices (len(idx), V, 3) of each person at master samples idx."""
    out = []
    for P, tr in zip(people, tracks, strict=True):
        out.append(forward(P.model, P.betas, tr.pose[idx], tr.R[idx], tr.T[idx], rest=P.rest).vertices)
    return out


def pair_distances(V0: np.ndarray, V1: np.ndarray, faces: np.ndarray, normals: VertexNormals,
                   near: float = C.NEAR_M) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Signed distance of every vertex of each body to the other body's surface (negative
    inside), where it matters: vertices within ``near`` of the other's bounding box.

    V0, V1: (V, 3) metres. Returns ([d0 (V,), d1 (V,)], [c0 (V, 3), c1 (V, 3)]): distances
    (+inf for vertices far from the other body) and the closest points on the other body (NaN
    where far). Exact (libigl, pseudonormal sign, on the other body's local faces) for vertices
    less than constants.EXACT_BAND_M outside the other body by a first estimate (the
    nearest vertex, signed by its normal), on a patch of the other surface around them
    (constants.EXACT_PATCH_K nearest vertices); further vertices get that
    nearest-vertex distance, signed by the vertex normal there (only deep penetrations reach
    this case, confirmed by the winding number); vertices with no vertex of the other body within constants.FAR_M count as far.
    """
    import igl

    V = [V0, V1]
    out = [np.full(len(V0), np.inf), np.full(len(V1), np.inf)]
    cps = [np.full((len(V0), 3), np.nan), np.full((len(V1), 3), np.nan)]
    lo = np.maximum(V0.min(0), V1.min(0)) - near
    hi = np.minimum(V0.max(0), V1.max(0)) + near
    if np.any(lo > hi):
        return out, cps
    inbox = [np.all((v > lo) & (v < hi), axis=1) for v in V]
    if not inbox[0].any() or not inbox[1].any():
        return out, cps
    for a in range(2):
        b = 1 - a
        qa = np.flatnonzero(inbox[a])
        vb = np.flatnonzero(inbox[b])
        tree = cKDTree(V[b][vb])
        dnn, k = tree.query(V[a][qa], distance_upper_bound=C.FAR_M)
        far = ~np.isfinite(dnn)
        qa, dnn, k = qa[~far], dnn[~far], k[~far]
        Nb = normals(V[b])
        sign = np.sign(np.einsum("md,md->m", V[a][qa] - V[b][vb[k]], Nb[vb[k]]))
        d = dnn * np.where(sign == 0, 1.0, sign)
        cp = V[b][vb[k]].copy()
        band = (d < C.EXACT_BAND_M) & (dnn < 2 * C.EXACT_BAND_M)
        if band.any():
            # a local patch of the other surface around the queried points is enough
            _, nb = tree.query(V[a][qa[band]], k=C.EXACT_PATCH_K)
            inset = np.zeros(len(V[b]), bool)
            inset[vb[np.unique(nb)]] = True
            fb = faces[inset[faces].any(1)]
            sd, _, cc, _ = igl.signed_distance(V[a][qa[band]], V[b], fb,
                                               igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
            d[band] = sd
            cp[band] = cc
        deep = np.flatnonzero(~band & (d < 0))
        if len(deep):
            # the normal-sign guess fails in folds (armpits, between fingers): ask the winding
            # number of the whole other body
            w = igl.fast_winding_number(V[b], faces, V[a][qa[deep]])
            d[deep[w < 0.5]] = dnn[deep[w < 0.5]]
        out[a][qa] = d
        cps[a][qa] = cp
    return out, cps


@dataclass(frozen=True)
class SynthReport:
    """min_gap_m: (contacts, N) measured gap of each contact at each sample (NaN where
    inactive); max_penetration_m: (N,) deepest approximate penetration between the bodies."""

    min_gap_m: np.ndarray
    max_penetration_m: np.ndarray


def synthesize(people: list[Person], nominal: list[Track], contacts: list[Contact],
               movable: int, check_samples: np.ndarray, passes: int = C.SYNTH_PASSES
               ) -> tuple[list[Track], SynthReport]:
    """Solve the contacts and separate the bodies.

    people: the two persons; nominal: their nominal tracks (not modified); movable: the person
    whose root is pushed away when bodies interpenetrate outside the contacts; check_samples:
    master samples where gaps and penetration are measured and corrected (the video frames;
    corrections are smoothed over the samples between them). Returns the final tracks and a
    report (measured at check_samples, NaN / 0 elsewhere).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # tiny dense solves: threads only add overhead
        return _synthesize(people, nominal, contacts, movable, passes, check_samples)


def _add_repulsion(c: Contact, people: list[Person], tracks: list[Track], i: int,
                   V: list[np.ndarray], d: np.ndarray, cp: np.ndarray) -> bool:
    """Where the contact's limb (``c.chain_vertices``) is inside the other body at sample i,
    add IK goals that pull the deepest points out along the way to the closest surface point
    (kept for later passes, updated if the point is still inside). The goal's target is
    attached to the other body (an :class:`Anchor` on its nearest vertex's bone), so it follows
    that body when it moves."""
    person, track = people[c.who], tracks[c.who]
    other, otrack = people[1 - c.who], tracks[1 - c.who]
    Vm, Vo = V[c.who], V[1 - c.who]
    if c.chain_vertices is None:
        return False
    cv = c.chain_vertices
    depth = -d[cv]
    tol = np.where(np.isin(cv, c.region), C.CONTACT_PRESS_M + C.PENETRATION_TOL_M, C.PENETRATION_TOL_M)
    bad = depth > tol
    if not bad.any():
        return False
    t, G = person.fk(track.pose[i:i + 1], track.R[i:i + 1], track.T[i:i + 1])
    to, Go = other.fk(otrack.pose[i:i + 1], otrack.R[i:i + 1], otrack.T[i:i + 1])
    tree = cKDTree(Vo)
    goals = c.repel.setdefault(i, {})
    order = np.argsort(-depth)
    used = set()
    for q in order[: 4 * C.REPEL_POINTS]:
        if not bad[q]:
            break
        v = cv[q]
        bone = int(c.vertex_bone[v])
        if bone in used:
            continue
        used.add(bone)
        out = cp[v] - Vm[v]
        n = np.linalg.norm(out)
        if not np.isfinite(n) or n < 1e-9:
            continue
        target = cp[v] + out / n * C.SEPARATION_MARGIN_M
        off = G[0, bone].T @ (Vm[v] - t[0, bone])
        ob = int(c.vertex_bone[tree.query(cp[v])[1]])
        anc = Anchor(ob, Go[0, ob].T @ (target - to[0, ob]), np.zeros(3))
        goals[(bone, v)] = (bone, off, anc)
        if len(used) >= C.REPEL_POINTS:
            break
    return bool(used)


def _is_desc(j: int, anc: int, parents: np.ndarray) -> bool:
    """True if joint j is anc or below it."""
    while j >= 0:
        if j == anc:
            return True
        j = parents[j]
    return False


def _near_samples(people: list[Person], tracks: list[Track]) -> np.ndarray:
    """(N,) bool: samples where the two bodies' joint boxes, grown by constants.FLESH_M (the
    most flesh around a joint), overlap (a cheap broad phase)."""
    boxes = []
    for P, tr in zip(people, tracks, strict=True):
        t, _ = P.fk(tr.pose, tr.R, tr.T)
        boxes.append((t.min(1) - C.FLESH_M, t.max(1) + C.FLESH_M))
    lo = np.maximum(boxes[0][0], boxes[1][0])
    hi = np.minimum(boxes[0][1], boxes[1][1])
    return np.all(lo <= hi, axis=1)


def _synthesize(people, nominal, contacts, movable, passes, check_samples):
    tracks = [t.copy() for t in nominal]
    N = len(tracks[0].T)
    normals = VertexNormals(people[0].model.faces, people[0].model.num_vertices)
    push = np.zeros((N, 3))
    base_T = nominal[movable].T.copy()
    dom = np.asarray(people[0].model.weights.argmax(axis=1)).ravel()
    par = people[0].model.parents
    chain_any = [np.zeros(people[i].model.num_vertices, bool) for i in range(2)]
    for c in contacts:
        c.adjust = np.zeros(N)
        c.repel_gain = np.ones(N)
        c.repel = {}
        c.vertex_bone = dom
        moved = {d.joint for d in c.dofs}
        sub = np.array([any(_is_desc(j, m, par) for m in moved) for j in range(len(par))])
        c.chain_vertices = np.flatnonzero(sub[dom])
        chain_any[c.who][c.chain_vertices] = True
    off_region = [np.setdiff1d(c.chain_vertices, c.region) for c in contacts]
    report = None
    todo = np.ones(N, bool)
    faces = people[0].model.faces
    check = np.zeros(N, bool)  # measure at the video frames only (the ground truth's samples)
    check[check_samples] = True
    spread = int(np.min(np.diff(check_samples))) - 1 if len(check_samples) > 1 else 0
    gaps = np.full((len(contacts), N), np.nan)
    limb = np.full((len(contacts), N), np.inf)  # deepest point of each contact's limb
    arm = np.full((len(contacts), N), np.inf)  # ... of the limb without the effector's part
    pen = np.zeros(N)

    def measure(only=None):
        """Gaps, interpenetration and corrections at the checked samples (those in ``only``;
        the others keep their last values)."""
        near = _near_samples(people, tracks)
        near[~check] = False
        sel = near if only is None else near & only
        clear = check if only is None else check & only
        gaps[:, clear] = np.nan
        limb[:, clear] = np.inf
        arm[:, clear] = np.inf
        pen[clear] = 0.0
        idx = np.flatnonzero(sel)
        need = np.zeros((N, 3))
        repelled = np.zeros(N, bool)
        verts = skin_all(people, tracks, idx) if len(idx) else None
        for k, i in enumerate(idx):
            V = [verts[0][k], verts[1][k]]
            d, cp = pair_distances(V[0], V[1], faces, normals)
            for ci, c in enumerate(contacts):
                limb[ci, i] = d[c.who][c.chain_vertices].min()
                arm[ci, i] = d[c.who][off_region[ci]].min(initial=np.inf)
                if c.weight[i] > 0.05 and c.refine:
                    g = d[c.who][c.region].min()
                    if c.anchor_region is not None:
                        g = min(g, d[1 - c.who][c.anchor_region].min())
                    gaps[ci, i] = g
            pen[i] = max(0.0, -min(d[0].min(), d[1].min()))
            for c in contacts:
                if _add_repulsion(c, people, tracks, i, V, d[c.who], cp[c.who]):
                    lo_i, hi_i = max(0, i - spread), min(N, i + spread + 1)
                    for j2 in range(lo_i, hi_i):
                        if j2 != i:
                            c.repel.setdefault(j2, {}).update(c.repel[i])
                    repelled[lo_i:hi_i] = True
            free = min(_body_overlap(d[0], cp[0], V[1], chain_any[0], chain_any[1]),
                       _body_overlap(d[1], cp[1], V[0], chain_any[1], chain_any[0]))
            if -free > C.PENETRATION_TOL_M:
                # bodies (not the IK limbs) overlap: push the movable person away from the
                # other along the horizontal line between their roots
                cm = (tracks[movable].T[i] + people[movable].rest.joints[0, 0]) - (
                    tracks[1 - movable].T[i] + people[1 - movable].rest.joints[0, 0])
                cm[2] = 0
                need[i] = cm / np.linalg.norm(cm) * (-free + C.SEPARATION_MARGIN_M)
        return gaps, limb, pen, need, repelled

    def apply_push(need):
        nonlocal push
        if not np.any(need):
            return np.zeros(N, bool)
        # a smooth push, held while needed and eased in and out
        mag = _grow(np.linalg.norm(need, axis=1))
        env = gaussian_filter1d(_grow(mag), C.SEPARATION_SMOOTH)
        dirs = need.sum(0)
        dirs = dirs / max(np.linalg.norm(dirs), 1e-9)
        push = push + env[:, None] * dirs[None]
        tracks[movable].T = base_T + push
        return env > C.REFINE_TOL_M

    base_w = [c.weight.copy() for c in contacts]
    scale = [np.ones(N) for _ in contacts]
    last = passes + C.RETREAT_ROUNDS + C.GIVE_WAY_ROUNDS
    for it in range(last + 1):
        tracks[movable].T = base_T + push
        if todo.any():
            _solve_contacts(people, tracks, nominal, contacts, active=todo, warm_pass=it > 0)
        gaps, limb, pen, need, repelled = measure(None if it <= passes else _grow_mask(todo, 1))
        report = SynthReport(gaps.copy(), pen.copy())
        if it == last or (it >= passes and pen.max() <= C.PENETRATION_MAX_M):
            break
        todo = repelled.copy() if it < passes else np.zeros(N, bool)
        if it < passes:
            # contact refinement: move each target along its normal by the measured gap
            for ci, c in enumerate(contacts):
                g = gaps[ci]
                ok = np.isfinite(g)
                if ok.any():
                    # in contact: close the gap; while reaching or letting go: only undo
                    # penetration (the blend moves the effector by weight * correction)
                    full = c.weight > 0.98
                    want = np.where(full, g + C.CONTACT_PRESS_M, np.minimum(g + C.CONTACT_PRESS_M, 0.0))
                    corr = np.interp(np.arange(N), np.flatnonzero(ok), want[ok])
                    corr = corr / np.maximum(c.weight, 0.2) * (c.weight > 0.05)
                    delta = C.REFINE_GAIN * gaussian_filter1d(corr, 1.0) * (c.weight > 0.05)
                    c.adjust = c.adjust - delta
                    todo |= np.abs(delta) > C.REFINE_TOL_M
        elif it >= passes + C.RETREAT_ROUNDS:
            # last resort: where a limb is still inside the other body, reach less there
            for ci, c in enumerate(contacts):
                bad = (limb[ci] < -C.PENETRATION_MAX_M) & check
                if bad.any():
                    cut = np.ones(N)
                    cut[_grow_mask(bad, spread + 1)] = C.GIVE_WAY_FACTOR
                    scale[ci] = scale[ci] * np.minimum(1.0, gaussian_filter1d(cut, 1.0) + 0.0)
                    c.weight = base_w[ci] * scale[ci]
                    todo |= cut < 1
        else:
            # where a limb is still inside the other body: first push it out harder (the hand
            # stays on its target), then aim further out there (the hand lifts off)
            for ci, c in enumerate(contacts):
                bad = (limb[ci] < -C.PENETRATION_MAX_M) & check
                # (only where the limb away from the effector is inside: where the effector
                # itself is, its target is what is wrong)
                stiffen = bad & (arm[ci] < -C.PENETRATION_MAX_M) & (c.repel_gain < C.REPEL_GAIN_MAX)
                if stiffen.any():
                    grown = _grow_mask(stiffen, spread + 1)
                    c.repel_gain[grown] = np.minimum(c.repel_gain[grown] * 2.0, C.REPEL_GAIN_MAX)
                    todo |= grown
                    bad &= ~stiffen
                if bad.any():
                    depth = np.zeros(N)
                    depth[bad] = -limb[ci][bad] + C.SEPARATION_MARGIN_M
                    depth = gaussian_filter1d(_grow(depth), 1.5)
                    c.adjust = c.adjust + depth / np.maximum(c.weight, 0.2) * (c.weight > 0.05)
                    todo |= depth > C.REFINE_TOL_M
        todo |= apply_push(need)
        if not todo.any():
            break
    return tracks, report


def _body_overlap(d: np.ndarray, cp: np.ndarray, V_other: np.ndarray, mine: np.ndarray,
                  theirs: np.ndarray) -> float:
    """Deepest signed distance of this body's vertices that are neither on its IK limbs
    (``mine``) nor inside the other's IK limbs (closest point within constants.LIMB_NEAR_M of
    one of ``theirs`` vertices): the overlap that moving the roots apart can fix."""
    cand = np.flatnonzero((d < -C.PENETRATION_TOL_M) & ~mine)
    if not len(cand):
        return float(np.min(d[~mine], initial=np.inf))
    if theirs.any():
        dl, _ = cKDTree(V_other[theirs]).query(cp[cand])
        cand = cand[dl > C.LIMB_NEAR_M]
    return float(d[cand].min()) if len(cand) else 0.0


def _grow_mask(mask: np.ndarray, n: int) -> np.ndarray:
    """Dilate a boolean mask over time by n samples."""
    from scipy.ndimage import maximum_filter1d

    return maximum_filter1d(mask.astype(np.uint8), size=2 * n + 1).astype(bool)


def _grow(mag: np.ndarray) -> np.ndarray:
    """Dilate a per-sample push magnitude in time (a few samples) so the smoothed push still
    covers every sample that needed it."""
    from scipy.ndimage import maximum_filter1d

    return maximum_filter1d(mag, size=2 * C.SEPARATION_SMOOTH + 1)
