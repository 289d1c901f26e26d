"""The one residual function of a marker-wearing subject's frame: ``L_3d`` on markers and
``L_2d`` on (hand) keypoints seen by calibrated cameras.

Everything that changes between frames, subjects or sequences is a parameter; the graph
depends only on :class:`GraphSpec` (the reduced tree, the slot counts, the camera count and
lens model), so it is compiled once per spec and cached (``fitting/compiled.py``).

Parameter vector ``p`` (:meth:`MarkerGraph.params` packs it):
    u (Q, 3)            reduced-tree offsets (fitting/skinned.py), metres
    Hm (M, 3, Q, 4)     slot coefficients of each marker's three face corners, only on the
                        marker's support joints (``skinned.SkinnedPoints.corners``)
    bary (M, 3), offset (M,)        the markers' barycentric coordinates and normal offsets
    Hk (K, Q, 4)        keypoint slot coefficients, likewise
    cams (C, 21)        packed cameras (calib.camera_vector)
    obs (M, 3), vis (M,)            observed markers (metres, world) and visibility 0/1
    uv (C, K, 2), conf (C, K)       detected keypoints (pixels) and confidence (0 = missing)
Residual ``r = [L_3d (3M), L_2d (2CK)]`` (fitting/terms.py), unweighted.

Markers on the body (:class:`Placement`: face, barycentric coordinates, offset along the
posed face normal) and what the graph needs of them (corner coefficients, supports) live
here too, so the marker fit and the shape fit share them without importing each other.
A marker is a ``fitting.skinned.SurfacePoints`` point: the bary blend of its posed face
corners plus the offset along the posed unit face normal, the same definition as
``body.markers.marker_positions`` on ``body.forward``'s mesh (so ``fit.npz`` residuals are
reproduced through the public API).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from artifacts import ShapeFit
from body import markers as body_markers
from body.lbs import rest_state
from body.model import BodyModel
from calib import project_cs
from calib.constants import CAM_VECTOR_SIZE
from fitting import compiled, skinned, terms
from geometry import face_normals

# constants
SUPPORT_RADIUS_M = 0.06  # a marker's graph support: joints skinning the surface this close
OBSERVED_WEIGHT = 0.05  # a marker (keypoint, point) moves with the joints skinning it more


# ---------------------------------------------------------------------------- markers


@dataclass(frozen=True)
class Placement:
    """Markers on the surface: names (M,), face (M,) int, bary (M, 3), offset (M,) metres;
    segments: the set's near-rigid groups (``body.markers.segments_of``) and labels: the lab's
    C3D label per marker where it differs, when the set gives them."""

    names: tuple[str, ...]
    face: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    segments: dict | None = None
    labels: dict | None = None

    def points(self) -> skinned.SurfacePoints:
        """The markers as surface points (fitting/skinned.py)."""
        return skinned.SurfacePoints(self.face, self.bary, self.offset)

    def markerset(self) -> body_markers.MarkerSet:
        """The placement as a ``body.markers.MarkerSet`` (for ``marker_positions``)."""
        return body_markers.make_markerset(self.names, self.face, self.bary, self.offset,
                                           segments=self.segments, labels=self.labels)


def marker_rest_points(rest_vertices: np.ndarray, faces: np.ndarray, pl: Placement) -> np.ndarray:
    """(M, 3) the markers on the rest mesh: surface point + offset * rest face normal, metres
    (the marker definition evaluated on the unposed mesh)."""
    tri = rest_vertices[faces[pl.face]]  # (M, 3, 3)
    surf = np.einsum("mk,mkd->md", pl.bary, tri)
    return surf + pl.offset[:, None] * face_normals(rest_vertices, faces[pl.face])


def marker_weights(model: BodyModel, pl: Placement) -> sp.csr_matrix:
    """(M, J) skinning weights of the markers' surface points (their face's vertex weights
    blended by bary; the shape fit's linearised placement update)."""
    M = len(pl.face)
    vids = model.faces[pl.face]  # (M, 3)
    B = sp.csr_matrix((pl.bary.reshape(-1), (np.repeat(np.arange(M), 3), vids.reshape(-1))),
                      shape=(M, model.num_vertices))
    return (B @ model.weights).tocsr()


