"""Named anatomical landmarks on the body model, and marker sets a lab writes (``markerset/2``).

A lab describes its marker set by anatomy, not by mesh faces: each marker is a landmark of
:data:`LANDMARKS` (``left_asis``, ``right_lateral_malleolus``, ``c7``, ...), a position along a
body segment of :data:`SEGMENTS` (``{segment: left_forearm, along: 0.5, side: lateral}``) or
a point between two landmarks (``{between: [left_asis, left_psis], at: 0.3}``), plus an offset
from the skin (marker radius + base, default 9.5 mm). The code places each marker on the model
surface (face + barycentric coordinates, ``body.markers.MarkerSet``), so the set follows any
shape. Landmarks are defined once, on Anny's mean rest mesh, by a ray from inside the body to
the bony landmark: the Plug-in Gait and CMU positions reuse exactly the rays that place those
built-in sets (``body.markers._anny_pig_rays`` / ``_anny_cmu_rays``), so
:func:`builtin_definition` (the built-in sets written as ``markerset/2``) reproduces them.

File format (YAML or JSON, ``.yaml`` / ``.yml`` / ``.json``)::

    format: markerset/2
    model: anny              # optional; landmarks are defined on Anny
    offset_mm: 9.5           # optional default offset from the skin, millimetres
    markers:                 # a mapping name -> definition (or a list of {name: ..., ...})
      LASI: left_asis                          # a landmark, by name
      RKNE: {landmark: right_lateral_femoral_epicondyle, offset_mm: 12, label: R_Knee}
      LFA2: {segment: left_forearm, along: 0.5, side: lateral}
      LTH3: {between: [left_greater_trochanter, left_lateral_femoral_epicondyle], at: 0.3}
    segments:                # optional near-rigid groups for the marker cleaner
      pelvis: [LASI, RASI, LPSI, RPSI]

``along`` runs from the segment's proximal joint (0) to its distal joint (1); ``side`` is one
of :data:`SIDES` (``lateral``/``medial`` on sided segments, ``left``/``right`` on midline
ones): the marker sits where a ray from that point of the segment's axis, perpendicular to
it, leaves the body. ``between`` takes the landmarks' skin points, ``at`` from the first (0) to
the second (1), and the closest surface point. ``label``: the lab's C3D label of the marker
where it differs from the name (``MarkerSet.labels``).

- :func:`load_markerset` (path, model): ``markerset/2`` (YAML or JSON) or ``markerset/1``
  (``body.markers.load_json``); errors are ``formats.errors.InputError(file, field, msg)``
  naming the marker and its field (``markers.LKNE.landmark: unknown landmark 'left_knee'
  (nearest: left_lateral_femoral_epicondyle, ...)``);
- :func:`place_definition` (model, doc): the same from a parsed document;
- :func:`landmark_points` (model, names): the landmarks' (face, bary) on the model;
- :func:`builtin_definition` (name): a built-in set as a ``markerset/2`` document.
"""
from __future__ import annotations

import difflib
import json
from pathlib import Path

import numpy as np

from body import markers as M
from body.model import BodyModel
from formats.errors import InputError

FORMAT = "markerset/2"
SUFFIXES = (".json", ".yaml", ".yml")
MAX_OFFSET_MM = 100.0  # a marker farther than this from the skin is a unit error

# Plug-in Gait marker -> landmark (left names; the right twins mirror them)
_PIG_SIDED = {
    "FHD": "front_head", "BHD": "back_head", "SHO": "acromion", "UPA": "lateral_upper_arm",
    "ELB": "lateral_epicondyle_humerus", "FRM": "dorsal_forearm", "WRA": "radial_styloid",
    "WRB": "ulnar_styloid", "FIN": "second_metacarpal_head", "ASI": "asis", "PSI": "psis",
    "THI": "lateral_thigh", "KNE": "lateral_femoral_epicondyle", "TIB": "lateral_shank",
    "ANK": "lateral_malleolus", "HEE": "calcaneus", "TOE": "second_metatarsal_head",
}
_PIG_MID = {"C7": "c7", "T10": "t10", "CLAV": "jugular_notch", "STRN": "xiphoid_process",
            "RBAK": "right_scapula"}
