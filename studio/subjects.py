"""The two subjects of a session: Anny shapes (different people), clothing colours per body part,
and their marker placement (the nominal Plug-in Gait set, slid a few millimetres per person as a
lab would place it)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from body import BodyModel
from body.anny import betas_from_anny
from studio import constants as C
from studio.kin import Person

# Dominant skinning bone -> clothing part. Order matters: first matching prefix wins.
_PARTS = (
    (("wrist", "finger", "metacarpal", "neck", "head", "eye", "jaw"), "skin"),
    (("foot", "toe"), "shoes"),
    (("root", "pelvis", "upperleg", "lowerleg"), "trousers"),
    (("upperarm", "lowerarm"), "sleeve"),
    (("spine", "breast", "clavicle", "shoulder"), "shirt"),
)


@dataclass(frozen=True, eq=False)
class Subject:
    """One person. id: recipe subject id; index: 0 or 1 (clothing palette); phenotypes: (6,)
    anny phenotypes in [0, 1]; local_changes: (L,) anny body sliders; betas: (S,) exact betas
    of that body; person: kinematics; colors: (V, 3) uint8 clothing colour per vertex;
    part: (V,) str clothing part per vertex."""

    id: str
    index: int
    phenotypes: np.ndarray
    local_changes: np.ndarray
    betas: np.ndarray
    person: Person
    colors: np.ndarray
    part: np.ndarray


def vertex_parts(model: BodyModel) -> np.ndarray:
    """(V,) clothing part name of each vertex from its dominant skinning bone."""
    dom = np.asarray(model.weights.argmax(axis=1)).ravel()
    names = model.joint_names
    bone_part = []
    for n in names:
        part = "skin"
        for prefixes, p in _PARTS:
            if n.startswith(prefixes):
                part = p
                break
        bone_part.append(part)
    return np.array(bone_part, dtype=object)[dom].astype(str)


def clothing_colors(parts: np.ndarray, index: int) -> np.ndarray:
    """(V, 3) uint8 colours for the parts of person ``index`` (constants.CLOTHING)."""
    pal = dict(C.CLOTHING[index])
    pal["skin"] = C.SKIN_RGB
    return np.array([pal[p] for p in parts], dtype=np.uint8)


def make_subjects(model: BodyModel, ids: tuple[str, str], rng: np.random.Generator) -> list[Subject]:
    """Two clearly different adults: person 0 taller and male-leaning, person 1 shorter and
    female-leaning, each with random build and a few random body sliders."""
    parts = vertex_parts(model)
    L = len(model.extras["local_change_labels"])
    out = []
    for i, sid in enumerate(ids):
        ph = np.array([
            rng.uniform(0.75, 0.95) if i == 0 else rng.uniform(0.05, 0.25),  # gender
            rng.uniform(0.45, 0.6),  # age (0.5 = anny's default adult)
            rng.uniform(0.35, 0.7),  # muscle
            rng.uniform(0.3, 0.7),  # weight
            rng.uniform(0.6, 0.85) if i == 0 else rng.uniform(0.25, 0.5),  # height
            rng.uniform(0.35, 0.65),  # proportions
        ])
        lc = np.zeros(L)
        pick = rng.choice(L, size=C.SUBJECT_SLIDERS, replace=False)
        lc[pick] = rng.uniform(-C.SUBJECT_SLIDER_RANGE, C.SUBJECT_SLIDER_RANGE, len(pick))
        betas = betas_from_anny(model, ph, lc)
        out.append(Subject(sid, i, ph, lc, betas, Person.make(model, betas),
                           clothing_colors(parts, i), parts))
    return out
