"""Contact sheet: the four views of one frame in a 2x2 grid, with the annotated contact points
drawn on them (a picture to check a session at a glance)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calib import Camera, project
from drawing import constants as C


def contact_sheet(images: list[np.ndarray], cams: list[Camera], title: str,
                  points: np.ndarray | None = None, scale: float = 0.5) -> np.ndarray:
    """images: four (H, W, 3) uint8 RGB views; cams: their cameras; points: (P, 3) world
    metres to mark (contact facets), or None. Returns (2 h, 2 w, 3) uint8 RGB, h = H * scale."""
    import cv2

    tiles = []
    for img, cam in zip(images, cams, strict=True):
        t = np.ascontiguousarray(img.copy())
        if points is not None and len(points):
            for u, v in project(cam, np.asarray(points)):
                if np.isfinite(u) and np.isfinite(v):
                    cv2.circle(t, (int(round(u)), int(round(v))), C.SHEET_POINT_RADIUS_PX,
                               C.SHEET_POINT_RGB, 2, cv2.LINE_AA)
        t = cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.putText(t, cam.name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, C.SHEET_TEXT_RGB, 2,
                    cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) < 4:
        tiles.append(np.zeros_like(tiles[0]))
    sheet = np.concatenate([np.concatenate(tiles[:2], 1), np.concatenate(tiles[2:4], 1)], 0)
    cv2.putText(sheet, title, (8, sheet.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                C.SHEET_TEXT_RGB, 2, cv2.LINE_AA)
    return sheet


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG (parents created)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"{path}: could not write PNG")
    return path


def close_up_cameras(point: np.ndarray, dist: float = C.CLOSE_M,
                     size: int = C.CLOSE_SIZE_PX) -> list[Camera]:
    """Four pinhole cameras (``size`` x ``size`` px, focal length ``size``) around ``point``
    (3,) world metres, ``dist`` away and a little above it (constants.CLOSE_RISE), looking at
    it from constants.CLOSE_AZIMUTHS_DEG."""
    from calib.camera import look_at

    point = np.asarray(point, float)
    cams = []
    for k, az in enumerate(C.CLOSE_AZIMUTHS_DEG):
        a = np.deg2rad(az)
        c = point + dist * np.array([np.cos(a), np.sin(a), C.CLOSE_RISE])
        cams.append(look_at(f"close{k}", c, point, (size, size), (size / 2, size / 2), size, size))
    return cams


def close_up(people: list, point: np.ndarray, title: str, dist: float = C.CLOSE_M,
             size: int = C.CLOSE_SIZE_PX) -> np.ndarray:
    """A contact sheet of meshes (``drawing.render.PersonMesh``) seen from the four
    :func:`close_up_cameras` around ``point`` (3,) world metres, the point marked. Opens its
    own :class:`drawing.render.Renderer` (one renderer at a time per process). Returns
    (size, size, 3) uint8 RGB."""
    from drawing.render import Renderer

    point = np.asarray(point, float)
    cams = close_up_cameras(point, dist, size)
    with Renderer(cams) as r:
        imgs = r.render(people)
    return contact_sheet(imgs, cams, title, point[None], scale=0.5)