# CMU marker -> landmark where the CMU set differs from Plug-in Gait
_CMU_SIDED = {"FHD": "temple", "BHD": "upper_back_head", "TOE": "second_toe",
              "FWT": "front_waist", "BWT": "back_waist", "SHN": "anterior_tibia",
              "MT5": "fifth_metatarsal_head"}
_SIDE_WORD = {"L": "left", "R": "right"}

#: Body segments for ``{segment: ..., along: ..., side: ...}``: (proximal joint, distal joint)
#: of Anny (``.S`` = the side's suffix), and whether the segment is sided (lateral/medial).
_SEGMENT_JOINTS = {
    "upper_arm": ("upperarm01", "lowerarm01"), "forearm": ("lowerarm01", "wrist"),
    "hand": ("wrist", "finger3-1"), "thigh": ("upperleg01", "lowerleg01"),
    "shank": ("lowerleg01", "foot"), "foot": ("foot", "toe2-1"),
}
_MID_SEGMENTS = {"trunk": ("spine05", "neck01"), "neck": ("neck01", "head")}
SEGMENTS: tuple[str, ...] = tuple(
    [f"{w}_{s}" for w in ("left", "right") for s in _SEGMENT_JOINTS] + list(_MID_SEGMENTS)
    + ["head"])
#: ray directions of ``side`` in Anny's frame (z up, the body faces -y, its left is +x);
#: lateral/medial flip with the side
SIDES: tuple[str, ...] = ("lateral", "medial", "anterior", "posterior", "superior", "inferior",
                          "left", "right", "anterolateral", "anteromedial", "posterolateral",
                          "posteromedial")


def _side_dir(side: str, sx: float | None) -> np.ndarray | None:
    """Direction of ``side`` (sx = +1 left, -1 right, None midline); None if undefined."""
    base = {"anterior": (0, -1, 0), "posterior": (0, 1, 0), "superior": (0, 0, 1),
            "inferior": (0, 0, -1), "left": (1, 0, 0), "right": (-1, 0, 0)}
    if side in base:
        return np.array(base[side], float)
    if sx is None:
        return None
    lat = np.array([sx, 0.0, 0.0])
    parts = {"lateral": lat, "medial": -lat, "anterolateral": lat + base["anterior"],
             "anteromedial": -lat + base["anterior"], "posterolateral": lat + base["posterior"],
             "posteromedial": -lat + base["posterior"]}
    return np.asarray(parts[side], float) if side in parts else None


