"""Contact annotations from the true geometry, as CHI3D's annotators would make them: the
contact interval (frames where the two surfaces touch), one annotated frame, and a signature
of 3-6 facet-to-facet correspondences that really touch, spread over the contact area, with
their region ids."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry import VertexNormals, deepest_inside, face_centroids, inside_points, nearest_surface
from studio import constants as C
from studio.motion import pair_distances


@dataclass(frozen=True)
class ContactTruth:
    """min_dist: (F,) smallest signed distance between the bodies per video frame (metres,
    negative = interpenetration); touching: (F,) int vertices within constants.TOUCH_M of the
    other body; start, end: contact interval (inclusive video frames) or -1; fr_id: annotated
    frame or -1; faces: (P, 2) facet pairs (person 0, person 1); regions: (P, 2); dist: (P,)
    distance from each person-0 facet's centroid to its person-1 facet, metres (an upper
    bound of the facet-to-facet distance)."""

    min_dist: np.ndarray
    touching: np.ndarray
    start: int
    end: int
    fr_id: int
    faces: np.ndarray
    regions: np.ndarray
    dist: np.ndarray


def longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start, end) inclusive of the longest run of True, or (-1, -1)."""
    best, cur, s0 = (-1, -1), 0, 0
    for i, m in enumerate(mask):
        if m:
            if cur == 0:
                s0 = i
            cur += 1
            if cur > best[1] - best[0] + 1 or best[0] < 0:
                best = (s0, i)
        else:
            cur = 0
    return best


def annotate(verts0: np.ndarray, verts1: np.ndarray, faces: np.ndarray, face_region: np.ndarray,
             rng: np.random.Generator, hint: tuple[int, int] | None = None,
             incidental: np.ndarray | None = None) -> ContactTruth:
    """Contact truth of one sequence.

    verts0, verts1: (F, V, 3) vertices of person 0 (marker wearer) and person 1 at the video
    frames, metres; faces: (T, 3); face_region: (T,) region id per facet; hint: optional
    (first, last) frames where the motion plans contact (the search for the annotated frame
    prefers them); incidental: region ids whose mutual touches an annotator would skip when
    there are others (feet). Returns a :class:`ContactTruth`.
    """
    F = len(verts0)
    normals = VertexNormals(faces, verts0.shape[1])
    min_dist = np.full(F, np.inf)
    touching = np.zeros(F, int)
    for f in range(F):
        d, _ = pair_distances(verts0[f], verts1[f], faces, normals)
        min_dist[f] = min(d[0].min(), d[1].min())
        touching[f] = int((d[0] < C.TOUCH_M).sum() + (d[1] < C.TOUCH_M).sum())
    start, end = longest_run(min_dist < C.TOUCH_M)
    empty = np.zeros((0, 2), np.int64)
    if start < 0:
        return ContactTruth(min_dist, touching, -1, -1, -1, empty, empty, np.zeros(0))
    # the annotated frame: most touching area, preferring the planned contact phase
    score = touching[start:end + 1].astype(float)
    if hint is not None:
        fr = np.arange(start, end + 1)
        score = score * np.where((fr >= hint[0]) & (fr <= hint[1]), 1.0, 0.5)
    fr_id = int(start + np.argmax(score))
    V0, V1 = verts0[fr_id], verts1[fr_id]
    cen = face_centroids(V0, faces)
    d1, partner, _ = nearest_surface(cen, V1, faces)
    cand = np.flatnonzero(d1 < C.SIGNATURE_DIST_M)
    if incidental is not None and len(cand):
        # feet brushing while standing close are not what an annotator marks
        keep = ~np.isin(face_region[cand], incidental) | ~np.isin(face_region[partner[cand]], incidental)
        if keep.sum() >= C.SIGNATURE_PAIRS[0]:
            cand = cand[keep]
    if not len(cand):
        return ContactTruth(min_dist, touching, start, end, fr_id, empty, empty, np.zeros(0))
    want = int(rng.integers(C.SIGNATURE_PAIRS[0], C.SIGNATURE_PAIRS[1] + 1))
    # spread like an annotator: farthest-point sampling over the candidate centroids
    pick = [int(cand[np.argmin(d1[cand])])]
    while len(pick) < min(want, len(cand)):
        dd = np.min(np.linalg.norm(cen[cand][:, None] - cen[pick][None], axis=2), axis=1)
        if dd.max() <= 0:
            break
        pick.append(int(cand[np.argmax(dd)]))
    pick = np.array(pick)
    pairs = np.stack([pick, partner[pick]], 1).astype(np.int64)
    regions = face_region[pairs]
    return ContactTruth(min_dist, touching, start, end, fr_id, pairs, regions.astype(np.int64),
                        d1[pick])


