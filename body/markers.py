"""Markers on the body surface: (face, barycentric coordinates, offset along the normal).

A marker moves with the skin: ``p = sum_k bary_k v[face_k] + offset * n(face)``, ``n`` the unit
normal of the posed triangle (outward; the offset is the marker's radius plus the skin-to-marker
distance, MoSh++'s default ``DEFAULT_OFFSET_M`` = 9.5 mm). Topology-based, so one MarkerSet
serves every shape of a model.

- ``MarkerSet(names, faces (M,), bary (M, 3), offsets (M,))``, frozen;
- ``marker_positions(vertices (F, V, 3) or (V, 3), faces (NF, 3), markerset) -> (F, M, 3)``;
- ``plug_in_gait(model)``: the 39-marker Vicon Plug-in Gait full-body set placed on Anny;
  ``cmu41(model)``: the CMU mocap database's 41-marker set (``CMU41_NAMES``);
  ``hand_markers(model)``: 5 fingertip-nail markers per hand (optional extra set);
- JSON format (``save_json`` / ``load_json``)::

    {"format": "markerset/1", "model": "anny", "num_faces": 27420,
     "markers": [{"name": "LFHD", "face": 123, "bary": [0.2, 0.3, 0.5], "offset": 0.0095}, ...]}

- ``place_markers(model, names, points)``: a set from 3D points on/near the rest surface of
  betas 0 (closest surface point), e.g. a lab's own layout or after a shape fit;
- ``plug_in_gait_lower(model)``: the 16 lower-body Plug-in Gait markers (``PLUG_IN_GAIT_LOWER_NAMES``);
- ``segments_of(name | MarkerSet)``: the near-rigid segment groups (``{segment: marker names}``)
  of a built-in set (``BUILTIN_SEGMENTS``) or of a set read from a file (its own ``segments``,
  else the best-matching built-in groups restricted to its markers). The lab-writable format
  ``markerset/2`` (markers named by anatomical landmark) is read by ``body.landmarks``.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from body.model import BodyModel
from body.rotations import rodrigues
from formats.errors import InputError
from geometry import face_normals

DEFAULT_OFFSET_M = 0.0095
RAY_MAX_M = 0.25  # markers are placed by casting rays this far from inside the body

PLUG_IN_GAIT_NAMES = (
    "LFHD", "RFHD", "LBHD", "RBHD", "C7", "T10", "CLAV", "STRN", "RBAK",
    "LSHO", "LUPA", "LELB", "LFRM", "LWRA", "LWRB", "LFIN",
    "RSHO", "RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN",
    "LASI", "RASI", "LPSI", "RPSI",
    "LTHI", "LKNE", "LTIB", "LANK", "LHEE", "LTOE",
    "RTHI", "RKNE", "RTIB", "RANK", "RHEE", "RTOE",
)  # fmt: skip

#: The CMU mocap database's 41 markers (the order of its C3D files). Waist markers RFWT/LFWT
#: (front, ~ASIS) and RBWT/LBWT (back, ~PSIS), RBAC ~ Plug-in Gait's RBAK, LSHN/RSHN on the
#: shin, LMT5/RMT5 on the 5th metatarsal head; the rest as Plug-in Gait.
CMU41_NAMES = (
    "RBWT", "LBWT", "RFWT", "LFWT", "RTHI", "LWRB", "LFRM", "LTHI", "RWRA", "LFIN", "RWRB",
    "RFRM", "LWRA", "RFIN", "LELB", "RELB", "RKNE", "LKNE", "STRN", "T10", "LUPA", "RUPA",
    "RBAC", "CLAV", "RSHO", "LSHO", "C7", "LSHN", "RBHD", "LBHD", "RANK", "LANK", "LHEE",
    "LFHD", "RHEE", "RTOE", "RMT5", "RFHD", "LMT5", "LTOE", "RSHN",
)  # fmt: skip

#: The 16 lower-body markers of Plug-in Gait (its lower-body model).
PLUG_IN_GAIT_LOWER_NAMES = (
    "LASI", "RASI", "LPSI", "RPSI",
    "LTHI", "LKNE", "LTIB", "LANK", "LHEE", "LTOE",
    "RTHI", "RKNE", "RTIB", "RANK", "RHEE", "RTOE",
)  # fmt: skip

#: Near-rigid segment groups of the Vicon Plug-in Gait full-body set, for the marker cleaner
#: (``fitting.marker_clean``; a marker may be in several: the knee marker sits near the knee
#: axis, at a fixed distance from the thigh's and the shank's markers). Not grouped: the elbow
#: marker with the forearm (elbow extension and pronation move it 3-5 cm relative to the wrist
#: in the tennis serve) and RBAK (on the scapula: 4 cm relative to T10 when the arm rises).
PLUG_IN_GAIT_SEGMENTS: dict[str, tuple[str, ...]] = {
    "head": ("LFHD", "RFHD", "LBHD", "RBHD"),
    "trunk": ("C7", "T10", "CLAV", "STRN"),
    "pelvis": ("LASI", "RASI", "LPSI", "RPSI"),
    **{f"{s}_{seg}": tuple(s + n for n in names) for s in "LR" for seg, names in (
        ("upper_arm", ("SHO", "UPA", "ELB")),
        ("forearm", ("FRM", "WRA", "WRB")),
        ("hand", ("WRA", "WRB", "FIN")),
        ("thigh", ("THI", "KNE")),
        ("shank", ("KNE", "TIB", "ANK")),
        ("foot", ("ANK", "HEE", "TOE")),
    )},
}
#: The same for the CMU mocap database's 41-marker set (waist markers ~ ASIS/PSIS, shin, MT5).
CMU41_SEGMENTS: dict[str, tuple[str, ...]] = {
    "head": ("LFHD", "RFHD", "LBHD", "RBHD"),
    "trunk": ("C7", "T10", "CLAV", "STRN"),
    "pelvis": ("LFWT", "RFWT", "LBWT", "RBWT"),
    **{f"{s}_{seg}": tuple(s + n for n in names) for s in "LR" for seg, names in (
        ("upper_arm", ("SHO", "UPA", "ELB")),
        ("forearm", ("FRM", "WRA", "WRB")),
        ("hand", ("WRA", "WRB", "FIN")),
        ("thigh", ("THI", "KNE")),
        ("shank", ("KNE", "SHN", "ANK")),
        ("foot", ("ANK", "HEE", "TOE", "MT5")),
    )},
}
PLUG_IN_GAIT_LOWER_SEGMENTS: dict[str, tuple[str, ...]] = {
    k: v for k, v in PLUG_IN_GAIT_SEGMENTS.items()
    if set(v) <= set(PLUG_IN_GAIT_LOWER_NAMES)}
#: Segment groups of every built-in set by its recipe name (Plug-in Gait first: the cleaner's
#: best match on a tie).
BUILTIN_SEGMENTS: dict[str, dict[str, tuple[str, ...]]] = {
    "plug-in-gait": PLUG_IN_GAIT_SEGMENTS,
    "cmu": CMU41_SEGMENTS,
    "plug-in-gait-lower": PLUG_IN_GAIT_LOWER_SEGMENTS,
}
BUILTIN_NAMES: dict[str, tuple[str, ...]] = {
    "plug-in-gait": PLUG_IN_GAIT_NAMES, "cmu": CMU41_NAMES,
    "plug-in-gait-lower": PLUG_IN_GAIT_LOWER_NAMES,
}


@dataclasses.dataclass(frozen=True, eq=False)
class MarkerSet:
    """names: M names; faces: (M,) int64 face ids; bary: (M, 3) float64 (rows sum to 1);
    offsets: (M,) float64 metres along the outward face normal; segments: optional
    ``{segment: marker names}`` near-rigid groups (a ``markerset/2`` file's, see
    :func:`segments_of`); labels: optional ``{marker: the lab's C3D label}`` where they differ."""

    names: tuple[str, ...]
    faces: np.ndarray
    bary: np.ndarray
    offsets: np.ndarray
    segments: dict | None = None
    labels: dict | None = None

    def __post_init__(self):
        for f in ("faces", "bary", "offsets"):
            getattr(self, f).flags.writeable = False

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def subset(self, names) -> MarkerSet:
        idx = [self.index(n) for n in names]
        keep = set(names)
        segs = None if self.segments is None else _restrict_groups(self.segments, keep)
        labels = None if self.labels is None else {k: v for k, v in self.labels.items() if k in keep}
        return MarkerSet(tuple(names), self.faces[idx].copy(), self.bary[idx].copy(),
                         self.offsets[idx].copy(), segs, labels)

    def with_offsets(self, offsets) -> MarkerSet:
        o = np.broadcast_to(np.asarray(offsets, dtype=float), (len(self),)).copy()
        return MarkerSet(self.names, self.faces.copy(), self.bary.copy(), o, self.segments,
                         self.labels)


def _restrict_groups(groups, present) -> dict[str, tuple[str, ...]]:
    """The groups restricted to the markers ``present``; groups left with < 2 are dropped."""
    out = {}
    for g, members in groups.items():
        m = tuple(n for n in members if n in present)
        if len(m) >= 2:
            out[g] = m
    return out


def segments_of(markerset) -> dict[str, tuple[str, ...]]:
    """Near-rigid segment groups ``{segment: marker names}`` of a marker set, for the marker
    cleaner (``fitting.marker_clean.clean_markers(names_by_segment=)``).

    markerset: a built-in set's recipe name (``BUILTIN_SEGMENTS``: ``plug-in-gait``, ``cmu``,
    ``plug-in-gait-lower``) or a :class:`MarkerSet` (its own ``segments`` when it has them,
    e.g. from a ``markerset/2`` file; else the built-in groups matching most of its names,
    restricted to them). Groups left with fewer than 2 markers are dropped."""
    if isinstance(markerset, str):
        if markerset not in BUILTIN_SEGMENTS:
            raise ValueError(f"markerset {markerset!r}: not a built-in set (known: "
                             f"{', '.join(BUILTIN_SEGMENTS)})")
        return dict(BUILTIN_SEGMENTS[markerset])
    present = set(markerset.names)
    if getattr(markerset, "segments", None) is not None:
        return _restrict_groups(markerset.segments, present)
    return segments_for_names(present)


def segments_for_names(names) -> dict[str, tuple[str, ...]]:
    """The segment groups of the built-in set that the marker ``names`` match best
    (Plug-in Gait, CMU or its lower body), restricted to them (groups of < 2 dropped)."""
    present = set(names)
    best = max(BUILTIN_SEGMENTS.values(),
               key=lambda g: len(present & {n for v in g.values() for n in v}))
    return _restrict_groups(best, present)


def restrict_groups(groups, present) -> dict[str, tuple[str, ...]]:
    """``groups`` restricted to the markers ``present``; groups left with < 2 are dropped."""
    return _restrict_groups(groups, set(present))


def make_markerset(names, faces, bary, offsets=DEFAULT_OFFSET_M, segments=None,
                   labels=None) -> MarkerSet:
    names = tuple(str(n) for n in names)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1)
    bary = np.asarray(bary, dtype=float).reshape(-1, 3)
    offsets = np.broadcast_to(np.asarray(offsets, dtype=float), (len(names),)).copy()
    if not (len(names) == len(faces) == len(bary)):
        raise ValueError(f"markers: {len(names)} names, {len(faces)} faces, {len(bary)} bary rows")
    return MarkerSet(names, faces.copy(), bary.copy(), offsets,
                     None if segments is None else {str(k): tuple(v) for k, v in segments.items()},
                     None if labels is None else dict(labels))


