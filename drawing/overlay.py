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


# ------------------------------------------------------------------------------ fast path
# The QA stage draws its overlays without the EGL renderer: each person's decimated mesh is
# projected through the camera (lens included, ``calib.project``) and filled triangle by
# triangle with OpenCV, farthest first (painter's order; back faces culled), at the output's
# scale. About 1,500 faces per body at half size cost ~10 ms for four views, against ~0.3 s
# for the renderer's colour and id passes at full size. Triangles that cross each other are
# drawn whole in depth order (no per-pixel depth test): at the overlays' scale it shows at
# most where the two bodies interpenetrate.

RASTER_SUBPIXEL_BITS = 4  # fixed-point fraction of the triangle corners (1/16 px)


def scaled_size(cam: Camera, scale: float) -> tuple[int, int]:
    """(width, height) of ``cam``'s image at ``scale`` (what ``tile_views`` makes of it)."""
    return (max(1, int(round(cam.width * scale))), max(1, int(round(cam.height * scale))))


class RasterScene:
    """The people of one frame ready for :func:`raster_people` in any view: their vertices
    and faces stacked, each face's flat colour (the mean of its vertices' ``colors`` times the
    Lambert shading of its normal under the studio lights, ``drawing.render.shading``) and
    person index, computed once for all views."""

    def __init__(self, people: list[PersonMesh]):
        from drawing.render import shading

        Vs, Fs, cols, pid, off = [], [], [], [], 0
        for k, p in enumerate(people):
            V = np.asarray(p.vertices, float).reshape(-1, 3)
            F = np.asarray(p.faces, np.int64).reshape(-1, 3)
            n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            Vs.append(V)
            Fs.append(F + off)
            cols.append(np.asarray(p.colors, float).reshape(-1, 3)[F].mean(1) * shading(n)[:, None])
            pid.append(np.full(len(F), k, np.int8))
            off += len(V)
        self.n_people = len(people)
        self.V = np.concatenate(Vs) if Vs else np.zeros((0, 3))
        self.F = np.concatenate(Fs) if Fs else np.zeros((0, 3), np.int64)
        self.lut_rgb = np.zeros((len(self.F) + 1, 3), np.uint8)  # 0: nobody
        self.lut_id = np.full(len(self.F) + 1, -1, np.int8)
        if Fs:
            self.lut_rgb[1:] = np.clip(np.rint(np.concatenate(cols)), 0, 255).astype(np.uint8)
            self.lut_id[1:] = np.concatenate(pid)


