"""drawing.overlay and drawing.qa_plots: the fitted meshes sit on the people in the video to
the pixel (distortion included), the views tile, the overlay MP4 plays the requested frames,
and the QA plot shades the flagged spans.

The overlay tests use the small studio session's truth (``tests/conftest.py``): the truth
meshes of both people, the calibration files and the videos the studio rendered from them
(real lens distortion), read through the same readers as the pipeline.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

SEQ = "s01/Handshake 1"
FRAME = 12


def _session(recipe: Path):
    """Cameras, video paths and truth meshes (vertices (2, F, V, 3), faces) of SEQ."""
    import yaml

    from calib.io import read_chi3d_camera

    root = recipe.parent
    rec = yaml.safe_load(recipe.read_text())
    seq = rec["sequences"][SEQ]
    names = [str(c) for c in rec["cameras"]]
    cams = [read_chi3d_camera(root / seq["calibration"][n], name=n) for n in names]
    videos = [root / seq["videos"][n] for n in names]
    group, action = SEQ.split("/")
    gt = np.load(root / "gt" / group / f"{action}.npz")
    assert list(gt["frames"]) == list(range(len(gt["frames"])))  # gt row = video frame
    return cams, videos, gt["vertices"].astype(float), np.asarray(gt["faces"])


def _mesh(vertices, faces, rgb):
    from drawing.render import PersonMesh

    return PersonMesh(vertices, faces, np.tile(np.asarray(rgb, np.uint8), (len(vertices), 1)))


def _no_lens(cam):
    return dataclasses.replace(cam, k=np.zeros(3), p=np.zeros(2))


def _outline_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Symmetric distances (px) between the outlines of two masks: each outline pixel of one
    to the nearest outline pixel of the other."""
    import cv2

    from drawing.overlay import silhouette_outline

    oa, ob = silhouette_outline(a), silhouette_outline(b)
    da = cv2.distanceTransform((~ob).astype(np.uint8), cv2.DIST_L2, 5)[oa]
    db = cv2.distanceTransform((~oa).astype(np.uint8), cv2.DIST_L2, 5)[ob]
    return np.concatenate([da, db])


