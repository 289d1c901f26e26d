"""annotate: proposals from fitted surfaces and from keypoints, the file (CHI3D layout, atomic,
validated by the partner fit's reader, stale or bad files refused), the agreement table, and
`make annotate` handing its variables over verbatim. The page itself: test_annotate_browser.py.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from formats.errors import InputError

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rmap(anny):
    from body.regions import region_map

    return region_map(anny)


@pytest.fixture(scope="module")
def truth(small_session):
    """The small session's true motion of the handshake: (frames, V (2, F, V, 3), npz)."""
    z = np.load(small_session.parent / "gt" / "s01" / "Handshake 1.npz")
    return np.asarray(z["frames"]), np.asarray(z["vertices"], np.float32), z


# ------------------------------------------------------------------------------ proposals

def test_proposal_from_fits_finds_the_frames_and_regions_in_contact(anny, rmap, truth):
    from annotate.proposals import NEAR_M, from_fits

    frames, V, z = truth
    V = V.copy()
    V[1, :10] += np.array([0.0, 0.0, 0.6], np.float32)  # the partner lifted away in frames 0..9
    p = from_fits(frames, V, anny.faces, rmap)
    assert p["interval"] == [int(frames[10]), int(frames[-1])]
    assert p["interval"][0] <= p["fr_id"] <= p["interval"][1]
    d = np.array(p["distance_mm"])
    assert np.all(d[:10] > 100) and np.all(d[10:] < NEAR_M * 1000)
    pairs = np.array(p["pairs"])
    assert len(pairs) > 0 and np.all(np.array(p["pair_distance_mm"]) < NEAR_M * 1000)
    # the candidates are where the studio made the hands touch (its recorded signature regions)
    got = {tuple(r) for r in rmap.region_of(pairs).tolist()}
    want = {tuple(r) for r in np.asarray(z["signature_regions"]).tolist()}
    assert got & want, (got, want)
    # and each candidate really is a pair of facets a few mm apart at the contact frame
    from geometry import face_centroids, nearest_surface

    row = list(frames).index(p["fr_id"])
    c0 = face_centroids(V[0, row].astype(float), anny.faces)[pairs[:, 0]]
    near = nearest_surface(c0, V[1, row].astype(float), anny.faces)
    assert np.array_equal(near.face, pairs[:, 1])


def test_proposal_from_fits_strides_long_sequences(anny, rmap, truth):
    """Over max_frames frames every k-th is scanned (meshes asked for row by row)."""
    from annotate.proposals import from_fits

    frames, V, _ = truth
    V = V.copy()
    V[1, :10] += np.array([0.0, 0.0, 0.6], np.float32)
    asked = []

    def at(i):
        asked.append(i)
        return V[:, i]

    p = from_fits(frames, at, anny.faces, rmap, max_frames=6)
    assert p["stride"] == 4 and p["frames"] == frames[::4].tolist()
    assert p["interval"] == [int(frames[12]), int(frames[20])]
    assert set(asked) <= set(range(0, 24, 4))


def test_proposal_from_fits_without_contact(anny, rmap, truth):
    from annotate.proposals import from_fits

    frames, V, _ = truth
    V = V[:, :4].copy()
    V[1] += np.array([1.5, 0.0, 0.0], np.float32)
    p = from_fits(frames[:4], V, anny.faces, rmap)
    assert p["interval"] is None and p["fr_id"] is None and p["pairs"] == []
    assert min(p["distance_mm"]) > 500


def test_proposal_from_keypoints_picks_the_closest_approach(small_session):
    """Both people's true joints projected into the four cameras as 'keypoints': the proposed
    contact frame is the frame where the true joints of the two come closest."""
    from annotate.proposals import from_keypoints
    from calib.camera import project
    from calib.io import read_camera
    from recipes.schema import load_recipe

    r = load_recipe(small_session, check_files=False)
    seq = r.sequence("s01/Push 1")
    cams = [read_camera(seq.calibration[c], c) for c in r.cameras]
    z = np.load(small_session.parent / "gt" / "s01" / "Push 1.npz")
    J = np.asarray(z["joints3d_25"], float)[:, :8]  # (2, F, 25, 3), 8 frames
    J[1] += np.linspace(0.8, 0, 8)[:, None, None] * np.array([1.0, 0, 0])  # they approach
    kp = np.ones((len(cams), 8, 2, 25, 3))
    for c, cam in enumerate(cams):
        for p in range(2):
            kp[c, :, p, :, :2] = project(cam, J[p].reshape(-1, 3)).reshape(8, 25, 2)
    frames = np.arange(8) + 100
    prop = from_keypoints(cams, kp, frames)
    true_d = np.linalg.norm(J[0][:, :, None] - J[1][:, None], axis=-1).min(axis=(1, 2))
    assert prop["fr_id"] == frames[int(np.argmin(true_d))]
    assert prop["interval"][0] <= prop["fr_id"] <= prop["interval"][1]
    np.testing.assert_allclose(prop["distance_mm"], true_d * 1000, atol=2.0)
    assert prop["pairs"] == []


