"""Tests of a generated studio session and of its ground truth itself (the ``small_session``
fixture): the recipe loads, the files are in the real formats, the markers lie on the true
surface plus their offset, the annotated contact facets touch in the truth, the bodies do not
interpenetrate, and the true joints project onto the rendered people in the videos."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

# the first test generates the session (~40-90 s) unless it is cached in assets/cache
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def session(small_session):
    from body import load_model
    from recipes import load_recipe

    recipe = load_recipe(small_session)
    root = Path(small_session).parent
    gt = {sid: dict(np.load(root / "gt" / sid.split("/")[0] / f"{sid.split('/')[1]}.npz"))
          for sid in recipe.sequences}
    return {"recipe": recipe, "root": root, "gt": gt, "model": load_model("anny"),
            "meta": json.loads((root / "gt" / "session.json").read_text())}


def _faces(session):
    return np.asarray(session["model"].faces)


def test_recipe_loads_and_every_file_exists(session):
    r = session["recipe"]
    assert len(r.cameras) == 4 and len(r.subjects) == 2 and len(r.sequences) == 2
    wearers = [s.markers_on for s in r.sequences.values()]
    assert len(set(wearers)) == 2  # who wears the markers alternates
    for sid, s in r.sequences.items():
        assert s.partner != s.markers_on and s.text
        for p in [s.c3d, s.contact, *s.videos.values(), *s.calibration.values()]:
            assert Path(p).is_file(), (sid, p)
        assert s.mocap.sync_offset_s < 0
    for sub in r.subjects.values():
        assert Path(sub.scan).is_file()


def test_subjects_have_different_shapes(session):
    g = next(iter(session["gt"].values()))
    V = g["vertices"][:, 0]
    heights = V[..., 2].max(1) - V[..., 2].min(1)
    assert abs(heights[0] - heights[1]) > 0.05
    assert np.linalg.norm(g["betas"][0] - g["betas"][1]) > 1.0


def test_cameras_and_videos_in_chi3d_layout(session):
    from calib.io import read_chi3d_camera
    from formats.video import video_info

    r = session["recipe"]
    for sid, s in r.sequences.items():
        F = len(session["gt"][sid]["frames"])
        cams = [read_chi3d_camera(s.calibration[c]) for c in r.cameras]
        assert [c.name for c in cams] == r.cameras
        assert all(c.model == "h36m" and np.any(c.k != 0) for c in cams)
        for c in r.cameras:
            info = video_info(s.videos[c])
            assert (info.width, info.height) == (900, 900)
            assert info.n_frames == F and info.fps == pytest.approx(50.0)


def test_c3d_markers_lie_on_the_true_surface_plus_offset(session):
    """C3D samples at the video frames vs the marker positions computed from the true
    vertices and the subject's true marker placement; and each true marker sits at its offset
    from the true surface."""
    import igl

    from body.markers import load_json, marker_positions
    from formats.c3d import read_c3d

    root, faces = session["root"], _faces(session)
    for sid, s in session["recipe"].sequences.items():
        g = session["gt"][sid]
        mk = read_c3d(s.c3d)
        assert mk.rate_hz == pytest.approx(float(g["mocap_hz"]))
        ms = load_json(root / "gt" / "subjects" / f"{s.markers_on}_markers.json", len(faces))
        assert mk.names == ms.names and len(ms) == 39
        truth = marker_positions(g["vertices"][0].astype(float), faces, ms)  # (F, M, 3)
        obs = mk.xyz[g["mocap_of_frame"]]
        vis = np.isfinite(obs).all(2)
        err = np.linalg.norm(obs - truth, axis=2)[vis]
        assert 0.5e-3 < np.sqrt(np.mean(err ** 2)) < 1.6e-3  # ~1 mm of noise, no more
        assert err.max() < 6e-3
        # occlusion gaps: runs of 5-50 samples on some markers
        gap = ~np.isfinite(mk.xyz).all(2)
        assert 0 < gap.any(0).sum() < len(ms.names)
        for m in np.flatnonzero(gap.any(0)):
            x = np.concatenate([[0], gap[:, m].astype(int), [0]])
            runs = np.flatnonzero(np.diff(x) == -1) - np.flatnonzero(np.diff(x) == 1)
            assert runs.min() >= 5
        # each true marker is offset from the true skin by its offset
        f = len(g["frames"]) // 2
        d2, _, _ = igl.point_mesh_squared_distance(truth[f], g["vertices"][0, f].astype(float), faces)
        np.testing.assert_allclose(np.sqrt(d2), ms.offsets, atol=1.5e-3)


def test_scans_are_noisy_holed_views_of_the_true_shape(session):
    import igl
    import trimesh

    root, faces = session["root"], _faces(session)
    for sub_id, sub in session["recipe"].subjects.items():
        gt = np.load(root / "gt" / "subjects" / f"{sub_id}.npz")
        pc = trimesh.load(sub.scan)
        P = np.asarray(pc.vertices, float)
        assert len(P) > 20000
        sd = igl.signed_distance(P, gt["scan_vertices"].astype(float), faces)[0]
        assert 1.5e-3 < np.std(sd) < 2.6e-3 and abs(np.median(sd)) < 1e-3
        for h in gt["scan_holes"]:
            assert np.linalg.norm(P - h, axis=1).min() > 0.04
        zmin = gt["scan_vertices"][:, 2].min()
        assert np.sum(P[:, 2] < zmin + 0.01) < 0.002 * len(P)  # no soles


def test_contact_annotation_touches_in_the_truth(session):
    """The annotated facets of each pair are within 1 cm of each other in the true meshes at
    the annotated frame, with the region ids of body.regions; the interval is where the true
    surfaces touch."""
    import igl

    from body.regions import region_map
    from formats.chi3d import read_contact_signatures

    faces = _faces(session)
    regions = region_map(session["model"])
    for sid, s in session["recipe"].sequences.items():
        action = sid.split("/")[1]
        g = session["gt"][sid]
        sig = read_contact_signatures(s.contact)[action]
        raw = json.loads(Path(s.contact).read_text())[action]["anny_signature"]
        pairs, regs = np.array(raw["face_id"]), np.array(raw["region_id"])
        assert 3 <= len(pairs) <= 6
        np.testing.assert_array_equal(regs, regions.face_region[pairs])
        fr = sig.fr_id
        assert sig.start_fr <= fr <= sig.end_fr
        assert sig.end_fr - sig.start_fr >= 3
        V0, V1 = g["vertices"][0, fr].astype(float), g["vertices"][1, fr].astype(float)
        for f0, f1 in pairs:
            c0 = V0[faces[f0]].mean(0)
            d2, _, _ = igl.point_mesh_squared_distance(c0[None], V1, faces[f1][None])
            assert np.sqrt(d2[0]) < 0.01, (sid, f0, f1)
        # spread over the contact area like an annotator's clicks, not one spot
        cen = V0[faces[pairs[:, 0]]].mean(1)
        assert np.linalg.norm(cen[:, None] - cen[None], axis=2).max() > 0.01
        # outside the interval the people do not touch
        for f in (sig.start_fr - 2, sig.end_fr + 2):
            if 0 <= f < len(g["frames"]):
                d2, _, _ = igl.point_mesh_squared_distance(g["vertices"][0, f].astype(float),
                                                           g["vertices"][1, f].astype(float), faces)
                assert np.sqrt(d2.min()) > 0.003


def test_no_true_interpenetration(session):
    """libigl's winding number: no vertex of one body deeper than 5 mm inside the other."""
    from geometry import interpenetration

    faces = _faces(session)
    for sid, g in session["gt"].items():
        worst = max(interpenetration(g["vertices"][0, f], g["vertices"][1, f], faces).depth
                    for f in range(0, len(g["frames"]), 2))
        assert worst < 5e-3, (sid, worst)
        info = session["meta"]["sequences"][sid]
        # the generator's own check agrees (it measures every frame, this test every other one)
        assert worst * 1000 <= info["max_penetration_mm"] + 0.01 < 5.0, (sid, worst, info)
        assert info["motion_ok"] and info["motion_draw"] >= 0
        assert all(t >= 0.75 for t in info["contact_touching"].values()), info