def marker_positions(vertices: np.ndarray, faces: np.ndarray, markerset: MarkerSet) -> np.ndarray:
    """Marker positions. vertices: (F, V, 3) or (V, 3) metres; faces: (NF, 3) the model's faces.
    Returns (F, M, 3) (or (M, 3)), same frame as the vertices."""
    v = np.asarray(vertices, dtype=float)
    tri = np.asarray(faces)[markerset.faces]  # (M, 3)
    corners = v[..., tri, :]  # (..., M, 3, 3)
    p = np.einsum("...mkd,mk->...md", corners, markerset.bary)
    return p + markerset.offsets[:, None] * face_normals(v, tri)


# ----------------------------------------------------------------------------- JSON


def save_json(markerset: MarkerSet, path: str | Path, model: str = "", num_faces: int | None = None) -> None:
    doc = {
        "format": "markerset/1",
        "model": model,
        "num_faces": num_faces,
        "markers": [
            {"name": n, "face": int(f), "bary": [float(x) for x in b], "offset": float(o)}
            for n, f, b, o in zip(markerset.names, markerset.faces, markerset.bary,
                                  markerset.offsets, strict=True)
        ],
    }
    Path(path).write_text(json.dumps(doc, indent=1))


def load_json(path: str | Path, num_faces: int | None = None) -> MarkerSet:
    """Read a marker-set JSON; InputError names the file and the field (``markers[3].bary``).
    num_faces: the model's face count, checked against the file and the face ids."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, "-", f"cannot read marker set: {e}") from e
    if not isinstance(doc, dict) or doc.get("format") != "markerset/1":
        raise InputError(path, "format", "expected \"markerset/1\"")
    if num_faces is not None and doc.get("num_faces") not in (None, num_faces):
        raise InputError(path, "num_faces", f"file is for a mesh of {doc['num_faces']} faces, model has {num_faces}")
    ms = doc.get("markers")
    if not isinstance(ms, list) or not ms:
        raise InputError(path, "markers", "expected a non-empty list")
    names, faces, bary, offs = [], [], [], []
    for i, m in enumerate(ms):
        where = f"markers[{i}]"
        try:
            names.append(str(m["name"]))
            f = int(m["face"])
            b = np.asarray(m["bary"], dtype=float)
            o = float(m.get("offset", DEFAULT_OFFSET_M))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(path, where, f"bad marker entry: {e}") from e
        if b.shape != (3,) or np.any(b < -1e-6) or abs(b.sum() - 1) > 1e-6:
            raise InputError(path, f"{where}.bary", f"expected 3 non-negative numbers summing to 1, got {m['bary']}")
        if f < 0 or (num_faces is not None and f >= num_faces):
            raise InputError(path, f"{where}.face", f"face id {f} out of range")
        faces.append(f)
        bary.append(b)
        offs.append(o)
    if len(set(names)) != len(names):
        raise InputError(path, "markers", "duplicate marker names")
    return make_markerset(names, faces, bary, offs)


# ----------------------------------------------------------------------------- placement


def closest_surface_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest surface point of each query. Returns (face ids (N,), bary (N, 3), dist (N,))."""
    import igl

    v = np.ascontiguousarray(vertices, dtype=float)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    p = np.ascontiguousarray(np.atleast_2d(points), dtype=float)
    d2, fid, cp = igl.point_mesh_squared_distance(p, v, f)
    tri = v[f[fid]]
    bary = _barycentric(cp, tri)
    return fid.astype(np.int64), bary, np.sqrt(d2)


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - w1 - w2, w1, w2], 1)
    bary = np.clip(bary, 0, None)
    return bary / bary.sum(1, keepdims=True)


