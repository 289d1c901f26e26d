"""C3D files with the traits of real Vicon Plug-in Gait exports, and what marker_fit makes of them.

``write_vicon_pig`` reproduces what a lab's Nexus export of a Plug-in Gait full-body trial
contains beyond the 39 markers: a ``Subject:`` prefix on every label, 200-240 Hz, a non-zero
first frame, occlusion gaps (residual -1), Plug-in Gait's model outputs stored as points
(segment origins/axes ``PELO``, ``PELA``, ``LFEO``, ``LFEA``..., joint centres, the centre of
mass) and joint angles stored as points in degrees and declared under ``POINT:ANGLES``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from body.markers import PLUG_IN_GAIT_NAMES
from fitting import mocap

#: The 39 markers of the Plug-in Gait full-body model (Vicon's order).
PIG_MARKERS = PLUG_IN_GAIT_NAMES
#: Model outputs Nexus writes as points next to the markers (not markers).
PIG_SEGMENT_POINTS = tuple(
    f"{seg}{axis}" for seg in ("PEL", "LFE", "RFE", "LTI", "RTI", "LFO", "RFO", "HED", "TRX")
    for axis in ("O", "A", "L", "P")
) + ("LHJC", "RHJC", "LKJC", "RKJC", "CentreOfMass", "CentreOfMassFloor")
PIG_ANGLES = ("LHipAngles", "RHipAngles", "LKneeAngles", "RKneeAngles", "LAnkleAngles",
              "RAnkleAngles", "LPelvisAngles", "RPelvisAngles", "LShoulderAngles",
              "RShoulderAngles", "LElbowAngles", "RElbowAngles")


def write_vicon_pig(path: Path, xyz: np.ndarray, rate_hz: float, rng: np.random.Generator,
                    subject: str = "Sub01", first_frame: int = 117, n_gaps: int = 12,
                    gap_len: tuple[int, int] = (3, 40), names=PIG_MARKERS) -> np.ndarray:
    """Write a Nexus-like Plug-in Gait C3D.

    xyz : (F, 39, 3) marker positions, metres, world (the PIG order of ``names``).
    Returns the (F, 39) bool gap mask that was written (residual -1, coordinates zeroed).
    """
    from formats.c3d import Markers, write_c3d

    F, M, _ = xyz.shape
    gaps = np.zeros((F, M), dtype=bool)
    for _ in range(n_gaps):
        m = rng.integers(M)
        L = int(rng.integers(gap_len[0], gap_len[1] + 1))
        s = int(rng.integers(0, max(1, F - L)))
        gaps[s:s + L, m] = True
    data = np.where(gaps[..., None], np.nan, xyz)
    centre = np.nanmean(xyz, axis=1)  # (F, 3)
    extra = {}
    for k, lab in enumerate(PIG_SEGMENT_POINTS):
        # model outputs: plausible positions near the body (metres), like PELO/LFEA
        extra[lab] = centre + 0.1 * np.array([np.cos(k), np.sin(k), 0.3 * np.cos(3 * k)])
    for lab in PIG_ANGLES:  # degrees stored as points, declared under POINT:ANGLES
        extra[lab] = rng.uniform(-60, 60, 3) + 5 * np.sin(np.arange(F) / 20.0)[:, None]
    write_c3d(path, Markers(tuple(names), data, rate_hz, first_frame, subject),
              subject=subject, extra_points=extra, angles=PIG_ANGLES)
    return gaps


def test_write_vicon_pig_reads_back_with_traits(tmp_path):
    import ezc3d

    from formats.c3d import read_c3d

    rng = np.random.default_rng(0)
    F = 120
    xyz = rng.normal(0, 0.3, (F, 39, 3)) + [0, 0, 1]
    gaps = write_vicon_pig(tmp_path / "t.c3d", xyz, 240.0, rng)
    c = ezc3d.c3d(str(tmp_path / "t.c3d"))
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    assert len(labels) == 39 + len(PIG_SEGMENT_POINTS) + len(PIG_ANGLES)
    assert all(lb.startswith("Sub01:") for lb in labels)
    assert "Sub01:PELO" in labels and "Sub01:LFEA" in labels and "Sub01:LKneeAngles" in labels
    m = read_c3d(tmp_path / "t.c3d", markers=PIG_MARKERS)
    assert m.rate_hz == 240.0 and m.first_frame == 117 and m.subject == "Sub01"
    assert np.array_equal(np.isnan(m.xyz[..., 0]), gaps) and gaps.any()
    np.testing.assert_allclose(m.xyz[~gaps], xyz[~gaps], atol=1e-6)


def test_resample_interpolates_and_never_bridges_gaps():
    rate = 240.0
    t_src = (117 + np.arange(480)) / rate  # first_frame 117
    M = 3
    xyz = np.stack([np.stack([t_src, 2 * t_src, np.full_like(t_src, k)], 1) for k in range(M)], 1)
    xyz[100:110, 1] = np.nan  # a gap on marker 1
    td = mocap.frame_times(150, 50.0, sync_offset_s=-0.5)  # video starts 0.5 s after mocap time 0
    obs, vis = mocap.resample(t_src, xyz, td)
    inside = (td >= t_src[0]) & (td <= t_src[-1])
    assert np.array_equal(vis[:, 0], inside) and inside.any() and not inside.all()
    # linear in t: interpolation is exact
    np.testing.assert_allclose(obs[inside, 0, 0], td[inside], atol=1e-12)
    np.testing.assert_allclose(obs[inside, 0, 1], 2 * td[inside], atol=1e-12)
    in_gap = (td > t_src[99]) & (td < t_src[110])
    assert in_gap.any()
    assert not vis[in_gap, 1].any() and vis[in_gap, 0].all()
    assert np.all(obs[~vis] == 0)
    # exact sample times hit the sample itself even next to a gap
    obs2, vis2 = mocap.resample(t_src, xyz, t_src[[99, 110]])
    assert vis2[:, 1].all()
    np.testing.assert_allclose(obs2[:, 1], xyz[[99, 110], 1], atol=1e-12)
