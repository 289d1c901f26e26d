"""Per-frame logs of a sequence in one MCAP file, viewable in Foxglove Studio.

- JSON streams written with ``mcap`` (message encoding ``json``, schema encoding
  ``jsonschema``): ``/markers``, ``/keypoints/<camera>``, ``/fit/<person>``, ``/metrics``, or any
  topic registered with :meth:`SequenceLog.add_json_channel`. NaN is not JSON: gaps are
  ``null``.
- A 3D scene channel ``/scene`` in Foxglove's well-known ``foxglove.SceneUpdate`` schema
  (protobuf; schema and serialization from ``foxglove-sdk``): points as spheres, bones as line
  lists, camera frustums (given as world points: this module knows no camera model), all in
  frame ``world`` (metres, z-up).

Time: frame ``j`` is logged at ``start_ns + round(j / fps * 1e9)`` nanoseconds.
Read back with :func:`read_log` (JSON decoded with ``json``, protobuf with
``mcap-protobuf-support``).
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from mcap.decoder import DecoderFactory as _McapDecoderFactory

from formats.errors import InputError

WORLD_FRAME = "world"

_NUM = {"type": "number"}
_XYZ_OR_NULL = {"oneOf": [{"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3},
                          {"type": "null"}]}
MARKERS_SCHEMA = {
    "title": "mocap.Markers", "type": "object",
    "properties": {"frame": {"type": "integer"}, "names": {"type": "array", "items": {"type": "string"}},
                   "xyz": {"type": "array", "items": _XYZ_OR_NULL,
                           "description": "world metres, null = gap"}},
    "required": ["frame", "names", "xyz"],
}
KEYPOINTS_SCHEMA = {
    "title": "mocap.Keypoints2D", "type": "object",
    "properties": {"frame": {"type": "integer"}, "camera": {"type": "string"},
                   "people": {"type": "array", "items": {
                       "type": "object",
                       "properties": {"person": {"type": "integer"},
                                      "kp": {"type": "array", "items": {
                                          "type": "array", "items": _NUM, "minItems": 3,
                                          "maxItems": 3},
                                          "description": "KP65 x, y pixels, confidence"}},
                       "required": ["person", "kp"]}}},
    "required": ["frame", "camera", "people"],
}
PARAMS_SCHEMA = {
    "title": "mocap.FitParams", "type": "object",
    "properties": {"frame": {"type": "integer"}, "person": {"type": "integer"},
                   "params": {"type": "object", "additionalProperties": {
                       "type": "array", "items": {"type": ["number", "null"]}},
                       "description": "flattened parameter arrays by name"}},
    "required": ["frame", "person", "params"],
}
METRICS_SCHEMA = {
    "title": "mocap.Metrics", "type": "object",
    "properties": {"frame": {"type": "integer"},
                   "values": {"type": "object", "additionalProperties": {"type": ["number", "null"]}}},
    "required": ["frame", "values"],
}


def _nulls(a: np.ndarray) -> list:
    """(N, D) array -> list of rows, a row with any NaN -> None."""
    a = np.asarray(a, dtype=np.float64)
    return [None if not np.all(np.isfinite(r)) else r.tolist() for r in a]


def _finite_or_none(a) -> list:
    a = np.asarray(a, dtype=np.float64).ravel()
    return [float(v) if np.isfinite(v) else None for v in a]


class SequenceLog:
    """Writer of one sequence's MCAP log. Use as a context manager::

        with SequenceLog(path, fps=50) as log:
            log.log_markers(j, names, xyz)
            log.log_scene(j, points={"markers": xyz}, bones={"skeleton": (joints, edges)})

    fps: video frame rate (frame -> time); start_ns: time of frame 0; validate: check every
    JSON message against its channel's jsonschema while writing (slower).
    """

    def __init__(self, path: str | Path, fps: float, start_ns: int = 0, validate: bool = False):
        from mcap.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps = float(fps)
        self.start_ns = int(start_ns)
        self.validate = validate
        self._fh = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self._w = Writer(self._fh)
        self._w.start(profile="", library="chi3d-gt formats.mcap_log")
        self._channels: dict[str, tuple[int, dict | None]] = {}
        self._seq: dict[str, int] = {}
        self._scene_schema = None

    # ------------------------------------------------------------------------------ plumbing
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._fh.closed:
            return
        self._w.finish()
        self._fh.close()

    def time_ns(self, frame: int) -> int:
        return self.start_ns + int(round(frame / self.fps * 1e9))

    def add_json_channel(self, topic: str, schema: Mapping) -> None:
        """Register a JSON topic with its jsonschema (idempotent for the same topic)."""
        if topic in self._channels:
            return
        sid = self._w.register_schema(name=str(schema.get("title", topic)), encoding="jsonschema",
                                      data=json.dumps(schema).encode())
        cid = self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        self._channels[topic] = (cid, dict(schema))

    def _write(self, topic: str, frame: int, data: bytes) -> None:
        cid = self._channels[topic][0]
        t = self.time_ns(frame)
        seq = self._seq.get(topic, 0)
        self._w.add_message(cid, log_time=t, data=data, publish_time=t, sequence=seq)
        self._seq[topic] = seq + 1

    def log_json(self, topic: str, frame: int, payload: Mapping) -> None:
        """Log ``payload`` (JSON-serialisable, no NaN) on a registered topic at ``frame``."""
        if topic not in self._channels:
            raise KeyError(f"log_json: topic {topic!r} not registered (add_json_channel)")
        if self.validate:
            import jsonschema

            jsonschema.validate(payload, self._channels[topic][1])
        self._write(topic, frame, json.dumps(payload, allow_nan=False).encode())

    # --------------------------------------------------------------------------- streams
    def log_markers(self, frame: int, names: Sequence[str], xyz: np.ndarray, topic: str = "/markers"):
        """names: (M,); xyz: (M, 3) world metres, NaN = gap."""
        self.add_json_channel(topic, MARKERS_SCHEMA)
        self.log_json(topic, frame, {"frame": int(frame), "names": list(names), "xyz": _nulls(xyz)})

    def log_keypoints(self, frame: int, camera: str, kp: np.ndarray):
        """kp: (P, 65, 3) people of one view (x, y pixels, confidence) -> ``/keypoints/<camera>``."""
        topic = f"/keypoints/{camera}"
        self.add_json_channel(topic, KEYPOINTS_SCHEMA)
        kp = np.nan_to_num(np.asarray(kp, dtype=np.float64), nan=0.0)
        people = [{"person": i, "kp": p.tolist()} for i, p in enumerate(kp)]
        self.log_json(topic, frame, {"frame": int(frame), "camera": camera, "people": people})

    def log_params(self, frame: int, person: int, params: Mapping[str, np.ndarray]):
        """Fitted parameters of one person (arrays flattened) -> ``/fit/<person>``."""
        topic = f"/fit/{person}"
        self.add_json_channel(topic, PARAMS_SCHEMA)
        self.log_json(topic, frame, {"frame": int(frame), "person": int(person),
                                     "params": {k: _finite_or_none(v) for k, v in params.items()}})

    def log_metrics(self, frame: int, values: Mapping[str, float]):
        """Per-frame scalars (NaN -> null) -> ``/metrics``."""
        self.add_json_channel("/metrics", METRICS_SCHEMA)
        self.log_json("/metrics", frame, {"frame": int(frame), "values": {
            k: _finite_or_none(v)[0] for k, v in values.items()}})

    # ------------------------------------------------------------------------------ scene
    def log_scene(self, frame: int, points: Mapping[str, np.ndarray] | None = None,
                  bones: Mapping[str, tuple[np.ndarray, Sequence[tuple[int, int]]]] | None = None,
                  frustums: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
                  colors: Mapping[str, tuple] | None = None,
                  radius: float = 0.012, topic: str = "/scene") -> None:
        """One ``foxglove.SceneUpdate`` for ``frame``.

        points: {entity: (N, 3) world metres} drawn as spheres (NaN rows skipped);
        bones: {entity: ((J, 3) joints, [(a, b), ...] edges)} drawn as a line list (edges with
        a NaN end skipped); frustums: {camera name: (centre (3,), corners (4, 3))} world points
        (the camera centre and where the rays through the 4 image corners reach a chosen depth,
        e.g. from ``calib.camera.rays_from_pixels``) drawn as viewing pyramids (entity
        ``camera/<name>``, :func:`frustum_lines`); colors: {entity: (r, g, b, a)} in [0, 1].
        """
        from foxglove import messages as fm

        if topic not in self._channels:
            s = fm.SceneUpdate.get_schema()
            sid = self._w.register_schema(name=s.name, encoding=s.encoding, data=bytes(s.data))
            cid = self._w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
            self._channels[topic] = (cid, None)
        t = self.time_ns(frame)
        stamp = fm.Timestamp(sec=t // 1_000_000_000, nsec=t % 1_000_000_000)
        colors = dict(colors or {})
        palette = [(0.9, 0.2, 0.2, 1), (0.2, 0.5, 0.9, 1), (0.2, 0.8, 0.3, 1), (0.9, 0.7, 0.1, 1)]
        ident = fm.Quaternion(x=0, y=0, z=0, w=1)

        def color(name, i):
            r, g, b, a = colors.get(name, palette[i % len(palette)])
            return fm.Color(r=r, g=g, b=b, a=a)

        def p3(v):
            return fm.Point3(x=float(v[0]), y=float(v[1]), z=float(v[2]))

        entities = []
        for i, (name, xyz) in enumerate((points or {}).items()):
            c = color(name, i)
            size = fm.Vector3(x=2 * radius, y=2 * radius, z=2 * radius)
            spheres = [fm.SpherePrimitive(pose=fm.Pose(position=fm.Vector3(
                x=float(v[0]), y=float(v[1]), z=float(v[2])), orientation=ident), size=size, color=c)
                for v in np.asarray(xyz, dtype=np.float64) if np.all(np.isfinite(v))]
            entities.append(fm.SceneEntity(timestamp=stamp, frame_id=WORLD_FRAME, id=name,
                                           spheres=spheres))
        for i, (name, (joints, edges)) in enumerate((bones or {}).items()):
            J = np.asarray(joints, dtype=np.float64)
            pts = [p3(J[e]) for a, b in edges if np.all(np.isfinite(J[[a, b]])) for e in (a, b)]
            line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineList, pose=fm.Pose(
                position=fm.Vector3(x=0, y=0, z=0), orientation=ident), thickness=0.01,
                scale_invariant=False, points=pts, color=color(name, i + 1))
            entities.append(fm.SceneEntity(timestamp=stamp, frame_id=WORLD_FRAME, id=name,
                                           lines=[line]))
        for name, (centre, corners) in (frustums or {}).items():
            entities.append(fm.SceneEntity(timestamp=stamp, frame_id=WORLD_FRAME,
                                           id=f"camera/{name}", lines=[fm.LinePrimitive(
                                               type=fm.LinePrimitiveLineType.LineList,
                                               pose=fm.Pose(position=fm.Vector3(x=0, y=0, z=0),
                                                            orientation=ident),
                                               thickness=0.01, scale_invariant=False,
                                               points=[p3(v) for v in frustum_lines(centre, corners, name)],
                                               color=fm.Color(r=0.8, g=0.8, b=0.8, a=1))]))
        self._write(topic, frame, fm.SceneUpdate(entities=entities).encode())


def frustum_lines(centre, corners, name: str = "frustum") -> np.ndarray:
    """(16, 3) world points, pairs forming the 8 edges of a viewing pyramid: the centre (3,) to
    each of the 4 corners (4, 3), and the corners' rectangle (corner i to corner i + 1).
    Raises ValueError naming ``name`` on wrong shapes or non-finite points."""
    c = np.asarray(centre, dtype=np.float64)
    q = np.asarray(corners, dtype=np.float64)
    if c.shape != (3,) or q.shape != (4, 3):
        raise ValueError(f"frustum {name!r}: expected centre (3,) and corners (4, 3), "
                         f"got {c.shape} and {q.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(q))):
        raise ValueError(f"frustum {name!r}: non-finite centre or corners")
    seg = []
    for i in range(4):
        seg += [c, q[i], q[i], q[(i + 1) % 4]]
    return np.asarray(seg)


class _JsonDecoderFactory(_McapDecoderFactory):
    def decoder_for(self, message_encoding, schema):  # noqa: ARG002 (mcap interface)
        return json.loads if message_encoding == "json" else None


def read_log(path: str | Path, topics: Sequence[str] | None = None) -> dict[str, list[tuple[int, object]]]:
    """Read an MCAP log back: ``{topic: [(log_time_ns, message), ...]}`` in file order; JSON
    messages as dicts, ``foxglove.SceneUpdate`` as decoded protobuf messages."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "missing")
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[_JsonDecoderFactory(), DecoderFactory()])
        try:
            for _schema, channel, msg, decoded in reader.iter_decoded_messages(topics=topics):
                out.setdefault(channel.topic, []).append((msg.log_time, decoded))
        except (McapError, EOFError, ValueError, json.JSONDecodeError) as e:
            raise InputError(path, "<mcap>", f"corrupt or truncated: {e}") from None
    return out
