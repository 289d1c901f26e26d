"""What an optical marker system records: the true marker positions plus noise, with gaps
where markers are occluded (:func:`observe_markers`, what the demo and bench presets use), and
optionally everything else a real, uncleaned capture has (:func:`capture`, the ``markers``
preset):

- per-subject placement by hand (:func:`realistic_placement`): each marker slid tangentially by
  1.5-2.5 cm (sd) from the template, kept on its segment, with a per-marker skin offset
  (8-25 mm, larger on the pelvis and thigh than on the head);
- soft-tissue artefact (:func:`soft_tissue`): fleshy markers move relative to the bone as a
  smooth function of the adjacent joints' rotations plus a damped wobble driven by the
  marker's acceleration; bony markers (head band, ankles, heels, toes, ASIS) do not move;
- labelling faults (:func:`inject_faults`): label swaps of nearby markers, ghosts (a label
  jumps to a reflection), 1-sample spikes, all recorded in :class:`Faults`;
- the rest of a Vicon file (:func:`model_outputs`, :func:`unlabelled_points`,
  :func:`analog_channels`): Plug-in Gait model outputs (``PELO``, ``LFEA``...), joint angles
  under ``POINT:ANGLES``, unlabelled ``*12`` points, force-plate and EMG analog channels, a
  non-zero first frame.

Every figure comes from ``studio.constants`` (where each says where it comes from).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from body.markers import MarkerSet, closest_surface_points, make_markerset, marker_positions
from formats.c3d import Markers, write_c3d
from geometry import face_normals
from studio import constants as C


@dataclass(frozen=True)
class MocapOptions:
    """noise_sd_m: per-axis Gaussian noise, metres; gap_fraction: share of markers that get
    gaps; gaps_per_marker: (min, max) gaps on an affected marker; gap_len: (min, max) run
    length in samples."""

    noise_sd_m: float = C.MARKER_NOISE_SD_M
    gap_fraction: float = C.MARKER_GAP_FRACTION
    gaps_per_marker: tuple[int, int] = C.MARKER_GAPS_PER_MARKER
    gap_len: tuple[int, int] = C.MARKER_GAP_LEN


def observe_markers(true_xyz: np.ndarray, rng: np.random.Generator,
                    opts: MocapOptions = MocapOptions()) -> tuple[np.ndarray, np.ndarray]:
    """true_xyz: (F, M, 3) metres, world. Returns (observed (F, M, 3) with NaN in gaps,
    gap mask (F, M) bool). Gaps never cover a whole trajectory: runs are at most F // 2 long."""
    F, M, _ = true_xyz.shape
    obs = true_xyz + rng.normal(0.0, opts.noise_sd_m, true_xyz.shape)
    gap = np.zeros((F, M), bool)
    n_aff = int(round(opts.gap_fraction * M))
    for m in rng.choice(M, size=n_aff, replace=False):
        for _ in range(rng.integers(opts.gaps_per_marker[0], opts.gaps_per_marker[1] + 1)):
            hi = min(opts.gap_len[1], max(opts.gap_len[0], F // 2))
            L = int(rng.integers(min(opts.gap_len[0], hi), hi + 1))
            s = int(rng.integers(0, max(1, F - L)))
            gap[s:s + L, m] = True
    obs[gap] = np.nan
    return obs, gap


# ------------------------------------------------------------------------------ options
@dataclass(frozen=True)
class RealismOptions:
    """What makes a capture realistic (defaults: ``studio.constants``). Rates are per minute
    of capture; lengths in samples; distances in metres. ``sta=False`` turns the soft-tissue
    artefact off; rates of 0 turn a fault kind off; ``unlabelled=0`` / ``analog_ratio=0``
    write no unlabelled points / analog channels; ``model_outputs=False`` no Plug-in Gait
    outputs."""

    slide_sd_m: dict = field(default_factory=lambda: dict(C.MARKER_PLACE_SLIDE_SD_M))
    slide_max_m: float = C.MARKER_PLACE_SLIDE_MAX_M
    offset_m: dict = field(default_factory=lambda: dict(C.MARKER_PLACE_OFFSET_M))
    sta: bool = True
    sta_amplitude_m: dict = field(default_factory=lambda: dict(C.MARKER_STA_AMPLITUDE_M))
    wobble_hz: float = C.MARKER_WOBBLE_HZ
    wobble_damping: float = C.MARKER_WOBBLE_DAMPING
    swaps_per_min: float = C.MARKER_SWAPS_PER_MIN
    swap_len: tuple[int, int] = C.MARKER_SWAP_LEN
    swap_max_dist_m: float = C.MARKER_SWAP_MAX_DIST_M
    ghosts_per_min: float = C.MARKER_GHOSTS_PER_MIN
    ghost_len: tuple[int, int] = C.MARKER_GHOST_LEN
    ghost_dist_m: tuple[float, float] = C.MARKER_GHOST_DIST_M
    spikes_per_min: float = C.MARKER_SPIKES_PER_MIN
    spike_m: tuple[float, float] = C.MARKER_SPIKE_M
    gaps: MocapOptions = MocapOptions(gap_len=C.MARKER_REAL_GAP_LEN)
    unlabelled: int = C.MARKER_UNLABELLED
    analog_ratio: int = C.ANALOG_RATIO
    model_outputs: bool = True


# ------------------------------------------------------------------------------ names, segments
def stem(name: str) -> tuple[str, str]:
    """Plug-in Gait stem and side of a marker name: ``"LTHI"`` -> ("THI", "L"), ``"RBAK"`` ->
    ("BAK", "R"), ``"C7"`` -> ("C7", "")."""
    known = set(C.MARKER_PLACE_CLASS) | set(C.MARKER_STA_AMPLITUDE_M)
    if len(name) > 1 and name[0] in "LR" and name[1:] in known:
        return name[1:], name[0]
    return name, ""


def place_class(name: str) -> str:
    """Placement class of a marker (constants.MARKER_PLACE_CLASS; unknown names: "bony")."""
    return C.MARKER_PLACE_CLASS.get(stem(name)[0], "bony")


# Bone-name prefix -> segment; first match wins (spine04/05 belong to the pelvis).
_SEGMENTS = (
    ("head", ("head", "neck", "eye", "jaw")),
    ("pelvis", ("root", "pelvis", "spine04", "spine05")),
    ("trunk", ("spine", "clavicle", "breast")),
    ("upperarm", ("shoulder", "upperarm")),
    ("forearm", ("lowerarm",)),
    ("hand", ("wrist", "metacarpal", "finger")),
    ("thigh", ("upperleg",)),
    ("shank", ("lowerleg",)),
    ("foot", ("foot", "toe")),
)


def bone_segment(bone: str) -> str:
    """Segment of a skinning bone: ``"upperleg02.L"`` -> ``"thigh.L"``, ``"spine02"`` -> ``"trunk"``."""
    side = bone[bone.rfind("."):] if bone.endswith((".L", ".R")) else ""
    for seg, prefixes in _SEGMENTS:
        if bone.startswith(prefixes):
            return seg + side
    return bone


def surface_segments(model, faces: np.ndarray, bary: np.ndarray) -> list[str]:
    """Segment of each surface point (face ids (M,), bary (M, 3)): that of its dominant bone."""
    W = model.weights
    W = W.tocsr() if sp.issparse(W) else sp.csr_matrix(np.asarray(W))
    tri = np.asarray(model.faces)[np.asarray(faces)]  # (M, 3)
    out = []
    for t, b in zip(tri, np.asarray(bary), strict=True):
        w = np.asarray(W[t].toarray()).T @ b  # (J,)
        out.append(bone_segment(model.joint_names[int(np.argmax(w))]))
    return out


# ------------------------------------------------------------------------------ placement
@dataclass(frozen=True, eq=False)
class Placement:
    """A subject's true marker placement. markerset: faces, bary, offsets as placed;
    template_xyz / placed_xyz: (M, 3) the template's and the placed surface points on the
    subject's rest mesh (offset 0, metres, body frame); segments: (M,) the segment each
    marker stays on; halvings: (M,) how often its slide was halved to stay there (-1: the
    template point kept)."""

    markerset: MarkerSet
    template_xyz: np.ndarray
    placed_xyz: np.ndarray
    segments: tuple[str, ...]
    halvings: np.ndarray

    @property
    def slide_m(self) -> np.ndarray:
        """(M,) distance between placed and template surface points, metres."""
        return np.linalg.norm(self.placed_xyz - self.template_xyz, axis=1)

    def arrays(self) -> dict:
        ms = self.markerset
        return {"marker_names": np.array(ms.names), "marker_face": ms.faces, "marker_bary": ms.bary,
                "marker_offset": ms.offsets, "template_xyz": self.template_xyz,
                "placed_xyz": self.placed_xyz, "slide_m": self.slide_m,
                "marker_segment": np.array(self.segments), "slide_halvings": self.halvings}


def realistic_placement(model, rest_vertices: np.ndarray, template: MarkerSet,
                        rng: np.random.Generator, opts: RealismOptions = RealismOptions()) -> Placement:
    """Place ``template`` on one subject as a person would by hand: each marker slid along the
    surface (tangential, sd per class ``opts.slide_sd_m``, capped at ``opts.slide_max_m``) to
    the closest surface point; a slide that leaves the template point's segment (dominant
    skinning bone, :func:`bone_segment`) is halved until it does not (constants
    .MARKER_PLACE_HALVINGS times, then the template point is kept). Offsets are drawn per
    marker from ``opts.offset_m`` of its class. rest_vertices: (V, 3) the subject's rest mesh."""
    V0 = np.asarray(rest_vertices, float)
    M = len(template)
    names = template.names
    p0 = marker_positions(V0, model.faces, template.with_offsets(0.0))
    n0 = face_normals(V0, np.asarray(model.faces)[template.faces])
    sd = np.array([opts.slide_sd_m[place_class(n)] for n in names])
    d = rng.normal(0.0, 1.0, (M, 3)) * sd[:, None]
    d -= (d * n0).sum(1, keepdims=True) * n0
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.minimum(1.0, opts.slide_max_m / np.maximum(norm, 1e-12))
    lo_hi = np.array([opts.offset_m[place_class(n)] for n in names])
    offsets = rng.uniform(lo_hi[:, 0], lo_hi[:, 1])
    seg0 = surface_segments(model, template.faces, template.bary)
    faces = template.faces.copy()
    bary = template.bary.copy()
    halv = np.full(M, -1)
    todo = np.arange(M)
    for k in range(C.MARKER_PLACE_HALVINGS + 1):
        if not len(todo):
            break
        f, b, _ = closest_surface_points(V0, model.faces, p0[todo] + d[todo] / 2 ** k)
        seg = surface_segments(model, f, b)
        ok = np.array([s == seg0[m] for s, m in zip(seg, todo, strict=True)])
        faces[todo[ok]], bary[todo[ok]], halv[todo[ok]] = f[ok], b[ok], k
        todo = todo[~ok]
    ms = make_markerset(names, faces, bary, offsets)
    placed = marker_positions(V0, model.faces, ms.with_offsets(0.0))
    return Placement(ms, p0, placed, tuple(seg0), halv)


# ------------------------------------------------------------------------------ soft tissue
def surface_frames(vertices: np.ndarray, faces: np.ndarray, markerset: MarkerSet) -> np.ndarray:
    """(F, M, 3, 3) orthonormal frames of the marker faces, rows (t1, t2, n): t1 along the
    face's first edge, n the outward normal. vertices: (F, V, 3)."""
    tri = np.asarray(faces)[markerset.faces]
    v = np.asarray(vertices, float)
    a, b = v[:, tri[:, 0]], v[:, tri[:, 1]]
    n = face_normals(v, tri)
    t1 = b - a
    t1 -= (t1 * n).sum(-1, keepdims=True) * n
    t1 /= np.maximum(np.linalg.norm(t1, axis=-1, keepdims=True), 1e-12)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=-2)


@dataclass(frozen=True, eq=False)
class SoftTissue:
    """The STA of a capture, world metres: joint (F, M, 3) the joint-angle term, wobble
    (F, M, 3) the damped response to accelerations, total (F, M, 3) their sum capped at
    constants.MARKER_STA_MAX_M; amplitude (M,) the peak of the joint term per marker (0: a bony
    marker, no STA at all); joints: per marker the joint indices that drive it."""

    joint: np.ndarray
    wobble: np.ndarray
    total: np.ndarray
    amplitude: np.ndarray
    joints: tuple[tuple[int, ...], ...]


def sta_joints(names, joint_names) -> tuple[tuple[int, ...], ...]:
    """Per marker, the indices of the joints whose rotations drive its STA (empty: none)."""
    out = []
    for n in names:
        st, side = stem(n)
        pats = C.MARKER_STA_JOINTS.get(st, ())
        out.append(tuple(joint_names.index(p.format(s=side or "L")) for p in pats
                         if p.format(s=side or "L") in joint_names))
    return tuple(out)


def _wobble_system(hz: float, f0: float, zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation of x'' + 2 zeta w x' + w^2 x = u (state (x, x'))."""
    from scipy.linalg import expm

    w = 2 * np.pi * f0
    A = np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]])
    B = np.array([0.0, 1.0])
    Ad = expm(A / hz)
    Bd = np.linalg.solve(A, (Ad - np.eye(2)) @ B)
    return Ad, Bd


def soft_tissue(names, pose: np.ndarray, joint_names, frames: np.ndarray, rigid_xyz: np.ndarray,
                hz: float, rng: np.random.Generator, opts: RealismOptions = RealismOptions()) -> SoftTissue:
    """Soft-tissue artefact of markers ``names`` over a motion.

    pose: (F, J, 3) local axis-angle of the joints; frames: (F, M, 3, 3) the marker surface
    frames (:func:`surface_frames`); rigid_xyz: (F, M, 3) the markers rigidly attached to the
    skin (metres, world); hz: sample rate. Joint term, in the marker's surface frame:
    ``A * tanh(W theta / constants.MARKER_STA_ANGLE_REF_RAD)`` with theta the driving joints'
    rotation vectors (zero at the rest pose, where the markers were placed), W a random (3, 3k)
    matrix with unit rows per marker, A the stem's amplitude (constants.MARKER_STA_AMPLITUDE_M),
    the normal component scaled by constants.MARKER_STA_NORMAL_SHARE. Wobble: a
    mass-spring-damper (``opts.wobble_hz``, ``opts.wobble_damping``) driven by minus the rigid
    marker's acceleration, gain A x constants.MARKER_WOBBLE_GAIN_PER_M."""
    names = tuple(names)
    F, M = len(pose), len(names)
    idx = sta_joints(names, tuple(joint_names))
    amp = np.array([opts.sta_amplitude_m.get(stem(n)[0], 0.0) if opts.sta and idx[m] else 0.0
                    for m, n in enumerate(names)])
    joint = np.zeros((F, M, 3))
    share = np.array([1.0, 1.0, C.MARKER_STA_NORMAL_SHARE])
    for m in range(M):
        k = len(idx[m])
        W = rng.normal(size=(3, 3 * max(k, 1)))
        W /= np.linalg.norm(W, axis=1, keepdims=True)
        if amp[m] == 0:
            continue
        th = pose[:, list(idx[m])].reshape(F, 3 * k)
        local = amp[m] * np.tanh(th @ W.T / C.MARKER_STA_ANGLE_REF_RAD) * share
        joint[:, m] = np.einsum("fk,fkd->fd", local, frames[:, m])
    wob = np.zeros((F, M, 3))
    fleshy = np.flatnonzero(amp > 0)
    if len(fleshy) and F > 2:
        acc = np.gradient(np.gradient(rigid_xyz[:, fleshy], axis=0), axis=0) * hz * hz
        acc = np.nan_to_num(acc)
        gain = amp[fleshy] * C.MARKER_WOBBLE_GAIN_PER_M
        Ad, Bd = _wobble_system(hz, opts.wobble_hz, opts.wobble_damping)
        x = np.zeros((2,) + acc.shape[1:])
        for f in range(F):
            u = -gain[:, None] * acc[f]
            x = np.einsum("ab,b...->a...", Ad, x) + Bd[:, None, None] * u
            wob[f, fleshy] = x[0]
    total = joint + wob
    mag = np.linalg.norm(total, axis=-1, keepdims=True)
    total = total * np.minimum(1.0, C.MARKER_STA_MAX_M / np.maximum(mag, 1e-12))
    return SoftTissue(joint, wob, total, amp, idx)


