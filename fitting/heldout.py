"""The held-out view: the honest accuracy figure where no truth exists (issue #28 item 3).

Each camera in turn is left out: the people are fitted from the other views (the partner
fit, :func:`fitting.partner_fit.fit_partner`, on a stride of the frames), their KP65
keypoints projected into the left-out view and compared with that view's own detections
(pixels, per keypoint group: ``face`` (nose, eyes, ears), ``body`` (the other 18 body and
foot keypoints), ``hands`` (42)). Beside it the plain baseline: each keypoint triangulated
from the other views alone (linear DLT, ``calib.dlt.triangulate_points``) and
projected into the left-out view. Both are measured on the same detections (the ones the
baseline can predict: seen in at least two of the other views), so the difference is what
the body model adds.

Pure functions over arrays and typed artifacts; the stage is ``stages/heldout.py``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from calib import project

#: keypoint groups of KP65 the figure is given for
GROUPS = {"face": np.arange(0, 5), "body": np.arange(5, 23), "hands": np.arange(23, 65)}


def project_front(cam, X: np.ndarray) -> np.ndarray:
    """(..., 2) pixels of world points ``X (..., 3)``; NaN for points not finite or behind
    the camera."""
    X = np.asarray(X, float)
    out = np.full(X.shape[:-1] + (2,), np.nan)
    Xc = (X - np.asarray(cam.T, float)) @ np.asarray(cam.R, float).T
    ok = np.all(np.isfinite(X), axis=-1) & (Xc[..., 2] > 0.05)
    if ok.any():
        out[ok] = project(cam, X[ok])
    return out


def pixel_errors(cam, X: np.ndarray, det: np.ndarray, min_conf: float) -> np.ndarray:
    """(F, K) pixel distance between ``X (F, K, 3)`` projected into ``cam`` and the view's
    detections ``det (F, K, 3)`` (x, y, confidence); NaN where the keypoint is not detected
    (confidence below ``min_conf``) or not predicted."""
    uv = project_front(cam, X)
    e = np.linalg.norm(uv - np.asarray(det, float)[..., :2], axis=-1)
    return np.where(np.asarray(det)[..., 2] >= min_conf, e, np.nan)


def triangulated(cams, kp: np.ndarray, min_conf: float) -> np.ndarray:
    """(F, K, 3) every keypoint triangulated per frame from the views ``cams`` (``kp (C, F,
    K, 3)``, detections at confidence >= ``min_conf``); NaN where fewer than two views see
    it."""
    from calib.dlt import triangulate_points

    kp = np.asarray(kp, float)
    ok = kp[..., 2] >= min_conf
    return np.stack([triangulate_points(cams, kp[:, f, :, :2], ok[:, f])
                     for f in range(kp.shape[1])])


def group_stats(e: np.ndarray) -> dict:
    """``{group: {median_px, p90_px, n}}`` of the errors ``e (F, 65)`` (NaN skipped) per
    :data:`GROUPS` and over all."""
    out = {}
    for g, idx in {**GROUPS, "all": np.arange(65)}.items():
        v = np.asarray(e, float)[:, idx]
        v = v[np.isfinite(v)]
        out[g] = ({"median_px": round(float(np.median(v)), 2),
                   "p90_px": round(float(np.percentile(v, 90)), 2), "n": int(len(v))}
                  if len(v) else {"median_px": None, "p90_px": None, "n": 0})
    return out


@dataclass(frozen=True)
class HeldOut:
    """Per left-out camera and person: the errors of the fit and of the baseline, ``(F, 65)``
    pixels on the same detections (NaN elsewhere), the frames, and the fits' CPU seconds."""

    camera: str
    person: int
    frames: np.ndarray
    fit_px: np.ndarray
    baseline_px: np.ndarray
    fit_cpu_s: float