def _extra_rays(model: BodyModel) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Landmarks neither built-in set uses: medial ones, the other scapula, trochanters,
    the first metatarsal head, the vertex. Rays leave the body at the first exit."""
    J = model.joint_template

    def h(n):
        return J[model.joint_index(n)]

    skull = h("head") + np.array([0.0, 0.01, 0.07])
    rays = {"vertex": (skull, np.array([0.0, 0.0, 1.0]), "first_exit"),
            "left_scapula": (h("spine01") + [0.085, 0.0, 0.02], np.array([0.0, 1.0, 0.0]),
                             "farthest")}
    for s, S, sx in (("left", "L", 1.0), ("right", "R", -1.0)):
        lat = np.array([sx, 0.0, 0.0])
        fa, wr = h(f"lowerarm01.{S}"), h(f"wrist.{S}")
        hip, knee, ank = h(f"upperleg01.{S}"), h(f"lowerleg01.{S}"), h(f"foot.{S}")
        rays[f"{s}_medial_epicondyle_humerus"] = (fa, M._perp(-lat + [0, 0.3, 0], wr - fa),
                                                  "first_exit")
        rays[f"{s}_medial_femoral_epicondyle"] = (knee, M._perp(-lat, ank - knee), "first_exit")
        rays[f"{s}_medial_malleolus"] = (ank, M._perp(-lat, ank - knee), "first_exit")
        rays[f"{s}_greater_trochanter"] = (hip, M._perp(lat, knee - hip), "first_exit")
        toe = h(f"toe1-1.{S}")
        rays[f"{s}_first_metatarsal_head"] = (toe + 0.2 * (ank - toe) * [1, 1, 0],
                                              np.array([-sx, 0.1, 0.1]), "first_exit")
    return rays


def landmark_rays(model: BodyModel) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """``{landmark: (origin inside the body, direction, mode)}`` on Anny's mean rest mesh;
    mode ``farthest`` / ``first_exit`` (``body.markers.ray_surface``)."""
    if model.name != "anny":
        raise ValueError(f"landmarks are defined for anny, not {model.name}")
    pig, cmu = M._anny_pig_rays(model), M._anny_cmu_rays(model)
    out: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    for mk, lm in _PIG_MID.items():
        out[lm] = (*pig[mk], "farthest")
    for S, w in _SIDE_WORD.items():
        for mk, lm in _PIG_SIDED.items():
            out[f"{w}_{lm}"] = (*pig[S + mk], "farthest")
        for mk, lm in _CMU_SIDED.items():
            out[f"{w}_{lm}"] = (*cmu[S + mk], "farthest")
    out.update(_extra_rays(model))
    return out


def _vocabulary() -> tuple[str, ...]:
    names = list(_PIG_MID.values()) + ["left_scapula", "vertex"]
    for w in _SIDE_WORD.values():
        names += [f"{w}_{x}" for x in list(_PIG_SIDED.values()) + list(_CMU_SIDED.values())]
        names += [f"{w}_{x}" for x in ("medial_epicondyle_humerus", "medial_femoral_epicondyle",
                                        "medial_malleolus", "greater_trochanter",
                                        "first_metatarsal_head")]
    return tuple(names)


#: The landmark vocabulary (every name :func:`landmark_rays` defines).
LANDMARKS: tuple[str, ...] = _vocabulary()


def builtin_landmarks(name: str) -> dict[str, str]:
    """``{marker: landmark}`` of a built-in set (``plug-in-gait``, ``cmu``,
    ``plug-in-gait-lower``)."""
    if name not in M.BUILTIN_NAMES:
        raise ValueError(f"markerset {name!r}: not a built-in set (known: "
                         f"{', '.join(M.BUILTIN_NAMES)})")
    out = {}
    for mk in M.BUILTIN_NAMES[name]:
        if name == "cmu" and mk == "RBAC":
            out[mk] = "right_scapula"
        elif name == "cmu" and mk[1:] in _CMU_SIDED:
            out[mk] = f"{_SIDE_WORD[mk[0]]}_{_CMU_SIDED[mk[1:]]}"
        elif mk in _PIG_MID:
            out[mk] = _PIG_MID[mk]
        else:
            out[mk] = f"{_SIDE_WORD[mk[0]]}_{_PIG_SIDED[mk[1:]]}"
    return out


def builtin_definition(name: str) -> dict:
    """A built-in set written as a ``markerset/2`` document (landmarks and segment groups)."""
    return {"format": FORMAT, "model": "anny", "offset_mm": 1000 * M.DEFAULT_OFFSET_M,
            "markers": builtin_landmarks(name),
            "segments": {k: list(v) for k, v in M.BUILTIN_SEGMENTS[name].items()}}


def landmark_points(model: BodyModel, names, vertices=None) -> tuple[np.ndarray, np.ndarray]:
    """(faces (N,), bary (N, 3)) of the landmarks ``names`` on ``model`` (Anny's mean rest mesh
    by default). ValueError for an unknown name."""
    rays = landmark_rays(model)
    v = model.v_template if vertices is None else vertices
    faces, bary = [], []
    for n in names:
        if n not in rays:
            raise ValueError(f"unknown landmark {n!r} ({nearest_landmarks(n)})")
        o, d, mode = rays[n]
        hit = M.ray_surface(v, model.faces, np.asarray(o, float), np.asarray(d, float),
                            mode=mode)
        if hit is None:
            raise RuntimeError(f"landmark {n}: no surface hit")
        faces.append(hit[0])
        bary.append(hit[1])
    return np.asarray(faces, np.int64), np.asarray(bary, float).reshape(-1, 3)


_HINTS = {"knee": ("femoral", "epicondyle"), "ankle": ("malleolus",), "elbow": ("humerus",),
          "heel": ("calcaneus",), "wrist": ("styloid",), "shoulder": ("acromion",),
          "hip": ("asis", "psis", "trochanter"), "pelvis": ("asis", "psis"),
          "toe": ("toe", "metatarsal"), "head": ("head", "temple", "vertex"),
          "shin": ("tibia", "shank"), "back": ("scapula", "t10", "psis"),
          "chest": ("jugular", "xiphoid"), "sternum": ("jugular", "xiphoid"),
          "neck": ("c7",), "finger": ("metacarpal",), "hand": ("metacarpal", "styloid")}


def nearest_landmarks(name: str, n: int = 5) -> str:
    """Text naming the vocabulary's nearest names to ``name`` (shared words, common words
    for the landmark such as ``knee``, then spelling)."""
    low = str(name).lower().replace("-", "_").replace(" ", "_")
    words = set(low.split("_")) - {"", "left", "right", "l", "r"}
    want = set(words)
    for w in words:
        want.update(_HINTS.get(w, ()))
    side = "left" if low.startswith(("left", "l_")) else "right" if low.startswith(
        ("right", "r_")) else None
    def score(x):
        return len(want & set(x.split("_"))) + difflib.SequenceMatcher(None, low, x).ratio()

    hits = [x for x in LANDMARKS if want & set(x.split("_"))
            or difflib.SequenceMatcher(None, low, x).ratio() >= 0.5]
    hits.sort(key=lambda x: (side is not None and not x.startswith(side), -score(x)))
    near = hits[:n]
    return ("nearest: " + ", ".join(near)) if near else f"known: {', '.join(LANDMARKS)}"


def _segment_axis(model: BodyModel, segment: str):
    """(proximal point, distal point, sx) of a segment of :data:`SEGMENTS`."""
    J = model.joint_template

    def h(n):
        return J[model.joint_index(n)]

    if segment in _MID_SEGMENTS:
        a, b = _MID_SEGMENTS[segment]
        return h(a), h(b), None
    if segment == "head":
        return h("head"), h("head") + np.array([0.0, 0.01, 0.15]), None
    w, _, part = segment.partition("_")
    S, sx = ("L", 1.0) if w == "left" else ("R", -1.0)
    a, b = _SEGMENT_JOINTS[part]
    return h(f"{a}.{S}"), h(f"{b}.{S}"), sx


# ----------------------------------------------------------------------------- the file


def _read_doc(path: Path):
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(path, "-", f"cannot read marker set: {e}") from e
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        import yaml

        return yaml.safe_load(text)
    except Exception as e:  # yaml.YAMLError, json.JSONDecodeError
        raise InputError(path, "-", f"not valid {path.suffix.lstrip('.').upper()}: {e}") from e


def load_markerset(path: str | Path, model: BodyModel) -> M.MarkerSet:
    """A marker-set file placed on ``model``: ``markerset/2`` (YAML or JSON, this module's
    docstring) or ``markerset/1`` (JSON of faces and barycentric coordinates,
    ``body.markers.load_json``). InputError names the file, the marker and the field."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise InputError(path, "-", f"a marker-set file ends in {', '.join(SUFFIXES)}")
    doc = _read_doc(path)
    if isinstance(doc, dict) and doc.get("format") == "markerset/1":
        return M.load_json(path, num_faces=len(model.faces))
    return place_definition(model, doc, source=path)


