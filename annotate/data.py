"""What the annotation page shows of one sequence, read from the recipe and the engine's artifacts.

:class:`SequenceData` holds the body model (faces, 75-region map), the cameras (the ``capture``
stage's rig, else the recipe's calibration files), the videos, both people's 2D keypoints (the
partner fit's refined ones, else the ``keypoints`` stage's) and, where the fits exist, both
people's meshes per frame (person 0 = the marker wearer from ``marker_fit``, person 1 = the
partner from ``partner_fit``; on a markerless sequence both from ``partner_fit``). Artifacts are read from ``<outputs>/<session>/<group>/<action>/
<stage>/`` as they are on disk (the page annotates; it runs no stage).

Frames are video frame indices. A frame that a fit does not have shows the fit's nearest frame
(``mesh_frame`` says which); without fits the bodies are in their rest pose.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from formats.errors import InputError

VIEW_SIZE = 450  # px: each view of the 2x2 tile the page shows
KP_RADIUS = 3


class Fits:
    """Both people's fits on their common frames (``frames (F,)``); ``at(i)`` -> (2, V, 3)
    float32 vertices at row ``i``, skinned on demand (a few recent rows kept): a long sequence
    is never held as meshes in memory."""

    CACHE = 16

    def __init__(self, model, fits, frames: np.ndarray):
        from body import rest_state

        self.model, self.frames = model, np.asarray(frames, np.int64)
        self._fits = fits
        self._rows = [np.searchsorted(f.frames, self.frames) for f in fits]
        self._rest = [rest_state(model, np.asarray(f.betas, float)) for f in fits]
        self._cache: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.frames)

    def at(self, i: int) -> np.ndarray:
        from body import forward

        i = int(i)
        with self._lock:
            if i in self._cache:
                return self._cache[i]
        out = np.empty((2, self.model.num_vertices, 3), np.float32)
        for p, fit in enumerate(self._fits):
            r = self._rows[p][i:i + 1]
            out[p] = forward(self.model, None, fit.body_pose[r], fit.global_orient[r],
                             fit.transl[r], rest=self._rest[p]).vertices[0]
        with self._lock:
            if len(self._cache) >= self.CACHE:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = out
        return out


def _artifact(root: Path, stage: str) -> Path | None:
    d = root / stage
    return d if (d / "manifest.json").is_file() else None


class SequenceData:
    """One sequence of a recipe, as the page needs it (see module doc)."""

    def __init__(self, recipe_path: str | Path, seq_id: str, outputs: str | Path = "outputs"):
        from body import load_model
        from body.regions import region_map
        from recipes.schema import load_recipe
        from stages import common

        self.recipe_path = Path(recipe_path)
        self.recipe = load_recipe(self.recipe_path, check_files=False)
        self.seq_id = seq_id
        self.seq = self.recipe.sequence(seq_id)
        self.group, self.action = seq_id.split("/", 1)
        self.people = [str(p) for p in (getattr(self.seq, "persons", None)
                                        or [self.seq.markers_on, self.seq.partner]) if p is not None]
        if len(self.people) != 2:
            raise InputError(self.recipe_path, f"sequences.{seq_id}", f"contact is annotated "
                             f"between two people; the sequence has {len(self.people)} ({self.people})")
        self.model = load_model(self.recipe.body_model.kind, common.body_model_file(self.recipe))
        self.family = "smplx" if self.model.name == "smplx" else "anny"
        self.rmap = region_map(self.model)
        self.outputs = Path(outputs)
        self.root = self.outputs / self.recipe.session / self.group / self.action
        self.cameras = [str(c) for c in self.recipe.cameras] if self.seq.has_video else []
        self.cams = self._cameras()
        self.videos = [Path(self.seq.videos[c]) for c in self.cameras]
        if self.videos:
            self.n_frames = common.video_length(self.videos)[0]
        else:
            self.n_frames = 0
        self.keypoints = self._keypoints()
        self.fits = self._fits()
        if not self.n_frames:
            self.n_frames = int(self.fits.frames.max()) + 1 if self.fits is not None else 1
        self.rest = self._rest()
        self._lock = threading.Lock()  # the video readers are not thread-safe
        self._readers: dict[int, object] = {}

    # ------------------------------------------------------------------ inputs
    def _cameras(self) -> list:
        from artifacts import CameraRig

        if not self.cameras:
            return []
        cap = _artifact(self.root, "capture")
        if cap is not None and CameraRig.exists_in(cap):
            return CameraRig.load(cap).cameras(self.cameras)
        from calib.io import read_camera

        fmt = getattr(self.seq, "calibration_format", None)
        return [read_camera(self.seq.calibration[c], c, fmt) for c in self.cameras]

    def _keypoints(self):
        from artifacts.keypoints import Keypoints2D

        for stage in ("partner_fit", "keypoints"):
            d = _artifact(self.root, stage)
            if d is not None and Keypoints2D.exists_in(d):
                kp = Keypoints2D.load(d)
                if self.cameras and kp.camera_ids != self.cameras:
                    kp_idx = [kp.camera(c) for c in self.cameras]
                    return kp, kp_idx
                return kp, list(range(len(kp.camera_ids)))
        return None

    def _fits(self) -> Fits | None:
        from artifacts import BodyFit

        # person 0 = the marker wearer (marker_fit), person 1 = the partner (partner_fit); a
        # markerless sequence has both in partner_fit (person 0 in its person0/ folder)
        mf, pf = _artifact(self.root, "marker_fit"), _artifact(self.root, "partner_fit")
        if pf is None:
            return None
        sources = [mf, pf] if mf is not None else [pf / "person0", pf]
        if not all(BodyFit.exists_in(d) for d in sources):
            return None
        fits = [BodyFit.load(d) for d in sources]
        frames = np.intersect1d(fits[0].frames, fits[1].frames)
        if not len(frames):
            return None
        return Fits(self.model, fits, frames)

    def _rest(self) -> np.ndarray:
        """(2, V, 3) both subjects at their rest pose (their shape fits' betas, else the
        template), standing side by side."""
        from artifacts import ShapeFit
        from body import forward

        out = []
        for subject in self.people:
            betas = np.zeros(1)
            d = _artifact(self.outputs / self.recipe.session / str(subject), "shape_fit") if subject else None
            if d is not None and ShapeFit.exists_in(d):
                betas = np.asarray(ShapeFit.load(d).betas, float)
            J = self.model.num_joints
            o = forward(self.model, betas, np.zeros((1, J, 3)), np.eye(3)[None], np.zeros((1, 3)))
            out.append(o.vertices[0])
        return np.asarray(out, np.float32)

    # ------------------------------------------------------------------ queries
    @property
    def has_fits(self) -> bool:
        return self.fits is not None

    def mesh_frame(self, frame: int) -> int | None:
        """The fitted frame shown at video ``frame`` (the nearest one), None without fits."""
        if self.fits is None:
            return None
        fr = self.fits.frames
        return int(fr[np.argmin(np.abs(fr - int(frame)))])

    def vertices(self, frame: int | None) -> np.ndarray:
        """(2, V, 3) float32: both people at video ``frame`` (None: rest pose)."""
        if frame is None or self.fits is None:
            return self.rest
        row = int(np.argmin(np.abs(self.fits.frames - int(frame))))
        return self.fits.at(row)

    def keypoints_at(self, frame: int) -> np.ndarray | None:
        """(C, 2, 65, 3) keypoints at video ``frame`` in the page's camera order (None: none)."""
        if self.keypoints is None:
            return None
        kp, idx = self.keypoints
        row = np.flatnonzero(kp.frames == int(frame))
        if not len(row):
            return None
        return np.asarray(kp.kp[idx, row[0]])

    def image(self, cam: int, frame: int) -> np.ndarray:
        from formats.video import VideoReader

        c = self.cams[cam]
        with self._lock:
            r = self._readers.get(cam)
            if r is None:
                r = self._readers[cam] = VideoReader(self.videos[cam], size=(c.width, c.height))
            return r[int(frame)]

    def views_jpeg(self, frame: int, quality: int = 85) -> bytes:
        """The four views at ``frame`` tiled 2x2 (each ``VIEW_SIZE`` px wide), both people's
        fitted meshes shaded over them (where fitted) and their 2D keypoints drawn."""
        import cv2

        from calib.camera import project
        from drawing.qa_constants import PERSON_RGB

        frame = int(frame)
        if not 0 <= frame < self.n_frames:
            raise InputError(self.seq_id, "frame", f"outside 0..{self.n_frames - 1}", frame)
        tiles = []
        kps = self.keypoints_at(frame)
        V = self.vertices(frame) if self.fits is not None else None
        F = np.asarray(self.model.faces)
        for ci, cam in enumerate(self.cams):
            img = self.image(ci, frame)
            s = VIEW_SIZE / img.shape[1]
            img = cv2.resize(img, (VIEW_SIZE, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA)
            if V is not None:
                over = img.copy()
                for p in range(2):
                    uv = project(cam, V[p].astype(float)) * s
                    if not np.all(np.isfinite(uv)):
                        continue
                    tri = np.round(uv[F] * 8).astype(np.int32)  # 3 bits of sub-pixel precision
                    mask = np.zeros(img.shape[:2], np.uint8)
                    cv2.fillPoly(mask, list(tri), 1, lineType=cv2.LINE_8, shift=3)
                    over[mask > 0] = PERSON_RGB[p]
                    cnt, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                    cv2.drawContours(img, cnt, -1, PERSON_RGB[p], 1)
                img = cv2.addWeighted(img, 0.6, over, 0.4, 0)
            if kps is not None:
                for p in range(2):
                    for x, y, conf in kps[ci, p]:
                        if conf > 0.2 and np.isfinite(x) and np.isfinite(y):
                            cv2.circle(img, (int(x * s), int(y * s)), KP_RADIUS, PERSON_RGB[p], -1,
                                       lineType=cv2.LINE_AA)
                            cv2.circle(img, (int(x * s), int(y * s)), KP_RADIUS, (0, 0, 0), 1,
                                       lineType=cv2.LINE_AA)
            cv2.putText(img, cam.name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                        cv2.LINE_AA)
            tiles.append(img)
        if not tiles:
            tiles = [np.full((VIEW_SIZE, VIEW_SIZE, 3), 40, np.uint8)]
        h = max(t.shape[0] for t in tiles)
        tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        while len(tiles) % 2:
            tiles.append(np.zeros_like(tiles[0]))
        rows = [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles), 2)]
        grid = np.concatenate(rows, axis=0)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(grid, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("could not encode the views")
        return buf.tobytes()

    def conversion(self):
        """(SurfaceCorrespondence, target BodyModel) of the ``convert`` stage, or None."""
        from artifacts.smplx_fit import ConversionReport, SurfaceCorrespondence
        from body import load_model

        d = _artifact(self.root, "convert")
        if d is None or not SurfaceCorrespondence.exists_in(d) or not (d / "report.json").is_file():
            return None
        corr = SurfaceCorrespondence.load(d)
        target = ConversionReport.load(d).target
        path, kind = Path(target.path), target.kind
        if not path.exists():
            return None
        tm = load_model(kind, path)
        if len(tm.faces) != len(corr.tgt_faces) or len(self.model.faces) != len(corr.src_faces):
            return None
        return corr, tm

    def close(self) -> None:
        with self._lock:
            for r in self._readers.values():
                r.close()
            self._readers.clear()
