"""drawing/: the offscreen renderer against calib's projection (one renderer per module: see
drawing.render), contact sheets, and the residual plot's log axis and worst-frame marks."""
from __future__ import annotations

import numpy as np
import pytest


# ------------------------------------------------------------------------------ render
@pytest.fixture(scope="module")
def renderer():
    from drawing.render import Renderer
    from studio.rig import make_rig

    cams = make_rig(np.random.default_rng(1))
    with Renderer(cams) as r:
        yield r


def test_renderer_draws_points_where_calib_projects_them(renderer):
    """A small sphere rendered through the lens warp is centred on its projection (pyrender's
    intrinsics, the OpenGL pose and the distortion remap against calib.project)."""
    import trimesh

    from calib import project
    from drawing.render import PersonMesh

    rng = np.random.default_rng(2)
    err = []
    for _ in range(4):
        c = np.array([*rng.uniform(-0.8, 0.8, 2), rng.uniform(0.3, 1.8)])
        s = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
        mesh = PersonMesh(s.vertices + c, s.faces, np.full((len(s.vertices), 3), 200, np.uint8))
        ids = renderer.render_ids([mesh])
        for cam, m in zip(renderer.cams, ids, strict=True):
            ys, xs = np.nonzero(m == 0)
            assert len(xs) > 20
            uv = project(cam, c)
            # the silhouette of a sphere is centred on the projected centre up to perspective
            err.append((xs.mean() - uv[0], ys.mean() - uv[1]))
    err = np.array(err)
    assert np.abs(err.mean(0)).max() < 0.15, err.mean(0)  # no systematic shift
    assert np.hypot(*err.T).max() < 0.6, err


def test_render_shows_people_on_floor_and_background(renderer):
    import trimesh

    from drawing import constants as C
    from drawing.render import PersonMesh

    box = trimesh.creation.box((0.4, 0.3, 1.6))
    box.apply_translation([0, 0, 0.8])
    col = np.tile(np.array([40, 90, 200], np.uint8), (len(box.vertices), 1))
    rgb = renderer.render([PersonMesh(box.vertices, box.faces, col)])[0]
    ids = renderer.render_ids([PersonMesh(box.vertices, box.faces, col)])[0]
    assert rgb.shape == (900, 900, 3) and rgb.dtype == np.uint8
    bg = np.array(C.BACKGROUND_RGB)
    floor = np.array(C.FLOOR_RGB)
    out = rgb[ids < 0].astype(int)
    is_bg = np.abs(out - bg).max(1) <= 2
    is_floor = np.abs(out - floor).max(1) <= 2
    assert is_bg.mean() > 0.1 and is_floor.mean() > 0.3
    assert (is_bg | is_floor).mean() > 0.98
    person = rgb[ids == 0].astype(int)
    assert np.median(person[:, 2]) > np.median(person[:, 0]) + 40  # blue clothing



# ------------------------------------------------------------------------------ sheets
def test_contact_sheet_tiles_views_and_marks_points(tmp_path):
    import cv2

    from calib import project
    from drawing.sheet import close_up_cameras, contact_sheet, write_png

    point = np.array([0.3, -0.2, 1.1])
    cams = close_up_cameras(point, dist=0.5, size=200)
    for cam in cams:  # every close-up looks at the point
        np.testing.assert_allclose(project(cam, point), [100, 100], atol=1e-6)
    imgs = [np.full((200, 200, 3), 255, np.uint8) for _ in cams]
    sheet = contact_sheet(imgs, cams, "t", point[None], scale=0.5)
    assert sheet.shape == (200, 200, 3)
    # the ring around the point is drawn at the middle of each 100 x 100 tile, yellow
    for r0 in (0, 100):
        for c0 in (0, 100):
            tile = sheet[r0:r0 + 100, c0:c0 + 100].astype(int)
            ring = (tile[..., 2] < 150) & (tile[..., 0] > 200)
            ys, xs = np.nonzero(ring)
            assert len(xs) > 10 and abs(xs.mean() - 50) < 2 and abs(ys.mean() - 50) < 2
    p = write_png(tmp_path / "a" / "sheet.png", sheet)
    back = cv2.imread(str(p))[..., ::-1]
    np.testing.assert_array_equal(back, sheet)