def place_definition(model: BodyModel, doc, source: str | Path = "<markerset>") -> M.MarkerSet:
    """A parsed ``markerset/2`` document placed on ``model`` (Anny). ``source`` names the file
    in errors."""
    if not isinstance(doc, dict):
        raise InputError(source, "-", f"expected a mapping with format: {FORMAT}")
    if doc.get("format") != FORMAT:
        raise InputError(source, "format", f"expected \"{FORMAT}\" (or \"markerset/1\"), got "
                         f"{doc.get('format')!r}")
    unknown = sorted(set(doc) - {"format", "model", "offset_mm", "markers", "segments",
                                 "description"})
    if unknown:
        raise InputError(source, unknown[0], "unknown key (known: format, model, offset_mm, "
                         "markers, segments, description)")
    if doc.get("model", "anny") != "anny" or model.name != "anny":
        raise InputError(source, "model", f"landmarks are defined on anny (file: "
                         f"{doc.get('model')!r}, model: {model.name!r})")
    default_mm = _offset(doc.get("offset_mm", 1000 * M.DEFAULT_OFFSET_M), source, "offset_mm")
    entries = _entries(doc.get("markers"), source)
    rays = landmark_rays(model)
    v = np.asarray(model.v_template, float)
    cache: dict[str, tuple[int, np.ndarray]] = {}

    def landmark(name, field):
        if not isinstance(name, str) or name not in rays:
            raise InputError(source, field, f"unknown landmark {name!r} "
                             f"({nearest_landmarks(str(name))})")
        if name not in cache:
            f, b = landmark_points(model, [name])
            cache[name] = (int(f[0]), b[0])
        return cache[name]

    def surface_point(fb):
        return b_point(v, model.faces, *fb)

    names, faces, bary, offs, labels = [], [], [], [], {}
    for name, d in entries:
        where = f"markers.{name}"
        if isinstance(d, str):
            d = {"landmark": d}
        if not isinstance(d, dict):
            raise InputError(source, where, "expected a landmark name or a mapping with "
                             "landmark, segment or between")
        kinds = [k for k in ("landmark", "segment", "between") if k in d]
        if len(kinds) != 1:
            raise InputError(source, where, "give exactly one of landmark, segment, between "
                             f"(got {', '.join(kinds) or 'none'})")
        allowed = {"landmark": {"landmark"}, "segment": {"segment", "along", "side"},
                   "between": {"between", "at"}}[kinds[0]] | {"offset_mm", "label"}
        extra = sorted(set(d) - allowed)
        if extra:
            raise InputError(source, f"{where}.{extra[0]}", f"unknown key for a {kinds[0]} "
                             f"marker (allowed: {', '.join(sorted(allowed))})")
        if kinds[0] == "landmark":
            f, b = landmark(d["landmark"], f"{where}.landmark")
        elif kinds[0] == "segment":
            f, b = _on_segment(model, v, d, where, source)
        else:
            pair = d["between"]
            if not isinstance(pair, list) or len(pair) != 2:
                raise InputError(source, f"{where}.between", f"expected two landmark names, "
                                 f"got {pair!r}")
            t = _fraction(d.get("at", 0.5), source, f"{where}.at")
            pa = surface_point(landmark(pair[0], f"{where}.between[0]"))
            pb = surface_point(landmark(pair[1], f"{where}.between[1]"))
            fid, bb, _ = M.closest_surface_points(v, model.faces, (1 - t) * pa + t * pb)
            f, b = int(fid[0]), bb[0]
        names.append(name)
        faces.append(f)
        bary.append(b)
        offs.append(_offset(d.get("offset_mm", default_mm), source, f"{where}.offset_mm") / 1000)
        if "label" in d:
            if not isinstance(d["label"], str) or not d["label"].strip():
                raise InputError(source, f"{where}.label", f"expected the C3D label (a "
                                 f"non-empty string), got {d['label']!r}")
            labels[name] = d["label"].strip()
    segs = _segments(doc.get("segments"), names, source)
    return M.make_markerset(names, faces, bary, offs, segments=segs,
                            labels=labels or None)


