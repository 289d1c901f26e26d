"""Reading two folders in the CHI3D layout for the evaluator (``../shared/FORMATS.md``).

A *root* holds subject folders (a subject folder is any folder with a ``joints3d_25/``
sub-folder: the root itself, ``<root>/<subject>`` or ``<root>/<split>/<subject>``). The truth
defines the sequences ``<subject>/<action>``; the prediction must have each of them.

Per subject and action:

- ``joints3d_25/<action>.json`` (required; ``formats.chi3d.read_joints3d_25``): ``(P, F, 25, 3)``.
- vertices (optional), the first that applies of: ``anny/<action>.json``
  (``formats.anny_json``) posed with the Anny model, when BOTH sides have one (the same mesh on
  both sides); ``smplx/<action>.json`` with an SMPL-X model file (``--smplx-model`` /
  ``$SMPLX_MODEL_PATH``), posed by ``body.forward``; ``vertices/<action>.npz`` with
  ``vertices (P, F, V, 3)`` and ``root (P, F, 3)`` (the model's joint 0), metres, world. The
  result names the mesh used (``Vertices.mesh``: ``anny``, ``smplx`` or ``vertices npz``).
- truth only: ``camera_parameters/<camera>/<action>.json`` (the matching camera: the first
  serial; taken from the prediction's folder when the truth has none),
  ``interaction_contact_signature.json`` (the contact interval), ``valid/<action>.json``
  (``{"valid": (P, F) or (F,) booleans}``: frames published as ground truth; absent = all).
- prediction's ``valid/<action>.json`` (a release's): the person-frames it publishes; the others
  are not scored and are counted as excluded (``SequenceData.valid`` on the prediction side).

Errors are ``formats.errors.InputError`` naming the file and the field.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from body import forward, load_model
from body.rotations import rotmat_to_rotvec
from body.smplfamily import smplx_betas, smplx_pose
from calib.camera import Camera
from calib.io import read_chi3d_cameras
from evaluate import constants as K
from formats.chi3d import ContactSignature, read_contact_signatures, read_joints3d_25, read_smplx
from formats.errors import InputError


@dataclass(frozen=True, eq=False)
class Vertices:
    """Posed meshes of every person: ``vertices (P, F, V, 3)``, ``root (P, F, 3)`` (model joint
    0), metres, world; ``source``: the file they came from."""

    vertices: np.ndarray
    root: np.ndarray
    source: str
    mesh: str = "vertices npz"


@dataclass(frozen=True, eq=False)
class SequenceData:
    """One side (prediction or truth) of one sequence.

    joints: (P, F, 25, 3) metres; vertices: posed meshes or None, with ``vertices_note`` saying
    why not; valid: (P, F) bool (truth: all True when no mask file; prediction: the frames it
    publishes, None when it has no mask file); camera and contact: truth
    only (None for a prediction); files: {what: path} for messages."""

    name: str
    joints: np.ndarray
    files: dict
    vertices: Vertices | None = None
    vertices_note: str = ""
    valid: np.ndarray | None = None
    camera: Camera | None = None
    contact: ContactSignature | None = None
    contact_note: str = ""
    frame_ids: np.ndarray | None = None  # truth: its frame numbers kept (None: 0..F-1)


# ------------------------------------------------------------------------------------ discovery
def subject_dirs(root: str | Path) -> dict[str, Path]:
    """{relative name ("." for the root itself): folder} of the subject folders under root."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "<folder>", "not a folder")
    found = {}
    for cand in [root, *sorted(root.glob("*")), *sorted(root.glob("*/*"))]:
        if (cand / K.JOINTS_DIR).is_dir():
            found[cand.relative_to(root).as_posix()] = cand
    if not found:
        raise InputError(root, K.JOINTS_DIR, "no subject folder with a joints3d_25/ folder "
                         "(looked in the folder, its sub-folders and theirs)")
    return found


def sequences(root: str | Path) -> list[tuple[str, str]]:
    """[(subject, action)] of a truth root, sorted."""
    out = []
    for subj, d in subject_dirs(root).items():
        out += [(subj, p.stem) for p in sorted((d / K.JOINTS_DIR).glob("*.json"))]
    if not out:
        raise InputError(Path(root), f"{K.JOINTS_DIR}/<action>.json", "no action files")
    return out


