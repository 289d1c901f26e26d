"""CHI3D release files: ``joints3d_25/<action>.json``, ``smplx/<action>.json`` and
``interaction_contact_signature.json`` (see ``shared/FORMATS.md``). Readers validate shapes and
values and raise :class:`formats.errors.InputError` naming file, field and frame; writers
produce what code written for the real release reads (nested lists, person axis first).

Person 0 wears the markers, person 1 does not. World: metres, z-up.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from formats.errors import InputError

#: SMPL-X keys of ``smplx/<action>.json`` and the per-frame shape of each (after the person
#: and frame axes). Rotations are 3x3 matrices.
SMPLX_SHAPES: dict[str, tuple[int, ...]] = {
    "transl": (3,),
    "global_orient": (1, 3, 3),
    "body_pose": (21, 3, 3),
    "betas": (10,),
    "left_hand_pose": (15, 3, 3),
    "right_hand_pose": (15, 3, 3),
    "jaw_pose": (1, 3, 3),
    "leye_pose": (1, 3, 3),
    "reye_pose": (1, 3, 3),
    "expression": (10,),
}
ROTATION_TOL = 1e-4  # |R R^T - I| and |det R - 1| allowed in a stored rotation matrix


def _load(path: Path):
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(path, "<file>", f"cannot read: {e.strerror or e}") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(path, "<json>", f"invalid or truncated JSON: {e}") from None
    if not isinstance(d, dict):
        raise InputError(path, "<json>", f"expected an object, got {type(d).__name__}")
    return d


def _array(path, name: str, value, tail: tuple[int, ...]) -> np.ndarray:
    """(P, F, *tail) float64 array, checked; NaN/inf -> InputError naming the first frame."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, name, "not a rectangular numeric array (ragged or non-numbers)") from None
    if a.ndim != 2 + len(tail) or a.shape[2:] != tail or a.shape[0] not in (1, 2):
        want = ", ".join(["P", "F"] + [str(t) for t in tail])
        raise InputError(path, name, f"expected shape ({want}) with P in 1..2, got {a.shape}")
    bad = ~np.isfinite(a).reshape(a.shape[0], a.shape[1], -1).all(axis=(0, 2))
    if bad.any():
        raise InputError(path, name, "NaN or inf", frame=int(np.flatnonzero(bad)[0]))
    return a


def _dump(path: Path, d) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d, allow_nan=False))
    return path


# --------------------------------------------------------------------------------- joints3d_25
def read_joints3d_25(path: str | Path) -> np.ndarray:
    """``{"joints3d_25": (P, F, 25, 3)}`` -> (P, F, 25, 3) float64, world metres
    (P = 2 in CHI3D; 1 accepted for single-person sets)."""
    path = Path(path)
    d = _load(path)
    if "joints3d_25" not in d:
        raise InputError(path, "joints3d_25", "missing")
    return _array(path, "joints3d_25", d["joints3d_25"], (25, 3))


def write_joints3d_25(path: str | Path, joints: np.ndarray) -> Path:
    """joints: (P, F, 25, 3) world metres, finite."""
    j = _array("<memory>", "joints3d_25", joints, (25, 3))
    return _dump(path, {"joints3d_25": j.tolist()})


# ---------------------------------------------------------------------------------------- smplx
def read_smplx(path: str | Path) -> dict[str, np.ndarray]:
    """CHI3D ``smplx/<action>.json`` -> {key: (P, F, *SMPLX_SHAPES[key]) float64}.

    Every key of :data:`SMPLX_SHAPES` is required; P and F must agree across keys; rotation
    matrices must be orthonormal with det +1 (to ``ROTATION_TOL``).
    """
    path = Path(path)
    d = _load(path)
    out: dict[str, np.ndarray] = {}
    for key, tail in SMPLX_SHAPES.items():
        if key not in d:
            raise InputError(path, key, "missing")
        out[key] = _array(path, key, d[key], tail)
    _check_consistent(path, out)
    return out