def ray_surface(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, direction: np.ndarray,
                max_dist: float = RAY_MAX_M, mode: str = "farthest"):
    """The farthest hit of a ray within ``max_dist`` (the skin, seen from inside the body), or
    with ``mode="first_exit"`` the nearest hit where the ray leaves the body (the face's
    outward normal along the ray: a ray from a limb's axis towards the other limb or the trunk).

    Returns (face id, bary (3,)) or None (Moller-Trumbore over all faces)."""
    d = direction / np.linalg.norm(direction)
    tri = vertices[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pv = np.cross(d, e2)
    det = (e1 * pv).sum(1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = origin - tri[:, 0]
    u = (tv * pv).sum(1) * inv
    qv = np.cross(tv, e1)
    w = (qv @ d) * inv
    t = (e2 * qv).sum(1) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0) & (t < max_dist)
    if mode == "first_exit":
        hit &= np.cross(e1, e2) @ d > 0  # leaving the body (outward normal along the ray)
    elif mode != "farthest":
        raise ValueError(f"mode: 'farthest' or 'first_exit', got {mode!r}")
    if not hit.any():
        return None
    i = np.flatnonzero(hit)[np.argmin(t[hit]) if mode == "first_exit" else np.argmax(t[hit])]
    return int(i), np.array([1 - u[i] - w[i], u[i], w[i]])


def place_markers(model: BodyModel, names, points, offsets=DEFAULT_OFFSET_M, vertices=None) -> MarkerSet:
    """A MarkerSet from 3D points (M, 3) near the rest surface (default: the mean-shape rest
    mesh ``model.v_template``): each marker goes to the closest surface point."""
    v = model.v_template if vertices is None else vertices
    fid, bary, _ = closest_surface_points(v, model.faces, points)
    return make_markerset(names, fid, bary, offsets)


def _perp(d: np.ndarray, axis: np.ndarray) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    p = d - (d @ a) * a
    return p / np.linalg.norm(p)


def _anny_pig_rays(model: BodyModel) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(origin inside the body, direction) per Plug-in Gait marker, on Anny's mean rest mesh.

    Anny's frame: z up, the body faces -y, its left is +x. Right-side rays mirror x."""
    J = model.joint_template

    def h(n):
        return J[model.joint_index(n)]

    skull = h("head") + np.array([0.0, 0.01, 0.07])
    rays: dict[str, tuple[np.ndarray, np.ndarray]] = {
        "C7": (h("neck01") + [0, 0, 0.01], np.array([0.0, 1.0, 0.25])),
        "T10": (0.45 * h("spine01") + 0.55 * h("spine03"), np.array([0.0, 1.0, 0.0])),
        "CLAV": (h("neck01") - [0, 0, 0.035], np.array([0.0, -1.0, 0.15])),
        "STRN": (0.35 * h("spine01") + 0.65 * h("neck01") - [0, 0, 0.13], np.array([0.0, -1.0, 0.0])),
        "RBAK": (h("spine01") + [-0.085, 0.0, 0.02], np.array([0.0, 1.0, 0.0])),
    }
    for s, S, sx in (("L", "L", 1.0), ("R", "R", -1.0)):
        X = np.array([sx, 1.0, 1.0])
        rays[f"{s}FHD"] = (skull, np.array([0.45, -1.0, 0.3]) * X)
        rays[f"{s}BHD"] = (skull, np.array([0.45, 1.0, 0.2]) * X)
        ua, fa, wr = h(f"upperarm01.{S}"), h(f"lowerarm01.{S}"), h(f"wrist.{S}")
        rays[f"{s}SHO"] = (ua, np.array([0.35 * sx, 0.05, 1.0]))
        lat = np.array([sx, 0.0, 0.0])
        rays[f"{s}UPA"] = (0.45 * ua + 0.55 * fa, _perp(lat + [0, 0.4, 0], fa - ua))
        rays[f"{s}ELB"] = (fa, _perp(lat + [0, 0.3, 0], wr - fa))
        rays[f"{s}FRM"] = (0.5 * fa + 0.5 * wr, _perp(np.array([0.0, 1.0, 0.0]) + 0.5 * lat, wr - fa))
        thumb = h(f"finger1-1.{S}") - wr
        pinky = h(f"finger5-1.{S}") - wr
        rays[f"{s}WRA"] = (wr, _perp(thumb, wr - fa))
        rays[f"{s}WRB"] = (wr, _perp(pinky, wr - fa))
        f_dir = h(f"finger3-1.{S}") - wr
        r_dir = _perp(thumb, f_dir)
        dorsal = np.cross(f_dir, r_dir) * (-1.0 if s == "L" else 1.0)
        mcp2 = h(f"finger2-1.{S}")
        rays[f"{s}FIN"] = (mcp2 - 0.25 * (mcp2 - wr), dorsal / np.linalg.norm(dorsal))
        hip, knee, ank = h(f"upperleg01.{S}"), h(f"lowerleg01.{S}"), h(f"foot.{S}")
        rays[f"{s}ASI"] = (hip * [1.05, 0, 0] + [0, hip[1], hip[2] + 0.075], np.array([0.15 * sx, -1.0, 0.0]))
        rays[f"{s}PSI"] = (hip * [0.45, 0, 0] + [0, hip[1], hip[2] + 0.09], np.array([0.1 * sx, 1.0, 0.0]))
        rays[f"{s}THI"] = (0.4 * hip + 0.6 * knee, _perp(lat + [0, -0.15, 0], knee - hip))
        rays[f"{s}KNE"] = (knee, _perp(lat, ank - knee))
        rays[f"{s}TIB"] = (0.4 * knee + 0.6 * ank, _perp(lat + [0, -0.15, 0], ank - knee))
        rays[f"{s}ANK"] = (ank, _perp(lat, ank - knee))
        rays[f"{s}HEE"] = (ank + [0, 0.0, -0.035], np.array([0.0, 1.0, -0.15]))
        toe2 = h(f"toe2-1.{S}")
        rays[f"{s}TOE"] = (toe2 + 0.2 * (ank - toe2) * [1, 1, 0], np.array([0.0, -0.15, 1.0]))
    return rays


def _anny_cmu_rays(model: BodyModel) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(origin, direction) per CMU41 marker on Anny's mean rest mesh: the Plug-in Gait rays
    where the landmark is the same, new ones for the waist, the shin and the 5th metatarsal."""
    pig = _anny_pig_rays(model)
    J = model.joint_template

    def h(n):
        return J[model.joint_index(n)]

    rays = {n: pig[n] for n in CMU41_NAMES if n in pig}
    rays["RBAC"] = pig["RBAK"]
    skull = h("head") + np.array([0.0, 0.01, 0.07])
    for s, S, sx in (("L", "L", 1.0), ("R", "R", -1.0)):
        X = np.array([sx, 1.0, 1.0])
        # CMU's head markers sit wider than Plug-in Gait's (front at the temples: 17 cm
        # apart in nimble_cmu_02_05.c3d, back 10 cm), its toe marker on the toe, not the MTP
        rays[f"{s}FHD"] = (skull, np.array([1.0, -1.0, 0.3]) * X)
        rays[f"{s}BHD"] = (skull, np.array([0.7, 1.0, 0.35]) * X)
        toe2 = h(f"toe2-1.{S}")
        rays[f"{s}TOE"] = (toe2 - 0.15 * (h(f"foot.{S}") - toe2) * [1, 1, 0],
                           np.array([0.0, -0.3, 1.0]))
        hip, knee, ank = h(f"upperleg01.{S}"), h(f"lowerleg01.{S}"), h(f"foot.{S}")
        # waist: a belt at the iliac crests, front ~ above the ASIS, back ~ above the PSIS
        rays[f"{s}FWT"] = (hip * [1.1, 0, 0] + [0, hip[1], hip[2] + 0.08],
                           np.array([0.3 * sx, -1.0, 0.0]))
        rays[f"{s}BWT"] = (hip * [0.3, 0, 0] + [0, hip[1], hip[2] + 0.09],
                           np.array([0.05 * sx, 1.0, 0.0]))
        # shin: the anterior tibia, a little below mid-shank
        rays[f"{s}SHN"] = (0.45 * knee + 0.55 * ank,
                           _perp(np.array([0.1 * sx, -1.0, 0.0]), ank - knee))
        # 5th metatarsal head: the lateral forefoot, behind the little toe
        toe = 0.5 * (h(f"toe2-1.{S}") + h(f"toe5-1.{S}"))
        rays[f"{s}MT5"] = (toe + 0.2 * (ank - toe) * [1, 1, 0], np.array([sx, 0.1, 0.1]))
    return rays


def cmu41(model: BodyModel, offset: float = DEFAULT_OFFSET_M) -> MarkerSet:
    """The CMU mocap database's 41-marker set (``CMU41_NAMES``) placed on ``model`` by rays
    like :func:`plug_in_gait` (see ``_anny_cmu_rays``). Implemented for Anny."""
    if model.name != "anny":
        raise ValueError(f"CMU marker placement is defined for anny, not {model.name}")
    ms = _place_by_rays(model, _anny_cmu_rays(model), CMU41_NAMES, offset, "cmu41")
    return dataclasses.replace(ms, segments=dict(CMU41_SEGMENTS))


def _place_by_rays(model, rays, names, offset, what) -> MarkerSet:
    v = model.v_template
    faces, bary = [], []
    for n in names:
        o, d = rays[n]
        hit = ray_surface(v, model.faces, np.asarray(o, float), np.asarray(d, float))
        if hit is None:
            raise RuntimeError(f"{what}: no surface hit for {n}")
        faces.append(hit[0])
        bary.append(hit[1])
    return make_markerset(names, faces, bary, offset)


def plug_in_gait(model: BodyModel, offset: float = DEFAULT_OFFSET_M) -> MarkerSet:
    """The Vicon Plug-in Gait full-body set (39 markers, standard names) placed on ``model``.

    Placed once on the mean rest mesh by casting a ray from inside the segment towards the
    bony landmark (see ``_anny_pig_rays``); being face + barycentric, it follows any shape.
    Implemented for Anny."""
    if model.name != "anny":
        raise ValueError(f"plug-in-gait placement is defined for anny, not {model.name}")
    rays = _anny_pig_rays(model)
    v = model.v_template
    faces, bary = [], []
    for n in PLUG_IN_GAIT_NAMES:
        o, d = rays[n]
        hit = ray_surface(v, model.faces, np.asarray(o, float), np.asarray(d, float))
        if hit is None:
            raise RuntimeError(f"plug-in-gait: no surface hit for {n}")
        faces.append(hit[0])
        bary.append(hit[1])
    return make_markerset(PLUG_IN_GAIT_NAMES, faces, bary, offset,
                          segments=PLUG_IN_GAIT_SEGMENTS)


def plug_in_gait_lower(model: BodyModel, offset: float = DEFAULT_OFFSET_M) -> MarkerSet:
    """The 16 lower-body Plug-in Gait markers (``PLUG_IN_GAIT_LOWER_NAMES``: pelvis, thighs,
    knees, shanks, ankles, heels, toes) placed as :func:`plug_in_gait` places them; carries its
    segment groups. Implemented for Anny."""
    ms = plug_in_gait(model, offset).subset(PLUG_IN_GAIT_LOWER_NAMES)
    return dataclasses.replace(ms, segments=dict(PLUG_IN_GAIT_LOWER_SEGMENTS))


def hand_markers(model: BodyModel, offset: float = 0.006) -> MarkerSet:
    """Optional hand set: one marker on the nail side of each fingertip (L/R THM, IDX, MID,
    RNG, PNK + "TIP"), 6 mm offset (small hand markers). Anny only."""
    if model.name != "anny":
        raise ValueError(f"hand markers are defined for anny, not {model.name}")
    J = model.joint_template
    names, faces, bary = [], [], []
    for s, S in (("L", "L"), ("R", "R")):
        wr = J[model.joint_index(f"wrist.{S}")]
        f_dir = J[model.joint_index(f"finger3-1.{S}")] - wr
        thumb = J[model.joint_index(f"finger1-1.{S}")] - wr
        dorsal = np.cross(f_dir, _perp(thumb, f_dir)) * (-1.0 if s == "L" else 1.0)
        dorsal /= np.linalg.norm(dorsal)
        for fi, tag in enumerate(("THM", "IDX", "MID", "RNG", "PNK"), start=1):
            a = J[model.joint_index(f"finger{fi}-2.{S}")]
            b = J[model.joint_index(f"finger{fi}-3.{S}")]
            o = b + 0.5 * (b - a)
            hit = None
            # the nail side: the dorsal direction, or for the thumb (rotated about its axis)
            # the direction within 90 degrees of it whose hit is farthest from the bone
            for ang in ((0.0,) if fi > 1 else np.linspace(-np.pi / 2, np.pi / 2, 13)):
                ax = (b - a) / np.linalg.norm(b - a)
                d = rodrigues(ang * ax) @ _perp(dorsal, ax)
                h_ = ray_surface(model.v_template, model.faces, o, d, max_dist=0.05)
                if h_ is not None and (hit is None or ang == 0.0):
                    hit = h_
            if hit is None:
                raise RuntimeError(f"hand markers: no surface hit for {s}{tag}TIP")
            names.append(f"{s}{tag}TIP")
            faces.append(hit[0])
            bary.append(hit[1])
    return make_markerset(names, faces, bary, offset)
