"""Fitted meshes drawn over the video frames of the four views, tiled into one picture (PNG per
frame, or one MP4 over a run of frames): the QA overlays a person inspects.

The people are drawn by the shared :class:`drawing.render.Renderer`: the same camera model as
the fit, lens distortion included (the pinhole image is remapped through each camera's lens),
so a vertex lands on the pixel ``calib.project`` gives it and the mesh sits on the person in the
video where the fit is right. Each person's shaded mesh is blended over the video image where
:meth:`Renderer.render_ids` says the person is visible, and the visible silhouette gets a 1-px
outline in the person's colour (``drawing.qa_constants.PERSON_RGB``: wearer, partner).

Frames: ``frames`` are video frame indices (the fit's frame numbers); ``vertices`` are per
person ``(F, V, 3)`` on the QA frame axis and ``frame_index`` maps a video frame to its row. A
person whose row is not finite (not fitted there) is left out of that frame.

One renderer at a time per process (``docs/ARCHITECTURE.md``, "Drawing contract"):
:func:`render_overlays` and :func:`overlay_video` each open and close their own.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from calib import Camera
from drawing import qa_constants as Q
from drawing.render import PersonMesh, Renderer
from drawing.sheet import write_png
from formats.video import VideoReader, write_mp4


def person_colors(n: int, colors=None) -> list[tuple[int, int, int]]:
    """RGB per person: ``colors`` (one RGB triple per person) or qa_constants.PERSON_RGB."""
    if colors is None:
        return [tuple(Q.PERSON_RGB[k % len(Q.PERSON_RGB)]) for k in range(n)]
    colors = [tuple(int(c) for c in np.asarray(col).reshape(3)) for col in colors]
    if len(colors) < n:
        raise ValueError(f"colors: {len(colors)} for {n} people")
    return colors[:n]


def silhouette_outline(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` with a 4-neighbour outside it (a 1-px inner
    outline; the image border does not count as outside)."""
    import cv2

    m = np.ascontiguousarray(mask, np.uint8)
    inner = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)),
                      borderType=cv2.BORDER_REPLICATE)
    return mask.astype(bool) & ~inner.astype(bool)


def overlay_views(renderer: Renderer, cams: list[Camera], people: list[PersonMesh],
                  images: list[np.ndarray], alpha: float = Q.OVERLAY_ALPHA,
                  outline: bool = True, outline_colors=None) -> list[np.ndarray]:
    """The ``people`` rendered by ``renderer`` (opened on ``cams``, same order) blended over
    each view's video image: ``(1 - alpha) image + alpha render`` where the person is visible
    (``render_ids >= 0``), the video untouched elsewhere, and with ``outline`` a 1-px outline of
    each person's visible silhouette in ``outline_colors[k]`` (default: the mean colour of
    ``people[k].colors``). images: one (H, W, 3) uint8 RGB per camera, H, W its size. Returns
    one (H, W, 3) uint8 RGB per view."""
    if len(renderer.cams) != len(cams) or any(a is not b and not a.allclose(b)
                                              for a, b in zip(renderer.cams, cams, strict=True)):
        raise ValueError("overlay_views: the renderer was opened on other cameras")
    if len(images) != len(cams):
        raise ValueError(f"images: {len(images)} for {len(cams)} cameras")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha: expected 0..1, got {alpha}")
    for img, cam in zip(images, cams, strict=True):
        if np.shape(img) != (cam.height, cam.width, 3):
            raise ValueError(f"images: camera {cam.name} is {cam.width}x{cam.height}, its image "
                             f"has shape {np.shape(img)}")
    if not people:
        return [np.array(img, np.uint8, copy=True) for img in images]
    if outline_colors is None:
        outline_colors = [np.asarray(p.colors, float).reshape(-1, 3).mean(0).round() for p in people]
    rgbs = renderer.render(people)
    ids = renderer.render_ids(people)
    out = []
    for img, rgb, pid in zip(images, rgbs, ids, strict=True):
        o = np.array(img, np.uint8, copy=True)
        on = pid >= 0
        mix = (1.0 - alpha) * o[on].astype(np.float32) + alpha * rgb[on].astype(np.float32)
        o[on] = np.clip(np.rint(mix), 0, 255).astype(np.uint8)
        if outline:
            for k in range(len(people)):
                o[silhouette_outline(pid == k)] = np.asarray(outline_colors[k], np.uint8)
        out.append(o)
    return out