# ------------------------------------------------------------------------------ faults
@dataclass(frozen=True, eq=False)
class Faults:
    """Labelling faults put into a capture (sample indices of the capture, 0-based; ``end``
    exclusive). swaps: (Ns, 4) int ``(a, b, start, end)``: labels a and b carry each other's
    trajectory; ghosts: (Ng, 3) int ``(m, start, end)``: label m sits at ``ghost_xyz`` (Ng, 3)
    metres, a reflection; spikes: (Nk, 2) int ``(m, sample)``: label m is off by
    ``spike_offset`` (Nk, 3) metres for that one sample."""

    swaps: np.ndarray
    ghosts: np.ndarray
    ghost_xyz: np.ndarray
    spikes: np.ndarray
    spike_offset: np.ndarray

    @staticmethod
    def empty() -> Faults:
        return Faults(np.zeros((0, 4), int), np.zeros((0, 3), int), np.zeros((0, 3)),
                      np.zeros((0, 2), int), np.zeros((0, 3)))

    def mask(self, F: int, M: int) -> np.ndarray:
        """(F, M) bool: samples where a label does not carry its own marker."""
        out = np.zeros((F, M), bool)
        for a, b, s, e in self.swaps:
            out[s:e, [a, b]] = True
        for m, s, e in self.ghosts:
            out[s:e, m] = True
        for m, s in self.spikes:
            out[s, m] = True
        return out

    def arrays(self) -> dict:
        return {"fault_swaps": self.swaps, "fault_ghosts": self.ghosts,
                "fault_ghost_xyz": self.ghost_xyz, "fault_spikes": self.spikes,
                "fault_spike_offset": self.spike_offset}

    @staticmethod
    def from_arrays(d) -> Faults:
        return Faults(*(np.asarray(d[k]) for k in ("fault_swaps", "fault_ghosts", "fault_ghost_xyz",
                                                    "fault_spikes", "fault_spike_offset")))

    def as_json(self, names, first_frame: int = 0) -> dict:
        """Readable lists; ``frames`` are C3D frame numbers (1-based: first_frame + 1 + sample)."""
        fr = first_frame + 1
        return {
            "swaps": [{"markers": [names[a], names[b]], "samples": [int(s), int(e)],
                       "frames": [int(s) + fr, int(e) - 1 + fr]} for a, b, s, e in self.swaps],
            "ghosts": [{"marker": names[m], "samples": [int(s), int(e)],
                        "frames": [int(s) + fr, int(e) - 1 + fr],
                        "xyz_m": [round(float(x), 4) for x in p]}
                       for (m, s, e), p in zip(self.ghosts, self.ghost_xyz, strict=True)],
            "spikes": [{"marker": names[m], "sample": int(s), "frame": int(s) + fr,
                        "offset_m": [round(float(x), 4) for x in o]}
                       for (m, s), o in zip(self.spikes, self.spike_offset, strict=True)],
        }


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def swap_candidates(xyz: np.ndarray, max_dist_m: float) -> np.ndarray:
    """(P, 2) pairs of markers whose median distance over the capture is below max_dist_m
    (the pairs an auto-labeller confuses). xyz: (F, M, 3), NaN allowed."""
    d = np.nanmedian(np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=-1), axis=0)
    a, b = np.nonzero(np.triu(d < max_dist_m, 1))
    return np.stack([a, b], 1)


