"""Surface regions: our 75-region map, groupings, adjacency, the official-file loader."""
from __future__ import annotations

import json

import numpy as np
import pytest

from body import load_model
from body import regions as rg
from body.markers import plug_in_gait
from formats.errors import InputError


@pytest.fixture(scope="module")
def model():
    return load_model("anny")


@pytest.fixture(scope="module")
def rmap(model):
    return rg.region_map(model)


def _twin(name):
    return "r_" + name[2:] if name.startswith("l_") else "l_" + name[2:] if name.startswith("r_") else name


def test_names_and_nested_groupings():
    for n, names in rg.NAMES.items():
        assert len(names) == n and len(set(names)) == n
        assert all(_twin(x) in names for x in names)  # left/right symmetric
    for n in (37, 17, 9):
        g = rg.GROUPING[n]
        assert g.shape == (75,) and set(g) == set(range(n))
        # the twin of a region goes to the twin of its coarse region
        for i, name in enumerate(rg.REGIONS_75):
            assert rg.NAMES[n][g[rg.REGIONS_75.index(_twin(name))]] == _twin(rg.NAMES[n][g[i]])
    # nesting: 75 -> 37 -> 17 -> 9 compose
    assert rg.NAMES[9][rg.GROUPING[9][rg.REGIONS_75.index("l_thumb")]] == "l_hand"
    assert rg.NAMES[17][rg.GROUPING[17][rg.REGIONS_75.index("r_calf")]] == "r_lower_leg"


def test_anny_map_complete_symmetric_anatomical(model, rmap):
    fr = rmap.face_region
    assert fr.shape == (len(model.faces),) and fr.min() >= 0
    assert np.all(np.bincount(fr, minlength=75) > 0)
    for n in (37, 17, 9):
        assert np.all(np.bincount(rmap.coarse(n).face_region, minlength=n) > 0)
    # mirror symmetry (Anny's mesh is symmetric about x = 0)
    from scipy.spatial import cKDTree

    c = model.v_template[model.faces].mean(1)
    _, k = cKDTree(c).query(c * [-1, 1, 1])
    twin = np.array([rg.REGIONS_75.index(_twin(n)) for n in rg.REGIONS_75])
    assert np.mean(fr[k] == twin[fr]) > 0.97
    # markers land in the regions anatomy says
    ms = plug_in_gait(model)
    got = dict(zip(ms.names, (rg.REGIONS_75[r] for r in rmap.region_of(ms.faces)), strict=True))
    expect = {"LKNE": ("l_knee_front", "l_knee_back"), "RHEE": ("r_heel",), "LTOE": ("l_foot_top", "l_toes"),
              "STRN": ("l_chest_lower", "r_chest_lower", "l_chest_upper", "r_chest_upper"),
              "C7": ("neck_back", "l_upper_back", "r_upper_back"), "RBAK": ("r_upper_back", "r_mid_back"),
              "LFHD": ("l_face", "head_top"), "RBHD": ("r_head_back", "head_top"),
              "LELB": ("l_elbow_outer",), "RTHI": ("r_thigh_front",), "LTIB": ("l_shin", "l_calf"),
              "LFIN": ("l_hand_back",), "LUPA": ("l_upper_arm_back", "l_upper_arm_front")}
    for mname, ok in expect.items():
        assert got[mname] in ok, (mname, got[mname])


def test_adjacency(model, rmap):
    A = rmap.adjacency(model.faces)
    assert A.shape == (75, 75) and np.array_equal(A, A.T) and not A.diagonal().any()
    idx = rg.REGIONS_75.index
    assert A[idx("l_knee_front"), idx("l_shin")] and A[idx("neck_front"), idx("neck_back")]
    assert A[idx("l_palm"), idx("l_hand_back")]
    assert not A[idx("l_palm"), idx("r_palm")] and not A[idx("head_top"), idx("l_sole")]
    A17 = rmap.coarse(17).adjacency(model.faces)
    assert A17[rg.REGIONS_17.index("l_thigh"), rg.REGIONS_17.index("l_lower_leg")]


def test_official_loader(tmp_path):
    p = tmp_path / "contact_regions.json"
    doc = {"rid_to_smplx_fids": [[0, 1, 2], [3, 4], [5]], "rid_to_ghum_fids": {"0": [1], "1": [0, 2]},
           "rid_to_color": [[1, 0, 0]] * 3}
    p.write_text(json.dumps(doc))
    m = rg.load_official(p, "smplx", num_faces=8)
    assert m.names == ("r00", "r01", "r02") and list(m.face_region) == [0, 0, 0, 1, 1, 2, -1, -1]
    g = rg.load_official(p, "ghum")
    assert list(g.region_of([0, 1, 2])) == [1, 0, 1]
    with pytest.raises(ValueError):
        m.coarse(17)
    doc["rid_to_smplx_fids"][2] = [4]
    p.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"rid_to_smplx_fids\[2\]"):
        rg.load_official(p, "smplx")
    p.write_text(json.dumps({"rid_to_color": []}))
    with pytest.raises(InputError, match="rid_to_ghum_fids: missing"):
        rg.load_official(p, "ghum")


@pytest.mark.slow
def test_smplx_rig_map():
    from body.smplx_from_anny import smplx_from_anny_path

    m = load_model("smplx", smplx_from_anny_path())
    r = rg.region_map(m)
    assert np.all(np.bincount(r.face_region, minlength=75) > 0)