def b_point(v: np.ndarray, faces: np.ndarray, face: int, bary: np.ndarray) -> np.ndarray:
    """The surface point (3,) of (face, bary) on vertices ``v``."""
    return np.asarray(bary, float) @ v[np.asarray(faces)[face]]


def _entries(ms, source) -> list[tuple[str, object]]:
    if isinstance(ms, dict):
        out = [(str(k), d) for k, d in ms.items()]
    elif isinstance(ms, list):
        out = []
        for i, m in enumerate(ms):
            if not isinstance(m, dict) or not isinstance(m.get("name"), str):
                raise InputError(source, f"markers[{i}]", "expected a mapping with a name")
            out.append((m["name"], {k: x for k, x in m.items() if k != "name"}))
    else:
        raise InputError(source, "markers", "expected a mapping {name: definition} or a list")
    if not out:
        raise InputError(source, "markers", "no markers")
    seen = set()
    for n, _ in out:
        if not n.strip():
            raise InputError(source, "markers", "a marker with an empty name")
        if n in seen:
            raise InputError(source, f"markers.{n}", "duplicate marker name")
        seen.add(n)
    return out


def _number(x, source, field) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
        raise InputError(source, field, f"expected a number, got {x!r}")
    return float(x)


def _offset(x, source, field) -> float:
    o = _number(x, source, field)
    if not -MAX_OFFSET_MM < o < MAX_OFFSET_MM:
        raise InputError(source, field, f"{o:g} mm from the skin: expected |offset| < "
                         f"{MAX_OFFSET_MM:g} mm (millimetres)")
    return o