def raster_people(cam: Camera, people: list[PersonMesh] | RasterScene, scale: float = 1.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``people`` (or a :class:`RasterScene` of them) drawn in ``cam``'s image at
    ``scale``: ``(rgb (h, w, 3) uint8, ids (h, w) int8)`` with ``(w, h) = scaled_size(cam,
    scale)``. Each face is filled flat with its colour (:class:`RasterScene`), front faces only,
    farthest first; ``ids`` is the person index per pixel (-1: nobody), ``rgb`` black where
    nobody is. Corners are projected with the lens (``calib.project``): pixel centre ``u`` of
    the full image is ``(u + 0.5) scale - 0.5``."""
    import cv2

    from calib.camera import project, world_to_cam
    from drawing import constants as C

    if not scale > 0:
        raise ValueError(f"scale: expected > 0, got {scale}")
    sc = people if isinstance(people, RasterScene) else RasterScene(people)
    w, h = scaled_size(cam, scale)
    if not len(sc.F):
        return np.zeros((h, w, 3), np.uint8), np.full((h, w), -1, np.int8)
    V, F = sc.V, sc.F
    z = world_to_cam(cam, V)[:, 2]
    uv = (project(cam, V) + 0.5) * scale - 0.5
    tri = uv[F]  # (T, 3, 2)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    front = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0  # outward faces seen from outside
    lo, hi = tri.min(1), tri.max(1)
    keep = (front & (z[F] > C.ZNEAR_M).all(1) & np.isfinite(tri).all((1, 2))
            & (hi[:, 0] >= -1) & (hi[:, 1] >= -1) & (lo[:, 0] <= w) & (lo[:, 1] <= h)
            & (np.abs(tri) < 1e5).all((1, 2)))
    sel = np.flatnonzero(keep)
    sel = sel[np.argsort(-z[F[sel]].sum(1), kind="stable")]  # farthest first
    canvas = np.zeros((h, w), np.int32)
    pts = np.rint(tri[sel] * (1 << RASTER_SUBPIXEL_BITS)).astype(np.int32)
    fill, bits, line = cv2.fillConvexPoly, RASTER_SUBPIXEL_BITS, cv2.LINE_8
    for val, p in zip((sel + 1).tolist(), list(pts), strict=True):
        fill(canvas, p, val, line, bits)
    return sc.lut_rgb[canvas], sc.lut_id[canvas]


def blend_people(image: np.ndarray, rgb: np.ndarray, ids: np.ndarray, n_people: int,
                 outline_colors, alpha: float = Q.OVERLAY_ALPHA, outline: bool = True
                 ) -> np.ndarray:
    """``(1 - alpha) image + alpha rgb`` where ``ids >= 0``, the image elsewhere, and with
    ``outline`` a 1-px outline of each person's silhouette (``ids == k``) in
    ``outline_colors[k]`` (what :func:`overlay_views` does with the renderer's images)."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha: expected 0..1, got {alpha}")
    o = np.array(image, np.uint8, copy=True)
    on = ids >= 0
    mix = (1.0 - alpha) * o[on].astype(np.float32) + alpha * rgb[on].astype(np.float32)
    o[on] = np.clip(np.rint(mix), 0, 255).astype(np.uint8)
    if outline:
        for k in range(n_people):
            o[silhouette_outline(ids == k)] = np.asarray(outline_colors[k], np.uint8)
    return o


class _VideoOut:
    """The overlay video as MP4 (``mp4v``) and, with ``webm``, VP8 WebM beside it (same stem:
    what Chromium plays), written frame by frame from one stream of pictures. The encoders run
    in a thread (OpenCV releases the GIL while encoding: the VP8 encoder, the costly one, works
    beside the drawing); an encoder's error comes out of the next ``write`` or ``close``."""

    def __init__(self, path: Path, fps: float, webm: bool):
        self.path, self.fps, self.webm = Path(path), float(fps), webm
        self.writers: list = []
        self.size = None
        self._queue = None
        self._thread = None
        self._error: BaseException | None = None

    def _open(self, size) -> None:
        import cv2

        self.size = size
        self.path.parent.mkdir(parents=True, exist_ok=True)
        outs = [(self.path, "mp4v")] + ([(self.path.with_suffix(".webm"), "VP80")]
                                        if self.webm else [])
        for p, cc in outs:
            wr = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*cc), self.fps, self.size)
            if not wr.isOpened():
                self._release()
                raise OSError(f"{p}: cannot open a {cc} writer")
            self.writers.append(wr)

    def _encode(self) -> None:
        while True:
            img = self._queue.get()
            if img is None:
                return
            if self._error is not None:
                continue  # drain after a failure
            try:
                for wr in self.writers:
                    wr.write(img)
            except BaseException as e:  # noqa: BLE001 - handed to the drawing thread
                self._error = e

    def write(self, rgb: np.ndarray) -> None:
        import queue
        import threading

        import cv2

        img = cv2.cvtColor(np.ascontiguousarray(_even(rgb)), cv2.COLOR_RGB2BGR)
        if self._error is not None:
            raise self._error
        if self._thread is None:
            self._open((img.shape[1], img.shape[0]))
            self._queue = queue.Queue(maxsize=8)
            self._thread = threading.Thread(target=self._encode, name="overlay-video",
                                            daemon=True)
            self._thread.start()
        elif (img.shape[1], img.shape[0]) != self.size:
            raise ValueError(f"{self.path}: frame size {img.shape[1]}x{img.shape[0]} != "
                             f"{self.size[0]}x{self.size[1]}")
        self._queue.put(img)

    def _release(self) -> None:
        for wr in self.writers:
            wr.release()
        self.writers = []

    def close(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        self._release()
        if self._error is not None:
            raise self._error


def draw_overlays(cams: list[Camera], videos: list[Path], vertices: list[np.ndarray],
                  faces: np.ndarray, frame_index: dict[int, int], *,
                  png_frames=(), png_dir: Path | None = None, titles: dict[int, str] | None = None,
                  png_scale: float = 0.5, video_path: Path | None = None, video_frames=(),
                  video_fps: float = 25.0, video_scale: float = 0.25, webm: bool = True,
                  video_mesh: tuple[list[np.ndarray], np.ndarray] | None = None,
                  colors=None, progress=None, feed: FrameFeed | None = None,
                  feed_consumer: str = "overlay") -> tuple[dict[int, Path], Path | None]:
    """The QA overlays in one sequential pass over the videos, drawn by :func:`raster_people`:
    a PNG per frame of ``png_frames`` (``png_dir/overlay_<frame:06d>.png``, views at
    ``png_scale``, title ``titles[frame]``: what :func:`render_overlays` writes) and the video
    (``video_path``: MP4 and, with ``webm``, a WebM beside it) of ``video_frames`` (ascending),
    views at ``video_scale``, title ``frame <n>  <t> s``, played at ``video_fps``. Each video
    frame is decoded once, each view drawn once per scale. vertices: per person (F, V', 3) of
    the mesh ``faces`` (e.g. a decimated one) on the QA frame axis, ``frame_index`` video
    frame -> row; a person whose row is not finite is left out; video_mesh : ``(vertices,
    faces)`` of a coarser mesh for the video's smaller views (default the same); feed : the
    frames from a :class:`FrameFeed` (as ``feed_consumer``; it must hold every frame drawn, at
    ``png_scale`` and ``video_scale``) instead of reading ``videos`` here. Returns
    ``({frame: png}, video path or None)``."""
    png_frames = sorted({int(f) for f in png_frames})
    video_frames = [int(f) for f in video_frames]
    if png_frames and png_dir is None:
        raise ValueError("png_dir: needed for png_frames")
    if video_frames and video_path is None:
        raise ValueError("video_path: needed for video_frames")
    if any(np.diff(video_frames) <= 0):
        raise ValueError("video_frames: expected strictly increasing frames")
    if video_frames and not video_fps > 0:
        raise ValueError(f"video_fps: expected > 0, got {video_fps}")
    for name, s in (("png_scale", png_scale), ("video_scale", video_scale)):
        if not s > 0:
            raise ValueError(f"{name}: expected > 0, got {s}")
    frames = sorted(set(png_frames) | set(video_frames))
    faces, verts, rows = _check_inputs(cams, videos, vertices, faces, frame_index, frames)
    vfaces, vverts = faces, verts
    if video_mesh is not None:
        vfaces, vverts, _ = _check_inputs(cams, videos, video_mesh[0], video_mesh[1],
                                          frame_index, video_frames)
        if len(vverts) != len(verts):
            raise ValueError(f"video_mesh: {len(vverts)} people for {len(verts)}")
    cols = person_colors(len(verts), colors)
    labels = [c.name for c in cams]
    want_png, want_video = set(png_frames), set(video_frames)
    pngs: dict[int, Path] = {}
    if not frames:
        if feed is not None:
            feed.done(feed_consumer)
        return pngs, None
    if feed is not None:
        for s in (png_scale,) * bool(png_frames) + (video_scale,) * bool(video_frames):
            if float(s) not in feed.scales:
                feed.done(feed_consumer)
                raise ValueError(f"feed: keeps scales {feed.scales}, not {s}")
        readers = []
        vfps = feed.fps
    else:
        readers = _open_videos(cams, videos)
        vfps = readers[0].info.fps
    out = _VideoOut(video_path, video_fps, webm) if video_frames else None
    try:
        it = frames if progress is None else progress(frames, total=len(frames), desc="overlays")
        for f in it:
            images = [rd[f] for rd in readers]
            jobs = ([("png", png_scale, verts, faces)] if f in want_png else []) + \
                   ([("video", video_scale, vverts, vfaces)] if f in want_video else [])
            drawn = {}
            for what, s, vv, ff in jobs:
                if what == "video" and "png" in drawn and s == png_scale and vv is verts:
                    drawn[what] = drawn["png"]
                    continue
                people, outl = _people_at(vv, ff, rows[f], cols)
                scene = RasterScene(people)
                views = []
                if feed is not None:
                    images = feed.get(feed_consumer, f, s)  # already at the scale
                for cam, img in zip(cams, images, strict=True):
                    size = scaled_size(cam, s)
                    small = img if size == (img.shape[1], img.shape[0]) else _resize(img, size)
                    rgb, ids = raster_people(cam, scene, s)
                    views.append(blend_people(small, rgb, ids, len(people), outl))
                drawn[what] = views
            if f in want_png:
                title = (titles or {}).get(f, f"frame {f}")
                pngs[f] = write_png(Path(png_dir) / f"overlay_{f:06d}.png",
                                    tile_views(drawn["png"], labels, title, 1.0))
            if f in want_video:
                out.write(tile_views(drawn["video"], labels, f"frame {f}  {f / vfps:.2f} s",
                                     1.0))
    finally:
        for rd in readers:
            rd.close()
        if feed is not None:
            feed.done(feed_consumer)
        if out is not None:
            out.close()
    return pngs, (Path(video_path) if video_frames else None)


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    interp = cv2.INTER_AREA if size[0] < img.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(img, size, interpolation=interp)


class FrameFeed:
    """The video frames the QA drawings need, each decoded once: a thread reads ``frames``
    (ascending) of every view in order (one :class:`formats.video.VideoReader` per camera,
    padded to the calibration's size, reading on from where it stopped: no seek per frame) and
    keeps each at every one of ``scales`` (``scaled_size``, ``cv2.INTER_AREA`` from the full
    frame: what :func:`draw_overlays` and ``formats.foxglove_scene.write_scene`` do to it)
    until every consumer has gone past it. The decoding runs beside the caller (OpenCV
    releases the GIL while decoding and resizing), e.g. while the QA metrics are computed.

    ``consumers``: the names of the readers, given up front; each takes frames in ascending
    order with :meth:`get` (taking frame ``f`` releases its frames before ``f``) and says
    :meth:`done` when it needs no more. At most ``ahead`` frames are held: a consumer that
    falls behind holds the decoding back (so every consumer must run: one that runs only after
    another has finished must not be one of them). A decoding error comes out of :meth:`get`.
    :meth:`close` stops the thread and closes the videos."""

    def __init__(self, cams: list[Camera], videos: list[Path], frames, scales, consumers,
                 ahead: int = 32):
        import threading

        if len(videos) != len(cams):
            raise ValueError(f"videos: {len(videos)} for {len(cams)} cameras")
        if ahead < 1:
            raise ValueError(f"ahead: expected >= 1, got {ahead}")
        self.cams = list(cams)
        self.frames = sorted({int(f) for f in frames})
        self.scales = sorted({float(s) for s in scales})
        if not self.scales or not all(s > 0 for s in self.scales):
            raise ValueError(f"scales: expected values > 0, got {scales}")
        self.ahead = int(ahead)
        self._cursor = {str(c): -1 for c in consumers}
        self._store: dict[int, dict[float, list[np.ndarray]]] = {}
        self._cond = threading.Condition()
        self._error: BaseException | None = None
        self._finished = False
        self._stop = False
        self._readers = _open_videos(cams, videos)
        self.fps = self._readers[0].info.fps  # the first view's (titles of the video)
        self._thread = threading.Thread(target=self._run, name="qa-frames", daemon=True)
        self._thread.start()

    def _low(self) -> float:
        return min(self._cursor.values(), default=math.inf)

    def _release(self) -> None:  # under the lock
        low = self._low()
        for f in [f for f in self._store if f < low]:
            del self._store[f]
        self._cond.notify_all()

    def _run(self) -> None:
        try:
            for f in self.frames:
                with self._cond:
                    while not self._stop and len(self._store) >= self.ahead:
                        self._cond.wait()
                    if self._stop or f < self._low():  # stopped, or nobody needs it any more
                        if self._stop or self._low() == math.inf:
                            return
                        continue
                imgs = [rd[f] for rd in self._readers]
                scaled = {}
                for s in self.scales:
                    scaled[s] = [img if scaled_size(cam, s) == (img.shape[1], img.shape[0])
                                 else _resize(img, scaled_size(cam, s))
                                 for cam, img in zip(self.cams, imgs, strict=True)]
                with self._cond:
                    self._store[f] = scaled
                    self._cond.notify_all()
        except BaseException as e:  # noqa: BLE001 - handed to the consumers
            with self._cond:
                self._error = e
        finally:
            with self._cond:
                self._finished = True
                self._cond.notify_all()

    def get(self, consumer: str, frame: int, scale: float) -> list[np.ndarray]:
        """Frame ``frame`` of every view at ``scale`` (one of the feed's; (h, w, 3) uint8 RGB,
        ``(w, h) = scaled_size(cam, scale)``), waiting for it to be decoded. Frames before it
        are released for ``consumer``. The arrays are shared: do not write into them."""
        frame, scale = int(frame), float(scale)
        if scale not in self.scales:
            raise ValueError(f"scale {scale}: the feed keeps {self.scales}")
        with self._cond:
            if consumer not in self._cursor:
                raise ValueError(f"consumer {consumer!r}: not one of {list(self._cursor)}")
            if frame < self._cursor[consumer]:
                raise ValueError(f"{consumer}: frame {frame} after frame {self._cursor[consumer]} "
                                 "(frames are taken in ascending order)")
            self._cursor[consumer] = frame
            self._release()
            while frame not in self._store:
                if self._error is not None:
                    raise self._error
                if self._finished or self._stop:
                    raise ValueError(f"frame {frame}: not one of the feed's frames")
                self._cond.wait()
            return self._store[frame][scale]

    def done(self, consumer: str) -> None:
        """``consumer`` needs no more frames."""
        with self._cond:
            if consumer in self._cursor:
                self._cursor[consumer] = math.inf
                self._release()

    def close(self) -> None:
        """Stop the decoding thread, close the videos, drop the frames."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join()
        for rd in self._readers:
            rd.close()
        self._readers = []
        self._store.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