def test_motion_is_smooth(session):
    for sid, g in session["gt"].items():
        J = g["joints3d_25"]  # (2, F, 25, 3)
        v = np.diff(J, axis=1) * 50.0
        a = np.diff(J, 2, axis=1) * 2500.0
        assert np.abs(v).max() < 4.0, sid  # m/s
        assert np.percentile(np.linalg.norm(a, axis=-1), 99) < 60.0, sid  # m/s^2


def test_true_joints_project_onto_the_rendered_people(session):
    """Project the true joints3d_25 with the calibration; in the MP4 frames they land on a
    person's pixels (not floor or background), and on the right person where the true
    depth says nobody stands in front (person id render of the true meshes)."""
    from calib import project
    from calib.io import read_chi3d_camera
    from drawing import constants as C
    from drawing.render import PersonMesh, Renderer
    from formats.video import VideoReader

    faces = _faces(session)
    r = session["recipe"]
    sid, s = next(iter(r.sequences.items()))
    g = session["gt"][sid]
    cams = [read_chi3d_camera(s.calibration[c]) for c in r.cameras]
    F = len(g["frames"])
    frames = [0, F // 2, F - 1]
    on_person = right_person = total = checked = 0
    with Renderer(cams) as ren:
        for f in frames:
            ids = ren.render_ids([PersonMesh(g["vertices"][k, f], faces, np.zeros((len(g["vertices"][k, f]), 3), np.uint8))
                                  for k in range(2)])
            for c, cam in enumerate(cams):
                with VideoReader(s.videos[cam.name]) as vr:
                    img = vr[f].astype(int)
                bg = (np.abs(img - np.array(C.BACKGROUND_RGB)).max(2) <= 12) | \
                     (np.abs(img - np.array(C.FLOOR_RGB)).max(2) <= 12)
                # the video and the id render agree on where the people are
                people = ids[c] >= 0
                iou = (people & ~bg).sum() / (people | ~bg).sum()
                assert iou > 0.9, (cam.name, f, iou)
                for k in range(2):
                    uv = np.round(project(cam, g["joints3d_25"][k, f])).astype(int)
                    for u, v in uv:
                        if not (0 <= u < 900 and 0 <= v < 900):
                            continue
                        total += 1
                        on_person += not bg[v, u]
                        if ids[c][v, u] == k:
                            right_person += 1
                            checked += 1
                        elif ids[c][v, u] == 1 - k:
                            checked += 1  # the other person stands in front
    assert total > 100
    assert on_person / total > 0.97
    assert right_person / checked > 0.8


def test_ensure_generated_leaves_a_complete_session_alone(small_session):
    from studio import ensure_generated

    before = {p: p.stat().st_mtime_ns for p in Path(small_session).parent.rglob("*") if p.is_file()}
    assert ensure_generated(small_session) == small_session
    after = {p: p.stat().st_mtime_ns for p in Path(small_session).parent.rglob("*") if p.is_file()}
    assert before == after


def test_contact_sheet_written(session):
    import cv2

    sheets = sorted((session["root"] / "previews").glob("*_contact.png"))
    assert len(sheets) == len(session["recipe"].sequences)
    img = cv2.imread(str(sheets[0]))
    assert img.shape == (900, 900, 3) and img.std() > 10