def tile_views(images: list[np.ndarray], labels: list[str], title: str = "",
               scale: float = 0.5) -> np.ndarray:
    """The views in a grid (``ceil(sqrt(n))`` columns, as many rows as needed: 2 x 2 for
    four), each resized by ``scale`` into a cell of the largest tile's size (top-left aligned,
    black around), its label written top-left, and a title bar of
    qa_constants.TILE_TITLE_PX on top (drawn when ``title`` is empty too, so every tiled frame of
    a video has one size). images: (H, W, 3) uint8 RGB. Returns (TILE_TITLE_PX + rows h,
    cols w, 3) uint8 RGB."""
    import cv2

    if not images:
        raise ValueError("tile_views: no images")
    if len(labels) != len(images):
        raise ValueError(f"labels: {len(labels)} for {len(images)} images")
    if not scale > 0:
        raise ValueError(f"scale: expected > 0, got {scale}")
    tiles = []
    for img in images:
        img = np.asarray(img)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"tile_views: expected (H, W, 3) uint8 images, got {img.shape} {img.dtype}")
        h, w = max(1, int(round(img.shape[0] * scale))), max(1, int(round(img.shape[1] * scale)))
        interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        tiles.append(np.ascontiguousarray(cv2.resize(img, (w, h), interpolation=interp)))
    n = len(tiles)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    th, tw = max(t.shape[0] for t in tiles), max(t.shape[1] for t in tiles)
    bar = Q.TILE_TITLE_PX
    out = np.zeros((bar + rows * th, cols * tw, 3), np.uint8)
    out[:bar] = Q.TILE_TITLE_BG_RGB
    font, fs, m = cv2.FONT_HERSHEY_SIMPLEX, Q.TILE_TEXT_SCALE, Q.TILE_TEXT_MARGIN_PX
    for i, (t, lab) in enumerate(zip(tiles, labels, strict=True)):
        r, c = divmod(i, cols)
        y0, x0 = bar + r * th, c * tw
        cell = out[y0:y0 + th, x0:x0 + tw]
        cell[:t.shape[0], :t.shape[1]] = t
        if lab:
            org = (m, m + int(round(20 * fs)))
            cv2.putText(cell, str(lab), org, font, fs, Q.TILE_LABEL_SHADOW_RGB, 3, cv2.LINE_AA)
            cv2.putText(cell, str(lab), org, font, fs, Q.TILE_TEXT_RGB, 1, cv2.LINE_AA)
    if title:
        cv2.putText(out, str(title), (m, bar - m), font, fs, Q.TILE_TEXT_RGB, 1, cv2.LINE_AA)
    return out


def _check_inputs(cams, videos, vertices, faces, frame_index, frames):
    if len(videos) != len(cams):
        raise ValueError(f"videos: {len(videos)} for {len(cams)} cameras")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected (T, 3), got {faces.shape}")
    verts = []
    for k, v in enumerate(vertices):
        v = np.asarray(v)
        if v.ndim != 3 or v.shape[2] != 3:
            raise ValueError(f"vertices[{k}]: expected (F, V, 3), got {v.shape}")
        verts.append(v)
    rows = {}
    for f in frames:
        f = int(f)
        if f not in frame_index:
            raise ValueError(f"frame_index: video frame {f} has no row")
        i = int(frame_index[f])
        for k, v in enumerate(verts):
            if not 0 <= i < len(v):
                raise ValueError(f"frame_index: video frame {f} -> row {i}, but vertices[{k}] "
                                 f"has {len(v)} rows")
        rows[f] = i
    return faces, verts, rows