@dataclass(frozen=True)
class MotionCheck:
    """What a synthesized motion achieved. depth: (F,) deepest true interpenetration per video
    frame, metres (:func:`geometry.interpenetration`); gaps: {contact name: (H,) signed
    distance from the effector region to the other body at each video frame where the contact
    is fully held (weight > 0.98), metres; negative = pressed in}."""

    depth: np.ndarray
    gaps: dict

    def touching(self, name: str) -> float:
        """Fraction of the held frames of contact ``name`` where the surfaces touch
        (gap < constants.TOUCH_M)."""
        g = self.gaps[name]
        return float(np.mean(g < C.TOUCH_M)) if len(g) else 0.0

    @property
    def ok(self) -> bool:
        """The motion is good ground truth: never deeper than constants.MAX_TRUE_PENETRATION_M
        inside the other body, every contact touching in at least constants.MIN_TOUCHING of
        its held frames."""
        return bool(self.depth.max(initial=0.0) <= C.MAX_TRUE_PENETRATION_M
                    and all(self.touching(k) >= C.MIN_TOUCHING for k in self.gaps))

    def summary(self) -> str:
        """One line: the deepest interpenetration and each contact's touching fraction."""
        t = ", ".join(f"{k} touching {self.touching(k):.2f}" for k in self.gaps)
        return f"deepest {1000 * self.depth.max(initial=0.0):.1f} mm" + (f", {t}" if t else "")


def check_motion(model, motion, verts: list[np.ndarray] | None = None) -> MotionCheck:
    """Measure a :class:`studio.session.SequenceMotion` on its video frames: interpenetration of
    the two bodies and, for each contact of its scene, the gap while it is held. verts: the two
    bodies' vertices (F, V, 3) at the video frames, if already skinned.

    A gap is the smallest signed distance from the effector region's vertices to the other
    body: unsigned to its surface (:func:`geometry.nearest_surface`), negative for the vertices the depth test
    found inside the other body (its winding numbers, :func:`geometry.inside_points`), so each
    frame's winding numbers are computed once, and not at all where the bodies are apart."""
    vs = motion.video_samples
    V = verts if verts is not None else [o.vertices for o in motion.skin(model)]
    faces = np.asarray(model.faces)
    inside = [inside_points(V[0][f], V[1][f], faces) for f in range(len(V[0]))]
    depth = np.array([deepest_inside(ins).depth for ins in inside])
    cast_people = motion.cast.people
    person_of_role = [next(i for i, s in enumerate(motion.order) if s.person is p) for p in cast_people]
    gaps = {}
    for k, c in enumerate(motion.scene.contacts):
        held = np.flatnonzero(c.weight[vs] > 0.98)
        me, other = person_of_role[c.who], person_of_role[1 - c.who]
        g = []
        for f in held:
            d = nearest_surface(V[me][f][c.region], V[other][f], faces).distance
            d[np.isin(c.region, inside[f][me].index)] *= -1.0
            g.append(d.min())
        gaps[c.name if c.name not in gaps else f"{c.name}#{k}"] = np.array(g)
    return MotionCheck(depth, gaps)
