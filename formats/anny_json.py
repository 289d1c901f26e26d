"""Anny parameters in a CHI3D-style JSON file: ``<group>/anny/<action>.json``.

The release's twin of ``smplx/<action>.json`` for the body model the fits were made with (Anny),
so a user can pose the exact fitted mesh with ``body.forward`` instead of the SMPL-X conversion::

    {"transl": (P, F, 3), "global_orient": (P, F, 3, 3), "body_pose": (P, F, J, 3, 3),
     "betas": (P, F, S), "joint_names": [J names]}

Person axis first (person 0 wears the markers), metres, world z-up, rotations as 3x3 matrices
(``body.rotations.rodrigues`` / ``rotmat_to_rotvec`` convert from/to the axis-angle that
``body.forward`` takes); ``body_pose[:, :, j]`` is joint ``joint_names[j]``'s local rotation,
entry 0 the root (normally identity; the global rotation is ``global_orient``). Strict JSON
(no NaN). Readers raise :class:`formats.errors.InputError` naming file, field and frame.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from formats.errors import InputError
from formats.keypoints import load_json

#: Keys of the file and each one's layout after the (persons, frames) axes.
ANNY_KEYS = ("transl", "global_orient", "body_pose", "betas")
ROTATION_TOL = 1e-4  # |R R^T - I| and |det R - 1| allowed in a stored rotation matrix


def _array(path, name: str, value, ndim: int) -> np.ndarray:
    """float64 array with ``ndim`` dims and P in 1..2, finite (else InputError naming the frame)."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, name, "not a rectangular numeric array (ragged or non-numbers)") from None
    if a.ndim != ndim or a.shape[0] not in (1, 2):
        raise InputError(path, name, f"expected {ndim} axes (persons first, P in 1..2), got shape {a.shape}")
    if a.shape[1] == 0:
        raise InputError(path, name, "no frames")
    bad = ~np.isfinite(a).reshape(a.shape[0], a.shape[1], -1).all(axis=(0, 2))
    if bad.any():
        raise InputError(path, name, "NaN or inf", frame=int(np.flatnonzero(bad)[0]))
    return a


def _check(path, transl, global_orient, body_pose, betas, joint_names) -> dict:
    out = {
        "transl": _array(path, "transl", transl, 3),
        "global_orient": _array(path, "global_orient", global_orient, 4),
        "body_pose": _array(path, "body_pose", body_pose, 5),
        "betas": _array(path, "betas", betas, 3),
    }
    P, F = out["transl"].shape[:2]
    if out["transl"].shape[2] != 3:
        raise InputError(path, "transl", f"expected shape (P, F, 3), got {out['transl'].shape}")
    if out["global_orient"].shape[2:] != (3, 3):
        raise InputError(path, "global_orient",
                         f"expected shape (P, F, 3, 3), got {out['global_orient'].shape}")
    if out["body_pose"].shape[3:] != (3, 3):
        raise InputError(path, "body_pose", f"expected shape (P, F, J, 3, 3), got {out['body_pose'].shape}")
    for key, a in out.items():
        if a.shape[:2] != (P, F):
            raise InputError(path, key, f"(persons, frames) {a.shape[:2]} != transl's {(P, F)}")
    if not isinstance(joint_names, (list, tuple)) or not all(isinstance(n, str) for n in joint_names):
        raise InputError(path, "joint_names", "expected a list of strings")
    J = out["body_pose"].shape[2]
    if len(joint_names) != J:
        raise InputError(path, "joint_names", f"{len(joint_names)} names for body_pose's {J} joints")
    for key in ("global_orient", "body_pose"):
        a = out[key]
        err = np.abs(a @ np.swapaxes(a, -1, -2) - np.eye(3)).max(axis=(-1, -2))
        err = np.maximum(err, np.abs(np.linalg.det(a) - 1.0))
        bad = (err > ROTATION_TOL).reshape(P, F, -1).any(axis=(0, 2))
        if bad.any():
            raise InputError(path, key, "not a rotation matrix (R R^T != I or det != 1)",
                             frame=int(np.flatnonzero(bad)[0]))
    out["joint_names"] = tuple(joint_names)
    return out


def write_anny(path: str | Path, transl, global_orient, body_pose, betas, joint_names) -> Path:
    """Write ``anny/<action>.json``. transl (P, F, 3) m; global_orient (P, F, 3, 3);
    body_pose (P, F, J, 3, 3) local rotations (entry 0 = root); betas (P, F, S);
    joint_names: J names. Validated like :func:`read_anny` (InputError on ``<memory>``)."""
    d = _check("<memory>", transl, global_orient, body_pose, betas, joint_names)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {k: d[k].tolist() for k in ANNY_KEYS}
    doc["joint_names"] = list(d["joint_names"])
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, allow_nan=False))
    tmp.replace(path)
    return path


def read_anny(path: str | Path) -> dict:
    """``anny/<action>.json`` -> {transl (P, F, 3), global_orient (P, F, 3, 3),
    body_pose (P, F, J, 3, 3), betas (P, F, S): float64 arrays, joint_names: tuple of J str}."""
    path = Path(path)
    d = load_json(path)
    if not isinstance(d, dict):
        raise InputError(path, "<json>", f"expected an object, got {type(d).__name__}")
    for key in ANNY_KEYS + ("joint_names",):
        if key not in d:
            raise InputError(path, key, "missing")
    return _check(path, d["transl"], d["global_orient"], d["body_pose"], d["betas"], d["joint_names"])