def subset(keypoints, cam_ids: list[str], frame_idx: np.ndarray):
    """The :class:`artifacts.keypoints.Keypoints2D` of the views ``cam_ids`` at the frames
    ``frame_idx`` (indices into its frames)."""
    ci = [keypoints.camera(c) for c in cam_ids]
    fi = np.asarray(frame_idx)

    def sl(a):
        return np.asarray(a)[ci][:, fi]

    return dataclasses.replace(
        keypoints, kp=sl(keypoints.kp), boxes=sl(keypoints.boxes),
        hand_boxes=sl(keypoints.hand_boxes), frames=np.asarray(keypoints.frames)[fi],
        wearer_retry=sl(keypoints.wearer_retry), partner_mode=sl(keypoints.partner_mode),
        cross_view_outlier=sl(keypoints.cross_view_outlier), conf_raw=sl(keypoints.conf_raw),
        cameras=np.asarray(keypoints.cameras)[ci])


def fitted_keypoints(model, fit) -> np.ndarray:
    """(F, 65, 3) the KP65 keypoints of a :class:`artifacts.BodyFit` (NaN at frames not
    valid)."""
    from body import forward
    from body.joints import regressor

    est = forward(model, np.asarray(fit.betas, float), fit.body_pose, fit.global_orient,
                  fit.transl)
    R = regressor(model, "kp65")
    X = np.stack([R @ np.concatenate([v, j]) for v, j in zip(est.vertices, est.joints,
                                                              strict=True)])
    X[~np.asarray(fit.valid, bool)] = np.nan
    return X


def held_out_view(model, people_kp: list, betas: list, cams, held: int, frame_idx: np.ndarray,
                  opts, ground=None, min_conf: float = 0.3, progress=None) -> list[HeldOut]:
    """Camera ``cams[held]`` left out: every person (``people_kp[p]``: the keypoints with
    person ``p`` in the partner's slot; ``betas[p]`` its shape, held fixed) fitted from the
    other views at ``frame_idx`` (person 1 against person 0 with ``L_ic``), projected into
    the left-out view; the baseline triangulated from the same views."""
    import time

    from artifacts.keypoints import PARTNER
    from fitting.partner_fit import fit_partner

    others = [c for i, c in enumerate(cams) if i != held]
    ids = [c.name for c in others]
    out: list[HeldOut] = []
    prev = None
    for p, kp in enumerate(people_kp):
        sub = subset(kp, ids, frame_idx)
        t0 = time.process_time()
        fit, _ = fit_partner(model, SimpleNamespace(betas=np.asarray(betas[p], float)), sub,
                             others, prev, None, ground, opts, progress=progress)
        cpu = time.process_time() - t0
        prev = fit
        X = fitted_keypoints(model, fit)
        det = np.asarray(kp.person(PARTNER), float)[kp.camera(cams[held].name)][frame_idx]
        base = triangulated(others, np.asarray(sub.person(PARTNER), float), min_conf)
        e_fit = pixel_errors(cams[held], X, det, min_conf)
        e_base = pixel_errors(cams[held], base, det, min_conf)
        both = np.isfinite(e_fit) & np.isfinite(e_base)
        out.append(HeldOut(cams[held].name, p, np.asarray(sub.frames), np.where(both, e_fit, np.nan),
                           np.where(both, e_base, np.nan), cpu))
    return out


def summarise(results: list[HeldOut]) -> dict:
    """The report: per camera (over its people) and over every camera, the fit's and the
    baseline's :func:`group_stats`, and the fit's frames per CPU second."""
    per_cam: dict = {}
    for cam in dict.fromkeys(r.camera for r in results):
        rs = [r for r in results if r.camera == cam]
        per_cam[cam] = {"fit": group_stats(np.concatenate([r.fit_px for r in rs])),
                        "baseline": group_stats(np.concatenate([r.baseline_px for r in rs])),
                        "frames": int(len(rs[0].frames))}
    allf = np.concatenate([r.fit_px for r in results]) if results else np.zeros((0, 65))
    allb = np.concatenate([r.baseline_px for r in results]) if results else np.zeros((0, 65))
    frames = sum(len(r.frames) for r in results)
    cpu = sum(r.fit_cpu_s for r in results)
    return {"cameras": per_cam, "all": {"fit": group_stats(allf), "baseline": group_stats(allb)},
            "fit_frames": frames, "fit_cpu_s": round(cpu, 2),
            "fit_frames_per_cpu_s": round(frames / cpu, 3) if cpu > 0 else None}