def sequence_name(subject: str, action: str) -> str:
    return action if subject == "." else f"{subject}/{action}"


# --------------------------------------------------------------------------------------- files
def read_valid(path: Path, P: int, F: int) -> np.ndarray:
    """``valid/<action>.json`` -> (P, F) bool; a (F,) list applies to every person."""
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, "<json>", f"cannot read: {e}") from None
    if not isinstance(d, dict) or "valid" not in d:
        raise InputError(path, "valid", "missing")
    a = np.array(d["valid"], dtype=object)
    if a.shape == (F,):
        a = np.broadcast_to(a, (P, F))
    if a.shape != (P, F):
        raise InputError(path, "valid", f"expected shape ({P}, {F}) or ({F},) to match "
                         f"joints3d_25, got {a.shape}")
    bad = ~np.vectorize(lambda v: isinstance(v, (bool, np.bool_)) or v in (0, 1))(a)
    if bad.any():
        raise InputError(path, "valid", "expected booleans", frame=int(np.argwhere(bad)[0][1]))
    return a.astype(bool)


def read_vertices(path: Path, P: int, F: int) -> Vertices:
    """``vertices/<action>.npz`` -> Vertices, shapes checked against the joints' (P, F)."""
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(path, "<npz>", f"cannot read: {e}") from None
    with z:
        for key in ("vertices", "root"):
            if key not in z.files:
                raise InputError(path, key, "missing")
        v, r = np.asarray(z["vertices"], np.float64), np.asarray(z["root"], np.float64)
    if v.ndim != 4 or v.shape[:2] != (P, F) or v.shape[3] != 3:
        raise InputError(path, "vertices", f"expected shape ({P}, {F}, V, 3) to match "
                         f"joints3d_25, got {v.shape}")
    if r.shape != (P, F, 3):
        raise InputError(path, "root", f"expected shape ({P}, {F}, 3), got {r.shape}")
    for key, a in (("vertices", v), ("root", r)):
        bad = ~np.isfinite(a).reshape(P, F, -1).all(axis=(0, 2))
        if bad.any():
            raise InputError(path, key, "NaN or inf", frame=int(np.flatnonzero(bad)[0]))
    return Vertices(v, r, str(path), "vertices npz")


def vertices_from_smplx(model, params: dict, source: str) -> Vertices:
    """Pose an SMPL-X model with CHI3D parameters ``{key: (P, F, ...)}`` (rotation matrices,
    10 betas and 10 expression coefficients per frame) -> Vertices (root = posed joint 0)."""
    P = params["transl"].shape[0]
    vs, roots = [], []
    for p in range(P):
        def aa(key, _p=p):
            return rotmat_to_rotvec(params[key][_p])
        pose = smplx_pose(aa("body_pose"), aa("jaw_pose"), aa("leye_pose"), aa("reye_pose"),
                          aa("left_hand_pose"), aa("right_hand_pose"))
        betas = smplx_betas(model, params["betas"][p], params["expression"][p])
        out = forward(model, betas, pose, params["global_orient"][p][:, 0], params["transl"][p])
        vs.append(out.vertices)
        roots.append(out.joints[:, 0])
    return Vertices(np.stack(vs), np.stack(roots), source, "smplx")


def vertices_from_anny(model, path: Path, P: int, F: int) -> Vertices:
    """Pose the Anny model with ``anny/<action>.json`` -> Vertices (root = posed joint 0);
    (persons, frames) and the joint names are checked against the joints' and the model's."""
    from formats.anny_json import read_anny

    d = read_anny(path)
    if d["transl"].shape[:2] != (P, F):
        raise InputError(path, "transl", f"(persons, frames) {d['transl'].shape[:2]} != "
                         f"joints3d_25's {(P, F)}")
    if tuple(d["joint_names"]) != tuple(model.joint_names):
        raise InputError(path, "joint_names", f"{len(d['joint_names'])} joints that are not the "
                         f"Anny model's {model.num_joints} ({model.source})")
    if d["betas"].shape[2] > model.num_betas:
        raise InputError(path, "betas", f"{d['betas'].shape[2]} coefficients, the model has "
                         f"{model.num_betas}")
    pose, orient = rotmat_to_rotvec(d["body_pose"]), d["global_orient"]
    vs, roots = [], []
    for p in range(P):
        betas = d["betas"][p]
        if np.allclose(betas, betas[:1]):  # one shape per person (the usual case): one rest state
            betas = betas[0]
        out = forward(model, betas, pose[p], orient[p], d["transl"][p])
        vs.append(out.vertices)
        roots.append(out.joints[:, 0])
    return Vertices(np.stack(vs), np.stack(roots), str(path), "anny")


