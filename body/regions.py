"""Surface regions: an anatomical 75-region map for any (named-rig) model, 37/17/9 groupings,
facet -> region lookup, region adjacency, and the official CHI3D ``contact_regions.json``.

The paper groups facets into 75 regions "following the anatomical parts of the human body and
their symmetries"; the official map covers GHUM and SMPL-X facets only and no names are public.
Ours (``REGIONS_75``): 3 midline regions (head top, neck front, neck back) and 36 left/right
pairs (face, back of head, upper/lower chest, abdomen, groin, upper/mid/lower back, buttock,
flank, shoulder, armpit, upper arm front/back, elbow inner/outer, forearm front (palmar)/back,
palm, back of hand, thumb, fingers palmar/dorsal, hip side, thigh front/back/inner, knee
front/back, shin, calf, foot top, sole, heel, toes). Nested coarser maps: 37 (``REGIONS_37``),
17 and 9, each a union of finer regions (``GROUPING[n]``: 75-index -> n-index).

How a facet gets its region (``region_map(model)``), on the rest mesh at betas 0: its body part
is that of the bone with the largest summed skinning weight over its corners (a per-rig
table); the part is then cut by the body frame (up = pelvis -> neck, left = right hip -> left
hip, front = left x up) and by the limb axes (axial fraction, front/back/inner/outer angle
around the bone, palmar vs dorsal from the hand's joints). Rules in ``_assign``.

``load_official(path, mesh="smplx")`` reads ``contact_regions.json`` (``rid_to_smplx_fids`` /
``rid_to_ghum_fids``): a RegionMap with the official 75 regions (names ``r00``..``r74``).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from body.model import BodyModel
from formats.errors import InputError
from geometry import face_normals

_PAIRS = (
    "face", "head_back", "chest_upper", "chest_lower", "abdomen", "groin", "upper_back",
    "mid_back", "lower_back", "buttock", "flank", "shoulder", "armpit", "upper_arm_front",
    "upper_arm_back", "elbow_inner", "elbow_outer", "forearm_front", "forearm_back", "palm",
    "hand_back", "thumb", "fingers_palmar", "fingers_dorsal", "hip_side", "thigh_front",
    "thigh_back", "thigh_inner", "knee_front", "knee_back", "shin", "calf", "foot_top", "sole",
    "heel", "toes",
)  # fmt: skip
_MID = ("head_top", "neck_front", "neck_back")
REGIONS_75 = _MID + tuple(f"{s}_{p}" for p in _PAIRS for s in ("l", "r"))

_TO37 = {
    "face": "head_front", "head_back": "head_back", "head_top": "head_back",
    "neck_front": "neck", "neck_back": "neck",
    "chest_upper": "chest", "chest_lower": "chest", "abdomen": "abdomen", "groin": "abdomen",
    "flank": "flank", "upper_back": "upper_back", "mid_back": "upper_back",
    "lower_back": "lower_back", "buttock": "buttock", "shoulder": "shoulder", "armpit": "shoulder",
    "upper_arm_front": "upper_arm", "upper_arm_back": "upper_arm", "elbow_inner": "elbow",
    "elbow_outer": "elbow", "forearm_front": "forearm", "forearm_back": "forearm", "palm": "hand",
    "hand_back": "hand", "thumb": "hand", "fingers_palmar": "hand", "fingers_dorsal": "hand",
    "hip_side": "thigh_front", "thigh_front": "thigh_front", "thigh_inner": "thigh_front",
    "thigh_back": "thigh_back", "knee_front": "knee", "knee_back": "knee", "shin": "shin",
    "calf": "calf", "foot_top": "foot", "sole": "foot", "heel": "foot", "toes": "foot",
}  # fmt: skip
_MID37 = ("head_front", "head_back", "neck")
_PAIRS37 = ("chest", "abdomen", "flank", "upper_back", "lower_back", "buttock", "shoulder",
            "upper_arm", "elbow", "forearm", "hand", "thigh_front", "thigh_back", "knee", "shin",
            "calf", "foot")
REGIONS_37 = _MID37 + tuple(f"{s}_{p}" for p in _PAIRS37 for s in ("l", "r"))
_TO17 = {
    "head_front": "head", "head_back": "head", "neck": "head", "chest": "torso_front",
    "abdomen": "torso_front", "flank": "torso_front", "upper_back": "torso_back",
    "lower_back": "torso_back", "buttock": "torso_back", "shoulder": "shoulder",
    "upper_arm": "upper_arm", "elbow": "forearm", "forearm": "forearm", "hand": "hand",
    "thigh_front": "thigh", "thigh_back": "thigh", "knee": "lower_leg", "shin": "lower_leg",
    "calf": "lower_leg", "foot": "foot",
}  # fmt: skip
_MID17 = ("head", "torso_front", "torso_back")
_PAIRS17 = ("shoulder", "upper_arm", "forearm", "hand", "thigh", "lower_leg", "foot")
REGIONS_17 = _MID17 + tuple(f"{s}_{p}" for p in _PAIRS17 for s in ("l", "r"))
_TO9 = {"head": "head", "torso_front": "torso_front", "torso_back": "torso_back",
        "shoulder": "arm", "upper_arm": "arm", "forearm": "arm", "hand": "hand", "thigh": "leg",
        "lower_leg": "leg", "foot": "leg"}
REGIONS_9 = ("head", "torso_front", "torso_back") + tuple(
    f"{s}_{p}" for p in ("arm", "hand", "leg") for s in ("l", "r"))


def _split(name: str) -> tuple[str, str]:
    return (name[:2], name[2:]) if name[:2] in ("l_", "r_") else ("", name)


def _coarsen(fine: tuple[str, ...], table: dict, coarse: tuple[str, ...]) -> np.ndarray:
    out = []
    for n in fine:
        s, base = _split(n)
        c = table[base]
        out.append(coarse.index(c if c in coarse else s + c))
    return np.array(out, dtype=np.int64)


_G37 = _coarsen(REGIONS_75, _TO37, REGIONS_37)
_G17 = _coarsen(REGIONS_37, _TO17, REGIONS_17)
_G9 = _coarsen(REGIONS_17, _TO9, REGIONS_9)
GROUPING = {75: np.arange(75), 37: _G37, 17: _G17[_G37], 9: _G9[_G17[_G37]]}
NAMES = {75: REGIONS_75, 37: REGIONS_37, 17: REGIONS_17, 9: REGIONS_9}


@dataclasses.dataclass(frozen=True, eq=False)
class RegionMap:
    """names: region names; face_region: (F,) int64 region of each facet (-1 = none).

    ``level`` is 75 for our map (coarsen with :meth:`coarse`), or None for a foreign map."""

    names: tuple[str, ...]
    face_region: np.ndarray
    level: int | None = 75

    def __post_init__(self):
        self.face_region.flags.writeable = False

    def coarse(self, n: int) -> RegionMap:
        """The 37-, 17- or 9-region map (unions of our 75 regions)."""
        if self.level != 75:
            raise ValueError("only our 75-region map has the 37/17/9 groupings")
        g = GROUPING[n]
        fr = np.where(self.face_region >= 0, g[np.maximum(self.face_region, 0)], -1)
        return RegionMap(NAMES[n], fr, n)

    def region_of(self, faces) -> np.ndarray:
        """Facet -> region lookup: faces (...) int -> region ids (...)."""
        return self.face_region[np.asarray(faces)]

    def faces_of(self, region: int | str) -> np.ndarray:
        r = self.names.index(region) if isinstance(region, str) else int(region)
        return np.flatnonzero(self.face_region == r)

    def adjacency(self, faces: np.ndarray) -> np.ndarray:
        """(R, R) bool: regions sharing a mesh edge (faces (F, 3) of the mesh the map is for)."""
        return region_adjacency(faces, self.face_region, len(self.names))


def region_adjacency(faces: np.ndarray, face_region: np.ndarray, num_regions: int) -> np.ndarray:
    """(R, R) symmetric bool matrix, True where two regions share a mesh edge."""
    f = np.asarray(faces)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    fid = np.tile(np.arange(len(f)), 3)
    e = np.sort(e, 1)
    key = e[:, 0].astype(np.int64) * (int(f.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    k, fo = key[order], fid[order]
    same = k[1:] == k[:-1]
    a, b = face_region[fo[:-1][same]], face_region[fo[1:][same]]
    ok = (a >= 0) & (b >= 0) & (a != b)
    A = sp.coo_matrix((np.ones(ok.sum(), bool), (a[ok], b[ok])), shape=(num_regions, num_regions)).toarray()
    return A | A.T


# ----------------------------------------------------------------------------- our map

_ANNY_PARTS = {
    "head": ("head", "eye.L", "eye.R"), "neck": ("neck01", "neck02", "neck03"),
    "torso": ("root", "pelvis.L", "pelvis.R", "spine05", "spine04", "spine03", "spine02", "spine01"),
    "shoulder": ("clavicle", "shoulder01"), "upper_arm": ("upperarm01", "upperarm02"),
    "forearm": ("lowerarm01", "lowerarm02"), "hand": ("wrist", "metacarpal"),
    "thumb": ("finger1-",), "fingers": ("finger2-", "finger3-", "finger4-", "finger5-"),
    "thigh": ("upperleg01", "upperleg02"), "lower_leg": ("lowerleg01", "lowerleg02"),
    "foot": ("foot",), "toes": ("toe",),
}  # fmt: skip
_ANNY_LANDMARKS = {
    "pelvis": "root", "neck": "neck01", "head": "head", "shoulder": "upperarm01.{S}",
    "elbow": "lowerarm01.{S}", "wrist": "wrist.{S}", "mcp3": "finger3-1.{S}",
    "thumb": "finger1-1.{S}", "hip": "upperleg01.{S}", "knee": "lowerleg01.{S}", "ankle": "foot.{S}",
}
_SMPLX_PARTS = {
    "head": ("head", "jaw", "left_eye_smplhf", "right_eye_smplhf"), "neck": ("neck",),
    "torso": ("pelvis", "spine1", "spine2", "spine3"), "shoulder": ("left_collar", "right_collar"),
    "upper_arm": ("left_shoulder", "right_shoulder"), "forearm": ("left_elbow", "right_elbow"),
    "hand": ("left_wrist", "right_wrist", "left_hand", "right_hand"),
    "thumb": ("left_thumb", "right_thumb"),
    "fingers": tuple(f"{s}_{f}" for s in ("left", "right") for f in ("index", "middle", "ring", "pinky")),
    "thigh": ("left_hip", "right_hip"), "lower_leg": ("left_knee", "right_knee"),
    "foot": ("left_ankle", "right_ankle"), "toes": ("left_foot", "right_foot"),
}  # fmt: skip
_SMPLX_LANDMARKS = {
    "pelvis": "pelvis", "neck": "neck", "head": "head", "shoulder": "{side}_shoulder",
    "elbow": "{side}_elbow", "wrist": "{side}_wrist", "mcp3": "{side}_middle1",
    "thumb": "{side}_thumb1", "hip": "{side}_hip", "knee": "{side}_knee", "ankle": "{side}_ankle",
}


def _rig_tables(model: BodyModel):
    if model.name == "anny":
        parts, lm = _ANNY_PARTS, _ANNY_LANDMARKS
    elif model.name in ("smplx", "smplh", "smpl"):
        parts, lm = _SMPLX_PARTS, _SMPLX_LANDMARKS
    else:
        raise ValueError(f"no region rules for rig {model.name!r}")
    part_of = np.full(model.num_joints, -1)
    names = list(parts)
    for j, n in enumerate(model.joint_names):
        for pi, (_, prefixes) in enumerate(parts.items()):
            if any(n == p or n.startswith(p) for p in prefixes):
                part_of[j] = pi
                break
    if np.any(part_of < 0):
        missing = [model.joint_names[j] for j in np.flatnonzero(part_of < 0)]
        raise ValueError(f"joints without a body part: {missing}")

    def landmark(key, s=""):
        t = lm[key].format(S=s.upper(), side={"l": "left", "r": "right"}.get(s, ""))
        return model.joint_template[model.joint_index(t)]

    return names, part_of, landmark


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def region_map(model: BodyModel) -> RegionMap:
    """Our anatomical 75-region map of ``model`` (Anny or an SMPL-family rig). See module doc."""
    names, part_of, lmk = _rig_tables(model)
    V, F = model.v_template, np.asarray(model.faces)
    Wf = np.asarray(model.weights[F[:, 0]] + model.weights[F[:, 1]] + model.weights[F[:, 2]].toarray())
    Wf = np.asarray(Wf)
    # summed weight per part, then the dominant part of each facet
    P = np.zeros((model.num_joints, len(names)))
    P[np.arange(model.num_joints), part_of] = 1
    part = np.argmax(Wf @ P, axis=1)
    # side of limb bones from the dominant joint's name; torso/head/neck from geometry
    dom = np.argmax(Wf, axis=1)
    jside = np.array([1 if (n.endswith(".L") or n.startswith("left_")) else
                      -1 if (n.endswith(".R") or n.startswith("right_")) else 0
                      for n in model.joint_names])
    c = V[F].mean(1)
    n = face_normals(V, F)
    return RegionMap(REGIONS_75, _assign(names, part, jside[dom], c, n, lmk), 75)


def _assign(parts, part, jside, c, n, lmk) -> np.ndarray:
    """The rules: facet centroids c (F, 3), unit normals n (F, 3), part ids, side of the
    dominant joint (+1 left, -1 right, 0 midline), landmark(key, side) -> (3,)."""
    pelvis, neck, head = lmk("pelvis"), lmk("neck"), lmk("head")
    up = _unit(neck - pelvis)
    left = lmk("hip", "l") - lmk("hip", "r")
    left = _unit(left - (left @ up) * up)
    front = np.cross(left, up)
    lat = (c - pelvis) @ left
    fwd = (c - pelvis) @ front
    ht = (c - pelvis) @ up
    out = np.full(len(c), -1, dtype=np.int64)
    R = {name: i for i, name in enumerate(REGIONS_75)}
    geo_side = np.where(lat >= 0, 1, -1)
    side = np.where(jside != 0, jside, geo_side)
    sname = np.where(side > 0, "l_", "r_")

    def put(mask, base):
        idx = np.flatnonzero(mask)
        for i in idx:
            out[i] = R[base] if base in R else R[sname[i] + base]

    P = {p: part == i for i, p in enumerate(parts)}
    # head: top / face / back of head
    hrel = c - head
    top = P["head"] & (hrel @ up > 0.62 * np.max(np.where(P["head"], hrel @ up, -np.inf)))
    put(top, "head_top")
    put(P["head"] & ~top & (hrel @ front > 0.0), "face")
    put(P["head"] & ~top & (hrel @ front <= 0.0), "head_back")
    # neck
    nrel = c - neck
    put(P["neck"] & (nrel @ front > 0), "neck_front")
    put(P["neck"] & (nrel @ front <= 0), "neck_back")
    # torso: height fraction t between pelvis and neck, angle around the spine line
    t = ht / ((neck - pelvis) @ up)
    spine_fwd = np.interp(t, [0, 1], [0.0, (neck - pelvis) @ front])
    phi = np.degrees(np.arctan2(fwd - spine_fwd, np.abs(lat)))
    T = P["torso"]
    fr, bk = T & (phi > 30), T & (phi < -30)
    sd = T & ~fr & ~bk
    put(fr & (t > 0.72), "chest_upper")
    put(fr & (t > 0.5) & (t <= 0.72), "chest_lower")
    put(fr & (t > 0.15) & (t <= 0.5), "abdomen")
    put(fr & (t <= 0.15), "groin")
    put(bk & (t > 0.7), "upper_back")
    put(bk & (t > 0.42) & (t <= 0.7), "mid_back")
    put(bk & (t > 0.15) & (t <= 0.42), "lower_back")
    put(bk & (t <= 0.15), "buttock")
    put(sd & (t > 0.15), "flank")
    put(sd & (t <= 0.15) & (phi >= 0), "groin")
    put(sd & (t <= 0.15) & (phi < 0), "buttock")
    put(P["shoulder"], "shoulder")

    # limbs: per side, axial fraction along the bone and angle around it
    for s, sgn in (("l", 1), ("r", -1)):
        on = side == sgn
        sh, el, wr = lmk("shoulder", s), lmk("elbow", s), lmk("wrist", s)
        m3, th = lmk("mcp3", s), lmk("thumb", s)
        hp, kn, an = lmk("hip", s), lmk("knee", s), lmk("ankle", s)
        fdir = _unit(m3 - wr)
        rdir = th - wr
        rdir = _unit(rdir - (rdir @ fdir) * fdir)
        dorsal = np.cross(fdir, rdir) * (-1.0 if s == "l" else 1.0)
        lateral = left * sgn

        def frame(a, b, ref):
            ax = _unit(b - a)
            f0 = _unit(ref - (ref @ ax) * ax)
            return ax, f0, np.cross(ax, f0)

        def axial(a, b):
            return ((c - a) @ _unit(b - a)) / np.linalg.norm(b - a)

        def around(a, b, ref, outward):
            """Angle (deg) of the facet around the bone a->b from ref; + towards ``outward``."""
            ax, f0, f1 = frame(a, b, ref)
            r = c - a
            r = r - np.outer(r @ ax, ax)
            ang = np.degrees(np.arctan2(r @ f1, r @ f0))
            return ang if (np.cross(ax, f0) @ outward) >= 0 else -ang

        # upper arm: front/back about the body's front; armpit = medial top; elbow at the end
        U = P["upper_arm"] & on
        a = axial(sh, el)
        ang = around(sh, el, front, lateral)
        medial = np.abs(ang) > 100
        put(U & (a < 0.3) & medial, "armpit")
        rest = U & ~((a < 0.3) & medial)
        put(rest & (a > 0.88) & (np.abs(ang) <= 90), "elbow_inner")
        put(rest & (a > 0.88) & (np.abs(ang) > 90), "elbow_outer")
        mid = rest & (a <= 0.88)
        put(mid & (np.abs(ang) <= 90), "upper_arm_front")
        put(mid & (np.abs(ang) > 90), "upper_arm_back")
        # forearm: palmar (front) vs dorsal (back) from the hand's dorsal direction
        Fa = P["forearm"] & on
        a = axial(el, wr)
        pal = (c - el) @ dorsal < ((wr - el) @ dorsal) * np.clip(a, 0, 1)
        put(Fa & (a < 0.12) & pal, "elbow_inner")
        put(Fa & (a < 0.12) & ~pal, "elbow_outer")
        put(Fa & (a >= 0.12) & pal, "forearm_front")
        put(Fa & (a >= 0.12) & ~pal, "forearm_back")
        hc_ = 0.5 * (wr + m3)
        pal_h = (c - hc_) @ dorsal < 0
        put(P["hand"] & on & pal_h, "palm")
        put(P["hand"] & on & ~pal_h, "hand_back")
        put(P["thumb"] & on, "thumb")
        put(P["fingers"] & on & ((n @ dorsal) < 0), "fingers_palmar")
        put(P["fingers"] & on & ((n @ dorsal) >= 0), "fingers_dorsal")
        # thigh: hip side (lateral top), buttock fold (back top), front / back / inner, knee
        Th = P["thigh"] & on
        a = axial(hp, kn)
        ang = around(hp, kn, front, lateral)  # 0 front, +90 lateral, -90 medial, 180 back
        put(Th & (a < 0.3) & (ang > 45) & (ang <= 135), "hip_side")
        put(Th & (a < 0.12) & (np.abs(ang) > 135), "buttock")
        put(Th & (a < 0.12) & (np.abs(ang) <= 45), "groin")
        put(Th & (a < 0.12) & (ang < -45) & (ang >= -135), "groin")
        body = Th & (a >= 0.12) & ~((a < 0.3) & (ang > 45) & (ang <= 135))
        knee = body & (a > 0.88)
        put(knee & (np.abs(ang) <= 90), "knee_front")
        put(knee & (np.abs(ang) > 90), "knee_back")
        body &= ~knee
        put(body & (np.abs(ang) <= 45), "thigh_front")
        put(body & (ang > 45) & (ang <= 135), "thigh_front")
        put(body & (np.abs(ang) > 135), "thigh_back")
        put(body & (ang < -45) & (ang >= -135), "thigh_inner")
        # lower leg: knee top, shin front, calf back
        L = P["lower_leg"] & on
        a = axial(kn, an)
        ang = around(kn, an, front, lateral)
        put(L & (a < 0.1) & (np.abs(ang) <= 90), "knee_front")
        put(L & (a < 0.1) & (np.abs(ang) > 90), "knee_back")
        put(L & (a >= 0.1) & (np.abs(ang) <= 90), "shin")
        put(L & (a >= 0.1) & (np.abs(ang) > 90), "calf")
        # foot: sole (facing down), heel (behind the ankle), top; toes
        Fo = P["foot"] & on
        down = (n @ up) < -0.6
        behind = (c - an) @ front < -0.01
        put(Fo & down, "sole")
        put(Fo & ~down & behind, "heel")
        put(Fo & ~down & ~behind, "foot_top")
        put(P["toes"] & on, "toes")
    # anything left (rare: parts not on a side) takes the region of its nearest assigned facet
    miss = np.flatnonzero(out < 0)
    if len(miss):
        from scipy.spatial import cKDTree

        done = np.flatnonzero(out >= 0)
        _, k = cKDTree(c[done]).query(c[miss])
        out[miss] = out[done[k]]
    return out


# ----------------------------------------------------------------------------- official file


def load_official(path: str | Path, mesh: str = "smplx", num_faces: int | None = None) -> RegionMap:
    """Read CHI3D's ``contact_regions.json``; ``mesh`` = "smplx" or "ghum" picks
    ``rid_to_smplx_fids`` / ``rid_to_ghum_fids`` (a list of 75 facet lists, or a dict keyed by
    region id). num_faces: the mesh's face count (checked; default: max id + 1). InputError
    names the file and the key on a bad file."""
    path = Path(path)
    key = {"smplx": "rid_to_smplx_fids", "ghum": "rid_to_ghum_fids"}.get(mesh)
    if key is None:
        raise ValueError(f"mesh must be smplx or ghum, got {mesh!r}")
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, "-", f"cannot read contact regions: {e}") from e
    if not isinstance(doc, dict) or key not in doc:
        raise InputError(path, key, "missing")
    raw = doc[key]
    if isinstance(raw, dict):
        try:
            items = sorted(((int(k), v) for k, v in raw.items()), key=lambda kv: kv[0])
        except ValueError as e:
            raise InputError(path, key, f"region ids must be integers: {e}") from e
        if [k for k, _ in items] != list(range(len(items))):
            raise InputError(path, key, "region ids must be 0..R-1")
        lists = [v for _, v in items]
    elif isinstance(raw, list):
        lists = raw
    else:
        raise InputError(path, key, f"expected a list or a dict, got {type(raw).__name__}")
    try:
        arrs = [np.asarray(v, dtype=np.int64).ravel() for v in lists]
    except (TypeError, ValueError) as e:
        raise InputError(path, key, f"facet ids must be integers: {e}") from e
    top = max((int(a.max()) for a in arrs if a.size), default=-1)
    nf = num_faces if num_faces is not None else top + 1
    if top >= nf or any(a.size and a.min() < 0 for a in arrs):
        raise InputError(path, key, f"facet id outside [0, {nf})")
    fr = np.full(nf, -1, dtype=np.int64)
    for r, a in enumerate(arrs):
        if np.any(fr[a] >= 0):
            raise InputError(path, f"{key}[{r}]", "facets already in another region")
        fr[a] = r
    return RegionMap(tuple(f"r{r:02d}" for r in range(len(arrs))), fr, None)


def region_colors(num: int, seed: int = 0) -> np.ndarray:
    """(num, 3) distinct colours in [0, 1] (golden-angle hues, alternating lightness)."""
    h = (np.arange(num) * 0.618033988749895 + seed * 0.1) % 1.0
    import colorsys

    return np.array([colorsys.hls_to_rgb(x, 0.45 + 0.2 * (i % 3 == 1) - 0.12 * (i % 3 == 2), 0.75)
                     for i, x in enumerate(h)])


def render_png(model: BodyModel, rmap: RegionMap, path: str | Path, size: int = 700) -> None:
    """Render the regions on the model's rest mesh (betas 0), front and back side by side,
    into a PNG (pyrender offscreen; set PYOPENGL_PLATFORM=egl on a headless machine)."""
    import os

    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import pyrender
    import trimesh
    from PIL import Image, ImageDraw

    V = np.asarray(model.v_template)
    F = np.asarray(model.faces)
    cols = region_colors(len(rmap.names))
    fc = np.ones((len(F), 4))
    fc[:, :3] = np.where(rmap.face_region[:, None] >= 0, cols[np.maximum(rmap.face_region, 0)], 0.5)
    # body frame: z-up models (Anny) vs y-up (SMPL family files from the real world)
    up = np.array([0.0, 0.0, 1.0]) if np.ptp(V[:, 2]) > np.ptp(V[:, 1]) else np.array([0.0, 1.0, 0.0])
    mesh = trimesh.Trimesh(V, F, face_colors=(fc * 255).astype(np.uint8), process=False)
    centre = 0.5 * (V.min(0) + V.max(0))
    height = np.ptp(V @ up)
    # the body faces -y (Anny) or +z (SMPL): front = cross(+x (left), up)
    front = np.cross([1.0, 0.0, 0.0], up)
    images = []
    for sgn in (1, -1):
        scene = pyrender.Scene(ambient_light=[0.55, 0.55, 0.55], bg_color=[1, 1, 1, 1])
        scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
        eye = centre + sgn * front * 0.58 * height / np.tan(np.radians(11))
        z = _unit(eye - centre)
        x = _unit(np.cross(up, z))
        y = np.cross(z, x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, y, z], 1)
        pose[:3, 3] = eye
        scene.add(pyrender.PerspectiveCamera(yfov=np.radians(22)), pose=pose)
        scene.add(pyrender.DirectionalLight(intensity=2.5), pose=pose)
        r = pyrender.OffscreenRenderer(size, size)
        img, depth = r.render(scene)
        r.delete()
        img = img.copy()
        img[depth == 0] = 255
        im = Image.fromarray(img)
        ImageDraw.Draw(im).text((10, 10), "front" if sgn > 0 else "back", fill=(0, 0, 0))
        images.append(im)
    out = Image.new("RGB", (2 * size, size), "white")
    out.paste(images[0], (0, 0))
    out.paste(images[1], (size, 0))
    out.save(path)
