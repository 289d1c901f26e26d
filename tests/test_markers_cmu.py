"""body.markers.cmu41: the CMU database's 41-marker set on Anny, each marker on its segment,
and fitted to the first 100 frames of a real CMU capture (nimble_cmu_02_05.c3d)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from body.markers import CMU41_NAMES, PLUG_IN_GAIT_NAMES, cmu41, plug_in_gait
from fitting.marker_graph import marker_weights, template_placement, to_shape_fit

NIMBLE = Path(__file__).resolve().parents[2] / "shared" / "real" / "nimble_cmu_02_05.c3d"
# measured: median 8.2 mm, p90 81 mm over 100 frames (mean shape, template placement; CMU's
# T10 and waist differ from the template by several cm)
MAX_MEDIAN_MM = 15.0

# Anny joints by segment ("pelvis": Anny's lowest spine joints skin the pelvis surface)
SEGMENT_JOINTS = {
    "head": ("head", "neck"), "trunk": ("spine01", "spine02", "spine03", "neck01", "clavicle"),
    "pelvis": ("root", "pelvis", "spine04", "spine05"), "upper_arm": ("upperarm", "shoulder"),
    "forearm": ("lowerarm",), "hand": ("wrist", "metacarpal", "finger"),
    "thigh": ("upperleg",), "shank": ("lowerleg",), "foot": ("foot", "toe"),
}
EXPECTED = {
    **{n: ("head",) for n in ("LFHD", "RFHD", "LBHD", "RBHD")},
    **{n: ("trunk",) for n in ("C7", "T10", "CLAV", "STRN", "RBAC")},
    **{f"{s}{n}": segs for s in "LR" for n, segs in (
        ("FWT", ("pelvis",)), ("BWT", ("pelvis",)), ("SHO", ("upper_arm", "trunk")),
        ("UPA", ("upper_arm",)), ("ELB", ("upper_arm", "forearm")), ("FRM", ("forearm",)),
        ("WRA", ("forearm", "hand")), ("WRB", ("forearm", "hand")), ("FIN", ("hand",)),
        ("THI", ("thigh",)), ("KNE", ("thigh", "shank")), ("SHN", ("shank",)),
        ("ANK", ("shank", "foot")), ("HEE", ("foot",)), ("TOE", ("foot",)), ("MT5", ("foot",)))},
}


def test_every_cmu_marker_on_its_segment(anny):
    assert len(CMU41_NAMES) == 41 == len(set(CMU41_NAMES)) and set(EXPECTED) == set(CMU41_NAMES)
    pl = template_placement(anny, "cmu")
    assert pl.names == CMU41_NAMES
    W = marker_weights(anny, pl).toarray()
    for name, j in zip(pl.names, W.argmax(1), strict=True):
        joint = anny.joint_names[j]
        side = name[0] if name[0] in "LR" and name not in ("RBAC",) else None
        ok = any(joint.startswith(p) for seg in EXPECTED[name] for p in SEGMENT_JOINTS[seg])
        assert ok, f"{name} skinned mostly by {joint}, expected {EXPECTED[name]}"
        if side and "." in joint:
            assert joint.endswith("." + side), f"{name} on the wrong side ({joint})"
    # shared landmarks reuse the Plug-in Gait placement; the set follows the plug-in-gait rays
    pig = plug_in_gait(anny)
    ms = cmu41(anny)
    for n in ("C7", "CLAV", "LELB", "RWRA", "LKNE", "RHEE"):
        assert ms.faces[ms.index(n)] == pig.faces[pig.index(n)]
    assert ms.faces[ms.index("RBAC")] == pig.faces[pig.index("RBAK")]
    assert set(PLUG_IN_GAIT_NAMES) - set(CMU41_NAMES) == {"LASI", "RASI", "LPSI", "RPSI",
                                                          "LTIB", "RTIB", "RBAK"}


def test_cmu_capture_fits_with_the_template(anny):
    from fitting import mocap
    from fitting.marker_fit import MarkerFitOptions, fit_markers
    from formats.c3d import read_c3d

    if not NIMBLE.is_file():
        pytest.skip(f"{NIMBLE} not available")
    mk = read_c3d(NIMBLE, markers=CMU41_NAMES, allow_missing=True)
    assert mk.subject == "TakeoMonday" and mk.names == CMU41_NAMES
    tpl = template_placement(anny, "cmu")
    clock = mocap.VideoClock(mk.rate_hz, -mk.first_frame / mk.rate_hz)  # sample i = frame i
    fit, rep = fit_markers(anny, to_shape_fit(np.zeros(1), tpl, "mean", "template"), tpl, mk,
                           clock, np.arange(100), opts=MarkerFitOptions())
    assert rep["frames_valid"] == 100
    assert rep["residual_mm"]["median"] < MAX_MEDIAN_MM, rep["residual_mm"]