# ------------------------------------------------------------------------------ the file

def _entry(anny, rmap, pairs, interval=(3, 9), fr=5, who="ann"):
    from annotate.signature import entry

    return entry(anny, rmap, "anny", fr, interval, np.array(pairs), annotator=who)


def _facet(rmap, name: str, k: int = 0) -> int:
    return int(rmap.faces_of(name)[k])


def test_save_writes_chi3d_layout_read_by_the_partner_fit_reader(tmp_path, anny, rmap):
    from annotate.signature import load, save
    from fitting.contact_signature import load_contact
    from formats.chi3d import read_contact_signatures

    path = tmp_path / "interaction_contact_signature.json"
    path.write_text(json.dumps({"Push 1": {"fr_id": 2, "smplx_signature": {"region_id": [], "face_id": []}}}))
    pairs = [[_facet(rmap, "r_palm"), _facet(rmap, "l_palm")],
             [_facet(rmap, "r_palm", 5), _facet(rmap, "l_forearm_front")]]
    save(path, "Handshake 1", _entry(anny, rmap, pairs), anny, 24, "anny", rmap)
    raw = json.loads(path.read_text())
    assert set(raw) == {"Push 1", "Handshake 1"}  # the file's other actions are kept
    e = raw["Handshake 1"]
    assert (e["fr_id"], e["start_fr"], e["end_fr"]) == (5, 3, 9)
    assert e["smplx_signature"] == {"region_id": [], "face_id": []}  # no conversion given
    assert e["anny_signature"]["region_names"] == [["r_palm", "l_palm"], ["r_palm", "l_forearm_front"]]
    assert read_contact_signatures(path)["Handshake 1"].start_fr == 3
    ann = load_contact(path, "Handshake 1", anny, 24, family="anny")
    assert ann.interval == (3, 9) and ann.frame == 5
    assert ann.facet_pairs.tolist() == pairs
    assert [tuple(n) for n in ann.region_names] == [("r_palm", "l_palm"), ("r_palm", "l_forearm_front")]
    back = load(path, "Handshake 1", anny, 24, "anny", rmap)
    assert back == {"fr_id": 5, "interval": [3, 9], "pairs": pairs, "annotator": "ann"}
    assert load(path, "Grab 1", anny, 24, "anny", rmap) is None
    assert not [p for p in tmp_path.iterdir() if p.name != path.name]  # no temporary left


def test_save_refuses_a_bad_annotation_and_leaves_the_file(tmp_path, anny, rmap):
    from annotate.signature import save

    path = tmp_path / "sig.json"
    good = [[_facet(rmap, "r_palm"), _facet(rmap, "l_palm")]]
    save(path, "Hug 1", _entry(anny, rmap, good), anny, 24, "anny", rmap)
    before = path.read_bytes()
    with pytest.raises(InputError, match="outside the sequence's 24 frames") as e:
        save(path, "Hug 1", _entry(anny, rmap, good, interval=(3, 30), fr=5), anny, 24, "anny", rmap)
    assert str(path) in str(e.value)  # names the file being saved, not the temporary one
    assert path.read_bytes() == before
    with pytest.raises(InputError, match="outside the model's"):
        _entry(anny, rmap, [[0, len(anny.faces)]])
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sig.json"]


def test_load_refuses_stale_and_bad_files(tmp_path, anny, rmap):
    from annotate.signature import load

    path = tmp_path / "sig.json"
    e = _entry(anny, rmap, [[_facet(rmap, "r_palm"), _facet(rmap, "l_palm")]])
    e["annotation"]["num_faces"] = 20908  # made on another mesh
    path.write_text(json.dumps({"Hug 1": e}))
    with pytest.raises(InputError, match=r"annotation\.num_faces.*stale"):
        load(path, "Hug 1", anny, 24, "anny", rmap)
    e = _entry(anny, rmap, [[_facet(rmap, "r_palm"), _facet(rmap, "l_palm")]])
    e["anny_signature"]["face_id"][0][1] = len(anny.faces) + 7
    path.write_text(json.dumps({"Hug 1": e}))
    with pytest.raises(InputError, match="facet outside the model's"):
        load(path, "Hug 1", anny, 24, "anny", rmap)


def test_smplx_facets_come_from_the_conversion_correspondence(tmp_path, anny, rmap):
    """With a conversion, smplx_signature holds the target facets nearest to the annotated
    ones (src_face_tgt_face) and their regions in the target's map."""
    from types import SimpleNamespace

    from annotate.signature import entry
    from body.regions import RegionMap

    T = len(anny.faces)
    corr = SimpleNamespace(src_face_tgt_face=(np.arange(T) * 7) % 1000)
    trmap = RegionMap(rmap.names, np.arange(1000) % 75)
    target = SimpleNamespace(name="smplx", faces=np.zeros((1000, 3), np.int64))
    pairs = np.array([[_facet(rmap, "r_palm"), _facet(rmap, "l_palm")]])
    e = entry(anny, rmap, "anny", 5, (3, 9), pairs, conversion=(corr, target, trmap))
    tf = (pairs * 7) % 1000
    assert e["smplx_signature"] == {"face_id": tf.tolist(), "region_id": (tf % 75).tolist()}
    assert e["annotation"]["smplx_from"] == {"model": "smplx", "num_faces": 1000}