# ------------------------------------------------------------------------------ plots
def test_residual_plot_log_axis_marks_the_worst_frames(tmp_path):
    import cv2

    from drawing import constants as C
    from drawing.plots import residual_plot

    rng = np.random.default_rng(0)
    F, M = 300, 30
    res = rng.lognormal(np.log(2.0), 0.4, (F, M))
    res[rng.random((F, M)) < 0.1] = np.nan  # gaps
    res[7] = np.nan  # a frame with no marker seen
    res[9] = 0.0  # exact zeros sit on the floor of the log axis
    res[60, 3], res[61, 4] = 600.0, 550.0  # one spike over two frames: one mark
    res[200, 0] = 300.0
    frames = 10 + 2 * np.arange(F)  # video frame numbers of the rows (a stride of 2)
    fig = residual_plot(tmp_path / "out" / "residuals.png", res, fps=50.0, title="s01 grab",
                        frames=frames, worst=3)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    lo, hi = ax.get_ylim()
    assert 0 < lo < 1.0 and hi > 600  # the 2 mm bulk and the outliers both readable
    labels = [t.get_text() for t in ax.texts]
    assert labels[:2] == [f"f{frames[60]}: 600 mm", f"f{frames[200]}: 300 mm"]
    assert len(labels) == 3 and not any(lab.startswith(f"f{frames[61]}:") for lab in labels)
    # marks at the worst frames' times, on the max curve
    marks = next(line for line in ax.lines if line.get_label().startswith("worst"))
    np.testing.assert_allclose(marks.get_xdata()[:2], [60 / 50.0, 200 / 50.0])
    np.testing.assert_allclose(marks.get_ydata()[:2], [600.0, 300.0])
    floor = min(np.nanmin(line.get_ydata()) for line in ax.lines)
    assert floor == C.RESIDUAL_FLOOR_MM
    img = cv2.imread(str(tmp_path / "out" / "residuals.png"))
    w, h = C.PLOT_SIZE_IN
    assert img.shape[:2] == (round(h * C.PLOT_DPI), round(w * C.PLOT_DPI))
    with pytest.raises(ValueError, match=r"res_mm: expected \(F, M\), got \(300,\)"):
        residual_plot(tmp_path / "x.png", res[:, 0], 50.0, "x")
    with pytest.raises(ValueError, match=r"frames: expected \(300,\)"):
        residual_plot(tmp_path / "x.png", res, 50.0, "x", frames=frames[:5])


def test_worst_frames_one_per_spike():
    from drawing.plots import worst_frames

    v = np.array([1.0, 9.0, 8.5, np.nan, 2.0, 7.0, 1.0, 8.0])
    assert worst_frames(v, 3, separation=2).tolist() == [1, 7, 5]
    assert worst_frames(v, 9, separation=1).tolist() == [1, 2, 7, 5, 4, 0, 6]
    assert worst_frames(np.full(4, np.nan), 2, 1).tolist() == []


def test_drawing_imports_only_allowed_packages():
    from tests.conftest import REPO
    from tests.test_layering import imported_modules

    project = {"stages", "body", "calib", "formats", "fitting", "studio", "recipes", "detect",
               "bench", "pipeline", "drawing", "artifacts", "geometry"}
    allowed = {"body", "calib", "formats", "geometry", "drawing"}
    files = sorted((REPO / "drawing").glob("*.py"))
    assert len(files) >= 4
    bad = {f.name: sorted((imported_modules(f) & project) - allowed) for f in files}
    assert {k: v for k, v in bad.items() if v} == {}


def test_marker_residual_plot_shows_the_lost_arm_the_median_hides(tmp_path):
    """Five markers off by 0.3-0.5 m among 39 at 2 mm: the overall median stays ~2 mm, the
    per-marker plot draws those five in red above the warning line on a log axis, names the
    worst markers' frames, and says which marker was never seen."""
    from drawing.plots import marker_residual_plot

    rng = np.random.default_rng(1)
    F, M = 200, 39
    res = rng.lognormal(np.log(2.0), 0.3, (F, M))
    lost = [18, 19, 20, 21, 22]
    res[:, lost] = rng.uniform(300, 500, (F, len(lost)))
    res[:, 30] = np.nan
    res[123, 5] = 900.0  # one spike on a good marker: its frame is named, it stays blue
    assert np.nanmedian(res) < 3.0
    names = [f"M{i}" for i in range(M)]
    fig = marker_residual_plot(tmp_path / "m.png", res, names, "t", frames=1000 + np.arange(F),
                               warn_mm=15.0)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and (tmp_path / "m.png").stat().st_size > 1000
    red = [ln for ln in ax.lines if ln.get_marker() == "o" and ln.get_color() == "crimson"]
    assert len(red) == 1 and sorted(red[0].get_xdata().tolist()) == lost
    texts = [t.get_text() for t in ax.texts]
    assert "f1123" in texts and "not seen" in texts
    assert [tick.get_text() for tick in ax.get_xticklabels()] == names