def smplx_model_path(given: str | Path | None) -> Path | None:
    if given:
        return Path(given)
    env = os.environ.get("SMPLX_MODEL_PATH")
    return Path(env) if env else None


def first_camera(subject_dir: Path, action: str, files: dict) -> Camera:
    """The first camera (by serial) of ``camera_parameters/<camera>/<action>.json``."""
    cams = read_chi3d_cameras(subject_dir, action)
    camera = cams[sorted(cams)[0]]
    files["camera"] = str(subject_dir / K.CAMERAS_DIR / camera.name / f"{action}.json")
    return camera


def load_side(subject_dir: Path, action: str, name: str, P: int | None, F: int | None,
              smplx_model=None, truth: bool = False, anny_model=None) -> SequenceData:
    """Read one side of a sequence. P, F: the truth's persons and frames (None when reading the
    truth itself); the prediction must match them. smplx_model: a loaded SMPL-X BodyModel or
    None (vertices from smplx/ files are then not computed); anny_model: the Anny BodyModel when
    both sides have ``anny/<action>.json`` (those are then the vertices), else None."""
    jpath = subject_dir / K.JOINTS_DIR / f"{action}.json"
    if not jpath.is_file():
        raise InputError(jpath, K.JOINTS_DIR, f"missing: the truth has action {action!r}")
    joints = read_joints3d_25(jpath)
    if P is not None and joints.shape[0] != P:
        raise InputError(jpath, K.JOINTS_DIR, f"person axis of {joints.shape[0]}, the truth has "
                         f"{P} people (expected shape ({P}, F, 25, 3))")
    if F is not None and joints.shape[1] != F:
        raise InputError(jpath, K.JOINTS_DIR, f"{joints.shape[1]} frames, the truth has {F} "
                         f"(expected shape ({P}, {F}, 25, 3))")
    P, F = joints.shape[:2]
    files = {"joints3d_25": str(jpath)}

    vertices, note = None, ""
    vpath = subject_dir / K.VERTICES_DIR / f"{action}.npz"
    spath = subject_dir / K.SMPLX_DIR / f"{action}.json"
    apath = subject_dir / K.ANNY_DIR / f"{action}.json"
    if anny_model is not None and apath.is_file():
        vertices = vertices_from_anny(anny_model, apath, P, F)
    elif spath.is_file() and (smplx_model is not None or not vpath.is_file()):
        params = read_smplx(spath)
        if params["transl"].shape[:2] != (P, F):
            raise InputError(spath, "transl", f"(persons, frames) {params['transl'].shape[:2]} "
                             f"!= joints3d_25's {(P, F)}")
        if smplx_model is None:
            note = f"{spath} found but no SMPL-X model file (--smplx-model or $SMPLX_MODEL_PATH)"
        else:
            vertices = vertices_from_smplx(smplx_model, params, str(spath))
    elif vpath.is_file():
        vertices = read_vertices(vpath, P, F)
    else:
        note = (f"no {K.ANNY_DIR}/{action}.json on both sides, {K.SMPLX_DIR}/{action}.json or "
                f"{K.VERTICES_DIR}/{action}.npz in {subject_dir}")
    if vertices is not None:
        files["vertices"] = vertices.source

    valid = camera = contact = None
    contact_note = ""
    if not truth:
        mpath = subject_dir / K.VALID_DIR / f"{action}.json"
        if mpath.is_file():
            valid = read_valid(mpath, P, F)
            files["valid"] = str(mpath)
    if truth:
        valid = np.ones((P, F), bool)
        mpath = subject_dir / K.VALID_DIR / f"{action}.json"
        if mpath.is_file():
            valid = read_valid(mpath, P, F)
            files["valid"] = str(mpath)
        if (subject_dir / K.CAMERAS_DIR).is_dir():
            camera = first_camera(subject_dir, action, files)
        cpath = subject_dir / K.CONTACT_FILE
        if not cpath.is_file():
            contact_note = f"no {cpath}"
        else:
            sigs = read_contact_signatures(cpath)
            if action not in sigs:
                contact_note = f"{cpath} has no entry for {action!r}"
            else:
                contact = sigs[action]
                files["contact"] = str(cpath)
                last = contact.end_fr if contact.end_fr is not None else contact.fr_id
                if last >= F:
                    raise InputError(cpath, f"{action}.end_fr" if contact.end_fr is not None
                                     else f"{action}.fr_id",
                                     f"beyond the {F} frames of {jpath}", frame=last)
    return SequenceData(name=name, joints=joints, files=files, vertices=vertices,
                        vertices_note=note, valid=valid, camera=camera, contact=contact,
                        contact_note=contact_note)


