"""The people's silhouettes per camera and frame (issue #27, the silhouette term ``L_sil``).

- people mask: background subtraction against the camera's clean plate (the empty room, as
  labs record one): both images reduced to ``scale`` (area averaging takes most of the sensor
  noise), the colour distance above ``threshold``, then morphology (open removes
  speckle of the noise and the codec's blocks, close fills the seams of clothes that resemble
  the room) and components smaller than ``min_area_px`` dropped. The clean plate has the same
  camera look (gain, vignetting, white balance) as the camera's videos, so a plain colour
  distance is enough; the plate is the median of its frames (noise-free). Without a clean
  plate: OpenCV's ``createBackgroundSubtractorMOG2`` trained on the whole sequence, then
  applied to each frame without learning (a person standing still for long is part of its
  background: far worse than a clean plate, but something).
- the wearer's mask: its fitted body (``marker_fit``'s BodyFit posed with ``body.forward``)
  projected (lens distortion included) and rasterised face by face with ``cv2.fillPoly`` at
  the mask's resolution, dilated by ``wearer_dilate_px`` (its fit is a few mm off);
- the partner's mask: people less the wearer.

A view whose people mask covers less than ``min_fraction`` or more than ``max_fraction`` of the
image, or holds less than ``min_wearer_cover`` of the wearer's rendered body, is implausible
(nobody found, or the background subtraction failed: lights changed, the camera moved, MOG2
took people standing still for the room) and is flagged not usable.

Pure functions (frames come in as arrays): :func:`silhouettes`; the stage
``stages/silhouettes.py`` reads the videos and saves the :class:`artifacts.silhouettes
.Silhouettes`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import cv2
import numpy as np

from artifacts.silhouettes import SOURCES, Silhouettes, pack
from calib import project

# constants
SCALE = 0.5  # mask pixels per image pixel
THRESHOLD = 25.0  # RGB distance (0-255 units) after area reduction: the demo's sensor noise
#                   leaves < 4 at the 90th percentile, a person 50-250; the tests' lab render:
#                   IoU 0.94-0.95 with the renderer's people (20 with a 3x3 blur: 0.89-0.90,
#                   the outline half a pixel wider)
OPEN_PX = 1  # morphology radii, mask pixels (a close of 3 rounded the concave corners: IoU -0.01)
CLOSE_PX = 1
MIN_AREA_PX = 40  # connected components smaller than this (mask pixels) are noise
MAX_HOLE_PX = 30  # enclosed background smaller than this (mask pixels) is a hole to fill (a
#                   patch of clothes like the room); larger ones are real (between the legs,
#                   between two people)
WEARER_DILATE_PX = 2  # the wearer's rendered mask grows by this (mask pixels)
MIN_FRACTION = 0.002  # a usable view's people mask covers at least this share of the image ...
MAX_FRACTION = 0.5  # ... and at most this
MOG2_VAR_THRESHOLD = 16.0
MIN_WEARER_COVER = 0.7  # a usable view's people mask holds this share of the wearer's body: the
#                         wearer's fitted body is known, and somebody (MOG2 without a clean plate
#                         on the demo: people standing still fade into the background it learns,
#                         masks of 0-5 % of them) who is missing from the mask makes it useless
FRONT_AREA_PX2 = 0.5  # body_mask: faces of signed image area up to this (mask px^2) face the camera


@dataclass(frozen=True)
class SilhouetteOptions:
    """scale : mask pixels per image pixel; threshold : colour distance (RGB, 0-255) of a
    people pixel from the clean plate; open_px / close_px : morphology radii (mask pixels);
    min_area_px : smallest component kept (mask pixels); max_hole_px : enclosed background
    smaller than this is filled (mask pixels); wearer_dilate_px : the wearer's
    rendered mask grows by this; min_fraction / max_fraction : a view's people mask covering
    less / more of the image is not usable; min_wearer_cover : a view whose people mask holds
    less of the wearer's rendered body is not usable; mog2_var_threshold : MOG2's ``varThreshold``
    (views without a clean plate)."""

    scale: float = SCALE
    threshold: float = THRESHOLD
    open_px: int = OPEN_PX
    close_px: int = CLOSE_PX
    min_area_px: int = MIN_AREA_PX
    max_hole_px: int = MAX_HOLE_PX
    wearer_dilate_px: int = WEARER_DILATE_PX
    min_fraction: float = MIN_FRACTION
    max_fraction: float = MAX_FRACTION
    mog2_var_threshold: float = MOG2_VAR_THRESHOLD
    min_wearer_cover: float = MIN_WEARER_COVER

    def __post_init__(self):
        problems = []
        if not 0 < self.scale <= 1:
            problems.append(f"scale: must be in (0, 1], got {self.scale}")
        if not self.threshold > 0:
            problems.append(f"threshold: must be > 0, got {self.threshold}")
        for name in ("open_px", "close_px", "min_area_px", "max_hole_px", "wearer_dilate_px"):
            if getattr(self, name) < 0:
                problems.append(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.min_fraction < self.max_fraction <= 1:
            problems.append(f"min_fraction, max_fraction: need 0 <= min < max <= 1, got "
                            f"{self.min_fraction}, {self.max_fraction}")
        if not 0 <= self.min_wearer_cover <= 1:
            problems.append(f"min_wearer_cover: must be in [0, 1], got {self.min_wearer_cover}")
        if not self.mog2_var_threshold > 0:
            problems.append(f"mog2_var_threshold: must be > 0, got {self.mog2_var_threshold}")
        if problems:
            raise ValueError("; ".join(problems))


def mask_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """(height, width) of the mask of a ``width`` x ``height`` image."""
    return max(1, int(round(height * scale))), max(1, int(round(width * scale)))


def reduce(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) float32 of an image area-reduced to ``size`` (h, w) (area averaging takes most
    of the sensor noise and the codec's blocks at half resolution)."""
    h, w = size
    return cv2.resize(np.asarray(img), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)


