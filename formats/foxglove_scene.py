"""A sequence's 3D scene as one MCAP file in Foxglove's well-known schemas, to scrub in Foxglove.

Everything is in frame ``world`` (metres, z-up) unless named otherwise. Frame ``j`` of
``frames`` (video frame indices) is logged at ``start_ns + round((frames[j] - frames[0]) / fps
* 1e9)`` nanoseconds (log time = publish time = the messages' own ``timestamp``). Topics:

- ``/bodies`` (``foxglove.SceneUpdate``, protobuf, F messages): one entity per person (id =
  :class:`MeshTrack` ``name``, e.g. ``wearer`` / ``partner``), a ``TriangleListPrimitive`` with
  ``points`` = the frame's vertices, ``indices`` = the faces flattened, one colour. A frame in
  which a person's vertices are not all finite (no fit) carries a deletion of that entity
  instead. Vertices are rounded to multiples of :data:`VERTEX_QUANTUM_M` (2^-14 m, 0.06 mm) so
  the chunk compressor (zstd) squeezes the doubles.
- ``/markers`` (``foxglove.SceneUpdate``, F messages, only with ``markers``): entity
  ``markers``, one sphere per marker (gaps skipped); with ``marker_names`` also entity
  ``marker_labels``, one text per visible marker.
- ``/keypoints3d`` (``foxglove.SceneUpdate``, F messages, only with ``points3d``): one entity per
  name (e.g. triangulated keypoints of each person), one sphere per finite point.
- ``/tf`` (``foxglove.FrameTransforms``, F messages): ``world`` -> ``camera/<name>`` for every
  camera at every frame (the cameras are static; repeating them lets Foxglove seek anywhere).
  ``translation`` = the camera centre, ``rotation`` = R^T (world_from_cam) as a quaternion, so a
  point ``X_cam`` of the camera frame is ``R^T X_cam + centre`` in the world (OpenCV camera axes:
  x right, y down, z forward, as Foxglove's image frames).
- ``/camera/<name>/image`` (``foxglove.CompressedImage``, ``jpeg``, frame_id ``camera/<name>``):
  the video frame ``images[name](frames[j])`` resized by ``image_scale``; one message per frame
  for which the callable returns an image (None = no image: no message).
- ``/camera/<name>/calibration`` (``foxglove.CameraCalibration``, F messages, frame_id
  ``camera/<name>``): K, D (OpenCV plumb-bob order k1 k2 p1 p2 k3, as given; 4 given -> k3 = 0), R = I,
  P = [K | 0], width/height of the scaled image (K scaled to it, pixel centres kept:
  ``c' = (c + 0.5) s - 0.5``), ``distortion_model`` ``plumb_bob`` (``rational_polynomial`` for 8
  coefficients).
- ``/metrics`` (JSON, jsonschema ``mocap.SceneMetrics``, F messages, only with ``metrics``):
  ``{"frame": <video frame>, <name>: number | null, ...}`` flat, so that Foxglove's Plot panel
  plots ``/metrics.<name>``; NaN is ``null``.
- ``/flags`` (JSON, jsonschema ``mocap.SceneFlags``, F messages, only with ``flags``):
  ``{"frame": <video frame>, "flagged": 0 | 1}`` (a number, plottable as ``/flags.flagged``).

This module knows no camera model and no body model: meshes, cameras, points come in as arrays.
Read back with :func:`formats.mcap_log.read_log`.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formats.errors import InputError
from formats.mcap_log import WORLD_FRAME

VERTEX_QUANTUM_M = 2.0**-14
CAMERA_FRAME_PREFIX = "camera/"
_PALETTE = [(0.9, 0.3, 0.2, 1.0), (0.2, 0.5, 0.9, 1.0), (0.2, 0.8, 0.3, 1.0),
            (0.9, 0.7, 0.1, 1.0), (0.7, 0.3, 0.9, 1.0), (0.1, 0.8, 0.8, 1.0)]
_MARKER_RGBA = (1.0, 1.0, 1.0, 1.0)
_MARKER_DIAMETER_M = 0.02
_KEYPOINT_DIAMETER_M = 0.03


@dataclass(frozen=True)
class MeshTrack:
    """One person's mesh over the sequence: vertices (F, V, 3) world metres (a frame with any
    non-finite vertex = no mesh), faces (T, 3) into them, rgba in [0, 1]."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class CameraView:
    """One camera: R (3, 3) cam_from_world, centre (3,) world metres (CHI3D's T), K (3, 3) of
    the full-size image, dist (k,) OpenCV plumb-bob coefficients, width/height pixels."""

    name: str
    R: np.ndarray
    centre: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int