def inject_faults(obs: np.ndarray, gap: np.ndarray, hz: float, rng: np.random.Generator,
                  opts: RealismOptions = RealismOptions(), ref_xyz: np.ndarray | None = None
                  ) -> tuple[np.ndarray, Faults]:
    """Put labelling faults into observed trajectories (F, M, 3) (NaN in ``gap`` (F, M)): counts
    are Poisson of the rates of ``opts`` over the capture's length; each fault lies on samples
    where its markers are visible and no other fault is. ref_xyz: (F, M, 3) positions that decide
    which markers are near each other (default: obs). Returns (a faulted copy, Faults)."""
    F, M, _ = obs.shape
    out = obs.copy()
    busy = gap.copy()
    minutes = F / hz / 60.0
    swaps, ghosts, gxyz, spikes, soff = [], [], [], [], []

    def window(markers, lo_hi):
        for _ in range(40):
            L = int(rng.integers(lo_hi[0], lo_hi[1] + 1))
            if L > F:
                return None
            s = int(rng.integers(0, F - L + 1))
            if not busy[s:s + L, markers].any():
                return s, s + L
        return None

    pairs = swap_candidates(obs if ref_xyz is None else ref_xyz, opts.swap_max_dist_m)
    for _ in range(rng.poisson(opts.swaps_per_min * minutes) if len(pairs) else 0):
        a, b = (int(x) for x in pairs[rng.integers(len(pairs))])
        w = window([a, b], opts.swap_len)
        if w is None:
            continue
        s, e = w
        out[s:e, a], out[s:e, b] = obs[s:e, b], obs[s:e, a]
        busy[s:e, [a, b]] = True
        swaps.append((a, b, s, e))
    for _ in range(rng.poisson(opts.ghosts_per_min * minutes)):
        m = int(rng.integers(M))
        w = window([m], opts.ghost_len)
        if w is None:
            continue
        s, e = w
        p = obs[s, m] + _unit(rng, 1)[0] * rng.uniform(*opts.ghost_dist_m)
        out[s:e, m] = p
        busy[s:e, m] = True
        ghosts.append((m, s, e))
        gxyz.append(p)
    for _ in range(rng.poisson(opts.spikes_per_min * minutes)):
        m = int(rng.integers(M))
        w = window([m], (1, 1))
        if w is None:
            continue
        s = w[0]
        o = _unit(rng, 1)[0] * rng.uniform(*opts.spike_m)
        out[s, m] = obs[s, m] + o
        busy[s, m] = True
        spikes.append((m, s))
        soff.append(o)
    f = Faults(np.array(swaps, int).reshape(-1, 4), np.array(ghosts, int).reshape(-1, 3),
               np.array(gxyz, float).reshape(-1, 3), np.array(spikes, int).reshape(-1, 2),
               np.array(soff, float).reshape(-1, 3))
    return out, f


