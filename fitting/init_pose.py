"""The partner's initial state from keypoints triangulated across the views (issue #15: the
first frame, and any frame after a long run without detections; the fit then refines it).

1. Triangulate the person's KP65 keypoints of one frame over the C views
   (:func:`calib.geometry.triangulate`, pycolmap LO-RANSAC: a wrong detection in one view is
   an outlier of its rays and is left out).
2. Rigid fit (Kabsch, :func:`fitting.marker_fit.kabsch`) of the model's rest-pose keypoints
   (``body.joints.regressor(model, "kp65")`` on ``body.forward`` at pose 0) to the
   triangulated torso (shoulders and hips): global rotation ``R`` and translation. With the
   body contract's ``v = R (v_rest - J0) + J0 + T`` and Kabsch's ``R p + t``,
   ``T = t + R J0 - J0``.
3. Optionally the limb directions: each upper arm, forearm, thigh and shank gets the smallest
   local rotation (in its parent's frame) turning its rest keypoint segment (e.g. shoulder ->
   elbow) onto the triangulated one; twist is left at 0.

The state is ``x = [r (3), T (3), theta ((Q-1)*3)]`` of :mod:`fitting.skinned`'s fit skeleton
(radians, metres), as :func:`fitting.marker_fit.unpack` reads it. :func:`init_pose` returns a
:class:`PoseInit` with ``x`` None and a ``reason`` when too few keypoints triangulate.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from artifacts.keypoints import PARTNER, Keypoints2D
from body.joints import keypoints as model_keypoints
from body.lbs import forward
from body.model import BodyModel
from body.rotations import rodrigues, rotmat_to_rotvec
from calib.geometry import TriangulateOptions, triangulate
from fitting.marker_fit import kabsch
from fitting.skinned import FitSkeleton, fit_skeleton
from formats.errors import InputError
from formats.skeletons import KP65

#: KP65 indices of the torso keypoints the rigid fit uses (shoulders, hips).
TORSO = tuple(KP65.index(n) for n in ("l_shoulder", "r_shoulder", "l_hip", "r_hip"))
#: Limb segments: (joint name per model family, KP65 from, KP65 to), parents before children.
LIMBS = {
    "anny": (("upperarm01.L", "l_shoulder", "l_elbow"), ("lowerarm01.L", "l_elbow", "l_wrist"),
             ("upperarm01.R", "r_shoulder", "r_elbow"), ("lowerarm01.R", "r_elbow", "r_wrist"),
             ("upperleg01.L", "l_hip", "l_knee"), ("lowerleg01.L", "l_knee", "l_ankle"),
             ("upperleg01.R", "r_hip", "r_knee"), ("lowerleg01.R", "r_knee", "r_ankle")),
    "smplx": (("left_shoulder", "l_shoulder", "l_elbow"), ("left_elbow", "l_elbow", "l_wrist"),
              ("right_shoulder", "r_shoulder", "r_elbow"), ("right_elbow", "r_elbow", "r_wrist"),
              ("left_hip", "l_hip", "l_knee"), ("left_knee", "l_knee", "l_ankle"),
              ("right_hip", "r_hip", "r_knee"), ("right_knee", "r_knee", "r_ankle")),
}
LIMBS["smplh"] = LIMBS["smpl"] = LIMBS["smplx"]
MIN_SEGMENT_M = 0.05  # a triangulated limb segment shorter than this is not trusted


@dataclass(frozen=True)
class InitOptions:
    """triangulation: pycolmap options (RANSAC inlier threshold in pixels, min views);
    min_torso: torso keypoints (of :data:`TORSO`) that must triangulate for the rigid fit
    (3 fix a rotation); limbs: also set the limb directions; max_limb_rad: a limb rotation
    larger than this is not applied (a bad triangulation)."""

    triangulation: TriangulateOptions = field(default_factory=lambda: TriangulateOptions(max_error_px=8.0))
    min_torso: int = 3
    limbs: bool = True
    max_limb_rad: float = 2.5


@dataclass(frozen=True, eq=False)
class PoseInit:
    """x: (n,) state of the fit skeleton, or None (then ``reason`` says why).

    points: (65, 3) triangulated keypoints, world metres, NaN where not; errors_px: (65, C)
    reprojection error per view (NaN unobserved); inliers: (65, C) bool views RANSAC kept;
    n_triangulated: keypoints triangulated; reproj_rms_px: RMS over the inlier observations;
    view_inlier_rate: (C,) fraction of each view's observations kept (a wrong view: ~0);
    align_rms_m: RMS of the rigid torso fit; limbs_set: joint names whose direction was set."""

    x: np.ndarray | None
    reason: str
    points: np.ndarray
    errors_px: np.ndarray
    inliers: np.ndarray
    n_triangulated: int
    reproj_rms_px: float
    view_inlier_rate: np.ndarray
    align_rms_m: float = float("nan")
    limbs_set: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.x is not None


def rest_keypoints(model: BodyModel, betas) -> tuple[np.ndarray, np.ndarray]:
    """(KP65 rest-pose keypoints (65, 3), rest root joint J0 (3,)), metres, model frame."""
    J = model.num_joints
    out = forward(model, np.asarray(betas, float), np.zeros((1, J, 3)), np.eye(3)[None], np.zeros((1, 3)))
    return model_keypoints(model, out, "kp65")[0], out.joints[0, 0]


def _minimal_rotvec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (rotation vector) taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    c = np.cross(a, b)
    s, cos = np.linalg.norm(c), float(a @ b)
    if s < 1e-12:
        if cos > 0:
            return np.zeros(3)
        perp = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
        return np.pi * perp / np.linalg.norm(perp)
    return c / s * np.arctan2(s, cos)


def init_pose(model: BodyModel, betas, cams, kp: np.ndarray, skel: FitSkeleton | None = None,
              opts: InitOptions = InitOptions()) -> PoseInit:
    """The initial state of one person from one frame's keypoints.

    cams: C ``calib.Camera``; kp: (C, 65, 3) KP65 pixels and confidence of that person in
    each view (0 = missing); betas: the person's shape; skel: the fit skeleton (default
    ``fit_skeleton(model)``). Never raises on too few keypoints: returns ``x = None``.
    """
    kp = np.asarray(kp, float)
    C = len(cams)
    if kp.shape != (C, len(KP65), 3):
        raise ValueError(f"kp: expected ({C}, {len(KP65)}, 3), got {kp.shape}")
    skel = fit_skeleton(model) if skel is None else skel
    tri = triangulate(cams, kp, opts.triangulation)
    ok = np.all(np.isfinite(tri.xyz), axis=1)
    n_tri = int(ok.sum())
    err = tri.errors_px
    inl_err = err[tri.inliers & ok[:, None]]
    rms = float(np.sqrt(np.mean(inl_err ** 2))) if inl_err.size else float("nan")
    observed = (kp[..., 2].T >= opts.triangulation.min_conf) & ok[:, None]  # (65, C)
    n_obs = observed.sum(0)
    rate = np.where(n_obs > 0, (tri.inliers & observed).sum(0) / np.maximum(n_obs, 1), np.nan)
    base = dict(points=tri.xyz, errors_px=err, inliers=tri.inliers, n_triangulated=n_tri,
                reproj_rms_px=rms, view_inlier_rate=rate)
    torso = [k for k in TORSO if ok[k]]
    views = int((kp[..., 2] >= opts.triangulation.min_conf).any(axis=1).sum())
    if views < opts.triangulation.min_views:
        return PoseInit(None, f"keypoints in {views} view(s), fewer than the "
                        f"{opts.triangulation.min_views} triangulation needs", **base)
    if len(torso) < opts.min_torso:
        return PoseInit(None, f"{len(torso)} of the {len(TORSO)} torso keypoints (shoulders, hips) "
                        f"triangulated ({n_tri} keypoints in all), fewer than {opts.min_torso}", **base)
    rest, J0 = rest_keypoints(model, betas)
    R, t = kabsch(rest[torso], tri.xyz[torso])
    res = rest[torso] @ R.T + t - tri.xyz[torso]
    x = np.zeros(skel.n)
    x[:3] = rotmat_to_rotvec(R)
    x[3:6] = t + R @ J0 - J0
    limbs_set = []
    if opts.limbs:
        limbs_set = _set_limbs(model, skel, x, rest, tri.xyz, ok, opts)
    return PoseInit(x, "", **base, align_rms_m=float(np.sqrt(np.mean(np.sum(res ** 2, 1)))),
                    limbs_set=tuple(limbs_set))


def _set_limbs(model, skel, x, rest, pts, ok, opts) -> list[str]:
    """Set, in place in x, each limb's local rotation so that its rest segment points along
    the triangulated one (parents first: a child's parent frame includes the parent's turn)."""
    table = LIMBS.get(model.name, ())
    pos = {int(j): i for i, j in enumerate(skel.joints)}
    Q = len(skel.joints)
    G = [None] * Q  # world rotations of the fitted joints, filled on demand

    def world_rot(i):
        if G[i] is None:
            D = rodrigues(x[:3]) if i == 0 else rodrigues(x[6 + 3 * (i - 1): 9 + 3 * (i - 1)])
            G[i] = D if i == 0 else world_rot(int(skel.parents[i])) @ D
        return G[i]

    done = []
    for joint, a, b in table:
        if joint not in model.joint_names:
            continue
        j = model.joint_names.index(joint)
        if j not in pos:
            continue
        ka, kb = KP65.index(a), KP65.index(b)
        if not (ok[ka] and ok[kb]):
            continue
        target = pts[kb] - pts[ka]
        if np.linalg.norm(target) < MIN_SEGMENT_M:
            continue
        i = pos[j]
        Gp = world_rot(int(skel.parents[i]))
        r = _minimal_rotvec(rest[kb] - rest[ka], Gp.T @ target)
        if np.linalg.norm(r) > opts.max_limb_rad:
            continue
        x[6 + 3 * (i - 1): 9 + 3 * (i - 1)] = r
        G[i:] = [None] * (Q - i)  # joints after i in order may descend from it
        done.append(joint)
    return done


def init_from_keypoints(keypoints: Keypoints2D, frame: int, model: BodyModel, betas, cams,
                        person: int = PARTNER, skel: FitSkeleton | None = None,
                        opts: InitOptions = InitOptions(), file="<keypoints>") -> PoseInit:
    """:func:`init_pose` for ``person`` at video ``frame`` of a keypoints artifact; ``cams``
    are matched to its views by camera id. InputError (naming ``file``) when the frame was
    not detected or a camera is missing from the keypoints."""
    fr = np.asarray(keypoints.frames)
    hit = np.flatnonzero(fr == frame)
    if not len(hit):
        raise InputError(file, "frames", "video frame not among the detected frames", frame)
    try:
        idx = [keypoints.camera(c.name) for c in cams]
    except KeyError as e:
        raise InputError(file, "cameras", str(e.args[0]), frame) from None
    kp = np.asarray(keypoints.person(person), float)[idx, int(hit[0])]
    return init_pose(model, betas, cams, kp, skel, opts)