def camera_frame_id(name: str) -> str:
    return CAMERA_FRAME_PREFIX + name


def quaternion_from_matrix(M: np.ndarray) -> np.ndarray:
    """(x, y, z, w) unit quaternion of a rotation matrix (Shepperd's method, w >= 0)."""
    m = np.asarray(M, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def scaled_intrinsics(K: np.ndarray, width: int, height: int, scale: float) -> tuple[np.ndarray, int, int]:
    """K of the image resized by ``scale`` (size rounded, at least 1 px; pixel centres at
    integer coordinates kept: ``c' = (c + 0.5) s - 0.5`` with the exact per-axis ratio s)."""
    w2, h2 = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
    sx, sy = w2 / width, h2 / height
    K = np.asarray(K, dtype=np.float64)
    K2 = np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5],
                   [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5],
                   [0.0, 0.0, 1.0]])
    return K2, w2, h2


# ---------------------------------------------------------------------------------- checks
def _check_inputs(path, fps, frames, meshes, cameras, markers, marker_names, points3d, images,
                  metrics, flags, image_scale, jpeg_quality):
    def bad(field, msg, frame=None):
        raise InputError(path, field, msg, frame=frame)

    if not (np.isfinite(fps) and fps > 0):
        bad("fps", f"expected a positive frame rate, got {fps}")
    fr = np.asarray(frames)
    if fr.ndim != 1 or len(fr) == 0:
        bad("frames", f"expected a non-empty (F,) array, got shape {fr.shape}")
    if not np.all(np.isfinite(fr)):
        bad("frames", "non-finite frame index", frame=int(np.flatnonzero(~np.isfinite(fr))[0]))
    if len(fr) > 1 and np.any(np.diff(fr) <= 0):
        j = int(np.flatnonzero(np.diff(fr) <= 0)[0]) + 1
        bad("frames", f"not strictly increasing ({fr[j - 1]} then {fr[j]})", frame=j)
    F = len(fr)
    if not (np.isfinite(image_scale) and image_scale > 0):
        bad("image_scale", f"expected > 0, got {image_scale}")
    if not 1 <= int(jpeg_quality) <= 100:
        bad("jpeg_quality", f"expected 1..100, got {jpeg_quality}")

    def per_frame(a, field, tail):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 1 + len(tail) or a.shape[0] != F or any(
                t is not None and a.shape[1 + i] != t for i, t in enumerate(tail)):
            want = ", ".join(["F"] + [str(t) if t is not None else "N" for t in tail])
            bad(field, f"expected shape ({want}) with F = {F} frames, got {a.shape}")
        return a

    names = [m.name for m in meshes]
    if len(set(names)) != len(names):
        bad("meshes.name", f"duplicate mesh names {names}")
    for m in meshes:
        v = per_frame(m.vertices, f"meshes[{m.name}].vertices", (None, 3))
        f = np.asarray(m.faces)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            bad(f"meshes[{m.name}].faces", f"expected a non-empty integer (T, 3) array, got "
                f"{f.shape} {f.dtype}")
        if f.min() < 0 or f.max() >= v.shape[1]:
            bad(f"meshes[{m.name}].faces", f"index out of range [0, {v.shape[1]})")
        if len(m.rgba) != 4 or not all(0.0 <= float(c) <= 1.0 for c in m.rgba):
            bad(f"meshes[{m.name}].rgba", f"expected 4 values in [0, 1], got {m.rgba}")
        if np.any(np.isinf(v)):
            bad(f"meshes[{m.name}].vertices", "infinite vertex (NaN marks a frame without mesh)",
                frame=int(np.flatnonzero(np.isinf(v).any(axis=(1, 2)))[0]))
    cnames = [c.name for c in cameras]
    if len(set(cnames)) != len(cnames):
        bad("cameras.name", f"duplicate camera names {cnames}")
    for c in cameras:
        R = np.asarray(c.R, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.allclose(
                R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            bad(f"cameras[{c.name}].R", "expected a (3, 3) rotation (R R^T = I, det +1)")
        t = np.asarray(c.centre, dtype=np.float64)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            bad(f"cameras[{c.name}].centre", f"expected a finite (3,) point, got {t.shape}")
        K = np.asarray(c.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            bad(f"cameras[{c.name}].K", "expected a finite (3, 3) matrix with fx, fy > 0")
        d = np.asarray(c.dist, dtype=np.float64)
        if d.ndim != 1 or not np.all(np.isfinite(d)) or len(d) not in (4, 5, 8):
            bad(f"cameras[{c.name}].dist", f"expected 4, 5 or 8 finite OpenCV coefficients, got {d.shape}")
        if int(c.width) <= 0 or int(c.height) <= 0:
            bad(f"cameras[{c.name}].width/height", f"expected positive, got {c.width} x {c.height}")
    if markers is not None:
        mk = per_frame(markers, "markers", (None, 3))
        if marker_names is not None and len(marker_names) != mk.shape[1]:
            bad("marker_names", f"{len(marker_names)} names for {mk.shape[1]} markers")
    elif marker_names is not None:
        bad("marker_names", "given without markers")
    for name, p in (points3d or {}).items():
        per_frame(p, f"points3d[{name}]", (None, 3))
    for name in images or {}:
        if name not in cnames:
            bad(f"images[{name}]", f"no camera named {name!r} (cameras: {cnames})")
    for name, v in (metrics or {}).items():
        if name == "frame":
            bad("metrics", "'frame' is reserved (the video frame index field)")
        per_frame(v, f"metrics[{name}]", ())
    if flags is not None:
        fl = np.asarray(flags)
        if fl.shape != (F,):
            bad("flags", f"expected shape ({F},), got {fl.shape}")


# ---------------------------------------------------------------------------------- writer
class _Writer:
    def __init__(self, fh):
        from mcap.writer import Writer

        self.w = Writer(fh, chunk_size=4 * 1024 * 1024)
        self.w.start(profile="", library="chi3d-gt formats.foxglove_scene")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def proto_channel(self, topic: str, cls) -> None:
        if topic in self.channels:
            return
        s = cls.get_schema()
        if s.name not in self.schemas:
            self.schemas[s.name] = self.w.register_schema(name=s.name, encoding=s.encoding,
                                                          data=bytes(s.data))
        self.channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf",
                                                       schema_id=self.schemas[s.name])
        self.counts[topic] = 0

    def json_channel(self, topic: str, schema: dict) -> None:
        sid = self.w.register_schema(name=schema["title"], encoding="jsonschema",
                                     data=json.dumps(schema).encode())
        self.channels[topic] = self.w.register_channel(topic=topic, message_encoding="json",
                                                       schema_id=sid)
        self.counts[topic] = 0

    def write(self, topic: str, t: int, data: bytes) -> None:
        self.w.add_message(self.channels[topic], log_time=t, publish_time=t, data=data,
                           sequence=self.counts[topic])
        self.counts[topic] += 1

    def finish(self):
        self.w.finish()


def _time_ns(frames: np.ndarray, fps: float, start_ns: int) -> list[int]:
    fr = np.asarray(frames, dtype=np.float64)
    return [int(start_ns) + int(round((f - fr[0]) / fps * 1e9)) for f in fr]


def _metrics_schema(names) -> dict:
    return {"title": "mocap.SceneMetrics", "type": "object",
            "properties": {"frame": {"type": "integer"},
                           **{n: {"type": ["number", "null"]} for n in names}},
            "required": ["frame", *names]}


FLAGS_SCHEMA = {"title": "mocap.SceneFlags", "type": "object",
                "properties": {"frame": {"type": "integer"},
                               "flagged": {"type": "integer", "enum": [0, 1]}},
                "required": ["frame", "flagged"]}


def write_scene(path: Path, fps: float, frames: np.ndarray, meshes: list[MeshTrack],
                cameras: list[CameraView], markers: np.ndarray | None = None,
                marker_names: list[str] | None = None,
                points3d: dict[str, np.ndarray] | None = None,
                images: dict[str, Callable[[int], np.ndarray | None]] | None = None,
                metrics: dict[str, np.ndarray] | None = None,
                flags: np.ndarray | None = None,
                image_scale: float = 0.5, jpeg_quality: int = 80, start_ns: int = 0) -> dict:
    """Write the scene of one sequence to ``path`` (topics in the module docstring).

    frames: (F,) video frame indices (strictly increasing); meshes: per person (F, V, 3)
    vertices + faces (pass decimated meshes, :func:`decimate_for_scene`, to keep the file
    small); cameras: their transforms and calibrations; markers: (F, M, 3) NaN = gap, with
    optional marker_names (M,); points3d: {name: (F, K, 3)} NaN = none; images: {camera name:
    callable(video frame index) -> (H, W, 3) uint8 RGB of the camera's full size (or already
    resized to ``image_scale``: ``scaled_intrinsics``' size, ``cv2.INTER_AREA``), or None};
    metrics: {name: (F,)} NaN = null; flags: (F,) bool.

    Returns ``{"topics": {topic: message count}, "bytes": file size, "frames": F}``.
    Raises :class:`~formats.errors.InputError` naming ``path``, the field and the frame.
    """
    import cv2
    from foxglove import messages as fm

    path = Path(path)
    _check_inputs(path, fps, frames, meshes, cameras, markers, marker_names, points3d, images,
                  metrics, flags, image_scale, jpeg_quality)
    frames = np.asarray(frames)
    F = len(frames)
    times = _time_ns(frames, float(fps), start_ns)
    ident = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    origin = fm.Pose(position=fm.Vector3(x=0.0, y=0.0, z=0.0), orientation=ident)

    def stamp(t):
        return fm.Timestamp(sec=t // 1_000_000_000, nsec=t % 1_000_000_000)

    def color(rgba):
        r, g, b, a = (float(c) for c in rgba)
        return fm.Color(r=r, g=g, b=b, a=a)

    def spheres(xyz, diameter, rgba):
        size = fm.Vector3(x=diameter, y=diameter, z=diameter)
        c = color(rgba)
        return [fm.SpherePrimitive(pose=fm.Pose(position=fm.Vector3(
            x=float(p[0]), y=float(p[1]), z=float(p[2])), orientation=ident), size=size, color=c)
            for p in xyz if np.all(np.isfinite(p))]

    mesh_data = []
    for m in meshes:
        v = np.asarray(m.vertices, dtype=np.float64)
        vq = np.round(v / VERTEX_QUANTUM_M) * VERTEX_QUANTUM_M
        mesh_data.append((m.name, vq, np.asarray(m.faces, dtype=np.int64).ravel().tolist(),
                          color(m.rgba)))
    cams = []
    for c in cameras:
        R = np.asarray(c.R, dtype=np.float64)
        q = quaternion_from_matrix(R.T)
        K2, w2, h2 = scaled_intrinsics(c.K, int(c.width), int(c.height), image_scale)
        d = [float(x) for x in np.asarray(c.dist, dtype=np.float64)]
        d += [0.0] * (len(d) == 4)  # k1 k2 p1 p2 -> plumb_bob's five (k3 = 0)
        P = np.hstack([K2, np.zeros((3, 1))])
        cams.append((c, q, np.asarray(c.centre, dtype=np.float64), K2, w2, h2, d, P))
    markers_a = None if markers is None else np.asarray(markers, dtype=np.float64)
    pts3d = {k: np.asarray(v, dtype=np.float64) for k, v in (points3d or {}).items()}
    metric_a = {k: np.asarray(v, dtype=np.float64) for k, v in (metrics or {}).items()}

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        w = _Writer(fh)
        if meshes:
            w.proto_channel("/bodies", fm.SceneUpdate)
        if markers_a is not None:
            w.proto_channel("/markers", fm.SceneUpdate)
        if pts3d:
            w.proto_channel("/keypoints3d", fm.SceneUpdate)
        if cameras:
            w.proto_channel("/tf", fm.FrameTransforms)
        for c in cameras:
            w.proto_channel(f"/camera/{c.name}/calibration", fm.CameraCalibration)
            if images and c.name in images:
                w.proto_channel(f"/camera/{c.name}/image", fm.CompressedImage)
        if metric_a:
            w.json_channel("/metrics", _metrics_schema(list(metric_a)))
        if flags is not None:
            w.json_channel("/flags", FLAGS_SCHEMA)

        for j in range(F):
            t = times[j]
            ts = stamp(t)
            # bodies
            if meshes:
                ents, dels = [], []
                for name, vq, idx, col in mesh_data:
                    vj = vq[j]
                    if not np.all(np.isfinite(vj)):
                        dels.append(fm.SceneEntityDeletion(
                            timestamp=ts, type=fm.SceneEntityDeletionType.MatchingId, id=name))
                        continue
                    pts = [fm.Point3(x=x, y=y, z=z) for x, y, z in vj.tolist()]
                    ents.append(fm.SceneEntity(
                        timestamp=ts, frame_id=WORLD_FRAME, id=name, frame_locked=False,
                        triangles=[fm.TriangleListPrimitive(pose=origin, points=pts, color=col,
                                                            indices=idx)]))
                w.write("/bodies", t, fm.SceneUpdate(deletions=dels, entities=ents).encode())
            # markers
            if markers_a is not None:
                mk = markers_a[j]
                ents = [fm.SceneEntity(timestamp=ts, frame_id=WORLD_FRAME, id="markers",
                                       spheres=spheres(mk, _MARKER_DIAMETER_M, _MARKER_RGBA))]
                if marker_names is not None:
                    ents.append(fm.SceneEntity(
                        timestamp=ts, frame_id=WORLD_FRAME, id="marker_labels",
                        texts=[fm.TextPrimitive(
                            pose=fm.Pose(position=fm.Vector3(x=float(p[0]), y=float(p[1]),
                                                             z=float(p[2]) + 0.02),
                                         orientation=ident),
                            billboard=True, font_size=12.0, scale_invariant=True,
                            color=color(_MARKER_RGBA), text=str(n))
                            for n, p in zip(marker_names, mk, strict=True)
                            if np.all(np.isfinite(p))]))
                w.write("/markers", t, fm.SceneUpdate(entities=ents).encode())
            # triangulated keypoints
            if pts3d:
                ents = [fm.SceneEntity(timestamp=ts, frame_id=WORLD_FRAME, id=name,
                                       spheres=spheres(p[j], _KEYPOINT_DIAMETER_M,
                                                       _PALETTE[(i + 2) % len(_PALETTE)]))
                        for i, (name, p) in enumerate(pts3d.items())]
                w.write("/keypoints3d", t, fm.SceneUpdate(entities=ents).encode())
            # cameras
            if cameras:
                tfs = [fm.FrameTransform(
                    timestamp=ts, parent_frame_id=WORLD_FRAME, child_frame_id=camera_frame_id(c.name),
                    translation=fm.Vector3(x=float(C[0]), y=float(C[1]), z=float(C[2])),
                    rotation=fm.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
                    for c, q, C, *_ in cams]
                w.write("/tf", t, fm.FrameTransforms(transforms=tfs).encode())
            for c, _q, _C, K2, w2, h2, d, P in cams:
                fid = camera_frame_id(c.name)
                cal = fm.CameraCalibration(
                    timestamp=ts, frame_id=fid, width=w2, height=h2,
                    distortion_model="rational_polynomial" if len(d) == 8 else "plumb_bob",
                    D=d, K=K2.ravel().tolist(), R=np.eye(3).ravel().tolist(), P=P.ravel().tolist())
                w.write(f"/camera/{c.name}/calibration", t, cal.encode())
                if not images or c.name not in images:
                    continue
                img = images[c.name](int(frames[j]))
                if img is None:
                    continue
                img = np.asarray(img)
                if img.shape not in ((int(c.height), int(c.width), 3), (h2, w2, 3)) \
                        or img.dtype != np.uint8:
                    raise InputError(path, f"images[{c.name}]", f"expected ({c.height}, {c.width}, 3) "
                                     f"uint8 RGB (or ({h2}, {w2}, 3): already at image_scale), got "
                                     f"{img.shape} {img.dtype}", frame=int(frames[j]))
                small = img if (w2, h2) == (img.shape[1], img.shape[0]) else cv2.resize(
                    img, (w2, h2), interpolation=cv2.INTER_AREA)
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR),
                                       [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
                if not ok:
                    raise InputError(path, f"images[{c.name}]", "JPEG encoding failed",
                                     frame=int(frames[j]))
                w.write(f"/camera/{c.name}/image", t, fm.CompressedImage(
                    timestamp=ts, frame_id=fid, data=buf.tobytes(), format="jpeg").encode())
            # plots
            if metric_a:
                row = {"frame": int(frames[j])}
                for k, v in metric_a.items():
                    row[k] = float(v[j]) if np.isfinite(v[j]) else None
                w.write("/metrics", t, json.dumps(row, allow_nan=False).encode())
            if flags is not None:
                w.write("/flags", t, json.dumps({"frame": int(frames[j]),
                                                 "flagged": int(bool(flags[j]))}).encode())
        w.finish()
    return {"topics": dict(w.counts), "bytes": path.stat().st_size, "frames": F}


# ------------------------------------------------------------------------------ decimation
def decimate_for_scene(vertices_rest: np.ndarray, faces: np.ndarray,
                       target_faces: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """A fixed reduced mesh whose vertices are a subset of the full mesh's, so that posing it is
    indexing (``vertices[:, ids]``).

    Quadric-error edge collapse of the rest mesh (libigl's ``qslim``) to ``target_faces``, each
    new vertex snapped to its nearest full-mesh vertex, faces that became degenerate or
    duplicate dropped. Returns ``ids`` (V',) ascending int64 indices into the full mesh and
    ``faces`` (T', 3) int64 into ``ids``. A mesh already within the budget comes back whole
    (its referenced vertices). Raises InputError on bad shapes.
    """
    import igl
    from scipy.spatial import cKDTree

    V = np.asarray(vertices_rest, dtype=np.float64)
    Fc = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise InputError("<memory>", "vertices_rest", f"expected finite (V, 3), got {V.shape}")
    if Fc.ndim != 2 or Fc.shape[1] != 3 or len(Fc) == 0 or not np.issubdtype(Fc.dtype, np.integer) \
            or Fc.min() < 0 or Fc.max() >= len(V):
        raise InputError("<memory>", "faces", f"expected integer (T, 3) indices into {len(V)} "
                         f"vertices, got {Fc.shape} {Fc.dtype}")
    if int(target_faces) < 4:
        raise InputError("<memory>", "target_faces", f"expected >= 4, got {target_faces}")
    if len(Fc) <= target_faces:
        ids, inv = np.unique(Fc, return_inverse=True)
        return ids.astype(np.int64), inv.reshape(-1, 3).astype(np.int64)
    U, G, _J, _I = igl.qslim(np.asfortranarray(V), np.asfortranarray(Fc.astype(np.int32)),
                             int(target_faces))
    _d, nearest = cKDTree(V).query(np.asarray(U))
    G = nearest[np.asarray(G, dtype=np.int64)]
    keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 0] != G[:, 2])
    G = G[keep]
    _u, first = np.unique(np.sort(G, axis=1), axis=0, return_index=True)
    G = G[np.sort(first)]
    ids, inv = np.unique(G, return_inverse=True)
    return ids.astype(np.int64), inv.reshape(-1, 3).astype(np.int64)
