"""The true motion of every one of the paper's eight interaction classes, synthesized without
rendering as the generator does it (``studio.session.verified_motion``: a draw that fails the
checks is drawn again, up to four draws) and measured by ``studio.contact.check_motion``: the
planned contact really happens (the effector's surface touches the other body while the
contact is held) and the bodies never pass through each other (libigl winding number, a
measure independent of the synthesis' own).

A seed and length that none of the committed presets uses (seed 3 is the demo's, 11 the
bench's). Honesty note: posing and kick were redesigned while looking at this seed too, so it
is no longer unseen for them; hug was reworked on seeds 3 and 11, holding hands on seeds 1-8
and 11. ``python -m bench studio`` measures all classes on seed 11 and counts how many pass at
their first draw."""
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
    """The scene, :func:`studio.contact.check_motion` and draw of one class's true motion."""
    from studio.session import verified_motion

    model, plan, subjects = _session(seed, frames)
    seq = next(s for s in plan.sequences if s.scenario == scenario)
    mo, chk, draw, _ = verified_motion(plan, seq, subjects, model)
    return mo.scene, chk, draw


SCENARIOS = ["grab", "handshake", "hit", "holding_hands", "hug", "kick", "posing", "push"]


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_interaction_class_touches_without_interpenetrating(scenario):
    scene, chk, draw = _check(SEED, FRAMES, scenario)
    assert chk.depth.max() < 5e-3, (scenario, draw, int(chk.depth.argmax()), chk.depth.max())
    assert len(chk.gaps) == len(scene.contacts) >= 1
    for name, g in chk.gaps.items():
        # a hit lands and the receiver recoils: most, not all, of the held frames touch
        assert len(g) >= 5, (scenario, name)
        assert chk.touching(name) >= 0.75, (scenario, draw, name, np.round(g * 1000, 1))
        assert g.min() > -5e-3, (scenario, name, np.round(g * 1000, 1))
    assert chk.ok


def test_holding_hands_tall_and_short():
    """Holding hands with a short actor and a tall receiver (seed 6: 1.59 and 1.67 m; before
    the hold turned the palms to face each other, the forearms went through each other, 21 mm)."""
    _, chk, draw = _check(6, 60, "holding_hands")
    assert chk.ok and draw == 0, (draw, chk.summary())  # the scenario itself, not a redraw
