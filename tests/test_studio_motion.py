"""The true motion of every one of the paper's eight interaction classes, synthesized without
rendering (``studio.session.sequence_motion``) and measured by ``studio.contact.check_motion``:
the planned contact really happens (the effector's surface touches the other body while the
contact is held) and the bodies never pass through each other (libigl winding number, a
measure independent of the synthesis' own).

A seed and length that none of the committed presets uses (seed 3 is the demo's, 11 the
bench's). Honesty note: posing and kick were redesigned while looking at this seed too, so it
is no longer unseen for them; hug was reworked on seeds 3 and 11, holding hands on seeds 3, 5
and 11 (and measured on seeds 1-8). ``python -m bench studio`` measures all classes on seed 11.

Known failure, kept visible (strict: the test fails once it passes, so the mark comes off):
holding hands at seed 6 / 60 frames, where the forearms go through each other while the
hands come and go (about 21 mm; 23 mm on the bench's seed 11, a tall and a short subject)."""
from __future__ import annotations

import functools

import numpy as np
import pytest

pytestmark = pytest.mark.slow

SEED, FRAMES = 5, 60


@functools.cache
def _session(seed: int, frames: int):
    """(model, plan, subjects) of an eight-class plan (the sequence index seeds each sequence,
    so a class is only the same sequence within the full plan)."""
    from body import load_model
    from studio import plan as PL
    from studio.subjects import make_subjects

    model = load_model("anny")
    plan = PL.make_plan(seed, frames, tuple(PL.SCENARIOS))
    subjects = make_subjects(model, plan.subjects, np.random.default_rng([plan.seed, 2]))
    return model, plan, subjects


def _check(seed: int, frames: int, scenario: str):
    """The scene and :func:`studio.contact.check_motion` of one class's true motion."""
    from studio.contact import check_motion
    from studio.session import sequence_motion

    model, plan, subjects = _session(seed, frames)
    seq = next(s for s in plan.sequences if s.scenario == scenario)
    mo = sequence_motion(plan, seq, subjects)
    return mo.scene, check_motion(model, mo)


SCENARIOS = ["grab", "handshake", "hit", "holding_hands", "hug", "kick", "posing", "push"]


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_interaction_class_touches_without_interpenetrating(scenario):
    scene, chk = _check(SEED, FRAMES, scenario)
    assert chk.depth.max() < 5e-3, (scenario, int(chk.depth.argmax()), chk.depth.max())
    assert len(chk.gaps) == len(scene.contacts) >= 1
    for name, g in chk.gaps.items():
        # a hit lands and the receiver recoils: most, not all, of the held frames touch
        assert len(g) >= 5, (scenario, name)
        assert chk.touching(name) >= 0.75, (scenario, name, np.round(g * 1000, 1))
        assert g.min() > -5e-3, (scenario, name, np.round(g * 1000, 1))


@pytest.mark.xfail(strict=True, reason="issue #5 open: holding hands, the forearms cross while the "
                   "hands come and go (seeds 6 and 11)")
def test_holding_hands_known_failure_seed6():
    _, chk = _check(6, 60, "holding_hands")
    assert chk.depth.max() < 5e-3
