"""The contact signature of one action, validated against a body model, and the paper's
selection operators ``psi_D`` / ``psi_N`` (``L_G = L_D + L_N``, ../shared/paper.tex).

The file is CHI3D's ``interaction_contact_signature.json`` (read by
:func:`formats.chi3d.read_contact_signatures`): per action the contact frame ``fr_id``, the
interval ``start_fr..end_fr`` (video frames) and, per body-model family (``smplx``, ``ghum``,
``anny``: the studio writes the last one, with ``region_names``), pairs of regions and pairs
of facets that touch; person 0 = the marker wearer, person 1 = the partner.

:func:`load_contact` turns one action into a :class:`ContactAnnotation` for one model and its
region map, or raises :class:`formats.errors.InputError` naming the file, the field
(``<action>.<family>_signature.<key>``) and the contact frame.

``C(P1, P2)`` of the paper = ``annotation.region_pairs``; ``psi_D(r)`` =
:func:`select_facets` (all facets of the region, a uniform sample of ``n`` of them, or the
annotated facets); ``psi_N(r1, r2)`` = :func:`select_normal_pairs` (the annotated facet pairs,
or the nearest-facet matches that ``Phi_D`` found: ``geometry.facet_distances``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from body.model import BodyModel
from body.regions import RegionMap, region_map
from formats.chi3d import FAMILIES, read_contact_signatures
from formats.errors import InputError

#: Model names (``BodyModel.name``) whose facets a family's signature indexes.
FAMILY_MODELS = {"anny": ("anny",), "smplx": ("smplx",), "ghum": ("ghum",)}
#: psi_D modes.
MODES = ("all", "uniform", "annotated")


@dataclass(frozen=True, eq=False)
class ContactAnnotation:
    """One action's contact annotation, checked against a body model and its region map.

    file, action, family: where it came from. interval: (start, end) video frames, inclusive
    (``(frame, frame)`` when the file gives no interval); frame: the annotated contact frame.
    region_pairs: (R, 2) int64 region ids (into the region map's ``names``) in contact, person 0
    (wearer) first, unique, in the file's order. facet_pairs: (N, 2) int64 facet ids of the
    model's ``faces`` (person 0, person 1) annotated in contact. pair_of_facets: (N,) int64 the
    row of ``region_pairs`` each facet pair belongs to. region_names: (R, 2) names of the pairs.
    """

    file: str
    action: str
    family: str
    interval: tuple[int, int]
    frame: int
    region_pairs: np.ndarray
    facet_pairs: np.ndarray
    pair_of_facets: np.ndarray
    region_names: tuple[tuple[str, str], ...]

    def __post_init__(self):
        for a in (self.region_pairs, self.facet_pairs, self.pair_of_facets):
            a.flags.writeable = False

    @property
    def has_contact(self) -> bool:
        """True when at least one region pair is annotated."""
        return len(self.region_pairs) > 0

    def active(self, frame: int) -> bool:
        """``L_G`` applies at video ``frame``: in the interval and some pair annotated."""
        return self.has_contact and self.interval[0] <= frame <= self.interval[1]

    def facets_of_pair(self, r: int) -> np.ndarray:
        """(n, 2) annotated facet pairs of region pair ``r``."""
        return self.facet_pairs[self.pair_of_facets == r]


def model_family(model: BodyModel) -> str | None:
    """The signature family whose facet ids index ``model``'s faces (None: none)."""
    for fam, names in FAMILY_MODELS.items():
        if model.name in names:
            return fam
    return None


def load_contact(path: str | Path, action: str, model: BodyModel, n_frames: int,
                 family: str = "anny", rmap: RegionMap | None = None) -> ContactAnnotation:
    """The contact annotation of ``action`` in the signature file ``path`` for ``model``.

    n_frames: frames of the sequence's videos (the interval must lie inside); family: which
    signature of the file to use; rmap: the region map the region ids index (default
    ``body.regions.region_map(model)``; pass ``body.regions.load_official(...)`` for CHI3D's
    official ids). An action without contact (no pairs) gives ``has_contact == False``.
    Raises InputError(path, field, msg, frame) on: the action missing, a family other than the
    model's, a region id or name unknown to the map, a facet outside the model's faces, a facet
    whose region is not an annotated region pair, an interval outside the sequence.
    """
    path = Path(path)
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
    sigs = read_contact_signatures(path)
    if action not in sigs:
        raise InputError(path, action, f"action missing (the file has: {sorted(sigs)})")
    s = sigs[action]
    fr = s.fr_id
    key = f"{action}.{family}_signature"
    regions, faces = s.regions(family), s.faces(family)
    mine = model_family(model)
    if mine != family:
        raise InputError(path, key, f"a {family} signature cannot index the facets of model "
                         f"{model.name!r} (its family: {mine or 'none'})", fr)
    if not len(regions) and not len(faces):
        others = [f for f in s.families() if f != family]
        if others:
            raise InputError(path, key, f"empty: the action has a signature for {others} only, "
                             f"not for the model's family {family!r}", fr)
    # the interval
    start = fr if s.start_fr is None else s.start_fr
    end = fr if s.end_fr is None else s.end_fr
    if start > end:
        raise InputError(path, f"{action}.start_fr/end_fr", f"start {start} > end {end}", fr)
    if end >= n_frames or fr >= n_frames:
        which = "end_fr" if s.end_fr is not None and end >= n_frames else "fr_id"
        raise InputError(path, f"{action}.{which}",
                         f"interval {start}..{end} (contact frame {fr}) outside the sequence's "
                         f"{n_frames} frames (0..{n_frames - 1})", fr)
    rmap = region_map(model) if rmap is None else rmap
    R = len(rmap.names)
    # regions: ids in range, names known and agreeing with the ids
    bad = np.flatnonzero((regions >= R).any(axis=1))
    if len(bad):
        raise InputError(path, f"{key}.region_id", f"pair {int(bad[0])} {regions[bad[0]].tolist()}: "
                         f"region id unknown to the {R}-region map (0..{R - 1})", fr)
    names = s.anny_region_names if family == "anny" else ()
    for i, pair in enumerate(names):
        for person, n in enumerate(pair):
            if n not in rmap.names:
                raise InputError(path, f"{key}.region_names", f"pair {i}: region name {n!r} "
                                 f"unknown to the {R}-region map", fr)
            if rmap.names.index(n) != regions[i, person]:
                raise InputError(path, f"{key}.region_names", f"pair {i}: name {n!r} is region "
                                 f"{rmap.names.index(n)}, region_id says {int(regions[i, person])}", fr)
    # facets: in range, in an annotated region pair
    T = len(model.faces)
    bad = np.flatnonzero((faces >= T).any(axis=1))
    if len(bad):
        raise InputError(path, f"{key}.face_id", f"pair {int(bad[0])} {faces[bad[0]].tolist()}: "
                         f"facet outside the model's {T} faces (0..{T - 1})", fr)
    if len(rmap.face_region) != T:
        raise ValueError(f"rmap: a map of {len(rmap.face_region)} facets for a model of {T}")
    uniq, first = np.unique(regions, axis=0, return_index=True) if len(regions) else (regions, [])
    region_pairs = uniq[np.argsort(first)] if len(regions) else np.zeros((0, 2), np.int64)
    lookup = {(int(a), int(b)): i for i, (a, b) in enumerate(region_pairs)}
    of_facets = rmap.region_of(faces) if len(faces) else np.zeros((0, 2), np.int64)
    pair_of = np.zeros(len(faces), np.int64)
    for i, (r0, r1) in enumerate(of_facets):
        j = lookup.get((int(r0), int(r1)))
        if j is None:
            nm = [rmap.names[r] if r >= 0 else "none" for r in (r0, r1)]
            raise InputError(path, f"{key}.face_id", f"pair {i} {faces[i].tolist()}: facets in "
                             f"regions ({int(r0)} {nm[0]}, {int(r1)} {nm[1]}), not an annotated "
                             f"region pair of region_id", fr)
        pair_of[i] = j
    pair_names = tuple((rmap.names[a], rmap.names[b]) for a, b in region_pairs)
    return ContactAnnotation(str(path), action, family, (int(start), int(end)), int(fr),
                             region_pairs.astype(np.int64), faces.astype(np.int64), pair_of,
                             pair_names)


def select_facets(annotation: ContactAnnotation, rmap: RegionMap, mode: str = "annotated",
                  n: int | None = None, rng: np.random.Generator | None = None
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The paper's selection operator ``psi_D`` for each region pair of ``annotation``.

    mode "all": every facet of each region; "uniform": ``n`` facets of each region drawn
    without replacement by ``rng`` (all of them when the region has fewer), sorted;
    "annotated": the annotated facets of each side (unique, sorted). Returns one
    ``(facets of person 0, facets of person 1)`` int64 pair per row of ``region_pairs``.
    A region pair with no annotated facets in mode "annotated" raises ValueError.
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if mode == "uniform" and (n is None or n < 1 or rng is None):
        raise ValueError("mode 'uniform' needs n >= 1 and an np.random.Generator rng")
    out = []
    for r, (r0, r1) in enumerate(annotation.region_pairs):
        if mode == "annotated":
            fp = annotation.facets_of_pair(r)
            if not len(fp):
                raise ValueError(f"{annotation.file}: {annotation.action}: region pair {r} "
                                 f"{annotation.region_names[r]} has no annotated facets")
            out.append((np.unique(fp[:, 0]), np.unique(fp[:, 1])))
            continue
        sides = []
        for reg in (r0, r1):
            f = rmap.faces_of(int(reg)).astype(np.int64)
            if not len(f):
                raise ValueError(f"region {int(reg)} {rmap.names[reg]} has no facets in the map")
            if mode == "uniform" and len(f) > n:
                f = np.sort(rng.choice(f, size=n, replace=False))
            sides.append(f)
        out.append((sides[0], sides[1]))
    return out


def select_normal_pairs(annotation: ContactAnnotation, selection=None, distances=None
                        ) -> list[np.ndarray]:
    """The paper's ``psi_N``: per region pair, (K, 2) facet pairs (person 0, person 1) whose
    normals ``L_N`` turns opposite.

    Default: the annotated facet pairs. With ``selection`` (``select_facets``'s output) and
    ``distances`` (one ``geometry.FacetDistances`` per region pair, computed on those
    selections): the matches ``Phi_D`` found, each facet of person 0 with its nearest of
    person 1 and each facet of person 1 with its nearest of person 0 (duplicates removed).
    """
    if distances is None:
        return [annotation.facets_of_pair(r).copy() for r in range(len(annotation.region_pairs))]
    if selection is None or len(selection) != len(distances) or len(distances) != len(annotation.region_pairs):
        raise ValueError("select_normal_pairs: selection and distances must both be given, one per region pair")
    out = []
    for (s0, s1), d in zip(selection, distances, strict=True):
        p = np.concatenate([np.stack([np.asarray(s0), np.asarray(d.a_nearest)], 1),
                            np.stack([np.asarray(d.b_nearest), np.asarray(s1)], 1)]).astype(np.int64)
        out.append(np.unique(p, axis=0))
    return out
