"""The one residual function of a marker-wearing subject's frame: ``L_3d`` on markers and
``L_2d`` on (hand) keypoints seen by calibrated cameras.

Everything that changes between frames, subjects or sequences is a parameter; the graph
depends only on :class:`GraphSpec` (the reduced tree, the slot counts, the camera count and
lens model), so it is compiled once per spec and cached (``fitting/compiled.py``).

Parameter vector ``p`` (:meth:`MarkerGraph.params` packs it):
    u (Q, 3)            reduced-tree offsets (fitting/skinned.py), metres
    Hm (M, Q, 4)        marker slot coefficients
    Hk (K, Q, 4)        keypoint slot coefficients
    cams (C, 21)        packed cameras (calib.camera_vector)
    obs (M, 3), vis (M,)            observed markers (metres, world) and visibility 0/1
    uv (C, K, 2), conf (C, K)       detected keypoints (pixels) and confidence (0 = missing)
Residual ``r = [L_3d (3M), L_2d (2CK)]`` (fitting/terms.py), unweighted.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from calib import project_cs
from calib.constants import CAM_VECTOR_SIZE
from fitting import compiled, skinned, terms


@dataclass(frozen=True)
class GraphSpec:
    """What fixes the graph. parents: reduced tree (-1 root); n_markers M; n_keypoints K;
    n_cameras C (0 when K = 0); camera_model: the lens model of the cameras."""

    parents: tuple[int, ...]
    n_markers: int
    n_keypoints: int = 0
    n_cameras: int = 0
    camera_model: str = "h36m"

    @property
    def Q(self) -> int:
        return len(self.parents)

    @property
    def n_x(self) -> int:
        return 3 * self.Q + 3

    def name(self) -> str:
        kp = f"_k{self.n_keypoints}c{self.n_cameras}{self.camera_model}" if self.n_keypoints else ""
        return f"markers_q{self.Q}_m{self.n_markers}{kp}"


class MarkerGraph:
    """The compiled residual function of a :class:`GraphSpec` and its parameter layout."""

    def __init__(self, spec: GraphSpec, opts: compiled.CompileOptions | None = None, log=None):
        if spec.n_keypoints and not spec.n_cameras:
            raise ValueError("keypoints need cameras")
        self.spec = spec
        Q, M, K, C = spec.Q, spec.n_markers, spec.n_keypoints, spec.n_cameras
        sizes = [("u", Q * 3), ("Hm", M * Q * 4), ("Hk", K * Q * 4),
                 ("cams", C * CAM_VECTOR_SIZE), ("obs", M * 3), ("vis", M),
                 ("uv", C * K * 2), ("conf", C * K)]
        self.slices: dict[str, slice] = {}
        o = 0
        for name, n in sizes:
            self.slices[name] = slice(o, o + n)
            o += n
        self.n_p = o
        x = ca.SX.sym("x", spec.n_x)
        p = ca.SX.sym("p", self.n_p)

        def blk(name, rows, cols):  # row-major block of p as (rows, cols) SX
            return ca.reshape(p[self.slices[name]], cols, rows).T

        u = blk("u", Q, 3)
        G, t = skinned.fk_cs(spec.parents, x, u)
        Hm_all = p[self.slices["Hm"]]
        Hm = [ca.reshape(Hm_all[i * Q * 4:(i + 1) * Q * 4], 4, Q).T for i in range(M)]
        markers = skinned.slots_cs(G, t, Hm)
        r = [terms.L_3d(markers, blk("obs", M, 3), p[self.slices["vis"]])]
        if K:
            Hk_all = p[self.slices["Hk"]]
            Hk = [ca.reshape(Hk_all[i * Q * 4:(i + 1) * Q * 4], 4, Q).T for i in range(K)]
            kp = skinned.slots_cs(G, t, Hk)  # (K, 3)
            cams = blk("cams", C, CAM_VECTOR_SIZE)
            uv_model = []
            for c in range(C):
                cam = cams[c, :].T
                for k in range(K):
                    uv_model.append(project_cs(cam, kp[k, :].T, model=spec.camera_model).T)
            r.append(terms.L_2d(ca.vertcat(*uv_model), blk("uv", C * K, 2),
                                p[self.slices["conf"]]))
        self.rows_3d = slice(0, 3 * M)
        self.rows_2d = slice(3 * M, 3 * M + 2 * C * K)
        self.fun = compiled.build(spec.name(), x, p, ca.vertcat(*r),
                                  opts or compiled.CompileOptions(), log=log)

    def params(self, u, Hm, obs, vis, Hk=None, cams=None, uv=None, conf=None) -> np.ndarray:
        """Pack the parameter vector (shapes in the module docstring; gaps: vis 0, obs any)."""
        s = self.spec
        p = np.zeros(self.n_p)
        p[self.slices["u"]] = np.asarray(u, float).reshape(-1)
        p[self.slices["Hm"]] = np.asarray(Hm, float).reshape(-1)
        vis = np.asarray(vis, float).reshape(-1)
        p[self.slices["obs"]] = np.where(vis[:, None] > 0, np.nan_to_num(
            np.asarray(obs, float).reshape(s.n_markers, 3)), 0.0).reshape(-1)
        p[self.slices["vis"]] = vis
        if s.n_keypoints:
            p[self.slices["Hk"]] = np.asarray(Hk, float).reshape(-1)
            p[self.slices["cams"]] = np.asarray(cams, float).reshape(-1)
            conf = np.asarray(conf, float).reshape(-1)
            uvv = np.nan_to_num(np.asarray(uv, float).reshape(-1, 2))
            p[self.slices["uv"]] = np.where(conf[:, None] > 0, uvv, 0.0).reshape(-1)
            p[self.slices["conf"]] = conf
        return p

    def set_observations(self, p: np.ndarray, obs, vis, uv=None, conf=None) -> np.ndarray:
        """Overwrite the per-frame blocks of a packed ``p`` in place (returns it)."""
        vis = np.asarray(vis, float).reshape(-1)
        p[self.slices["obs"]] = np.where(vis[:, None] > 0, np.nan_to_num(
            np.asarray(obs, float).reshape(-1, 3)), 0.0).reshape(-1)
        p[self.slices["vis"]] = vis
        if self.spec.n_keypoints and uv is not None:
            conf = np.asarray(conf, float).reshape(-1)
            uvv = np.nan_to_num(np.asarray(uv, float).reshape(-1, 2))
            p[self.slices["uv"]] = np.where(conf[:, None] > 0, uvv, 0.0).reshape(-1)
            p[self.slices["conf"]] = conf
        return p