def marker_coeffs(model: BodyModel, rest, skel: skinned.FitSkeleton,
                  pl: Placement) -> skinned.SkinnedPoints:
    """The markers' :class:`fitting.skinned.SkinnedPoints` on the shape ``rest``."""
    return skinned.surface_coeffs(model, rest, skel, pl.points())



def body_joints(model: BodyModel) -> np.ndarray:
    """The fit joints without fingers (the scan and markers see no finger pose)."""
    fingers = ("finger", "metacarpal", "thumb", "index", "middle", "ring", "pinky")
    return np.array([j for j in model.fit_joints
                     if not any(f in model.joint_names[j].lower() for f in fingers)])



def marker_support(model: BodyModel, skel: skinned.FitSkeleton, template: Placement,
                   radius: float = SUPPORT_RADIUS_M) -> tuple[tuple[int, ...], ...]:
    """Graph support of each marker: the fitted joints skinning the mean-shape surface within
    ``radius`` of its template position (covers placement refinement and every subject, so
    one compiled graph serves all; fitting/skinned.py neighbourhood_support)."""
    rest0 = rest_state(model, np.zeros(1))
    pts = marker_rest_points(rest0.vertices[0], np.asarray(model.faces), template)
    return skinned.neighbourhood_support(model, rest0, skel, pts, radius)


def placement_support(model: BodyModel, skel: skinned.FitSkeleton, template: Placement,
                      Hm: skinned.SkinnedPoints,
                      radius: float = SUPPORT_RADIUS_M) -> tuple[tuple[int, ...], ...]:
    """Graph support of a subject's markers: the template's (:func:`marker_support`) joined
    with the joints that actually skin each marker of the subject's placement ``Hm``
    (``skinned.points_support``): a marker slid 10-20 cm from its template (real labs) skins
    exactly, nothing is dropped. The spec then depends on the placement (one compile per
    subject, cached on disk by its generated source)."""
    base = marker_support(model, skel, template, radius)
    exact = skinned.points_support(Hm)
    return tuple(tuple(sorted(set(a) | set(b))) for a, b in zip(base, exact, strict=True))


def template_placement(model: BodyModel, markerset) -> Placement:
    """The template placement of a marker set on ``model``: a built-in name
    (``"plug-in-gait"``: ``body.markers.plug_in_gait``, ``"cmu"``: ``body.markers.cmu41``,
    ``"plug-in-gait-lower"``: ``body.markers.plug_in_gait_lower``) or a
    ``body.markers.MarkerSet`` (read from its file by the caller:
    ``body.landmarks.load_markerset``). Carries the set's segment groups and labels."""
    builtin = {"plug-in-gait": body_markers.plug_in_gait, "cmu": body_markers.cmu41,
               "plug-in-gait-lower": body_markers.plug_in_gait_lower}
    if isinstance(markerset, body_markers.MarkerSet):
        ms = markerset
    elif isinstance(markerset, str) and markerset in builtin:
        ms = builtin[markerset](model)
    else:
        raise ValueError(f"markerset: expected one of {', '.join(builtin)} or a MarkerSet read "
                         f"from its .yaml/.yml/.json file, got {markerset!r}")
    return Placement(tuple(ms.names), np.asarray(ms.faces, np.int64), np.asarray(ms.bary, float),
                     np.asarray(ms.offsets, float), body_markers.segments_of(ms), ms.labels)


def observed_joints(model: BodyModel, skel: skinned.FitSkeleton, marker_support, visible,
                    keypoint_support=(), keypoint_seen=None) -> np.ndarray:
    """(F, J) bool: per frame, the model joints (``body_pose``'s J) the frame's evidence
    observes. A fitted joint (slot of ``skel``) is observed when a visible marker
    (``visible (F, M)``) or a seen keypoint (``keypoint_seen (F, K)``) moves with it: the slot
    is in the point's support (``marker_support`` / ``keypoint_support``, slot indices, e.g.
    ``skinned.points_support(Hm, OBSERVED_WEIGHT)``). A joint the fit does not solve rides
    with its fitted ancestor (``skel.owner``), except the joints a pose fit solves
    (``model.fit_joints``) that this one held at pose 0 (the fingers without hand keypoints):
    never observed."""
    vis = np.asarray(visible, bool)
    F, Q = len(vis), len(skel.joints)
    A = np.zeros((len(marker_support), Q), bool)
    for m, sup in enumerate(marker_support):
        A[m, list(sup)] = True
    slot = (vis.astype(np.int64) @ A) > 0  # (F, Q)
    if keypoint_seen is not None and len(keypoint_support):
        B = np.zeros((len(keypoint_support), Q), bool)
        for k, sup in enumerate(keypoint_support):
            B[k, list(sup)] = True
        slot |= (np.asarray(keypoint_seen, bool).astype(np.int64) @ B) > 0
    out = slot[:, np.asarray(skel.owner)] if F else np.zeros((0, len(skel.owner)), bool)
    held = sorted(set(int(j) for j in model.fit_joints) - set(int(j) for j in skel.joints))
    out[:, held] = False
    return out