def published_frames(subject_dir: Path, action: str) -> np.ndarray | None:
    """The ``frames`` (F',) of a prediction's ``valid/<action>.json`` (a release's: the truth's
    frame numbers it holds), or None when it gives none."""
    path = subject_dir / K.VALID_DIR / f"{action}.json"
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, "<json>", f"cannot read: {e}") from None
    if not isinstance(d, dict) or d.get("frames") is None:
        return None
    a = np.asarray(d["frames"])
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer) or (a < 0).any():
        raise InputError(path, "frames", f"expected (F,) non-negative frame numbers, got {a.shape}")
    return a.astype(np.int64)


def select_frames(gt: SequenceData, frames: np.ndarray, source: Path) -> SequenceData:
    """The truth restricted to the frame numbers ``frames`` (a release cut to its fitted
    frames); InputError naming ``source`` if one is beyond the truth."""
    F = gt.joints.shape[1]
    if len(frames) and frames.max() >= F:
        bad = int(np.flatnonzero(frames >= F)[0])
        raise InputError(source, "frames", f"frame {int(frames[bad])} beyond the truth's {F} "
                         f"frames ({gt.files['joints3d_25']})", frame=bad)
    v = gt.vertices
    if v is not None:
        v = replace(v, vertices=v.vertices[:, frames], root=v.root[:, frames])
    return replace(gt, joints=gt.joints[:, frames], vertices=v,
                   valid=None if gt.valid is None else gt.valid[:, frames], frame_ids=frames)


def load_pairs(pred_root: str | Path, gt_root: str | Path, smplx_model_file=None,
               anny_model_file=None):
    """[(pred SequenceData, truth SequenceData)] for every sequence of the truth, and the list
    of InputErrors met (every problem, not just the first). anny_model_file: the Anny model
    file for ``anny/`` files (None: ``body.load_model("anny")``'s default)."""
    pred_root, gt_root = Path(pred_root), Path(gt_root)
    gt_subjects = subject_dirs(gt_root)
    model = None
    mpath = smplx_model_path(smplx_model_file)
    if mpath is not None and (any((d / K.SMPLX_DIR).is_dir() for d in gt_subjects.values())):
        model = load_model("smplx", mpath)
    anny = None
    pairs, errors = [], []
    for subj, action in sequences(gt_root):
        name = sequence_name(subj, action)
        try:
            both_anny = all((d / K.ANNY_DIR / f"{action}.json").is_file()
                            for d in (gt_subjects[subj], pred_root / subj))
            if both_anny and anny is None:
                anny = load_model("anny", anny_model_file)
            am = anny if both_anny else None
            gt = load_side(gt_subjects[subj], action, name, None, None, model, truth=True,
                           anny_model=am)
            frames = published_frames(pred_root / subj, action)
            if frames is not None and not np.array_equal(frames, np.arange(gt.joints.shape[1])):
                gt = select_frames(gt, frames, pred_root / subj / K.VALID_DIR / f"{action}.json")
            pred = load_side(pred_root / subj, action, name, *gt.joints.shape[:2], model,
                             anny_model=am)
            if gt.camera is None:  # a truth without cameras (the studio's gt/): the prediction's
                if not (pred_root / subj / K.CAMERAS_DIR).is_dir():
                    raise InputError(gt_subjects[subj] / K.CAMERAS_DIR, K.CAMERAS_DIR,
                                     f"folder missing (and in {pred_root / subj}): the person "
                                     "matching needs a camera")
                gt = replace(gt, camera=first_camera(pred_root / subj, action, gt.files))
        except InputError as e:
            errors.append(e)
            continue
        pairs.append((pred, gt))
    return pairs, errors