# ------------------------------------------------------------------------------ agreement

def _sig_file(path: Path, who: str, actions: dict) -> Path:
    d = {}
    for action, (pairs, interval) in actions.items():
        d[action] = {"fr_id": interval[0], "start_fr": interval[0], "end_fr": interval[1],
                     "smplx_signature": {"region_id": [], "face_id": []},
                     "anny_signature": {"region_id": pairs, "face_id": []},
                     "annotation": {"annotator": who}}
    path.write_text(json.dumps(d))
    return path


def test_agreement_table_at_each_granularity(tmp_path, capsys):
    from annotate.agreement import agreement, main
    from body.regions import REGIONS_75

    r = REGIONS_75.index
    # A: right palm on left palm; B: right fingers (palmar) on left palm and right palm on left
    # thumb. At 75 regions they differ; from 37 up every hand region is "hand".
    a = _sig_file(tmp_path / "a.json", "alice", {"Handshake 1": ([[r("r_palm"), r("l_palm")]], (10, 19))})
    b = _sig_file(tmp_path / "b.json", "bob", {"Handshake 1": (
        [[r("r_fingers_palmar"), r("l_palm")], [r("r_palm"), r("l_thumb")]], (15, 24))})
    res = agreement([a, b])
    t = res["table"]
    # segmentation 75: person 0 {palm} vs {fingers_palmar, palm}: 1/2; person 1 {l_palm} vs
    # {l_palm, l_thumb}: 1/2 -> (1 + 1) / (2 + 2)
    assert t["75"]["segmentation_iou"] == pytest.approx(0.5)
    assert t["75"]["signature_iou"] == pytest.approx(0.0)  # no region pair in common
    for n in ("37", "17"):
        assert t[n]["segmentation_iou"] == pytest.approx(1.0)
        assert t[n]["signature_iou"] == pytest.approx(1.0)
    assert t["9"]["signature_iou"] == pytest.approx(1.0)
    assert res["interval_iou"] == pytest.approx(5 / 15)
    assert res["annotators"] == ["alice", "bob"]
    # the CLI prints the table and writes the JSON; one file is an error (exit 2)
    out = tmp_path / "table.json"
    assert main([str(a), str(b), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| 75 | 0.500 | 0.000 |" in text and "| 9 | 1.000 | 1.000 |" in text
    assert json.loads(out.read_text())["table"]["75"]["segmentation_iou"] == pytest.approx(0.5)
    assert main([str(a)]) == 2


def test_agreement_refuses_foreign_region_ids(tmp_path):
    from annotate.agreement import agreement

    a = _sig_file(tmp_path / "a.json", "a", {"Hug 1": ([[3, 80]], (1, 2))})
    b = _sig_file(tmp_path / "b.json", "b", {"Hug 1": ([[3, 4]], (1, 2))})
    with pytest.raises(InputError, match="not our 75-region map"):
        agreement([a, b])


# ------------------------------------------------------------------------------ make annotate

@pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")
def test_make_annotate_passes_variables_verbatim(tmp_path):
    fake = tmp_path / "fake_python"
    fake.write_text("#!/bin/sh\nfor a in \"$@\"; do printf '%s\\n' \"$a\"; done > \"$ARGV_FILE\"\n")
    fake.chmod(0o755)
    argv = tmp_path / "argv.txt"
    pwned = tmp_path / "pwned"
    seq = f"s01/Hand shake`touch {pwned}`"
    r = subprocess.run(["make", "-s", "-C", str(REPO), "-o", "setup", "annotate", f"PY={fake}",
                        f"SEQ={seq}", "FRAME=12", "PORT=9000", "CONTACT=my file.json", "ANNOTATOR=a b"],
                       env={**os.environ, "ARGV_FILE": str(argv)}, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert argv.read_text().splitlines() == [
        "-m", "annotate", "--recipe", "recipes/demo.yaml", "--seq", seq, "--frame", "12",
        "--port", "9000", "--out", "my file.json", "--annotator", "a b"]
    assert not pwned.exists()
    r = subprocess.run(["make", "-s", "-C", str(REPO), "-o", "setup", "annotate", f"PY={fake}"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "usage: make annotate" in r.stdout


def test_cli_bad_sequence_is_one_line_and_exit_2(small_session):
    import sys

    r = subprocess.run([sys.executable, "-m", "annotate", "--recipe", str(small_session),
                        "--seq", "s01/Nope 1", "--port", "0"], cwd=REPO, capture_output=True,
                       text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 2
    assert "no sequence 's01/Nope 1'" in r.stderr and "Traceback" not in r.stderr