def _fraction(x, source, field) -> float:
    t = _number(x, source, field)
    if not 0.0 <= t <= 1.0:
        raise InputError(source, field, f"expected a fraction in [0, 1], got {t:g}")
    return t


def _on_segment(model, v, d, where, source):
    seg = d["segment"]
    if seg not in SEGMENTS:
        near = difflib.get_close_matches(str(seg), SEGMENTS, n=4, cutoff=0.3)
        raise InputError(source, f"{where}.segment", f"unknown segment {seg!r} ("
                         + (f"nearest: {', '.join(near)}" if near else
                            f"known: {', '.join(SEGMENTS)}") + ")")
    if "along" not in d:
        raise InputError(source, f"{where}.along", "missing: the position along the segment, "
                         "0 = proximal joint, 1 = distal joint")
    t = _fraction(d["along"], source, f"{where}.along")
    a, b, sx = _segment_axis(model, seg)
    side = d.get("side", "lateral" if sx is not None else "anterior")
    dr = _side_dir(side, sx) if isinstance(side, str) else None
    if dr is None:
        ok = [s for s in SIDES if _side_dir(s, sx) is not None]
        raise InputError(source, f"{where}.side", f"{side!r} is not a side of {seg} (one of "
                         f"{', '.join(ok)})")
    axis = b - a
    if np.linalg.norm(np.cross(dr, axis)) < 0.3 * np.linalg.norm(axis):
        raise InputError(source, f"{where}.side", f"{side} runs along {seg}'s axis: pick a "
                         "side across it")
    origin = (1 - t) * a + t * b
    hit = M.ray_surface(v, model.faces, origin, M._perp(dr, axis), mode="first_exit")
    if hit is None:
        raise InputError(source, where, f"no skin {side} of {seg} at along={t:g}")
    return hit


def _segments(segs, names, source):
    if segs is None:
        return None
    if not isinstance(segs, dict):
        raise InputError(source, "segments", "expected a mapping {segment: [marker names]}")
    out = {}
    known = set(names)
    for g, members in segs.items():
        if not isinstance(members, list) or len(members) < 2:
            raise InputError(source, f"segments.{g}", "expected a list of 2 or more marker "
                             "names")
        bad = [m for m in members if m not in known]
        if bad:
            raise InputError(source, f"segments.{g}", f"marker {bad[0]!r} is not in markers")
        out[str(g)] = tuple(str(m) for m in members)
    return out