def _projected_silhouette(cam, vertices, faces) -> np.ndarray:
    """(H, W) bool: every triangle of the mesh, its corners projected by calib.project
    (distortion), filled at 1/16 px (triangles are a few px: straight edges are exact enough)."""
    import cv2

    from calib import project

    m = np.zeros((cam.height, cam.width), np.uint8)
    for tri in np.rint(project(cam, vertices)[faces] * 16).astype(np.int32):
        cv2.fillConvexPoly(m, tri, 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def test_overlay_outline_sits_on_the_projected_mesh(small_session):
    """Every projected vertex (calib.project, distortion) lies in the overlay's silhouette
    and the drawn 1-px outline is within ~1 px of the projected mesh's outline, on the
    session's four cameras and on a copy of one with strong barrel distortion; rendering
    through cameras without their distortion puts the outline visibly off."""
    import cv2

    from calib import project
    from drawing.overlay import overlay_views, silhouette_outline
    from drawing.render import Renderer

    cams, _, V, faces = _session(small_session)
    strong = dataclasses.replace(cams[0], name="strong", k=np.array([-0.35, 0.12, 0.0]))
    cams = cams + [strong]
    col = (255, 140, 0)

    def measure(render_cams):
        out = []  # per (person, view): max px of a vertex outside, outline distances, outline ok
        with Renderer(render_cams) as r:
            for k in range(2):
                mesh = _mesh(V[k, FRAME], faces, col)
                ids = r.render_ids([mesh])
                black = [np.zeros((c.height, c.width, 3), np.uint8) for c in render_cams]
                over = overlay_views(r, render_cams, [mesh], black, alpha=0.5,
                                     outline_colors=[col])
                for c, cam in enumerate(cams):  # the true lens: where the vertices are
                    sil = ids[c] == 0
                    drawn = np.all(over[c] == col, axis=-1)  # the outline's pixels
                    uv = np.rint(project(cam, V[k, FRAME])).astype(int)
                    assert ((uv >= 0) & (uv < [cam.width, cam.height])).all()
                    off = cv2.distanceTransform((~sil).astype(np.uint8), cv2.DIST_L2, 5)
                    out.append((off[uv[:, 1], uv[:, 0]].max(),
                                _outline_distances(sil, _projected_silhouette(cam, V[k, FRAME], faces)),
                                np.array_equal(drawn, silhouette_outline(sil)), sil.sum()))
        return out

    right = measure(cams)
    for k_view, (off, d, outline_ok, area) in enumerate(right):
        assert area > 5000, k_view
        assert outline_ok, k_view  # the drawn outline is the silhouette's 1-px border
        assert off <= 1.5, (k_view, off)  # every vertex in the silhouette (rounding: <= 1 px)
        assert d.mean() < 0.8 and np.percentile(d, 90) <= 1.5, (k_view, d.mean())
    # the strong camera without its lens: the mesh's periphery is drawn 4-8 px off
    wrong = measure([_no_lens(c) for c in cams])
    for i in (4, 9):  # the strong camera, person 0 and person 1
        assert wrong[i][0] > 4.0, wrong[i][0]  # vertices land well outside the silhouette
        assert np.percentile(wrong[i][1], 90) > 2.5, np.percentile(wrong[i][1], 90)
        assert wrong[i][1].mean() > 2 * right[i][1].mean(), (wrong[i][1].mean(), right[i][1].mean())


def test_overlay_covers_the_person_in_the_studio_video(small_session):
    """On the studio's video frames (its own render of the truth meshes), the truth meshes'
    overlay covers the people's pixels (background difference): IoU > 0.94 in every view;
    the same meshes moved 5 cm do not (IoU < 0.8); drawn without the lens distortion the
    mismatch grows where the lens moves pixels by > 2 px."""
    from calib.camera import undistort_pixels
    from drawing.overlay import overlay_views
    from drawing.render import Renderer
    from formats.video import VideoReader

    cams, videos, V, faces = _session(small_session)
    frames = []
    for p in videos:
        with VideoReader(p) as v:
            frames.append(v[FRAME])
    magenta = (255, 0, 255)

    def overlay_masks(render_cams, shift=(0.0, 0.0, 0.0)):
        people = [_mesh(V[k, FRAME] + np.asarray(shift), faces, magenta) for k in range(2)]
        with Renderer(render_cams) as r:
            empty = r.render([])
            over = overlay_views(r, render_cams, people, frames, alpha=1.0, outline=False)
        return [np.any(o != f, axis=-1) for o, f in zip(over, frames, strict=True)], empty

    def iou(a, b):
        return (a & b).sum() / (a | b).sum()

    right, empty = overlay_masks(cams)
    # the people's pixels: where the video differs from the studio without people
    person = [np.abs(f.astype(int) - e.astype(int)).max(-1) > 25 for f, e in zip(frames, empty, strict=True)]
    ious = [iou(p, m) for p, m in zip(person, right, strict=True)]
    assert min(ious) > 0.94 and np.mean(ious) > 0.955, ious
    moved, _ = overlay_masks(cams, shift=(0.05, 0.0, 0.0))
    assert max(iou(p, m) for p, m in zip(person, moved, strict=True)) < 0.8
    # distortion ignored: compare where the lens moves pixels by more than 2 px
    wrong, _ = overlay_masks([_no_lens(c) for c in cams])
    zones = []
    for cam in cams:
        uv = np.stack(np.meshgrid(np.arange(cam.width, dtype=float),
                                  np.arange(cam.height, dtype=float)), -1)
        zones.append(np.linalg.norm(undistort_pixels(cam, uv) - uv, axis=-1) > 2.0)
    c = int(np.argmax([(z & m).sum() for z, m in zip(zones, right, strict=True)]))
    z = zones[c]
    assert (z & right[c]).sum() > 1000  # the people reach where the lens matters
    err_right = ((person[c] ^ right[c]) & z).sum() / (right[c] & z).sum()
    err_wrong = ((person[c] ^ wrong[c]) & z).sum() / (right[c] & z).sum()
    assert err_wrong > 2.0 * err_right, (err_wrong, err_right)
    assert iou(person[c], wrong[c]) < iou(person[c], right[c])


# ------------------------------------------------------------------------------ fast path
def test_raster_covers_the_renderers_pixels(small_session):
    """The QA stage's fast overlays (``raster_people`` on the proxy decimated to the stage's
    default 1,500 faces, ``stages.qa.overlay_meshes``) cover the pixels the EGL renderer gives
    the full meshes, person by person: IoU >= 0.95 and outlines within ~1 px (median) at full
    size, >= 0.93 at the overlays' half size (the border is a larger share); the person drawn in front where the two
    overlap is the renderer's on >= 99 % of the pixels either draws. Drawn from the full
    meshes moved 5 cm, the IoU drops below 0.85 (the test can fail)."""
    from body import load_model
    from drawing.overlay import RasterScene, raster_people, scaled_size
    from drawing.render import Renderer
    from stages.qa import Options, overlay_meshes

    cams, _, V, faces = _session(small_session)
    cols = ((255, 140, 0), (0, 200, 255))
    full = [_mesh(V[k, FRAME], faces, cols[k]) for k in range(2)]
    tri, small = overlay_meshes(load_model("anny"), [V[k, FRAME][None] for k in range(2)],
                                Options().overlay_faces)
    assert 1000 <= len(tri) <= 1500
    fast = RasterScene([_mesh(small[k][0], tri, cols[k]) for k in range(2)])
    moved = RasterScene([_mesh(V[k, FRAME] + [0.05, 0, 0], faces, cols[k]) for k in range(2)])
    with Renderer(cams) as r:
        ref = r.render_ids(full)
    for c, cam in enumerate(cams):
        for scale in (1.0, 0.5):
            w, h = scaled_size(cam, scale)
            # the renderer's ids sampled at the scaled pixel centres
            ys = np.clip(np.rint((np.arange(h) + 0.5) / scale - 0.5).astype(int), 0, cam.height - 1)
            xs = np.clip(np.rint((np.arange(w) + 0.5) / scale - 0.5).astype(int), 0, cam.width - 1)
            want = ref[c][np.ix_(ys, xs)]
            rgb, ids = raster_people(cam, fast, scale)
            assert ids.shape == (h, w) and rgb.shape == (h, w, 3)
            assert (rgb[ids < 0] == 0).all() and (rgb[ids >= 0].max(-1) > 0).all()
            for k in range(2):
                a, b = want == k, ids == k
                assert a.sum() > 3000 * scale ** 2, (cam.name, k)
                iou = (a & b).sum() / (a | b).sum()
                assert iou >= (0.95 if scale == 1 else 0.93), (cam.name, scale, k, iou)
                d = _outline_distances(a, b)
                assert np.median(d) <= 1.0 and np.percentile(d, 90) <= 2.5 / scale ** 0.5, \
                    (cam.name, scale, k, np.median(d), np.percentile(d, 90))
            both = (want >= 0) & (ids >= 0)
            assert (want[both] == ids[both]).mean() >= 0.99, cam.name
            _, off = raster_people(cam, moved, scale)
            assert ((off == 0) & (want == 0)).sum() / ((off == 0) | (want == 0)).sum() < 0.85


def test_draw_overlays_decodes_each_frame_once(tmp_path, monkeypatch):
    """``draw_overlays``: one pass over the videos (each requested video frame decoded once,
    in increasing order), the PNGs at their scale with their titles' frames, the MP4 and the
    WebM with one frame per video frame at the video's scale, each showing its frame's grey
    and the box where the camera projects it; a person not fitted (NaN row) is left out; a
    separate mesh for the video is drawn in the video only."""
    import cv2
    import trimesh

    from calib import look_at, project
    from drawing import qa_constants as Q
    from drawing.overlay import draw_overlays
    from formats import video as FV

    cams = [look_at(f"c{i}", [3 * np.cos(a), 3 * np.sin(a), 1.5], [0, 0, 1], (150, 150),
                    (80, 60), 160, 120, k=(-0.2, 0.05, 0.0))
            for i, a in enumerate(np.deg2rad([45, 135, 225, 315]))]
    videos = [FV.write_mp4(tmp_path / f"v{c.name}.mp4",
                           (np.full((120, 160, 3), 30 + 40 * j, np.uint8) for j in range(5)), 25.0)
              for c in cams]
    box = trimesh.creation.box((0.3, 0.3, 0.6))
    verts = np.stack([box.vertices + [0.2 * i, 0, 1.0] for i in range(5)])
    gone = np.full_like(verts, np.nan)  # a second person fitted nowhere
    reads = []
    get = FV.VideoReader.__getitem__
    monkeypatch.setattr(FV.VideoReader, "__getitem__",
                        lambda self, i: reads.append((self.path.name, int(i))) or get(self, i))
    pngs, video = draw_overlays(cams, videos, [verts, gone], box.faces, {j: j for j in range(5)},
                                png_frames=[3, 1], png_dir=tmp_path / "png",
                                titles={1: "one"}, png_scale=1.0,
                                video_path=tmp_path / "o" / "overlay.mp4",
                                video_frames=[0, 1, 2, 4], video_fps=10.0, video_scale=0.5)
    for v in videos:  # frames 0..4 once each, in order
        assert [i for n, i in reads if n == v.name] == [0, 1, 2, 3, 4]
    assert sorted(pngs) == [1, 3]
    bar = Q.TILE_TITLE_PX
    for f, p in pngs.items():
        png = cv2.imread(str(p))[..., ::-1]
        assert png.shape == (bar + 240, 320, 3)
        for c, cam in enumerate(cams):
            r, k = divmod(c, 2)
            tile = png[bar + 120 * r: bar + 120 * (r + 1), 160 * k: 160 * (k + 1)]
            assert abs(int(tile[115, 150, 0]) - (30 + 40 * f)) <= 6
            u, w = np.rint(project(cam, verts[f].mean(0))).astype(int)
            assert np.abs(tile[w, u].astype(int) - (30 + 40 * f)).max() > 40
    for path in (video, video.with_suffix(".webm")):
        info = FV.video_info(path)
        assert info.n_frames == 4 and (info.width, info.height) == (160, bar + 120), path
        with FV.VideoReader(path) as rd:
            for i, f in enumerate([0, 1, 2, 4]):
                img = rd[i]
                cell = img[bar:bar + 60, :80]
                assert abs(int(cell[57, 75, 0]) - (30 + 40 * f)) <= 8, (path.name, f)
                u, w = np.rint((project(cams[0], verts[f].mean(0)) + 0.5) * 0.5 - 0.5).astype(int)
                assert np.abs(cell[w, u].astype(int) - (30 + 40 * f)).max() > 40, (path.name, f)
    with pytest.raises(ValueError, match="increasing"):
        draw_overlays(cams, videos, [verts], box.faces, {j: j for j in range(5)},
                      video_path=tmp_path / "x.mp4", video_frames=[2, 1])
    # a coarser mesh for the video (here: a small box far off): the video shows it, the PNG
    # of the same frame the full one
    far = trimesh.creation.box((0.05, 0.05, 0.05))
    fverts = np.stack([far.vertices + [0.2 * i, 0, 2.5] for i in range(5)])
    pngs, video = draw_overlays(cams, videos, [verts], box.faces, {j: j for j in range(5)},
                                png_frames=[2], png_dir=tmp_path / "png2", png_scale=0.5,
                                video_path=tmp_path / "v2" / "overlay.mp4", video_frames=[2],
                                video_fps=10.0, video_scale=0.5, webm=False,
                                video_mesh=([fverts], far.faces))
    assert not video.with_suffix(".webm").exists()
    u, w = np.rint((project(cams[0], verts[2].mean(0)) + 0.5) * 0.5 - 0.5).astype(int)
    png = cv2.imread(str(pngs[2]))[..., ::-1][bar:bar + 60, :80]
    with FV.VideoReader(video) as rd:
        cell = rd[0][bar:bar + 60, :80]
    assert np.abs(png[w, u].astype(int) - 110).max() > 40  # the box in the picture
    assert np.abs(cell[w, u].astype(int) - 110).max() <= 8  # not in the video: grey


def _box_session(tmp_path, n=5):
    """Four small cameras around a box moving along x, their videos (frame j grey 30 + 40 j)."""
    import trimesh

    from calib import look_at
    from formats import video as FV

    cams = [look_at(f"c{i}", [3 * np.cos(a), 3 * np.sin(a), 1.5], [0, 0, 1], (150, 150),
                    (80, 60), 160, 120, k=(-0.2, 0.05, 0.0))
            for i, a in enumerate(np.deg2rad([45, 135, 225, 315]))]
    videos = [FV.write_mp4(tmp_path / f"v{c.name}.mp4",
                           (np.full((120, 160, 3), 30 + 40 * j, np.uint8) for j in range(n)), 25.0)
              for c in cams]
    box = trimesh.creation.box((0.3, 0.3, 0.6))
    verts = np.stack([box.vertices + [0.2 * i, 0, 1.0] for i in range(n)])
    return cams, videos, verts, np.asarray(box.faces)


def test_frame_feed_decodes_each_frame_once_for_every_consumer(tmp_path, monkeypatch):
    """``FrameFeed``: each frame of each view decoded once, in increasing order, in its own
    thread; every consumer gets it at each kept scale (the full frame resized as the
    overlays resize it); a consumer that falls behind holds the decoding back (at most
    ``ahead`` frames kept) until it takes its frames or says done; a frame the feed does not
    hold, a scale it does not keep and a frame taken out of order are errors, and a decoding
    error comes out of ``get``."""
    import threading
    import time

    from drawing.overlay import FrameFeed, _resize, scaled_size
    from formats import video as FV

    cams, videos, _verts, _faces = _box_session(tmp_path, n=6)
    reads = []
    get = FV.VideoReader.__getitem__
    monkeypatch.setattr(FV.VideoReader, "__getitem__", lambda self, i: reads.append(
        (self.path.name, int(i), threading.get_ident())) or get(self, i))
    with FrameFeed(cams, videos, [0, 1, 2, 3, 5], [0.5, 1.0], ["a", "b"], ahead=2) as feed:
        full = feed.get("a", 1, 1.0)
        half = feed.get("a", 1, 0.5)
        assert [im.shape for im in full] == [(120, 160, 3)] * 4
        with FV.VideoReader(videos[2]) as rd:
            want = _resize(get(rd, 1), scaled_size(cams[2], 0.5))  # (not counted)
        np.testing.assert_array_equal(half[2], want)
        assert abs(int(full[0][5, 5, 0]) - 70) <= 6
        time.sleep(0.3)  # "b" has not taken frame 0: two frames kept, the third not decoded
        assert {i for _n, i, _t in reads} == {0, 1}
        feed.get("b", 2, 0.5)  # "b" moves on: frames 0, 1 are released for both
        for f in (2, 3):
            assert abs(int(feed.get("a", f, 1.0)[3][5, 5, 0]) - (30 + 40 * f)) <= 6
        feed.done("b")  # else "b" (at frame 2) would hold frame 5 back: 2 and 3 are kept
        assert abs(int(feed.get("a", 5, 1.0)[3][5, 5, 0]) - 230) <= 6
        with pytest.raises(ValueError, match="ascending"):
            feed.get("a", 3, 1.0)
        with pytest.raises(ValueError, match="scale 0.25"):
            feed.get("a", 5, 0.25)
    for v in videos:  # once each, in order, in one thread that is not this one
        mine = [(i, t) for n, i, t in reads if n == v.name]
        assert [i for i, _ in mine] == [0, 1, 2, 3, 5]
        assert {t for _, t in mine} != {threading.get_ident()} and len({t for _, t in mine}) == 1
    with FrameFeed(cams, videos, [1, 4], [1.0], ["a"]) as feed:
        with pytest.raises(ValueError, match="frame 2: not one of the feed's frames"):
            feed.get("a", 2, 1.0)
    with FrameFeed(cams, videos, [1, 9], [1.0], ["a"]) as feed:  # 9: past the end
        feed.get("a", 1, 1.0)
        with pytest.raises(FV.InputError):
            feed.get("a", 9, 1.0)


def test_draw_overlays_from_a_frame_feed_draws_the_same_pictures(tmp_path):
    """``draw_overlays`` given a ``FrameFeed`` (frames already at the PNG's and the video's
    scales) writes the PNGs and the video it writes when it reads the videos itself."""
    import cv2

    from drawing.overlay import FrameFeed, draw_overlays
    from formats import video as FV

    cams, videos, verts, faces = _box_session(tmp_path)
    out = {}
    for how in ("read", "feed"):
        feed = FrameFeed(cams, videos, range(5), [0.5, 0.25], ["overlay"]) if how == "feed" else None
        try:
            out[how] = draw_overlays(cams, videos, [verts], faces, {j: j for j in range(5)},
                                     png_frames=[1, 3], png_dir=tmp_path / how, png_scale=0.5,
                                     video_path=tmp_path / how / "o.mp4", video_frames=[0, 2, 3],
                                     video_fps=10.0, video_scale=0.25, webm=False, feed=feed)
        finally:
            if feed is not None:
                feed.close()
    (pa, va), (pb, vb) = out["read"], out["feed"]
    assert sorted(pa) == sorted(pb) == [1, 3]
    for f in pa:
        np.testing.assert_array_equal(cv2.imread(str(pa[f])), cv2.imread(str(pb[f])))
    with FV.VideoReader(va) as ra, FV.VideoReader(vb) as rb:
        assert len(ra) == len(rb) == 3
        for i in range(3):
            np.testing.assert_array_equal(ra[i], rb[i])
    with pytest.raises(ValueError, match="keeps scales"):
        with FrameFeed(cams, videos, range(5), [0.5], ["overlay"]) as feed:
            draw_overlays(cams, videos, [verts], faces, {j: j for j in range(5)},
                          video_path=tmp_path / "x.mp4", video_frames=[0], video_scale=0.25,
                          feed=feed)


def test_video_encoder_error_comes_out_of_close(tmp_path):
    """The overlay video is encoded in a thread: frames come out in order, and an encoder
    that fails makes ``close`` raise its error (not a silently short video)."""
    from drawing.overlay import _VideoOut
    from formats.video import VideoReader, video_info

    out = _VideoOut(tmp_path / "v.mp4", 10.0, webm=False)
    for j in range(5):
        out.write(np.full((32, 48, 3), 40 * j, np.uint8))
    out.close()
    assert video_info(tmp_path / "v.mp4").n_frames == 5
    with VideoReader(tmp_path / "v.mp4") as rd:
        assert [int(round(rd[j].mean() / 40)) for j in range(5)] == [0, 1, 2, 3, 4]

    class Broken:
        def write(self, img):
            raise RuntimeError("disk full")

        def release(self):
            pass

    out = _VideoOut(tmp_path / "w.mp4", 10.0, webm=False)
    out.write(np.zeros((32, 48, 3), np.uint8))
    out.writers.append(Broken())
    out.write(np.zeros((32, 48, 3), np.uint8))
    with pytest.raises(RuntimeError, match="disk full"):
        out.close()


# ------------------------------------------------------------------------------ tiles
def test_tile_views_grid_and_labels():
    from drawing import qa_constants as Q
    from drawing.overlay import tile_views

    cols = [(200, 30, 30), (30, 200, 30), (30, 30, 200), (200, 200, 30), (30, 200, 200)]
    imgs = []
    for c in cols:
        im = np.zeros((160, 200, 3), np.uint8)
        im[:, :100] = c
        im[:, 100:] = 255 - np.asarray(c)  # right half: the complement (orientation kept)
        imgs.append(im)
    bar = Q.TILE_TITLE_PX

    def white(a):
        return (a.min(-1) > 200).sum()

    out = tile_views(imgs[:4], ["a", "b", "", "d"], title="frame 7", scale=0.5)
    assert out.shape == (bar + 2 * 80, 2 * 100, 3) and out.dtype == np.uint8
    assert white(out[:bar]) > 20  # the title
    for i, c in enumerate(cols[:4]):
        r, k = divmod(i, 2)
        cell = out[bar + 80 * r: bar + 80 * (r + 1), 100 * k: 100 * (k + 1)]
        np.testing.assert_array_equal(cell[40:, 5:45], np.broadcast_to(c, (40, 40, 3)))
        np.testing.assert_array_equal(cell[40:, 55:95], np.broadcast_to(255 - np.asarray(c), (40, 40, 3)))
        assert (white(cell[:25, :40]) > 5) == (i != 2), i  # labelled cells only
    five = tile_views(imgs, list("abcde"), scale=0.25)  # 5 views: 3 columns, 2 rows
    assert five.shape == (bar + 2 * 40, 3 * 50, 3)
    assert (five[bar + 40:, 100:] == 0).all()  # the sixth cell is empty
    np.testing.assert_array_equal(five[bar + 75, 60], cols[4])  # the fifth, row 2 column 2
    with pytest.raises(ValueError, match="labels"):
        tile_views(imgs, ["a"])


# ------------------------------------------------------------------------------ video
def test_overlay_video_and_pngs_show_the_requested_frames(tmp_path):
    """A tiny rig (4 views 160 x 120, lens distortion) and videos whose frame j is grey
    level 30 + 50 j: the MP4 has one frame per requested frame, in order, each showing that
    video frame with the box drawn on it; the PNGs are the same pictures."""
    import cv2
    import trimesh

    from calib import look_at, project
    from drawing import qa_constants as Q
    from drawing.overlay import overlay_video, render_overlays
    from formats.video import VideoReader, video_info, write_mp4

    cams = [look_at(f"c{i}", [3 * np.cos(a), 3 * np.sin(a), 1.5], [0, 0, 1], (150, 150),
                    (80, 60), 160, 120, k=(-0.2, 0.05, 0.0))
            for i, a in enumerate(np.deg2rad([45, 135, 225, 315]))]
    videos = [write_mp4(tmp_path / f"v{c.name}.mp4",
                        (np.full((120, 160, 3), 30 + 50 * j, np.uint8) for j in range(4)), 25.0)
              for c in cams]
    box = trimesh.creation.box((0.3, 0.3, 0.6))
    F = 4
    # the box moves along x: row i (video frame i) at x = 0.2 i
    verts = np.stack([box.vertices + [0.2 * i, 0, 1.0] for i in range(F)])
    frame_index = {j: j for j in range(F)}
    req = [2, 0, 3]
    path = overlay_video(tmp_path / "out" / "overlay.mp4", cams, videos, req, [verts],
                         box.faces, frame_index, fps=10.0, scale=1.0)
    info = video_info(path)
    assert info.n_frames == len(req) and info.fps == pytest.approx(10.0)
    bar = Q.TILE_TITLE_PX
    assert (info.width, info.height) == (320, bar + 240)
    pngs = render_overlays(cams, videos, req, [verts], box.faces, frame_index, tmp_path / "png",
                           scale=1.0)
    assert sorted(pngs) == sorted(req)
    with VideoReader(path) as v:
        for i, f in enumerate(req):
            img = v[i]
            png = cv2.imread(str(pngs[f]))[..., ::-1]
            assert pngs[f].name == f"overlay_{f:06d}.png"
            assert np.abs(img.astype(int) - png.astype(int)).mean() < 6  # same picture (mp4v)
            for c, cam in enumerate(cams):
                r, k = divmod(c, 2)
                tile = png[bar + 120 * r: bar + 120 * (r + 1), 160 * k: 160 * (k + 1)]
                assert abs(int(tile[115, 150, 0]) - (30 + 50 * f)) <= 6  # the frame's grey (mp4v: +-3)
                u, w = np.rint(project(cam, verts[f].mean(0))).astype(int)
                assert np.abs(tile[w, u].astype(int) - (30 + 50 * f)).max() > 40  # the box on it
    with pytest.raises(ValueError, match="frame_index"):
        render_overlays(cams, videos, [9], [verts], box.faces, frame_index, tmp_path / "png")


# ------------------------------------------------------------------------------ plot
def test_qa_plot_shades_flagged_spans(tmp_path):
    import cv2

    from drawing import qa_constants as Q
    from drawing.qa_plots import qa_figure, qa_plot

    F = 100
    frames = np.arange(F)
    rng = np.random.default_rng(0)
    med = rng.gamma(2, 2, F)
    med[70:75] = np.nan  # a gap
    values = {"wearer.marker_median_mm": med,
              "wearer.reproj_body_px.50591643": rng.gamma(2, 3, F),
              "penetration_mm": np.full(F, np.nan)}  # no data: no panel
    units = {"wearer.marker_median_mm": "mm", "wearer.reproj_body_px.50591643": "px",
             "penetration_mm": "mm"}
    thresholds = {"wearer.marker_median_mm": 10.0}
    spans = [(40, 59, "wearer.marker_median_mm")]
    p = qa_plot(tmp_path / "qa" / "qa.png", frames, 50.0, values, units, thresholds, spans,
                "s01 / Handshake 1")
    fig = qa_figure(frames, 50.0, values, units, thresholds, spans, "s01 / Handshake 1")
    assert fig.qa_panels == ["markers", "reproj.body"]
    img = cv2.imread(str(p))[..., ::-1].astype(int)
    H = img.shape[0]
    shade = np.rint(255 * (1 - Q.QA_SPAN_ALPHA + Q.QA_SPAN_ALPHA * np.asarray(Q.QA_SPAN_RGB)))
    is_shade = np.abs(img - shade).max(-1) <= 2
    for ax in fig.qa_axes:
        (x0, _), (x1, _) = ax.transData.transform([(39.5, 0.0), (59.5, 0.0)])
        (_, top), (_, bottom) = ax.transAxes.transform([(0.0, 1.0), (0.0, 0.0)])
        rows = slice(int(H - top) + 2, int(H - bottom) - 2)  # the panel (image rows go down)
        cols = np.flatnonzero(is_shade[rows].any(0))
        assert len(cols) > 0.8 * (x1 - x0)  # the span is shaded...
        assert cols.min() >= x0 - 2 and cols.max() <= x1 + 2  # ...and nothing else
        assert is_shade[rows, int(x0) + 3: int(x1) - 3].mean() > 0.5
    line = fig.qa_axes[0].lines[0]
    assert np.isnan(line.get_ydata()[70:75]).all()  # the gap stays a gap
    thr = [ln for ln in fig.qa_axes[0].lines if ln.get_linestyle() == "--"]
    assert len(thr) == 1 and thr[0].get_ydata()[0] == 10.0