def point_joints(model: BodyModel, R, tol: float = OBSERVED_WEIGHT) -> list[tuple[int, ...]]:
    """Per row of a regressor ``R (K, V + J)`` acting on posed vertices stacked with posed joints
    (``body.joints.regressor``): the model joints its point depends on: the joints skinning its
    vertices by more than ``tol``, and for a joint centre (bone head) the parent bone that
    carries it (the root itself)."""
    R = sp.csr_matrix(R)
    V = model.num_vertices
    W = sp.csr_matrix(model.weights)
    par = np.asarray(model.parents)
    out = []
    for k in range(R.shape[0]):
        cols = R.indices[R.indptr[k]:R.indptr[k + 1]]
        vals = np.abs(R.data[R.indptr[k]:R.indptr[k + 1]])
        js = set()
        vc = cols[cols < V]
        if len(vc):
            w = np.asarray((sp.csr_matrix((vals[cols < V], (np.zeros(len(vc), int), vc)),
                                          shape=(1, V)) @ W).todense()).ravel()
            w /= max(w.sum(), 1e-12)
            js.update(int(j) for j in np.flatnonzero(w > tol))
        for j in cols[cols >= V] - V:
            js.add(int(par[j]) if par[j] >= 0 else int(j))
        out.append(tuple(sorted(js)))
    return out


def observed_points(model: BodyModel, R, observed: np.ndarray,
                    tol: float = OBSERVED_WEIGHT) -> np.ndarray:
    """(F, K) bool: the regressed points (``R (K, V + J)``, e.g. ``joints3d_25``) whose every
    joint (:func:`point_joints`) is observed (``observed (F, J)``, ``BodyFit.observed``)."""
    obs = np.asarray(observed, bool)
    deps = point_joints(model, R, tol)
    return np.stack([obs[:, list(d)].all(axis=1) if d else np.ones(len(obs), bool)
                     for d in deps], axis=1)


def fit_points_observed(model: BodyModel, fit, layout: str = "joints3d_25") -> np.ndarray:
    """(F, K) bool: the points of ``layout`` (``body.joints.regressor``) that are ground truth
    in each frame of ``fit`` (``artifacts.BodyFit``): the frame valid, every joint the point
    hangs on observed (:func:`observed_points`), and a point named like a KP65 keypoint
    (an elbow, a knee) also observed itself where the fit says which keypoints it observed
    (``BodyFit.keypoints_observed``)."""
    from body.joints import regressor
    from formats.skeletons import KP65, LAYOUTS

    pts = observed_points(model, regressor(model, layout), fit.joints_observed())
    kpo = fit.keypoints_observed
    if kpo is not None:
        kpo = np.asarray(kpo, bool)
        for i, name in enumerate(LAYOUTS[layout]):
            if name in KP65:
                pts[:, i] &= kpo[:, KP65.index(name)]
    return pts


def placement_of(shape: ShapeFit) -> Placement:
    """The marker placement a :class:`artifacts.ShapeFit` carries."""
    return Placement(shape.names, np.asarray(shape.marker_face, np.int64),
                     np.asarray(shape.marker_bary, float), np.asarray(shape.marker_offset, float))


def to_shape_fit(betas, pl: Placement, shape_source: str, placement_source: str) -> ShapeFit:
    """A :class:`artifacts.ShapeFit` of ``betas`` and a placement (sources as ShapeFit says)."""
    return ShapeFit(betas=np.asarray(betas, float), marker_names=np.array(pl.names),
                    marker_face=np.asarray(pl.face, np.int64),
                    marker_bary=np.asarray(pl.bary, float),
                    marker_offset=np.asarray(pl.offset, float), shape_source=shape_source,
                    placement_source=placement_source)


# ---------------------------------------------------------------------------- graph