def plate_image(frames: Iterable[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """The clean plate at mask resolution: the median of its reduced frames."""
    imgs = [reduce(f, size) for f in frames]
    if not imgs:
        raise ValueError("a clean plate needs at least one frame")
    return np.median(np.stack(imgs), axis=0).astype(np.float32)


def _disc(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def clean_mask(raw: np.ndarray, opts: SilhouetteOptions) -> np.ndarray:
    """Morphology on a raw foreground mask: open, close, small components dropped, small holes
    (background components not touching the border, smaller than ``max_hole_px``) filled."""
    m = np.asarray(raw, np.uint8)
    if opts.open_px:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disc(opts.open_px))
    if opts.close_px:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disc(opts.close_px))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= opts.min_area_px
    m = keep[lab]
    # holes: small background components that do not reach the image border
    n, lab, stats, _ = cv2.connectedComponentsWithStats((~m).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    hole = stats[:, cv2.CC_STAT_AREA] < opts.max_hole_px
    hole[border] = False
    hole[0] = False  # label 0: the people pixels themselves
    return m | hole[lab]


def people_mask(frame_small: np.ndarray, plate_small: np.ndarray,
                opts: SilhouetteOptions = SilhouetteOptions()) -> np.ndarray:
    """(h, w) bool people mask of a reduced frame (:func:`reduce`) against the reduced clean
    plate (:func:`plate_image`)."""
    d = np.linalg.norm(np.asarray(frame_small, np.float32) - plate_small, axis=-1)
    return clean_mask(d > opts.threshold, opts)


def body_mask(cam, vertices: np.ndarray, faces: np.ndarray, size: tuple[int, int],
              scale: float) -> np.ndarray:
    """(h, w) bool mask of a closed mesh seen by ``cam`` at mask resolution ``size`` (h, w):
    its faces that turn toward the camera (outward winding; for a closed mesh their union is
    the silhouette) projected (with the lens distortion) and filled one by one
    (``cv2.fillConvexPoly``: one ``cv2.fillPoly`` call over all faces fills by parity, so
    overlapping faces, an arm in front of the body, cancel into holes); faces with a corner
    behind the camera are skipped."""
    V = np.asarray(vertices, float)
    Xc = (V - cam.T) @ cam.R.T
    uv = project(cam, V)
    m = np.zeros(size, np.uint8)
    F = np.asarray(faces)
    ok = (Xc[F, 2] > 1e-3).all(1)
    if not ok.any():
        return m.astype(bool)
    px = ((uv + 0.5) * scale - 0.5)[F[ok]]  # (T, 3, 2) mask pixels
    a = ((px[:, 1, 0] - px[:, 0, 0]) * (px[:, 2, 1] - px[:, 0, 1])
         - (px[:, 1, 1] - px[:, 0, 1]) * (px[:, 2, 0] - px[:, 0, 0]))
    lim = 4 * max(size)
    px = np.clip(px[a <= FRONT_AREA_PX2], -lim, lim)
    pts = np.round(px * 16).astype(np.int32)  # 4 bits of sub-pixel precision
    for p in pts:
        cv2.fillConvexPoly(m, p, 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def silhouettes(read: Callable[[int, int], np.ndarray], cams, frames: np.ndarray,
                plates: dict[int, Iterable[np.ndarray]], wearer_vertices=None, faces=None,
                opts: SilhouetteOptions = SilhouetteOptions(),
                progress=None) -> tuple[Silhouettes, dict]:
    """The people's and the partner's masks of every frame and camera.

    read : ``read(c, frame) -> (H, W, 3)`` uint8 image of camera index ``c`` at video frame
    ``frame`` (RGB; only the difference to the plate counts, so BGR works too if the plate is
    read alike); cams : ``calib.Camera`` per view (their image size); frames : (F,) video frames,
    increasing; plates : camera index -> the clean plate's frames (same channel order as
    ``read``); a camera without one uses MOG2 over ``frames``; wearer_vertices : per frame the
    wearer's posed mesh (V, 3) or None (``body.lbs.posed_at``), or None (no wearer: partner =
    people); faces : (T, 3) the mesh's faces; progress : iterable wrapper.

    Returns the :class:`Silhouettes` and a report: per camera the source, the median people
    and partner mask areas (share of the image), the frames not usable and why."""
    frames = np.asarray(frames, np.int64)
    F, C = len(frames), len(cams)
    if wearer_vertices is not None and faces is None:
        raise ValueError("faces: needed with wearer_vertices")
    h, w = mask_size(cams[0].width, cams[0].height, opts.scale)
    for c in cams[1:]:
        if mask_size(c.width, c.height, opts.scale) != (h, w):
            raise ValueError("cameras of different image sizes are not supported")
    plate = {c: plate_image(p, (h, w)) for c, p in plates.items()}
    mog = {c: cv2.createBackgroundSubtractorMOG2(history=max(F, 2), detectShadows=True,
                                                 varThreshold=opts.mog2_var_threshold)
           for c in range(C) if c not in plate}
    for c in mog:  # MOG2 learns the whole sequence first, then judges each frame against it
        for f in frames:  # (learning as it goes took people standing from frame 0 for the room)
            mog[c].apply(reduce(read(c, int(f)), (h, w)).astype(np.uint8))
    B = (h * w + 7) // 8
    people = np.zeros((F, C, B), np.uint8)
    partner = np.zeros((F, C, B), np.uint8)
    frac_p = np.zeros((F, C))
    frac_q = np.zeros((F, C))
    cover = np.full((F, C), np.nan)
    grow = _disc(opts.wearer_dilate_px) if opts.wearer_dilate_px else None
    it = range(F) if progress is None else progress(range(F), total=F, desc="silhouettes")
    for i in it:
        for c, cam in enumerate(cams):
            img = read(c, int(frames[i]))
            if img.shape[:2] != (cam.height, cam.width):
                raise ValueError(f"camera {cam.name}: frame {int(frames[i])} is "
                                 f"{img.shape[1]}x{img.shape[0]}, the camera {cam.width}x{cam.height}")
            small = reduce(img, (h, w))
            if c in plate:
                m = people_mask(small, plate[c], opts)
            else:
                fg = mog[c].apply(small.astype(np.uint8), learningRate=0)
                m = clean_mask(fg == 255, opts)  # 127: MOG2's shadows
            q = m
            V = None if wearer_vertices is None else wearer_vertices[i]
            if V is not None:
                wm = body_mask(cam, V, faces, (h, w), opts.scale).astype(np.uint8)
                if wm.any():  # the wearer is somebody: the people mask must hold it
                    cover[i, c] = float((m & wm.astype(bool)).sum() / wm.sum())
                if grow is not None:
                    wm = cv2.dilate(wm, grow)
                q = m & ~wm.astype(bool)
            people[i, c], partner[i, c] = pack(m), pack(q)
            frac_p[i, c], frac_q[i, c] = m.mean(), q.mean()
    usable = (frac_p >= opts.min_fraction) & (frac_p <= opts.max_fraction)
    usable &= ~(cover < opts.min_wearer_cover)  # NaN (no wearer in the view): not judged
    source = np.array([0 if c in plate else 1 for c in range(C)], np.int8)
    out = Silhouettes(frames=frames, cameras=np.array([c.name for c in cams]),
                      scale=np.float64(opts.scale), size=np.array([h, w], np.int64),
                      people=people, partner=partner, people_fraction=frac_p,
                      partner_fraction=frac_q, wearer_cover=cover, usable=usable,
                      source=source)
    return out, silhouette_report(out, opts)


def silhouette_report(s: Silhouettes, opts: SilhouetteOptions) -> dict:
    """Per camera: source, median / max people and partner mask shares, the median share of
    the wearer's body the people mask holds, the frames whose mask is implausible (empty, most
    of the image, or missing the wearer) and so not usable."""
    cams = {}
    for c, name in enumerate(s.cameras):
        fp, fq = s.people_fraction[:, c], s.partner_fraction[:, c]
        empty = s.frames[fp < opts.min_fraction]
        full = s.frames[fp > opts.max_fraction]
        wc = s.wearer_cover[:, c]
        missed = s.frames[wc < opts.min_wearer_cover]
        cams[str(name)] = {
            "source": SOURCES[int(s.source[c])],
            "people_fraction_median": round(float(np.median(fp)), 5) if len(fp) else None,
            "people_fraction_max": round(float(fp.max()), 5) if len(fp) else None,
            "partner_fraction_median": round(float(np.median(fq)), 5) if len(fq) else None,
            "frames_usable": int(s.usable[:, c].sum()),
            "wearer_cover_median": round(float(np.nanmedian(wc)), 4) if np.isfinite(wc).any() else None,
            "not_usable": {"empty": [int(f) for f in empty], "most_of_image": [int(f) for f in full],
                           "wearer_missing": [int(f) for f in missed]},
        }
    return {"frames": int(len(s.frames)), "mask_size": [int(v) for v in s.size],
            "scale": float(s.scale), "views_usable": int(s.usable.sum()),
            "views": int(s.usable.size), "cameras": cams,
            "thresholds": {"min_fraction": opts.min_fraction, "max_fraction": opts.max_fraction,
                           "min_wearer_cover": opts.min_wearer_cover,
                           "colour_distance": opts.threshold}}


def overlay(images: list[np.ndarray], s: Silhouettes, i: int) -> np.ndarray:
    """The frames (one per camera, RGB) with the masks of frame index ``i`` drawn over them
    (people: blue, the partner: orange; a view not usable: a red frame), tiled two across,
    at mask resolution; RGB uint8."""
    h, w = s.shape
    tiles = []
    for c, img in enumerate(images):
        t = cv2.resize(np.asarray(img), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        ppl, par = s.mask(i, c, "people"), s.mask(i, c, "partner")
        t[ppl & ~par] = 0.45 * t[ppl & ~par] + 0.55 * np.array([40, 90, 255])
        t[par] = 0.45 * t[par] + 0.55 * np.array([255, 150, 0])
        t = t.astype(np.uint8)
        edge = cv2.morphologyEx(ppl.astype(np.uint8), cv2.MORPH_GRADIENT, _disc(1)) > 0
        t[edge] = (255, 255, 255)
        if not s.usable[i, c]:
            cv2.rectangle(t, (0, 0), (w - 1, h - 1), (255, 0, 0), 4)
        cv2.putText(t, f"{s.cameras[c]}  {100 * s.people_fraction[i, c]:.1f}% / "
                    f"{100 * s.partner_fraction[i, c]:.1f}%", (6, 18), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[k:k + 2], axis=1) for k in range(0, len(tiles), 2)]
    return np.concatenate(rows, axis=0)
