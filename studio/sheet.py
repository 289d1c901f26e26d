"""Contact sheet: the four views of one frame in a 2x2 grid, with the annotated contact points
drawn on them (a picture to check a session at a glance)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calib import Camera, project


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
                    cv2.circle(t, (int(round(u)), int(round(v))), 7, (255, 230, 0), 2, cv2.LINE_AA)
        t = cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.putText(t, cam.name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (20, 20, 20), 2, cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) < 4:
        tiles.append(np.zeros_like(tiles[0]))
    sheet = np.concatenate([np.concatenate(tiles[:2], 1), np.concatenate(tiles[2:4], 1)], 0)
    cv2.putText(sheet, title, (8, sheet.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                (20, 20, 20), 2, cv2.LINE_AA)
    return sheet


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG (parents created)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"{path}: could not write PNG")
    return path