@dataclass(frozen=True)
class GraphSpec:
    """What fixes the graph. parents: reduced tree (-1 root); marker_support: per marker, the
    fitted joints its coefficients may use (fitting.skinned.neighbourhood_support), M of them;
    keypoint_support: the same for the K keypoints; n_cameras C (0 when K = 0);
    camera_model: the lens model of the cameras."""

    parents: tuple[int, ...]
    marker_support: tuple[tuple[int, ...], ...]
    keypoint_support: tuple[tuple[int, ...], ...] = ()
    n_cameras: int = 0
    camera_model: str = "h36m"

    @property
    def n_markers(self) -> int:
        return len(self.marker_support)

    @property
    def n_keypoints(self) -> int:
        return len(self.keypoint_support)

    @property
    def Q(self) -> int:
        return len(self.parents)

    @property
    def n_x(self) -> int:
        return 3 * self.Q + 3

    def name(self) -> str:
        kp = f"_k{self.n_keypoints}c{self.n_cameras}{self.camera_model}" if self.n_keypoints else ""
        nz = sum(len(s) for s in self.marker_support) + sum(len(s) for s in self.keypoint_support)
        return f"markers_q{self.Q}_s{self.n_markers}{kp}_nz{nz}"


class MarkerGraph:
    """The compiled residual function of a :class:`GraphSpec` and its parameter layout."""

    def __init__(self, spec: GraphSpec, opts: compiled.CompileOptions | None = None, log=None):
        if spec.n_keypoints and not spec.n_cameras:
            raise ValueError("keypoints need cameras")
        self.spec = spec
        Q, M, K, C = spec.Q, spec.n_markers, spec.n_keypoints, spec.n_cameras
        self.n_hm = 12 * sum(len(sp) for sp in spec.marker_support)
        self.n_hk = 4 * sum(len(sp) for sp in spec.keypoint_support)
        sizes = [("u", Q * 3), ("Hm", self.n_hm), ("bary", 3 * M), ("offset", M),
                 ("Hk", self.n_hk),
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
        corners = skinned.corners_cs(G, t, self._blocks(p[self.slices["Hm"]], spec.marker_support,
                                                        3), spec.marker_support)
        markers = skinned.surface_points_cs(corners, blk("bary", M, 3), p[self.slices["offset"]])
        r = [terms.L_3d(markers, blk("obs", M, 3), p[self.slices["vis"]])]
        if K:
            kp = skinned.slots_cs(G, t, self._blocks(p[self.slices["Hk"]], spec.keypoint_support),
                                  spec.keypoint_support)  # (K, 3)
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

    @staticmethod
    def _blocks(flat, support, per=1):
        out, o = [], 0
        for sup in support:
            n = per * len(sup)
            out.append(ca.reshape(flat[o:o + 4 * n], 4, n).T)
            o += 4 * n
        return out

    def params(self, u, Hm, obs, vis, Hk=None, cams=None, uv=None, conf=None) -> np.ndarray:
        """Pack the parameter vector (shapes in the module docstring; gaps: vis 0, obs any).
        ``Hm`` (:class:`fitting.skinned.SkinnedPoints`, M points) and ``Hk (K, Q, 4)`` are
        restricted to the spec's supports; the largest weight that falls outside is kept in
        ``self.dropped_weight``."""
        s = self.spec
        if len(Hm) != s.n_markers:
            raise ValueError(f"{len(Hm)} markers for a graph of {s.n_markers}")
        p = np.zeros(self.n_p)
        p[self.slices["u"]] = np.asarray(u, float).reshape(-1)
        p[self.slices["Hm"]], self.dropped_weight = skinned.restrict_points(Hm, s.marker_support)
        p[self.slices["bary"]] = np.asarray(Hm.bary, float).reshape(-1)
        p[self.slices["offset"]] = np.asarray(Hm.offset, float).reshape(-1)
        vis = np.asarray(vis, float).reshape(-1)
        p[self.slices["obs"]] = np.where(vis[:, None] > 0, np.nan_to_num(
            np.asarray(obs, float).reshape(s.n_markers, 3)), 0.0).reshape(-1)
        p[self.slices["vis"]] = vis
        if s.n_keypoints:
            p[self.slices["Hk"]], dk = skinned.restrict(np.asarray(Hk, float), s.keypoint_support)
            self.dropped_weight = max(self.dropped_weight, dk)
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