def _apart(boxes, gap=0.0):
    """No two display boxes overlap (closer than ``gap`` pixels)."""
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            if (a.x0 < b.x1 + gap and b.x0 < a.x1 + gap and a.y0 < b.y1 + gap
                    and b.y0 < a.y1 + gap):
                return False
    return True


def test_residual_plot_worst_frame_labels_never_stack(tmp_path):
    """Five spikes of similar height 0.3 s apart in a 60 s capture are a few pixels apart on
    the time axis: their labels (C3D frame numbers, as the caller passes them) are moved
    apart, no two text boxes of the figure overlap, and each still names its frame."""
    from drawing.plots import residual_plot, text_boxes

    rng = np.random.default_rng(3)
    F, M, fps = 3000, 20, 50.0
    res = rng.lognormal(np.log(2.0), 0.3, (F, M))
    spikes = 1500 + 15 * np.arange(5)  # 0.3 s apart (> the 0.2 s separation): five marks
    res[spikes, 2] = [160.0, 150.0, 155.0, 148.0, 152.0]
    frames = 4821 + np.arange(F)  # first_frame + sample + 1 of a capture starting at 4820
    fig = residual_plot(tmp_path / "r.png", res, fps, "stacked", frames=frames, worst=5)
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert sorted(texts) == sorted(f"f{frames[i]}: {res[i, 2]:.0f} mm" for i in spikes)
    boxes = text_boxes(fig)
    assert len(boxes) == 5 and _apart(boxes)
    # without the separation they would have stacked: the marked points are < 10 px apart
    ax = fig.axes[0]
    px = ax.transData.transform(np.c_[spikes / fps, res[spikes, 2]])
    assert np.ptp(px[:, 0]) < 20  # a label is ~70 px wide
    inside = ax.get_window_extent(fig.canvas.get_renderer())  # and none over the title
    assert all(b.y1 <= inside.y1 and b.x0 >= inside.x0 for b in boxes)


def test_marker_residual_plot_frame_labels_never_stack(tmp_path):
    """Neighbouring markers with maxima of the same height: their frame labels (wider than a
    marker's column) do not overlap."""
    from drawing.plots import marker_residual_plot, text_boxes

    rng = np.random.default_rng(4)
    F, M = 400, 39
    res = rng.lognormal(np.log(2.0), 0.3, (F, M))
    for k, m in enumerate(range(10, 15)):
        res[100 + k, m] = 200.0 + k
    frames = 123456 + np.arange(F)  # long frame numbers: wide labels
    fig = marker_residual_plot(tmp_path / "m.png", res, [f"M{i}" for i in range(M)], "t",
                               frames=frames, warn_mm=15.0)
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert sorted(texts) == sorted(f"f{frames[100 + k]}" for k in range(5))
    assert _apart(text_boxes(fig))
    inside = fig.axes[0].get_window_extent(fig.canvas.get_renderer())
    assert all(b.x0 >= inside.x0 and b.x1 <= inside.x1 and b.y1 <= inside.y1
               for b in text_boxes(fig))


_ROOM_DIGEST = """
import hashlib
import numpy as np
from drawing.render import PersonMesh, Renderer
from studio import plan as PL
from studio.session import SessionParts

plan = PL.realistic(PL.make_plan(0, frames=10, scenarios=("grab",)))
parts = SessionParts.of(plan)
cams = parts.cams[:2]
V = np.array([[0.0, 0.0, 0.5], [0.4, 0.0, 0.5], [0.0, 0.0, 1.5]])
people = [PersonMesh(V + (0.2 * i, 0.0, 0.0), np.array([[0, 1, 2]]), np.full((3, 3), 90 + 60 * i))
          for i in range(2)]  # two triangles, one behind the other in part
with Renderer(cams, room=parts.room) as r:
    imgs = list(r.render_room()) + list(r.render(people))
print(" ".join(hashlib.md5(np.ascontiguousarray(x).tobytes()).hexdigest() for x in imgs))
"""


def test_the_lab_room_renders_the_same_bytes_in_every_process():
    """pyrender draws its nodes in a set's order, which changes from process to process; where
    two surfaces tie in depth (the lab room's parts against the floor and the walls) the first
    drawn wins the pixel. The room is one mesh of ordered primitives and each person a node of
    its own pose, so two processes render the same bytes (before: 8-93 pixels per view
    differed, up to 41 grey levels, and every realistic video with them)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    runs = [subprocess.run([sys.executable, "-c", _ROOM_DIGEST], cwd=root, env=env, check=True,
                           capture_output=True, text=True).stdout.split() for _ in range(3)]
    assert len(runs[0]) == 4
    assert runs[0] == runs[1] == runs[2]