def _check_consistent(path, params: Mapping[str, np.ndarray]) -> None:
    ref_key = "transl"
    P, F = params[ref_key].shape[:2]
    for key, a in params.items():
        if a.shape[:2] != (P, F):
            raise InputError(path, key, f"(persons, frames) {a.shape[:2]} != {ref_key}'s {(P, F)}")
        if SMPLX_SHAPES.get(key, ())[-2:] == (3, 3):  # by the key's layout, not the array's tail
            err = np.abs(a @ np.swapaxes(a, -1, -2) - np.eye(3)).max(axis=(-1, -2))
            err = np.maximum(err, np.abs(np.linalg.det(a) - 1.0))
            bad = (err > ROTATION_TOL).reshape(P, F, -1).any(axis=(0, 2))
            if bad.any():
                raise InputError(path, key, "not a rotation matrix (R R^T != I or det != 1)",
                                 frame=int(np.flatnonzero(bad)[0]))


def write_smplx(path: str | Path, params: Mapping[str, np.ndarray]) -> Path:
    """params: every key of :data:`SMPLX_SHAPES`, each (P, F, *shape); rotations as 3x3."""
    checked = {}
    for key, tail in SMPLX_SHAPES.items():
        if key not in params:
            raise InputError("<memory>", key, "missing")
        checked[key] = _array("<memory>", key, params[key], tail)
    _check_consistent("<memory>", checked)
    return _dump(path, {k: v.tolist() for k, v in checked.items()})


def smplx_in_camera(global_orient: np.ndarray, transl: np.ndarray, pelvis: np.ndarray, cam):
    """Express SMPL-X root parameters in a camera frame (the release's convention).

    global_orient: (..., 3, 3) world rotation; transl: (..., 3) metres; pelvis: (..., 3) rest
    root joint ``J_0(betas)`` (body-model frame, metres); cam: calib Camera.
    Returns ``(R @ global_orient, (transl + pelvis - T) @ R.T - pelvis)``.
    """
    R, T = cam.R, cam.T
    return R @ np.asarray(global_orient), (np.asarray(transl) + pelvis - T) @ R.T - pelvis


# ---------------------------------------------------------------------------- contact signatures
@dataclass(frozen=True, eq=False)
class ContactSignature:
    """One action's contact annotation.

    fr_id: the annotated contact frame; start_fr, end_fr: the contact interval (None when the
    file has none); smplx_regions, smplx_faces, ghum_regions, ghum_faces: (N, 2) int64 pairs
    (person 0's region/facet, person 1's region/facet) that touch. anny_regions, anny_faces,
    anny_region_names: the studio's ``anny_signature`` on the Anny mesh (names: (N,) pairs of
    region names, empty when the file gives none). Only the families in :data:`FAMILIES`.
    """

    fr_id: int
    smplx_regions: np.ndarray
    smplx_faces: np.ndarray
    ghum_regions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    ghum_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    start_fr: int | None = None
    end_fr: int | None = None
    anny_regions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    anny_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    anny_region_names: tuple[tuple[str, str], ...] = ()

    def regions(self, family: str) -> np.ndarray:
        """(N, 2) region-id pairs of ``family`` (``"smplx"``, ``"ghum"``, ``"anny"``)."""
        return getattr(self, f"{_family(family)}_regions")

    def faces(self, family: str) -> np.ndarray:
        """(N, 2) facet-id pairs of ``family``."""
        return getattr(self, f"{_family(family)}_faces")

    def families(self) -> tuple[str, ...]:
        """The families with at least one region or facet pair."""
        return tuple(f for f in FAMILIES if len(self.regions(f)) or len(self.faces(f)))


#: Body-model families a signature can be given for (``<family>_signature`` in the file).
FAMILIES = ("smplx", "ghum", "anny")


def _family(family: str) -> str:
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
    return family


def _names(path, name: str, value, n: int, frame: int | None) -> tuple[tuple[str, str], ...]:
    if value is None:
        return ()
    if (not isinstance(value, list) or len(value) != n
            or any(not isinstance(p, list) or len(p) != 2 or not all(isinstance(x, str) for x in p)
                   for p in value)):
        raise InputError(path, name, f"expected {n} [person0, person1] pairs of region names "
                         "(one per region_id pair)", frame)
    return tuple((a, b) for a, b in value)


