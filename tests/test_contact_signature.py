"""Contact signatures validated against a body model (fitting.contact_signature): every input
error names file, action and field; the studio's layout round-trips; psi_D / psi_N selections."""
from __future__ import annotations

import json

import numpy as np
import pytest

from body import load_model
from body.regions import region_map
from fitting.contact_signature import load_contact, select_facets, select_normal_pairs
from formats.chi3d import ContactSignature, read_contact_signatures, write_contact_signatures
from formats.errors import InputError
from geometry import facet_distances

N_FRAMES = 30


@pytest.fixture(scope="module")
def anny():
    m = load_model("anny")
    return m, region_map(m)


def _studio_entry(rmap, rng, n_pairs=6, regions=(("l_palm", "r_palm"), ("l_fingers_palmar", "r_hand_back"))):
    """A signature as studio.session.signature_json writes it: facet pairs, their regions
    row by row, region names; smplx/ghum left empty."""
    faces, regs = [], []
    for k in range(n_pairs):
        a, b = regions[k % len(regions)]
        f0 = int(rng.choice(rmap.faces_of(a)))
        f1 = int(rng.choice(rmap.faces_of(b)))
        faces.append([f0, f1])
        regs.append([int(rmap.face_region[f0]), int(rmap.face_region[f1])])
    return {"fr_id": 12, "start_fr": 8, "end_fr": 20,
            "smplx_signature": {"region_id": [], "face_id": []},
            "ghum_signature": {"region_id": [], "face_id": []},
            "anny_signature": {"region_id": regs, "face_id": faces,
                               "region_names": [[rmap.names[a], rmap.names[b]] for a, b in regs]}}


def _write(tmp_path, d):
    p = tmp_path / "interaction_contact_signature.json"
    p.write_text(json.dumps(d))
    return p


def _expect(p, action, field, call):
    with pytest.raises(InputError) as e:
        call()
    msg = str(e.value)
    assert e.value.file == str(p) and str(p) in msg
    assert action in msg and field in msg, msg
    return e.value


def test_studio_signature_round_trip(tmp_path, anny):
    model, rmap = anny
    rng = np.random.default_rng(0)
    e = _studio_entry(rmap, rng)
    p = _write(tmp_path, {"Handshake 1": e})
    ann = load_contact(p, "Handshake 1", model, N_FRAMES)
    assert ann.interval == (8, 20) and ann.frame == 12 and ann.family == "anny"
    assert np.array_equal(ann.facet_pairs, e["anny_signature"]["face_id"])
    # unique region pairs in file order, each facet pair pointing to its own
    want = [tuple(r) for r in dict.fromkeys(tuple(r) for r in e["anny_signature"]["region_id"])]
    assert [tuple(r) for r in ann.region_pairs] == want
    assert ann.region_names[0] == ("l_palm", "r_palm")
    for (f0, f1), r in zip(ann.facet_pairs, ann.pair_of_facets, strict=True):
        assert tuple(ann.region_pairs[r]) == (rmap.face_region[f0], rmap.face_region[f1])
    assert ann.active(8) and ann.active(20) and not ann.active(7) and not ann.active(21)
    # the chi3d writer keeps the anny part: write what we read, read it again
    sigs = read_contact_signatures(p)
    p2 = write_contact_signatures(tmp_path / "again.json", sigs)
    back = read_contact_signatures(p2)["Handshake 1"]
    assert np.array_equal(back.anny_faces, sigs["Handshake 1"].anny_faces)
    assert back.anny_region_names == sigs["Handshake 1"].anny_region_names
    assert back.families() == ("anny",)
    assert np.array_equal(load_contact(p2, "Handshake 1", model, N_FRAMES).facet_pairs, ann.facet_pairs)


def test_real_studio_file_loads(tmp_path, anny):
    """The studio's own writer (studio.session.signature_json) on a hand-made ContactTruth."""
    from studio.contact import ContactTruth
    from studio.session import signature_json

    model, rmap = anny
    rng = np.random.default_rng(1)
    faces = np.array([[int(rng.choice(rmap.faces_of("r_palm"))), int(rng.choice(rmap.faces_of("l_upper_back")))]
                      for _ in range(4)])
    ct = ContactTruth(np.zeros(10), np.zeros(10, int), 2, 6, 4, faces, rmap.face_region[faces], np.zeros(4))

    class Seq:
        action = "Hug 1"

    p = _write(tmp_path, signature_json([Seq()], [ct], rmap))
    ann = load_contact(p, "Hug 1", model, 10)
    assert ann.interval == (2, 6) and ann.region_names == (("r_palm", "l_upper_back"),)
    assert np.array_equal(ann.facet_pairs, faces)