def _open_videos(cams, videos) -> list[VideoReader]:
    readers = []
    try:
        for cam, p in zip(cams, videos, strict=True):
            # frames padded / cropped to the camera's size (a few pixels at most, right / bottom:
            # formats.video.size_fit; further off: InputError saying both sizes)
            readers.append(VideoReader(p, size=(cam.width, cam.height)))
    except BaseException:
        for r in readers:
            r.close()
        raise
    return readers


def _people_at(verts, faces, row, cols) -> tuple[list[PersonMesh], list]:
    people, outl = [], []
    for v, col in zip(verts, cols, strict=True):
        x = np.asarray(v[row], float)
        if np.all(np.isfinite(x)):
            people.append(PersonMesh(x, faces, np.tile(np.asarray(col, np.uint8), (len(x), 1))))
            outl.append(col)
    return people, outl


def _frames_tiled(cams, videos, frames, vertices, faces, frame_index, titles, colors, scale,
                  progress, desc):
    """Yield (frame, tiled RGB) per requested frame, one renderer and the video readers open."""
    faces, verts, rows = _check_inputs(cams, videos, vertices, faces, frame_index, frames)
    cols = person_colors(len(verts), colors)
    readers = _open_videos(cams, videos)
    try:
        with Renderer(cams) as r:
            it = frames if progress is None else progress(frames, total=len(frames), desc=desc)
            for f in it:
                f = int(f)
                images = [rd[f] for rd in readers]
                people, outl = _people_at(verts, faces, rows[f], cols)
                views = overlay_views(r, cams, people, images, outline_colors=outl)
                title = (titles or {}).get(f, f"frame {f}")
                yield f, tile_views(views, [c.name for c in cams], title, scale)
    finally:
        for rd in readers:
            rd.close()


def render_overlays(cams: list[Camera], videos: list[Path], frames: list[int],
                    vertices: list[np.ndarray], faces: np.ndarray, frame_index: dict[int, int],
                    out_dir: Path, titles: dict[int, str] | None = None, colors=None,
                    scale: float = 0.5, progress=None) -> dict[int, Path]:
    """One PNG per requested video frame, ``out_dir/overlay_<frame:06d>.png``: the people
    (``vertices[k][frame_index[frame]]``, ``faces``) overlaid on the frame of each view
    (``videos`` in the order of ``cams``) and the views tiled (:func:`tile_views`, labels the
    camera names, title ``titles[frame]`` or ``frame <n>``). colors: RGB per person (default
    wearer, partner of qa_constants.PERSON_RGB); progress: ``progress(iterable, total=,
    desc=)`` wrapper. Returns {frame: path}."""
    out_dir = Path(out_dir)
    out = {}
    for f, img in _frames_tiled(cams, videos, list(frames), vertices, faces, frame_index,
                                titles, colors, scale, progress, "overlays"):
        out[f] = write_png(out_dir / f"overlay_{f:06d}.png", img)
    return out


def _even(img: np.ndarray) -> np.ndarray:
    """Pad to even height and width (H.264/MPEG-4 encoders want even sizes)."""
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return img
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)))


def overlay_video(path: Path, cams: list[Camera], videos: list[Path], frames: list[int],
                  vertices: list[np.ndarray], faces: np.ndarray, frame_index: dict[int, int],
                  fps: float, scale: float = 0.5, progress=None, colors=None) -> Path:
    """One MP4 (``formats.video.write_mp4``, played at ``fps``) of the tiled overlays
    (:func:`render_overlays`' pictures, title ``frame <n>  <t> s``) over ``frames``, one video
    frame per requested frame, in the given order. Returns ``path``."""
    if not fps > 0:
        raise ValueError(f"fps: expected > 0, got {fps}")
    frames = [int(f) for f in frames]
    if len(videos) != len(cams):
        raise ValueError(f"videos: {len(videos)} for {len(cams)} cameras")
    if not frames:
        raise ValueError("frames: no frames for the overlay video")
    with VideoReader(videos[0]) as v0:
        vfps = v0.info.fps
    titles = {f: f"frame {f}  {f / vfps:.2f} s" for f in frames}
    gen = _frames_tiled(cams, videos, frames, vertices, faces, frame_index, titles, colors,
                        scale, progress, "overlay video")
    return write_mp4(path, (_even(img) for _, img in gen), fps)
