"""``L_2d`` of a fit skeleton's keypoint slots in numpy, with its exact Jacobian: the residual
function of the partner fit (``fitting/partner_fit.py``).

The keypoints are slots ``H (K, Q, 4)`` on the fit skeleton (``fitting.skinned
.regressed_coeffs``); per evaluation their world positions and exact Jacobian come from
``fitting.skinned.point_jacobian`` (closed-form derivative of the reduced-tree skinning) and
each view's pixels and ``d uv / d X`` from ``calib.project_jacobian``. The residual rows are
``fitting.terms.L_2d`` over the views, camera-major: row ``2 (c K + k) + {0, 1}``.

Why numpy and not the compiled CasADi graph the marker fit uses: with 65 keypoints over 52
joints and four views the generated C source is 17 MB and compiles too slowly to pay, and the
interpreted graph costs ~8 ms per evaluation; this costs ~1 ms (``make bench``,
``partner_fit.fps_per_core``). It offers the interface of ``fitting.compiled
.ResidualFunction`` that ``fitting.lm.solve`` uses (``n_x``, ``n_r``, ``_flat``, ``__call__(x,
p) -> (r, dense row-major Jacobian)``).
"""
from __future__ import annotations

import numpy as np

from calib import project_jacobian
from fitting import skinned, terms


class Reprojection:
    """``L_2d`` rows (2 C K,) of keypoint slots ``Hk (K, Q, 4)`` seen by ``cams`` (C views).

    ``set_observations(uv (C, K, 2) pixels, conf (C, K))`` (0 = missing) before a solve; the
    rows of a missing keypoint are 0. ``__call__(x, p)``: ``p`` is ignored (kept for the
    ``fitting.lm`` interface)."""

    compiled = False
    n_p = 0

    def __init__(self, skel: skinned.FitSkeleton, u: np.ndarray, Hk: np.ndarray, cams,
                 sub: np.ndarray | None = None):
        self.skel, self.u, self.cams = skel, np.asarray(u, float), list(cams)
        self.Hk = np.asarray(Hk, float)
        self.sub = skinned.subtree(skel) if sub is None else sub
        self.pattern = skinned.JacobianPattern(skel, self.Hk, self.sub)
        self.C, self.K = len(self.cams), len(self.Hk)
        self.n_x = skel.n
        self.n_r = 2 * self.C * self.K
        self._flat = np.arange(self.n_r * self.n_x)
        self.uv = np.zeros((self.C, self.K, 2))
        self.conf = np.zeros((self.C, self.K))

    def set_observations(self, uv: np.ndarray, conf: np.ndarray) -> None:
        uv, conf = np.asarray(uv, float), np.asarray(conf, float)
        if uv.shape != (self.C, self.K, 2) or conf.shape != (self.C, self.K):
            raise ValueError(f"observations: expected uv ({self.C}, {self.K}, 2) and conf "
                             f"({self.C}, {self.K}), got {uv.shape} and {conf.shape}")
        self.uv = np.where(conf[..., None] > 0, uv, 0.0)
        self.conf = conf

    def project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (C, K, 2) of the keypoints at unknowns x and their Jacobian (C, K, 2, n)."""
        pos, Jp = skinned.point_jacobian(self.skel, self.u, self.Hk, x, self.sub, self.pattern)
        uv = np.empty((self.C, self.K, 2))
        J = np.empty((self.C, self.K, 2, self.n_x))
        for c, cam in enumerate(self.cams):
            uv[c], Jc = project_jacobian(cam, pos)
            J[c] = Jc @ Jp
        return uv, J

    def __call__(self, x: np.ndarray, p=None) -> tuple[np.ndarray, np.ndarray]:  # noqa: ARG002
        uv, J = self.project(np.asarray(x, float))
        conf = self.conf.reshape(-1)
        r = terms.L_2d(uv.reshape(-1, 2), self.uv.reshape(-1, 2), conf)
        s = np.sqrt(conf / max(int(np.count_nonzero(conf > 0)), 1))  # L_2d's row scale
        J = (s[:, None, None] * J.reshape(-1, 2, self.n_x)).reshape(-1)
        return r, J
