"""The studio's ground truth in the CHI3D layout, so ``python -m evaluate`` can score a release
against it: from ``gt/<group>/<action>.npz`` (see ``studio.session``), write under ``gt/<group>/``

- ``anny/<action>.json``: the true Anny parameters (``formats.anny_json``), person 0 = the
  marker wearer (CHI3D), betas repeated per frame;
- ``valid/<action>.json``: every person-frame valid (the truth is known everywhere);
- ``camera_parameters/<camera>/<action>.json``: the true cameras: a copy of the session's
  calibration, or of ``true/camera_parameters/`` (written by generate) when the recipe's
  calibration was perturbed (``SessionPlan.calib_error``);
- ``interaction_contact_signature.json``: a copy of the session's.

``joints3d_25/<action>.json`` is written by the studio's generate itself. Idempotent (a file
whose content would not change is not rewritten) and atomic (temporary file + rename). Never
regenerates the session's inputs.
"""
from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

import numpy as np

from formats.errors import InputError

CONTACT_FILE = "interaction_contact_signature.json"


def _atomic_bytes(path: Path, data: bytes) -> bool:
    """Write ``data`` to ``path`` unless it already holds exactly that; True if written."""
    if path.is_file() and path.read_bytes() == data:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return True


def truth_files(session_dir: str | Path) -> list[Path]:
    """The CHI3D-layout truth files :func:`write_chi3d_truth` writes for a generated session."""
    session_dir = Path(session_dir)
    out = []
    for npz in sorted((session_dir / "gt").glob("*/*.npz")):
        group, action = npz.parent.name, npz.stem
        if group == "subjects" or not (session_dir / group / "camera_parameters").is_dir():
            continue  # marker-only sessions have no cameras and no CHI3D truth
        g = session_dir / "gt" / group
        out += [g / "anny" / f"{action}.json", g / "valid" / f"{action}.json"]
        for cam in sorted((session_dir / group / "camera_parameters").glob(f"*/{action}.json")):
            out.append(g / "camera_parameters" / cam.parent.name / f"{action}.json")
        if (session_dir / group / CONTACT_FILE).is_file():
            out.append(g / CONTACT_FILE)
    return sorted(set(out))


def _wearers(session_dir: Path) -> dict[str, str]:
    meta = session_dir / "gt" / "session.json"
    try:
        seqs = json.loads(meta.read_text())["sequences"]
    except (OSError, ValueError, KeyError) as e:
        raise InputError(meta, "sequences", f"cannot read the session's facts: {e}") from None
    return {k: v["markers_on"] for k, v in seqs.items() if "markers_on" in v}


def write_chi3d_truth(session_dir: str | Path, model=None) -> list[Path]:
    """Write the CHI3D-layout truth of a generated two-person session (module doc). model: the
    Anny BodyModel (for its joint names; loaded when None). Person order: person 0 wears the
    markers, checked against ``gt/session.json``'s ``markers_on`` and reordered if the npz's
    ``subjects`` disagree. Returns the files written (those already up to date are skipped)."""
    from body import load_model
    from body.rotations import rodrigues
    from formats.anny_json import write_anny

    session_dir = Path(session_dir)
    wearers = _wearers(session_dir)
    names = None
    written = []
    for npz in sorted((session_dir / "gt").glob("*/*.npz")):
        group, action = npz.parent.name, npz.stem
        if group == "subjects" or not (session_dir / group / "camera_parameters").is_dir():
            continue
        seq_id = f"{group}/{action}"
        g = session_dir / "gt" / group
        with np.load(npz, allow_pickle=False) as z:
            if "body_pose" not in z.files or z["body_pose"].ndim != 4:
                continue  # a marker-only trial (one person, no CHI3D truth)
            subjects = [str(s) for s in z["subjects"]]
            order = list(range(len(subjects)))
            want = wearers.get(seq_id)
            if want is not None:
                if want not in subjects:
                    raise InputError(npz, "subjects", f"{subjects} lack the marker wearer {want!r} "
                                     "of gt/session.json")
                order = [subjects.index(want)] + [i for i in order if subjects[i] != want]
            F = z["transl"].shape[1]
            body_pose = z["body_pose"][order]
            arrays = dict(transl=z["transl"][order], global_orient=z["global_orient"][order],
                          body_pose=rodrigues(body_pose),
                          betas=np.repeat(z["betas"][order][:, None, :], F, axis=1))
        if names is None:
            model = model or load_model("anny")
            names = list(model.joint_names)
        if body_pose.shape[2] != len(names):
            raise InputError(npz, "body_pose", f"{body_pose.shape[2]} joints, the Anny model has "
                             f"{len(names)}")
        tmp = g / "anny" / f".{action}.json.build"
        write_anny(tmp, **arrays, joint_names=names)
        data = tmp.read_bytes()
        tmp.unlink()
        target = g / "anny" / f"{action}.json"
        if _atomic_bytes(target, data):
            written.append(target)
        valid = {"valid": [[True] * F for _ in order], "reason": [[""] * F for _ in order],
                 "frames": list(range(F))}
        target = g / "valid" / f"{action}.json"
        if _atomic_bytes(target, json.dumps(valid).encode()):
            written.append(target)
        for cam in sorted((session_dir / group / "camera_parameters").glob(f"*/{action}.json")):
            target = g / "camera_parameters" / cam.parent.name / f"{action}.json"
            # the true camera when the recipe's calibration is not (SessionPlan.calib_error)
            true = g / "true" / "camera_parameters" / cam.parent.name / f"{action}.json"
            if _atomic_bytes(target, (true if true.is_file() else cam).read_bytes()):
                written.append(target)
        src = session_dir / group / CONTACT_FILE
        if src.is_file() and _atomic_bytes(g / CONTACT_FILE, src.read_bytes()):
            written.append(g / CONTACT_FILE)
    return written


def ensure_truth(session_dir: str | Path) -> list[Path]:
    """Write the CHI3D truth of an already generated session when any of its files is missing
    (never touches the session's inputs). Returns the files written."""
    session_dir = Path(session_dir)
    files = truth_files(session_dir)
    if all(f.is_file() for f in files):  # complete, or no per-sequence truth to lay out
        return []
    return write_chi3d_truth(session_dir)


__all__ = ["ensure_truth", "truth_files", "write_chi3d_truth"]