# ------------------------------------------------------------------------------ the rest of the file
def _euler_deg(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("xyz", degrees=True).reshape(R.shape[:-2] + (3,))


def model_outputs(joints: np.ndarray, joint_rot: np.ndarray, pose: np.ndarray,
                  joint_names) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """Vicon Plug-in Gait model outputs from the true skeleton: segment origin and anterior /
    lateral / proximal axis points 100 mm out (``PELO PELA PELL PELP``, femur ``LFEO``...,
    tibia ``LTIO``...; metres) and joint angles in degrees (``LHipAngles``...; Euler xyz of
    the local rotations, ``LPelvisAngles`` of the global pelvis), to be declared under
    ``POINT:ANGLES``. joints (F, J, 3), joint_rot (F, J, 3, 3) world, pose (F, J, 3).
    Returns ({label: (F, 3)}, angle labels)."""
    from body.rotations import rodrigues

    jn = tuple(joint_names)
    pts: dict[str, np.ndarray] = {}
    segs = [("PEL", "root", "root")]
    for s in ("L", "R"):
        segs += [(f"{s}FE", f"lowerleg01.{s}", f"upperleg01.{s}"), (f"{s}TI", f"foot.{s}", f"lowerleg01.{s}")]
    for lab, origin, rot in segs:
        o = joints[:, jn.index(origin)]
        G = joint_rot[:, jn.index(rot)]
        pts[lab + "O"] = o
        for k, ax in enumerate("LAP"):  # lateral x, anterior -y (the body faces -y), proximal z
            sgn = -1.0 if ax == "A" else 1.0
            pts[lab + ax] = o + 0.1 * sgn * G[:, :, k]
    angles = []
    for s in ("L", "R"):
        for lab, j in (("Hip", f"upperleg01.{s}"), ("Knee", f"lowerleg01.{s}"), ("Ankle", f"foot.{s}")):
            pts[f"{s}{lab}Angles"] = _euler_deg(rodrigues(pose[:, jn.index(j)]))
            angles.append(f"{s}{lab}Angles")
    pts["LPelvisAngles"] = _euler_deg(joint_rot[:, 0])
    angles.append("LPelvisAngles")
    return pts, tuple(angles)


def unlabelled_points(n: int, F: int, centre: np.ndarray, rng: np.random.Generator,
                      first_id: int | None = None) -> dict[str, np.ndarray]:
    """``n`` unlabelled trajectories ``*12``, ``*13``... (Vicon's names for points it could not
    label): static reflections somewhere in the volume around ``centre`` (3,), jittering by a
    millimetre, visible in a few bursts (constants.MARKER_UNLABELLED_VISIBLE of the samples),
    NaN otherwise. Metres, world."""
    k0 = int(rng.integers(5, 40)) if first_id is None else first_id
    out = {}
    for i in range(n):
        p = np.asarray(centre, float) + np.array([*rng.uniform(-1.5, 1.5, 2), 0.0])
        p[2] = rng.uniform(0.0, 2.0)
        x = np.full((F, 3), np.nan)
        want = int(C.MARKER_UNLABELLED_VISIBLE * F)
        while np.isfinite(x[:, 0]).sum() < want:
            L = int(rng.integers(3, max(4, F // 8)))
            s = int(rng.integers(0, max(1, F - L)))
            x[s:s + L] = p + rng.normal(0, 0.001, (min(L, F - s), 3))
        out[f"*{k0 + i}"] = x
    return out


def body_mass(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mass (kg) of a closed mesh at constants.BODY_DENSITY (divergence theorem volume)."""
    v = np.asarray(vertices, float)[np.asarray(faces)]
    vol = abs(np.einsum("fi,fi->f", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum()) / 6.0
    return float(vol * C.BODY_DENSITY)


def analog_channels(joints: np.ndarray, joint_names, mass_kg: float, hz: float, ratio: int,
                    plate_centre: np.ndarray, rng: np.random.Generator
                    ) -> tuple[dict[str, np.ndarray], dict[str, str], dict]:
    """Analog channels at ``ratio`` x the point rate: one force plate (``Force.Fx1`` ...
    ``Moment.Mz1``, N and N.mm, the plate's coordinates = world axes, origin at its surface
    centre ``plate_centre`` (3,)) loaded by the feet standing on it (the body's weight and
    pelvis acceleration shared by the feet on the floor), with amplifier offsets and noise; two
    EMG channels (``Voltage.LVL``, ``Voltage.RVL``, V) of noise whose envelope follows the
    knees' angular speed. joints: (F, J, 3). Returns (channels {label: (F * ratio,)}, units,
    C3D parameters: the ``FORCE_PLATFORM`` group)."""
    jn = tuple(joint_names)
    F = len(joints)
    t = np.arange(F) / hz
    ta = np.arange(F * ratio) / (hz * ratio)
    root = joints[:, 0]
    acc = np.gradient(np.gradient(root, axis=0), axis=0) * hz * hz if F > 2 else np.zeros_like(root)
    feet = np.stack([joints[:, jn.index("foot.L")], joints[:, jn.index("foot.R")]], 1)  # (F, 2, 3)
    on_floor = feet[..., 2] < feet[..., 2].min() + 0.03
    half = np.array(C.FORCE_PLATE_SIZE_M) / 2
    on_plate = on_floor & np.all(np.abs(feet[..., :2] - plate_centre[:2]) < half, axis=-1)
    share = on_plate.sum(1) / np.maximum(on_floor.sum(1), 1)
    force = -share[:, None] * mass_kg * (acc + np.array([0.0, 0.0, 9.81]))  # on the plate
    w = on_plate / np.maximum(on_plate.sum(1, keepdims=True), 1)
    cop = np.einsum("fk,fkd->fd", w, feet[..., :2]) - plate_centre[:2]
    cop[share == 0] = 0.0
    mom = np.stack([cop[:, 1] * force[:, 2], -cop[:, 0] * force[:, 2], np.zeros(F)], 1) * 1000.0
    ch, units = {}, {}
    for k, ax in enumerate("xyz"):
        ch[f"Force.F{ax}1"], units[f"Force.F{ax}1"] = np.interp(ta, t, force[:, k]), "N"
    for k, ax in enumerate("xyz"):
        ch[f"Moment.M{ax}1"], units[f"Moment.M{ax}1"] = np.interp(ta, t, mom[:, k]), "Nmm"
    for lab in list(ch):
        scale = C.FORCE_NOISE_N * (1000.0 if lab.startswith("Moment") else 1.0)
        ch[lab] = ch[lab] + rng.normal(0, C.FORCE_OFFSET_N) * (100.0 if lab.startswith("Moment") else 1.0) \
            + rng.normal(0, scale, len(ta))
    for s in ("L", "R"):
        knee = joints[:, jn.index(f"lowerleg01.{s}")] - joints[:, jn.index(f"upperleg01.{s}")]
        speed = np.linalg.norm(np.gradient(knee, axis=0), axis=1) * hz if F > 1 else np.zeros(F)
        env = 0.1 + np.interp(ta, t, speed) / 0.5
        ch[f"Voltage.{s}VL"], units[f"Voltage.{s}VL"] = rng.normal(0, C.EMG_NOISE_V, len(ta)) * env, "V"
    cx, cy, cz = (np.asarray(plate_centre, float) * 1000.0).tolist()
    hx, hy = (half * 1000.0).tolist()
    corners = np.array([[cx + hx, cy + hy, cz], [cx - hx, cy + hy, cz],
                        [cx - hx, cy - hy, cz], [cx + hx, cy - hy, cz]]).T[:, :, None]  # (3, 4, 1)
    params = {"FORCE_PLATFORM": {"USED": [1], "TYPE": [2], "ZERO": [1, 0],
                                 "CORNERS": corners, "ORIGIN": np.array([[0.0], [0.0], [-40.0]]),
                                 "CHANNEL": np.arange(1.0, 7.0)[:, None]}}
    return ch, units, params


# ------------------------------------------------------------------------------ a whole capture
@dataclass(frozen=True, eq=False)
class Capture:
    """One realistic capture of one subject. markers: what the C3D's marker labels carry (NaN
    gaps, faults in, ``first_frame`` set); rigid_xyz (F, M, 3): the markers rigidly on the
    true skin (no STA, no noise); sta: the soft-tissue artefact; gap (F, M); faults; extra:
    non-marker points ``{label: (F, 3)}`` (model outputs in metres, angles in degrees,
    unlabelled ``*N``); angles: labels of ``extra`` that are angles; analogs, analog_units,
    parameters: what :func:`formats.c3d.write_c3d` writes besides the points."""

    markers: Markers
    rigid_xyz: np.ndarray
    sta: SoftTissue
    gap: np.ndarray
    faults: Faults
    extra: dict
    angles: tuple[str, ...]
    analogs: dict
    analog_units: dict
    parameters: dict

    @property
    def clean_xyz(self) -> np.ndarray:
        """(F, M, 3) where each marker really is: rigid + STA (what a perfect labeller sees)."""
        return self.rigid_xyz + self.sta.total

    def write(self, path: str | Path) -> Path:
        return write_c3d(path, self.markers, extra_points=self.extra, angles=self.angles,
                         analogs=self.analogs or None, analog_units=self.analog_units,
                         parameters=self.parameters)

    def gt_arrays(self) -> dict:
        """Ground-truth arrays (gt row i = capture sample i = C3D frame first_frame + 1 + i)."""
        F, M = self.gap.shape
        return {"marker_names": np.array(self.markers.names), "markers_true": self.rigid_xyz,
                "markers_sta": self.sta.total, "markers_sta_joint": self.sta.joint,
                "markers_sta_amplitude": self.sta.amplitude, "markers_gap": self.gap,
                "markers_fault": self.faults.mask(F, M), "first_frame": self.markers.first_frame,
                "c3d_frames": self.markers.first_frame + 1 + np.arange(F),
                "mocap_hz": self.markers.rate_hz, **self.faults.arrays()}


def capture(model, markerset: MarkerSet, vertices: np.ndarray, joints: np.ndarray,
            joint_rot: np.ndarray, pose: np.ndarray, hz: float, first_frame: int, subject: str,
            rng: np.random.Generator, opts: RealismOptions = RealismOptions(),
            plate_centre: np.ndarray | None = None) -> Capture:
    """A realistic capture of one subject wearing ``markerset``: vertices (F, V, 3), joints
    (F, J, 3), joint_rot (F, J, 3, 3) of the true motion (``body.forward``), pose (F, J, 3) its
    local axis-angle, hz the point rate, first_frame the 0-based C3D frame of sample 0.
    Order: rigid markers -> + STA -> noise and gaps (``opts.gaps``) -> labelling faults; then
    model outputs, unlabelled points and analog channels. Each part draws from its own stream
    spawned from ``rng``."""
    r_sta, r_obs, r_flt, r_unl, r_ana = rng.spawn(5)
    # only the vertices of the marker faces (vertices may be a long float32 sequence)
    used, inv = np.unique(np.asarray(model.faces)[markerset.faces], return_inverse=True)
    local = make_markerset(markerset.names, np.arange(len(markerset)), markerset.bary, markerset.offsets)
    Vm = np.asarray(vertices[:, used], dtype=np.float64)
    tri = inv.reshape(-1, 3)
    rigid = marker_positions(Vm, tri, local)
    frames = surface_frames(Vm, tri, local)
    sta = soft_tissue(markerset.names, pose, model.joint_names, frames, rigid, hz, r_sta, opts)
    clean = rigid + sta.total
    obs, gap = observe_markers(clean, r_obs, opts.gaps)
    obs, faults = inject_faults(obs, gap, hz, r_flt, opts, ref_xyz=clean)
    F = len(obs)
    extra, angles = model_outputs(joints, joint_rot, pose, model.joint_names) if opts.model_outputs \
        else ({}, ())
    if opts.unlabelled:
        extra.update(unlabelled_points(opts.unlabelled, F, np.nanmean(joints[:, 0], 0) * [1, 1, 0], r_unl))
    analogs, units, params = {}, {}, {}
    if opts.analog_ratio:
        pc = np.array([*joints[0, 0, :2], 0.0]) if plate_centre is None else np.asarray(plate_centre, float)
        mass = body_mass(np.asarray(vertices[0], np.float64), model.faces)
        analogs, units, params = analog_channels(joints, model.joint_names, mass, hz, opts.analog_ratio,
                                                 pc, r_ana)
    mk = Markers(markerset.names, obs, hz, int(first_frame), subject)
    return Capture(mk, rigid, sta, gap, faults, extra, angles, analogs, units, params)