def _pairs(path, name: str, value, frame: int | None) -> np.ndarray:
    a = np.array(value if value is not None else [], dtype=object)
    if a.size == 0:
        return np.zeros((0, 2), np.int64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise InputError(path, name, f"expected a list of [person0, person1] pairs, got shape "
                         f"{a.shape}", frame)
    try:
        f = a.astype(np.float64)
    except (TypeError, ValueError):
        raise InputError(path, name, "not numbers", frame) from None
    if not np.all(np.isfinite(f)) or np.any(f != np.round(f)) or np.any(f < 0):
        raise InputError(path, name, "ids must be non-negative integers", frame)
    return f.astype(np.int64)


def _int(path, name: str, v, frame: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v < 0:
        raise InputError(path, name, f"expected a non-negative integer frame, got {v!r}", frame)
    return int(v)


def read_contact_signatures(path: str | Path) -> dict[str, ContactSignature]:
    """``interaction_contact_signature.json`` -> {action: ContactSignature}.

    ``fr_id`` and ``smplx_signature`` are required; ``ghum_signature``, ``anny_signature``
    (the studio's, with ``region_names`` beside ``region_id``), ``start_fr``, ``end_fr``
    optional; when given, ``start_fr <= fr_id <= end_fr``. Ids are checked here only for being
    non-negative integers; against a body model by ``fitting.contact_signature.load_contact``.
    """
    path = Path(path)
    d = _load(path)
    out = {}
    for action, a in d.items():
        if not isinstance(a, dict):
            raise InputError(path, action, "expected an object")
        if "fr_id" not in a:
            raise InputError(path, f"{action}.fr_id", "missing")
        fr = _int(path, f"{action}.fr_id", a["fr_id"])
        start = _int(path, f"{action}.start_fr", a["start_fr"], fr) if "start_fr" in a else None
        end = _int(path, f"{action}.end_fr", a["end_fr"], fr) if "end_fr" in a else None
        if (start is not None and start > fr) or (end is not None and end < fr):
            raise InputError(path, f"{action}.start_fr/end_fr",
                             f"contact frame outside the interval {start}..{end}", fr)
        sig = {}
        for model in FAMILIES:
            key = f"{model}_signature"
            s = a.get(key)
            if s is None:
                if model == "smplx":
                    raise InputError(path, f"{action}.{key}", "missing", fr)
                s = {}
            if not isinstance(s, dict):
                raise InputError(path, f"{action}.{key}", "expected an object", fr)
            for kind, fieldname in (("region_id", "regions"), ("face_id", "faces")):
                if model == "smplx" and kind not in s:
                    raise InputError(path, f"{action}.{key}.{kind}", "missing", fr)
                sig[f"{model}_{fieldname}"] = _pairs(path, f"{action}.{key}.{kind}", s.get(kind), fr)
            if model == "anny":
                sig["anny_region_names"] = _names(path, f"{action}.{key}.region_names",
                                                  s.get("region_names"), len(sig["anny_regions"]), fr)
        out[action] = ContactSignature(fr_id=fr, start_fr=start, end_fr=end, **sig)
    return out


def write_contact_signatures(path: str | Path, signatures: Mapping[str, ContactSignature]) -> Path:
    """Write {action: ContactSignature} as ``interaction_contact_signature.json`` (both the
    smplx and ghum signatures, empty lists where none; the anny signature, with its
    ``region_names`` when known, only when it has pairs; start/end only when known)."""
    d = {}
    for action, s in signatures.items():
        e: dict = {"fr_id": int(s.fr_id)}
        if s.start_fr is not None:
            e["start_fr"] = int(s.start_fr)
        if s.end_fr is not None:
            e["end_fr"] = int(s.end_fr)
        for model in ("ghum", "smplx"):
            e[f"{model}_signature"] = {
                "region_id": np.asarray(getattr(s, f"{model}_regions"), np.int64).reshape(-1, 2).tolist(),
                "face_id": np.asarray(getattr(s, f"{model}_faces"), np.int64).reshape(-1, 2).tolist()}
        if len(s.anny_regions) or len(s.anny_faces):
            e["anny_signature"] = {
                "region_id": np.asarray(s.anny_regions, np.int64).reshape(-1, 2).tolist(),
                "face_id": np.asarray(s.anny_faces, np.int64).reshape(-1, 2).tolist()}
            if s.anny_region_names:
                e["anny_signature"]["region_names"] = [list(p) for p in s.anny_region_names]
        d[action] = e
    return _dump(path, d)