@pytest.mark.parametrize("case, action, field", [
    ("action missing", "Push 9", "Push 9"),
    ("region id unknown", "A", "A.anny_signature.region_id"),
    ("region name unknown", "A", "A.anny_signature.region_names"),
    ("region name disagrees with id", "A", "A.anny_signature.region_names"),
    ("facet outside the faces", "A", "A.anny_signature.face_id"),
    ("facet in another region", "A", "A.anny_signature.face_id"),
    ("interval past the end", "A", "A.end_fr"),
    ("start after end", "A", "A.start_fr/end_fr"),
    ("another family", "A", "A.anny_signature"),
])
def test_errors_name_file_action_field(tmp_path, anny, case, action, field):
    model, rmap = anny
    e = _studio_entry(rmap, np.random.default_rng(2))
    s = e["anny_signature"]
    if case == "region id unknown":
        s["region_id"][1][1] = 75
    elif case == "region name unknown":
        s["region_names"][0][0] = "l_tail"
    elif case == "region name disagrees with id":
        s["region_names"][0][1] = "head_top"
    elif case == "facet outside the faces":
        s["face_id"][2][0] = len(model.faces)
    elif case == "facet in another region":
        s["face_id"][0][1] = int(rmap.faces_of("l_heel")[0])
    elif case == "interval past the end":
        e["end_fr"] = N_FRAMES
    elif case == "start after end":
        e["start_fr"], e["end_fr"] = 13, 11
    elif case == "another family":
        e["smplx_signature"] = {"region_id": [[1, 2]], "face_id": [[10, 20]]}
        e.pop("anny_signature")
    p = _write(tmp_path, {"A": e})
    err = _expect(p, action, field, lambda: load_contact(p, "Push 9" if case == "action missing" else "A",
                                                         model, N_FRAMES))
    if case != "action missing":
        assert err.frame == 12


def test_family_other_than_the_model(tmp_path, anny):
    """An smplx signature asked for an Anny model: refused before any id is read."""
    model, rmap = anny
    e = _studio_entry(rmap, np.random.default_rng(3))
    e["smplx_signature"] = {"region_id": [[1, 2]], "face_id": [[10, 20]]}
    p = _write(tmp_path, {"A": e})
    err = _expect(p, "A", "A.smplx_signature", lambda: load_contact(p, "A", model, N_FRAMES, family="smplx"))
    assert "anny" in str(err)


def test_interval_defaults_and_no_contact(tmp_path, anny):
    model, _ = anny
    sig = {"Posing 1": ContactSignature(fr_id=5, smplx_regions=np.zeros((0, 2), int),
                                        smplx_faces=np.zeros((0, 2), int))}
    p = write_contact_signatures(tmp_path / "c.json", sig)
    ann = load_contact(p, "Posing 1", model, N_FRAMES)
    assert ann.interval == (5, 5) and not ann.has_contact and not ann.active(5)
    _expect(p, "Posing 1", "Posing 1.fr_id", lambda: load_contact(p, "Posing 1", model, 5))


def test_psi_D_modes(tmp_path, anny):
    model, rmap = anny
    e = _studio_entry(rmap, np.random.default_rng(4), n_pairs=8)
    p = _write(tmp_path, {"A": e})
    ann = load_contact(p, "A", model, N_FRAMES)
    full = select_facets(ann, rmap, "all")
    for (r0, r1), (s0, s1) in zip(ann.region_pairs, full, strict=True):
        assert np.array_equal(s0, np.flatnonzero(rmap.face_region == r0))
        assert np.array_equal(s1, np.flatnonzero(rmap.face_region == r1))
    uni = select_facets(ann, rmap, "uniform", n=25, rng=np.random.default_rng(0))
    for (a0, a1), (u0, u1) in zip(full, uni, strict=True):
        for a, u in ((a0, u0), (a1, u1)):
            assert len(u) == min(25, len(a)) and len(np.unique(u)) == len(u) and np.isin(u, a).all()
    big = select_facets(ann, rmap, "uniform", n=10 ** 6, rng=np.random.default_rng(0))
    assert all(np.array_equal(b[0], f[0]) for b, f in zip(big, full, strict=True))
    other = select_facets(ann, rmap, "uniform", n=25, rng=np.random.default_rng(1))
    assert any(not np.array_equal(a[0], b[0]) for a, b in zip(uni, other, strict=True))
    ann_sel = select_facets(ann, rmap, "annotated")
    fp = np.array(e["anny_signature"]["face_id"])
    for r, (s0, s1) in enumerate(ann_sel):
        rows = fp[ann.pair_of_facets == r]
        assert set(s0) == set(rows[:, 0]) and set(s1) == set(rows[:, 1])
    assert sum(len(ann.facets_of_pair(r)) for r in range(len(ann.region_pairs))) == len(fp)
    with pytest.raises(ValueError, match="uniform"):
        select_facets(ann, rmap, "uniform")
    with pytest.raises(ValueError, match="mode"):
        select_facets(ann, rmap, "random")


def test_psi_N_annotated_and_matched(tmp_path, anny):
    model, rmap = anny
    e = _studio_entry(rmap, np.random.default_rng(5))
    p = _write(tmp_path, {"A": e})
    ann = load_contact(p, "A", model, N_FRAMES)
    pairs = select_normal_pairs(ann)
    assert np.array_equal(np.concatenate(pairs), ann.facet_pairs[np.argsort(ann.pair_of_facets, kind="stable")])
    # the nearest-facet matches of Phi_D on two copies of the rest mesh, one shifted by 1 cm
    V = model.v_template
    sel = select_facets(ann, rmap, "uniform", n=30, rng=np.random.default_rng(0))
    d = [facet_distances(V, model.faces, s0, V + [0.0, 0.0, 0.01], model.faces, s1) for s0, s1 in sel]
    matched = select_normal_pairs(ann, sel, d)
    for (s0, s1), m, fd in zip(sel, matched, d, strict=True):
        assert np.isin(m[:, 0], np.union1d(s0, fd.b_nearest)).all()
        assert np.isin(m[:, 1], np.union1d(s1, fd.a_nearest)).all()
        assert {(a, b) for a, b in zip(s0, fd.a_nearest, strict=True)} <= {tuple(r) for r in m}
