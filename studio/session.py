"""Generate a whole capture session from a :class:`studio.plan.SessionPlan`: subjects and their
scans, then per sequence the motion, the C3D, the calibration, the videos, the contact
annotation, the ground truth and a contact sheet; finally the recipe.

Ground truth (``<out>/gt/``, never read by the pipeline):

- ``gt/session.json``: seed, plan, per-sequence facts (who wears the markers, contact frames,
  the deepest true interpenetration by ``geometry.interpenetration``), the studio's
  source hash;
- ``gt/subjects/<id>.npz``: ``betas (S,)``, ``phenotypes (6,)``, ``local_changes (L,)``,
  the scan's pose (``scan_R (3, 3)``, ``scan_T (3,)``, pose 0) and ``scan_vertices (V, 3)``;
  ``gt/subjects/<id>_markers.json``: the subject's true marker placement (body.markers JSON);
- ``gt/<group>/<action>.npz`` per sequence, person axis first, person 0 = the marker wearer
  (CHI3D): ``subjects (2,)``, ``betas (2, S)``, ``body_pose (2, F, J, 3)`` local axis-angle,
  ``global_orient (2, F, 3, 3)``, ``transl (2, F, 3)``, ``joints (2, F, J, 3)``,
  ``joints3d_25 (2, F, 25, 3)``, ``vertices (2, F, V, 3) float32``, ``faces (T, 3)``;
  ``frames (F,)``, ``fps``; mocap: ``marker_names (M,)``, ``markers_true (Fm, M, 3)`` (no
  noise), ``markers_gap (Fm, M)``, ``mocap_hz``, ``sync_offset_s``, ``mocap_of_frame (F,)``
  (the C3D sample of each video frame); contact: ``contact_start``, ``contact_end``,
  ``contact_frame``, ``signature_faces (P, 2)``, ``signature_regions (P, 2)``,
  ``signature_dist (P,)``, ``min_dist (F,)``;
- ``gt/<group>/joints3d_25/<action>.json``: the same joints in CHI3D's file format.

With ``plan.marker_realism`` the marker placement and capture are those of
:func:`studio.mocap.capture` and the sequence npz also holds its ground truth (below; first
frame 0).

The realistic studio (``studio.lab``; the demo and bench presets) adds, per plan option:

- ``lab``: the lab room, the second rig and the bystander are drawn in every video; the
  bystander's truth is in the sequence npz (``bystander_betas``, ``bystander_body_pose``,
  ``bystander_global_orient``, ``bystander_transl``, ``bystander_joints (F, J, 3)``) and its
  spot and least distance to the subjects in ``gt/session.json`` (``sequences.<id>.bystander``);
  a clean plate per camera (the empty room: ``<group>/videos/<camera>/clean_plate.mp4``, the
  same look as the camera's videos) listed in ``gt/session.json`` ``realism.clean_plates``
  (the recipe schema has no field for it: a stage finds it beside the camera's videos);
- ``camera_look``: ``realism.camera_looks`` (gain, white balance, vignetting, noise, JPEG
  quality, shutter per camera) and ``realism.compression`` (the codec used);
- ``calib_error``: the recipe's calibration is perturbed; the true cameras are
  ``gt/<group>/true/camera_parameters/<camera>/<action>.json`` (and ``studio.truth`` copies
  them, not the recipe's, to ``gt/<group>/camera_parameters``); the error per camera in
  ``realism.calibration_error``;
- ``desync_frames``: ``realism.desync`` (the camera, frames, seconds): that camera's frame
  ``f`` shows the motion at frame ``f + desync_frames`` (interpolated); the npz is at the
  frames of the other cameras.

A marker-only session (preset ``markers``, :func:`generate_markers`) has no scans, cameras,
videos or partner; its ground truth:

- ``gt/session.json``: seed, plan, per trial (``<group>/<name>``) its samples, first frame,
  fault counts, gap share, STA figures, seconds; the frame convention;
- ``gt/subjects/<id>.npz``: ``betas``, ``phenotypes``, ``local_changes``, ``sex`` and the true
  placement (:class:`studio.mocap.Placement`: ``marker_names``, ``marker_face``,
  ``marker_bary``, ``marker_offset`` (M,) metres, ``template_xyz`` / ``placed_xyz`` (M, 3) on
  the rest mesh, ``slide_m``, ``marker_segment``); ``gt/subjects/<id>_markers.json`` the same
  placement as a body.markers JSON;
- ``gt/<group>/<name>.npz`` per trial (static and motion), one row per mocap sample: **gt row
  i = C3D sample i, i.e. C3D frame number first_frame + 1 + i** (``c3d_frames (N,)``, 1-based;
  ``first_frame`` 0-based as ``formats.c3d.Markers``): ``subject``, ``kind``, ``betas (S,)``,
  ``body_pose (N, J, 3)``, ``global_orient (N, 3, 3)``, ``transl (N, 3)``, ``joints (N, J, 3)``,
  ``vertices (N, V, 3) float32``, ``faces``, ``mocap_hz``; markers: ``marker_names (M,)``,
  ``markers_true (N, M, 3)`` (rigidly on the skin, no STA, no noise), ``markers_sta (N, M, 3)``
  (soft-tissue displacement; observed = true + sta + noise outside gaps and faults),
  ``markers_sta_joint`` (its joint-angle term), ``markers_sta_amplitude (M,)`` (0: bony),
  ``markers_gap (N, M)``, ``markers_fault (N, M)`` (labels not carrying their own marker),
  ``fault_swaps (Ns, 4)`` (a, b, start, end), ``fault_ghosts (Ng, 3)`` (m, start, end) with
  ``fault_ghost_xyz``, ``fault_spikes (Nk, 2)`` (m, sample) with ``fault_spike_offset``
  (samples 0-based, end exclusive; :class:`studio.mocap.Faults`);
  ``gt/<group>/<name>_faults.json`` the same faults by name with C3D frame numbers.
"""
from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from body import forward, load_model
from body.joints import regress, regressor
from body.markers import (
    closest_surface_points,
    make_markerset,
    marker_positions,
    plug_in_gait,
    save_json,
)
from body.regions import region_map
from calib.io import write_chi3d_cameras
from drawing.render import Renderer
from drawing.sheet import contact_sheet, write_png
from formats.c3d import Markers, write_c3d
from formats.chi3d import write_joints3d_25
from formats.video import fourcc_available, write_mp4
from studio import constants as C
from studio import plan as PL
from studio.contact import annotate, check_motion
from studio.kin import UP, yaw
from studio.lab import (
    Developer,
    bystander_spot,
    bystander_track,
    calibration_error,
    camera_looks,
    dressed_colors,
    interpolate,
    lab_room,
    motion_blur,
    people_at,
)
from studio.mocap import RealismOptions, capture, observe_markers, realistic_placement, stem
from studio.motion import Track, make_timeline, synthesize
from studio.posture import anatomy, arm_directions, idle
from studio.rig import make_rig
from studio.scan import sample_scan, write_ply
from studio.scenarios import SCENES, Cast, place
from studio.subjects import Subject, make_subjects

STUDIO_DIR = Path(__file__).resolve().parent


#: The packages whose code decides what the studio writes (it imports only these, and
#: ``pipeline.procs`` for a worker pool whose workers die with it, which decides nothing).
SOURCE_PACKAGES = ("studio", "body", "calib", "formats", "geometry", "drawing")


def source_hash() -> str:
    """sha256 (16 hex) of every ``.py`` file of SOURCE_PACKAGES: what decides the output."""
    root = STUDIO_DIR.parent
    h = hashlib.sha256()
    for d in SOURCE_PACKAGES:
        for f in sorted((root / d).rglob("*.py")):
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _log(msg: str, warn: bool = False) -> None:
    print(f"[studio] {msg}", flush=True, file=sys.stderr if warn else sys.stdout)


# ------------------------------------------------------------------------------ subjects
def perturbed_markerset(model, subject: Subject, base, rng: np.random.Generator):
    """The nominal marker set slid on the subject's surface (constants.MARKER_SLIDE_SD_M) with
    per-marker offset changes: how one lab places the set on one person."""
    V0 = forward(model, subject.betas, np.zeros((1, model.num_joints, 3)), np.eye(3)[None],
                 np.zeros((1, 3)), rest=subject.person.rest).vertices[0]
    p = marker_positions(V0, model.faces, base.with_offsets(0.0))
    p = p + rng.normal(0, C.MARKER_SLIDE_SD_M, p.shape)
    faces, bary, _ = closest_surface_points(V0, model.faces, p)
    off = base.offsets + rng.normal(0, C.MARKER_OFFSET_SD_M, len(base))
    return make_markerset(base.names, faces, bary, off)


def make_scan(model, subject: Subject, rng: np.random.Generator, out: Path) -> dict:
    """Write the subject's scan (pose 0, random heading and shift on the scanner's floor)."""
    person = subject.person
    R = yaw(rng.uniform(0, 2 * np.pi))
    T = np.array([*rng.uniform(-C.SCAN_SHIFT_M, C.SCAN_SHIFT_M, 2), person.floor_z])
    J = model.num_joints
    o = forward(model, subject.betas, np.zeros((1, J, 3)), R[None], T[None], rest=person.rest)
    V = o.vertices[0]
    holes = []
    for s in ("L", "R"):
        sh = o.joints[0, model.joint_index(f"upperarm01.{s}")]
        centre = o.joints[0, model.joint_index("spine02")]
        lateral = (centre - sh) * np.array([1, 1, 0])
        holes.append(sh - UP * 0.07 + 0.25 * lateral)
    pts, nrm = sample_scan(V, model.faces, np.array(holes), rng)
    write_ply(out, pts, nrm)
    return {"scan_R": R, "scan_T": T, "scan_vertices": V.astype(np.float32),
            "scan_holes": np.array(holes)}


# ------------------------------------------------------------------------------ sequences
def place_pair(tracks: list[Track], people, R_pair: np.ndarray, t_pair: np.ndarray) -> list[Track]:
    """Rigidly move both tracks: v -> R_pair v + t_pair (body model convention: the root
    rotation acts about the rest root joint h0)."""
    out = []
    for tr, p in zip(tracks, people, strict=True):
        h0 = p.rest.joints[0, 0]
        R = R_pair[None] @ tr.R
        T = (tr.T + h0) @ R_pair.T + t_pair - h0
        out.append(Track(tr.pose.copy(), R, T))
    return out


@dataclass
class SequenceMotion:
    """The true motion of one sequence, on the master (mocap) timeline. order: the two
    subjects, person 0 = the marker wearer (CHI3D); tracks: their tracks, same order, placed in
    the studio; cast, scene: what built them (roles: 0 = actor); rng: the sequence's random
    stream, advanced past the motion (markers and annotation draw from it next)."""

    order: list
    tracks: list[Track]
    cast: Cast
    scene: object
    rng: np.random.Generator

    @property
    def video_samples(self) -> np.ndarray:
        return self.cast.tl.video_samples

    def skin(self, model) -> list:
        """The two bodies' model outputs (vertices, joints) at the video frames, in ``order``."""
        vs = self.video_samples
        return [forward(model, s.betas, t.pose[vs], t.R[vs], t.T[vs], rest=s.person.rest)
                for s, t in zip(self.order, self.tracks, strict=True)]


def sequence_motion(plan: PL.SessionPlan, seq: PL.SequencePlan, subjects,
                    attempt: int = 0) -> SequenceMotion:
    """Synthesize the motion of one sequence (no rendering, no files): the scenario's nominal
    motion, its contacts solved by IK and the bodies kept apart, then the pair placed at a random
    heading and shift. attempt: which draw (0: the sequence's own random stream; k > 0: stream k
    of it, see :func:`verified_motion`)."""
    rng = np.random.default_rng([plan.seed, 100 + seq.index] + ([attempt] if attempt else []))
    tl = make_timeline(seq.frames, plan.fps, plan.mocap_hz, plan.sync_offset_s)
    by_id = {s.id: s for s in subjects}
    actor = subjects[seq.actor]
    receiver = subjects[1 - seq.actor]
    cast = Cast([actor.person, receiver.person], [anatomy(actor.person), anatomy(receiver.person)],
                tl, rng)
    scene = SCENES[seq.scenario](cast)
    tracks, _ = synthesize(cast.people, scene.nominal, scene.contacts, scene.movable, tl.video_samples)
    ang = rng.uniform(0, 2 * np.pi)
    shift = np.array([*rng.uniform(-1, 1, 2) * C.PAIR_SHIFT_M, 0.0])
    tracks = place_pair(tracks, cast.people, yaw(ang), shift)
    role_of = {actor.id: 0, receiver.id: 1}
    order = [by_id[seq.markers_on], by_id[seq.partner]]
    return SequenceMotion(order, [tracks[role_of[s.id]] for s in order], cast, scene, rng)


def verified_motion(plan: PL.SessionPlan, seq: PL.SequencePlan, subjects, model):
    """The true motion of one sequence, checked (:func:`studio.contact.check_motion`): a draw
    that goes through the other body or misses its contact (``MotionCheck.ok``) is drawn again
    from the next random stream (the scenario's random choices: spacing, stance, timing of the
    swing...), up to constants.MOTION_ATTEMPTS draws. Returns (motion, its check, the draw's
    index, the skinned outputs at the video frames); when no draw passes, the best one (least
    deep, then most touching) with a warning on stderr: the session's ``gt/session.json``
    records ``motion_ok`` per sequence either way."""
    best = None
    for attempt in range(C.MOTION_ATTEMPTS):
        mo = sequence_motion(plan, seq, subjects, attempt)
        outs = mo.skin(model)
        chk = check_motion(model, mo, [o.vertices for o in outs])
        if chk.ok:
            return mo, chk, attempt, outs
        _log(f"{seq.seq_id}: draw {attempt} rejected ({chk.summary()})")
        key = (round(float(chk.depth.max(initial=0.0)), 4),
               -min((chk.touching(k) for k in chk.gaps), default=1.0))
        if best is None or key < best[0]:
            best = (key, (mo, chk, attempt, outs))
    mo, chk, attempt, outs = best[1]
    _log(f"WARNING {seq.seq_id}: none of {C.MOTION_ATTEMPTS} draws met the motion checks; "
         f"keeping draw {attempt} ({chk.summary()})", warn=True)
    return mo, chk, attempt, outs


@dataclass
class StudioLook:
    """What the realistic studio adds to a session's rendering (``studio.lab``; all None / 0
    in the kind studio). recipe_cams: the calibration written for the recipe (the true
    cameras perturbed, or the true ones); developer: per camera gain, noise, compression (and
    its looks' shutters: the motion blur); bystander: the third person (a Subject) or None;
    desync_cam: index of the camera out of sync (-1: none) by desync_frames."""

    recipe_cams: list
    developer: Developer | None = None
    bystander: Subject | None = None
    desync_cam: int = -1
    desync_frames: float = 0.0
    codecs: tuple = ("mp4v",)
    facts: dict = field(default_factory=dict)

    def time(self, f: int, c: int) -> float:
        """The (fractional) frame camera ``c`` records as its frame ``f``."""
        return f + (self.desync_frames if c == self.desync_cam else 0.0)

    def frames(self, renderer: Renderer, verts: list, faces, colors: list, frames):
        """The recorded views of ``frames`` (indices into verts' (F, V, 3) arrays), one list
        of RGB images per frame: rendered at each camera's time, blurred along the motion
        over its shutter, developed (gain, noise, compression)."""
        cams = renderer.cams
        for f in frames:
            groups: dict = {}
            for c in range(len(cams)):
                groups.setdefault(self.time(f, c), []).append(c)
            views: list = [None] * len(cams)
            for t, cs in groups.items():
                imgs = renderer.render(people_at(verts, faces, colors, t), views=cs)
                for c, img in zip(cs, imgs, strict=True):
                    if self.developer is not None:
                        sh = self.developer.looks[c].shutter
                        a, b = (np.concatenate([interpolate(v, t + e)[::C.BLUR_VERTEX_STRIDE] for v in verts])
                                for e in (-sh / 2, sh / 2))
                        img = self.developer(motion_blur(img, cams[c], a, b), c)
                    views[c] = img
            yield views


def make_look(plan: PL.SessionPlan, model, cams) -> StudioLook:
    """The session's StudioLook from its plan (every draw from its own random stream)."""
    look = StudioLook(list(cams))
    if plan.calib_error:
        look.recipe_cams, look.facts["calibration_error"] = calibration_error(
            cams, np.random.default_rng([plan.seed, 6]))
    if plan.camera_look:
        rng = np.random.default_rng([plan.seed, 8])
        looks = camera_looks(rng, len(cams))
        look.developer = Developer(looks, C.IMAGE_SIZE, rng)
        look.facts["camera_looks"] = {c.name: lk.as_json() for c, lk in zip(cams, looks, strict=True)}
        look.facts["motion_blur"] = "directional, along each pixel's motion over the camera's shutter"
        look.codecs = C.REALISTIC_CODECS
        codec = next((c for c in look.codecs if fourcc_available(c)), None)
        look.facts["compression"] = {
            "jpeg_pass": "each camera's jpeg_quality (the codec's block artefacts)",
            "codec": codec, "h264": codec == "avc1",
            "note": "" if codec == "avc1" else "no H.264 encoder in this OpenCV build: mp4v"}
    if plan.lab:
        by = make_subjects(model, ("bystander", "unused"), np.random.default_rng([plan.seed, 9]))[0]
        look.bystander = replace(by, id="bystander", colors=clothing_colors_of(model, by, 2, plan))
    if plan.desync_frames:
        look.desync_cam = len(cams) - 1
        look.desync_frames = float(plan.desync_frames)
        look.facts["desync"] = {"camera": cams[-1].name, "frames": look.desync_frames,
                                "seconds": round(look.desync_frames / plan.fps, 6)}
    return look


def clothing_colors_of(model, subject: Subject, palette: int, plan: PL.SessionPlan) -> np.ndarray:
    """The subject's colours: flat clothing (the kind studio) or dressed (patterns, skin tone,
    hair: ``plan.camera_look``); palette: index into constants.CLOTHING (2: the bystander's)."""
    if not plan.camera_look:
        return subject.colors
    o = forward(model, subject.betas, np.zeros((1, model.num_joints, 3)), np.eye(3)[None],
                np.zeros((1, 3)), rest=subject.person.rest)
    pal = (C.CLOTHING + (C.BYSTANDER_CLOTHING,))[palette]
    return dressed_colors(subject.part, o.vertices[0], o.joints[0], model.joint_index("head"), pal,
                          np.random.default_rng([plan.seed, 10, palette]))


def generate_sequence(out: Path, plan: PL.SessionPlan, seq: PL.SequencePlan, model, subjects,
                      cams, renderer: Renderer, markersets, reg25, regions,
                      look: StudioLook | None = None) -> dict:
    t0 = time.time()
    look = look or StudioLook(list(cams))
    if look.developer is not None:  # the sequence's own noise stream (any order, any process)
        look.developer.reseed([plan.seed, 8, 100 + seq.index])
    mo, chk, attempt, outs = verified_motion(plan, seq, subjects, model)
    cast, scene, rng, order, trk = mo.cast, mo.scene, mo.rng, mo.order, mo.tracks
    vs = mo.video_samples
    F = seq.frames
    verts = [o.vertices for o in outs]
    j25 = np.stack([regress(reg25, o.vertices, o.joints) for o in outs])
    # markers of the wearer at every mocap sample
    wear = order[0]
    mv = forward(model, wear.betas, trk[0].pose, trk[0].R, trk[0].T, rest=wear.person.rest).vertices
    ms = markersets[wear.id]
    c3d = out / PL.c3d_path(seq)
    real = {}
    if plan.marker_realism:
        full = forward(model, wear.betas, trk[0].pose, trk[0].R, trk[0].T, rest=wear.person.rest)
        cap = capture(model, ms, full.vertices, full.joints, full.joint_rot, trk[0].pose,
                      plan.mocap_hz, 0, wear.id, np.random.default_rng([plan.seed, 5000 + seq.index]))
        cap.write(c3d)
        m_true, m_gap = cap.rigid_xyz, cap.gap
        real = {k: v for k, v in cap.gt_arrays().items()
                if k not in ("marker_names", "markers_true", "markers_gap", "mocap_hz")}
    else:
        m_true = marker_positions(mv, model.faces, ms)
        m_obs, m_gap = observe_markers(m_true, rng)
        write_c3d(c3d, Markers(ms.names, m_obs, plan.mocap_hz, 0, wear.id))
    write_chi3d_cameras(out / seq.group, seq.action, look.recipe_cams)
    if plan.calib_error:  # the truth, copied to gt/<group>/camera_parameters by studio.truth
        write_chi3d_cameras(out / "gt" / seq.group / "true", seq.action, cams)
    # contact truth and annotation
    hint = tuple(cast.frame_of(h) for h in scene.contact_hint)
    feet = np.array([i for i, n in enumerate(regions.names) if n.endswith(C.INCIDENTAL_REGIONS)])
    ct = annotate(verts[0], verts[1], model.faces, regions.face_region, rng, hint,
                  incidental=feet if seq.scenario != "kick" else None)
    # videos
    colors = [s.colors for s in order]
    rverts = list(verts)
    by = {}
    if look.bystander is not None:  # the operator, a few metres behind the subjects
        b = look.bystander
        roots = np.concatenate([o.joints[:, 0, :2] for o in outs])
        xy, face = bystander_spot(np.random.default_rng([plan.seed, 200 + seq.index]), cams, roots,
                                  float(np.ptp(b.person.rest.vertices[0, :, 2])))
        btr = bystander_track(b.person, xy, face, F, plan.fps, np.random.default_rng([plan.seed, 300 + seq.index]))
        bo = forward(model, b.betas, btr.pose, btr.R, btr.T, rest=b.person.rest)
        rverts.append(bo.vertices.astype(np.float32))
        colors.append(b.colors)
        dist = min(float(np.linalg.norm(o.joints[:, :, :2] - bo.joints[:, None, 0, :2], axis=-1).min())
                   for o in outs)
        by = {"bystander_joints": bo.joints.astype(np.float32), "bystander_transl": btr.T,
              "bystander_global_orient": btr.R, "bystander_body_pose": btr.pose,
              "bystander_betas": b.betas}
        seq_by = {"xy": [round(float(v), 3) for v in xy], "min_dist_to_subjects_m": round(dist, 3)}
    tv = time.time()
    write_videos([out / PL.video_path(seq, cam.name) for cam in cams], plan.fps,
                 look.frames(renderer, rverts, model.faces, colors, range(F)), look.codecs)
    tv = time.time() - tv
    # contact sheet at the annotated frame (or the middle frame without contact)
    fr = ct.fr_id if ct.fr_id >= 0 else F // 2
    imgs = next(look.frames(renderer, rverts, model.faces, colors, [fr]))
    pts = verts[0][fr][model.faces[ct.faces[:, 0]]].mean(1) if len(ct.faces) else None
    write_png(out / PL.preview_path(seq), contact_sheet(imgs, cams, f"{seq.seq_id}  frame {fr}", pts))
    # ground truth
    gt = out / PL.gt_path(seq)
    gt.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        gt,
        subjects=np.array([s.id for s in order]),
        betas=np.stack([s.betas for s in order]),
        body_pose=np.stack([t.pose[vs] for t in trk]),
        global_orient=np.stack([t.R[vs] for t in trk]),
        transl=np.stack([t.T[vs] for t in trk]),
        joints=np.stack([o.joints for o in outs]),
        joints3d_25=j25,
        vertices=np.stack(verts).astype(np.float32),
        faces=np.asarray(model.faces, np.int32),
        frames=np.arange(F),
        fps=plan.fps,
        marker_names=np.array(ms.names),
        markers_true=m_true,
        markers_gap=m_gap,
        mocap_hz=plan.mocap_hz,
        sync_offset_s=plan.sync_offset_s,
        mocap_of_frame=vs,
        contact_start=ct.start,
        contact_end=ct.end,
        contact_frame=ct.fr_id,
        signature_faces=ct.faces,
        signature_regions=ct.regions,
        signature_dist=ct.dist,
        min_dist=ct.min_dist,
        **real,
        **by,
    )
    write_joints3d_25(out / "gt" / seq.group / "joints3d_25" / f"{seq.action}.json", j25)
    info = {
        "markers_on": seq.markers_on, "partner": seq.partner, "actor": plan.subjects[seq.actor],
        "scenario": seq.scenario, "frames": F, "contact_start": ct.start, "contact_end": ct.end,
        "contact_frame": ct.fr_id, "signature_pairs": int(len(ct.faces)),
        "max_penetration_mm": round(1000 * float(chk.depth.max(initial=0.0)), 2),
        "contact_touching": {k: round(chk.touching(k), 3) for k in chk.gaps},
        "motion_ok": chk.ok, "motion_draw": attempt,
        "video_seconds": round(tv, 2), "video_frames_per_s": round(F / max(tv, 1e-9), 2),
        "seconds": round(time.time() - t0, 1),
    }
    if by:
        info["bystander"] = seq_by
    _log(f"{seq.seq_id}: {F} frames, contact {ct.start}..{ct.end} (frame {ct.fr_id}, "
         f"{len(ct.faces)} pairs), deepest interpenetration {info['max_penetration_mm']:.1f} mm"
         f"{f' (draw {attempt})' if attempt else ''}, videos {F / max(tv, 1e-9):.1f} frames/s "
         f"({len(cams)} cameras), {info['seconds']} s")
    return info, ct


def write_videos(paths: list[Path], fps: float, frames, codecs: tuple[str, ...] = ("mp4v",)) -> None:
    """Write one MP4 per camera from an iterable of per-frame view lists (each a list of
    (H, W, 3) uint8 RGB, one per path), streaming: one writer thread per file
    (``formats.video.write_mp4`` with the first available of ``codecs``) fed through a small queue, so each frame is rendered once for
    all cameras and never kept."""
    import queue
    import threading

    qs = [queue.Queue(maxsize=4) for _ in paths]
    errors: list[BaseException] = []

    def drain(q):
        while True:
            item = q.get()
            if item is None:
                return
            yield item

    def work(path, q):
        try:
            write_mp4(path, drain(q), fps, codecs)
        except BaseException as e:  # reported by the caller
            errors.append(e)
            while q.get() is not None:  # keep the producer unblocked
                pass

    threads = [threading.Thread(target=work, args=(p, q), daemon=True) for p, q in zip(paths, qs, strict=True)]
    for t in threads:
        t.start()
    try:
        for views in frames:
            for q, img in zip(qs, views, strict=True):
                q.put(img)
    finally:
        for q in qs:
            q.put(None)
        for t in threads:
            t.join()
    if errors:
        raise errors[0]


def signature_json(seqs, cts, regions) -> dict:
    """The group's interaction_contact_signature.json: CHI3D's layout (``fr_id``, ``start_fr``,
    ``end_fr``, ``smplx_signature`` / ``ghum_signature`` left empty: those meshes are not
    ours) plus ``anny_signature`` with the facets and region ids of the Anny mesh (person 0 =
    the marker wearer)."""
    d = {}
    for seq, ct in zip(seqs, cts, strict=True):
        fr = ct.fr_id if ct.fr_id >= 0 else 0
        e = {"fr_id": int(fr)}
        if ct.start >= 0:
            e["start_fr"], e["end_fr"] = int(ct.start), int(ct.end)
        e["smplx_signature"] = {"region_id": [], "face_id": []}
        e["ghum_signature"] = {"region_id": [], "face_id": []}
        e["anny_signature"] = {"region_id": ct.regions.tolist(), "face_id": ct.faces.tolist(),
                               "region_names": [[regions.names[a], regions.names[b]]
                                                for a, b in ct.regions]}
        d[seq.action] = e
    return d


@dataclass
class SessionParts:
    """What every sequence of a session is made with, all drawn from the plan's own random
    streams (so a worker process rebuilds the same from the plan; the marker placements,
    drawn beside the scans, are handed over)."""

    model: object
    cams: list
    subjects: list
    look: StudioLook
    reg25: object
    regions: object
    room: list | None

    @classmethod
    def of(cls, plan: PL.SessionPlan) -> SessionParts:
        model = load_model("anny")
        cams = make_rig(np.random.default_rng([plan.seed, 1]))
        subjects = make_subjects(model, plan.subjects, np.random.default_rng([plan.seed, 2]))
        subjects = [replace(s, colors=clothing_colors_of(model, s, s.index, plan)) for s in subjects]
        room = lab_room(np.random.default_rng([plan.seed, 7]), cams) if plan.lab else None
        return cls(model, cams, subjects, make_look(plan, model, cams),
                   regressor(model, "joints3d_25"), region_map(model), room)


def studio_workers(plan: PL.SessionPlan | PL.MarkerSessionPlan) -> int:
    """How many processes make the session's sequences (or a marker session's trials):
    one per core, at most one per sequence, when they are long enough to pay for a worker's
    start (:data:`constants.PARALLEL_MIN_FRAMES`, ``PARALLEL_MIN_SAMPLES``), else 1; the
    environment's ``MOCAP_STUDIO_WORKERS`` overrides (1: all in this process)."""
    import os

    if isinstance(plan, PL.MarkerSessionPlan):
        units = [t for t in plan.trials if t.kind == "motion"]
        big = len(units) >= 2 and sum(t.samples for t in units) >= C.PARALLEL_MIN_SAMPLES
    else:
        units = list(plan.sequences)
        big = len(units) >= 2 and min(q.frames for q in units) >= C.PARALLEL_MIN_FRAMES
    env = os.environ.get("MOCAP_STUDIO_WORKERS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"MOCAP_STUDIO_WORKERS={env!r}: not a whole number") from None
        if n < 1:
            raise ValueError(f"MOCAP_STUDIO_WORKERS={env!r}: must be 1 or more")
        return max(1, min(n, len(units)))
    return max(1, min(len(os.sched_getaffinity(0)), len(units))) if big else 1


def one_blas_thread(fn):
    """Run ``fn`` with one thread in numpy's BLAS/LAPACK: the studio's numbers depend on the
    summation order, and a session must come out the same in any process, on any number of
    cores and whatever the environment says (``OMP_NUM_THREADS``), as the engine's stages do
    (``pipeline.engine.BLAS_THREADS``)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1):
            return fn(*args, **kwargs)

    return wrapper


@one_blas_thread
def _sequence_job(out: Path, plan: PL.SessionPlan, index: int, markersets: dict):
    """A worker process's sequence (``plan.sequences[index]``): (its facts, its contact)."""
    parts = SessionParts.of(plan)
    seq = plan.sequences[index]
    with Renderer(parts.cams, room=parts.room) as renderer:
        return generate_sequence(out, plan, seq, parts.model, parts.subjects, parts.cams,
                                 renderer, markersets, parts.reg25, parts.regions, parts.look)


def _in_workers(job, calls: list[tuple], workers: int) -> list:
    """``[job(*args) for args in calls]``, ``workers`` at a time in fresh processes (spawned:
    no GL context or thread is inherited; ``pipeline.procs.process_pool``: they die with this
    process), results in call order. The first failure kills the rest."""
    from pipeline.procs import process_pool

    with process_pool(workers) as ex:
        futs = [ex.submit(job, *args) for args in calls]
        return [f.result() for f in futs]


@one_blas_thread
def generate(out: str | Path, plan: PL.SessionPlan | PL.MarkerSessionPlan,
             workers: int | None = None) -> Path:
    """Write the whole session into ``out`` (created). Returns the recipe path. workers: how
    many processes make the sequences (None: :func:`studio_workers`); the files are the same
    for any number."""
    if isinstance(plan, PL.MarkerSessionPlan):
        return generate_markers(out, plan, workers=workers)
    t0 = time.time()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    parts = SessionParts.of(plan)
    model, cams, subjects, look = parts.model, parts.cams, parts.subjects, parts.look
    base = plug_in_gait(model)
    reg25, regions = parts.reg25, parts.regions
    markersets = {}
    rng_s = np.random.default_rng([plan.seed, 3])
    for s in subjects:
        markersets[s.id] = perturbed_markerset(model, s, base, rng_s)
        if plan.marker_realism:  # own stream: the scans stay those of the plan without realism
            markersets[s.id] = realistic_placement(
                model, rest_vertices(model, s), base, np.random.default_rng([plan.seed, 3, s.index])).markerset
        scan = make_scan(model, s, rng_s, out / PL.scan_path(s.id))
        gdir = out / "gt" / "subjects"
        gdir.mkdir(parents=True, exist_ok=True)
        np.savez(gdir / f"{s.id}.npz", betas=s.betas, phenotypes=s.phenotypes,
                 local_changes=s.local_changes, **scan)
        save_json(markersets[s.id], gdir / f"{s.id}_markers.json", model="anny",
                  num_faces=len(model.faces))
    _log(f"subjects and scans ready ({time.time() - t0:.1f} s)")
    infos, cts = {}, []
    workers = studio_workers(plan) if workers is None else max(1, int(workers))
    with Renderer(cams, room=parts.room) as renderer:
        if plan.lab:  # the empty room, as labs record one: one video per camera and group
            plates = {}
            for gi, g in enumerate(sorted({s.group for s in plan.sequences})):
                if look.developer is not None:
                    look.developer.reseed([plan.seed, 8, gi])
                paths = [out / PL.clean_plate_path(g, c.name) for c in cams]
                write_videos(paths, plan.fps, (
                    [look.developer(v, c) if look.developer else v
                     for c, v in enumerate(renderer.render_room())]
                    for _ in range(C.CLEAN_PLATE_FRAMES)), look.codecs)
                plates[g] = {c.name: p.relative_to(out).as_posix() for c, p in zip(cams, paths, strict=True)}
            look.facts["clean_plates"] = plates
        if workers == 1:
            made = [generate_sequence(out, plan, seq, model, subjects, cams, renderer,
                                      markersets, reg25, regions, look)
                    for seq in plan.sequences]
    if workers > 1:
        _log(f"{len(plan.sequences)} sequences in {workers} worker processes")
        made = _in_workers(_sequence_job, [(out, plan, i, markersets)
                                           for i in range(len(plan.sequences))], workers)
    for seq, (info, ct) in zip(plan.sequences, made, strict=True):
        infos[seq.seq_id] = info
        cts.append(ct)
    groups = sorted({s.group for s in plan.sequences})
    for g in groups:
        seqs = [s for s in plan.sequences if s.group == g]
        sig = signature_json(seqs, [c for s, c in zip(plan.sequences, cts, strict=True) if s.group == g],
                             regions)
        (out / g / "interaction_contact_signature.json").write_text(json.dumps(sig))
    meta = {"plan": plan_dict(plan), "sequences": infos, "studio_source": source_hash(),
            "seconds": round(time.time() - t0, 1)}
    if look.facts:
        meta["realism"] = look.facts
    (out / "gt" / "session.json").write_text(json.dumps(meta, indent=1))
    from studio.truth import write_chi3d_truth

    write_chi3d_truth(out, model)
    recipe = out / "recipe.yaml"
    write_recipe(recipe, {**PL.recipe_dict(plan), "stages": {"evaluate": {"truth": "gt"}}})
    _log(f"session {plan.session} written to {out} in {time.time() - t0:.0f} s")
    return recipe


def plan_dict(plan: PL.SessionPlan | PL.MarkerSessionPlan) -> dict:
    """The plan as stored in ``gt/session.json`` (JSON types). The realistic studio's options
    (``plan.REALISM``) only when on (sessions generated before they existed, and every kind
    session, still match their plans)."""
    d = asdict(plan)
    if isinstance(plan, PL.SessionPlan):
        d["sequences"] = [asdict(s) for s in plan.sequences]
        for k in PL.REALISM:
            if not d.get(k):
                d.pop(k, None)
    return json.loads(json.dumps(d))


# ------------------------------------------------------------------------------ marker-only sessions
def rest_vertices(model, subject: Subject) -> np.ndarray:
    """(V, 3) the subject's mesh at pose 0 (body frame)."""
    J = model.num_joints
    return forward(model, subject.betas, np.zeros((1, J, 3)), np.eye(3)[None], np.zeros((1, 3)),
                   rest=subject.person.rest).vertices[0]


def skinned(model, subject: Subject, track: Track, chunk: int = 64):
    """The track skinned in chunks (a long sequence's LBS at once needs GBs): vertices
    (N, V, 3) float32, joints (N, J, 3), joint_rot (N, J, 3, 3)."""
    outs = [forward(model, subject.betas, track.pose[a:a + chunk], track.R[a:a + chunk],
                    track.T[a:a + chunk], rest=subject.person.rest)
            for a in range(0, len(track.pose), chunk)]
    V = np.concatenate([o.vertices.astype(np.float32) for o in outs])
    return V, np.concatenate([o.joints for o in outs]), np.concatenate([o.joint_rot for o in outs])


def static_track(person, n: int, hz: float, rng: np.random.Generator) -> Track:
    """A static calibration trial: standing, arms abducted (constants.STATIC_ARM_ABDUCTION_RAD)
    with slightly bent elbows, breathing and head motion (``studio.posture.idle``, half
    amplitude) and a slight sway: a tilt about the point between the ankles of
    constants.STATIC_SWAY_RAD at constants.STATIC_SWAY_HZ, at a random place and heading."""
    from body.rotations import rodrigues
    from studio.kin import LEFT, UP

    an = anatomy(person)
    pose = np.zeros((person.model.num_joints, 3))
    for s, sgn in (("L", 1.0), ("R", -1.0)):
        a = rng.uniform(*C.STATIC_ARM_ABDUCTION_RAD)
        pose = arm_directions(person, an, pose, s, -UP * np.cos(a) + LEFT * sgn * np.sin(a),
                              rng.uniform(0.1, 0.25))
    t = np.arange(n) / hz
    poses = idle(person, pose, t, rng, 0.5)
    ang = rng.uniform(0, 2 * np.pi)
    tr = place(person, rng.uniform(-0.3, 0.3, 2), [np.cos(ang), np.sin(ang)], n, poses)
    joints, _ = person.fk(tr.pose[:1], tr.R[:1], tr.T[:1])
    c = 0.5 * (joints[0, person.j("foot.L")] + joints[0, person.j("foot.R")])
    tilt = np.zeros((n, 3))
    for ax in range(2):
        f = rng.uniform(*C.STATIC_SWAY_HZ, 2)
        ph = rng.uniform(0, 2 * np.pi, 2)
        tilt[:, ax] = C.STATIC_SWAY_RAD * (np.sin(2 * np.pi * f[0] * t + ph[0])
                                           + 0.5 * np.sin(2 * np.pi * f[1] * t + ph[1])) / 1.5
    Rs = rodrigues(tilt)
    h0 = person.rest.joints[0, 0]
    R = Rs @ tr.R
    T = np.einsum("nab,nb->na", Rs, tr.T + h0 - c) + c - h0
    return Track(tr.pose, R, T)


def trial_track(plan: PL.MarkerSessionPlan, trial: PL.TrialPlan, by_id: dict) -> Track:
    """The true motion of a trial on its mocap samples: a static stance, or the wearer's track
    of the trial's scenario (``sequence_motion``, the other role played by ``trial.partner``;
    contact not checked: nobody sees the partner)."""
    if trial.kind == "static":
        return static_track(by_id[trial.subject].person, trial.samples, plan.mocap_hz,
                            np.random.default_rng([plan.seed, 4500 + trial.index]))
    seq = PL.SequencePlan(index=trial.index, scenario=trial.scenario, group=trial.group,
                          action=trial.name, markers_on=trial.subject, partner=trial.partner,
                          frames=trial.frames, text="", actor=0)
    mo = sequence_motion(plan, seq, [by_id[trial.subject], by_id[trial.partner]])
    tr = mo.tracks[0]
    if len(tr.pose) != trial.samples:
        raise RuntimeError(f"{trial.seq_id}: motion has {len(tr.pose)} samples, plan says {trial.samples}")
    return tr


def generate_trial(out: Path, plan: PL.MarkerSessionPlan, trial: PL.TrialPlan, model, by_id: dict,
                   placements: dict, opts: RealismOptions | None = None) -> dict:
    """Write one trial's C3D and ground truth; returns its facts for ``gt/session.json``."""
    opts = opts or RealismOptions()
    t0 = time.time()
    subj = by_id[trial.subject]
    tr = trial_track(plan, trial, by_id)
    V, Jt, G = skinned(model, subj, tr)
    ms = placements[trial.subject].markerset
    cap = capture(model, ms, V, Jt, G, tr.pose, plan.mocap_hz, trial.first_frame, subj.id,
                  np.random.default_rng([plan.seed, 4000 + trial.index]), opts)
    cap.write(out / PL.trial_c3d_path(trial))
    gt = out / PL.trial_gt_path(trial)
    gt.parent.mkdir(parents=True, exist_ok=True)
    np.savez(gt, subject=subj.id, kind=trial.kind, betas=subj.betas, body_pose=tr.pose,
             global_orient=tr.R, transl=tr.T, joints=Jt, vertices=V,
             faces=np.asarray(model.faces, np.int32), **cap.gt_arrays())
    names = list(ms.names)
    (gt.parent / f"{trial.name}_faults.json").write_text(
        json.dumps(cap.faults.as_json(names, trial.first_frame), indent=1))
    sta = np.linalg.norm(cap.sta.total, axis=-1)  # (N, M)
    stems = np.array([stem(n)[0] for n in names])
    fleshy = cap.sta.amplitude > 0
    info = {
        "subject": subj.id, "kind": trial.kind, "scenario": trial.scenario, "samples": trial.samples,
        "first_frame": trial.first_frame,
        "c3d_frames": [trial.first_frame + 1, trial.first_frame + trial.samples],
        "swaps": int(len(cap.faults.swaps)), "ghosts": int(len(cap.faults.ghosts)),
        "spikes": int(len(cap.faults.spikes)),
        "gap_share": round(float(cap.gap.mean()), 4),
        "sta_rms_mm_fleshy": round(1000 * float(np.sqrt((sta[:, fleshy] ** 2).mean())), 2) if fleshy.any() else 0.0,
        "sta_max_mm": round(1000 * float(sta.max(initial=0.0)), 2),
        "sta_max_mm_by_stem": {st: round(1000 * float(sta[:, stems == st].max(initial=0.0)), 2)
                               for st in sorted(set(stems[fleshy]))},
        "sta_max_mm_bony": round(1000 * float(sta[:, ~fleshy].max(initial=0.0)), 2),
        "seconds": round(time.time() - t0, 1),
    }
    _log(f"{trial.seq_id}: {trial.kind}, {trial.samples} samples from frame {trial.first_frame + 1}, "
         f"{info['swaps']} swaps, {info['ghosts']} ghosts, {info['spikes']} spikes, "
         f"STA rms {info['sta_rms_mm_fleshy']} mm, {info['seconds']} s")
    return info


def _marker_subjects(model, plan: PL.MarkerSessionPlan) -> list:
    ids = tuple(plan.subjects) if len(plan.subjects) == 2 else (plan.subjects[0], f"{plan.subjects[0]}_partner")
    return make_subjects(model, ids, np.random.default_rng([plan.seed, 2]))


@one_blas_thread
def _trial_job(out: Path, plan: PL.MarkerSessionPlan, index: int, placements: dict,
               opts: RealismOptions) -> dict:
    """A worker process's trial (``plan.trials[index]``): its facts."""
    model = load_model("anny")
    by_id = {s.id: s for s in _marker_subjects(model, plan)}
    return generate_trial(out, plan, plan.trials[index], model, by_id, placements, opts)


@one_blas_thread
def generate_markers(out: str | Path, plan: PL.MarkerSessionPlan,
                     opts: RealismOptions | None = None, workers: int | None = None) -> Path:
    """Write a marker-only session (the ``markers`` preset) into ``out``: per subject its true
    placement, a static trial and its motion trials (C3D + ground truth, layout in this module's
    docstring); no rendering. Returns the recipe path. workers: as :func:`generate`'s (each
    trial draws from its own random streams)."""
    t0 = time.time()
    opts = opts or RealismOptions()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = load_model("anny")
    subjects = _marker_subjects(model, plan)
    by_id = {s.id: s for s in subjects}
    base = plug_in_gait(model)
    gdir = out / "gt" / "subjects"
    gdir.mkdir(parents=True, exist_ok=True)
    placements = {}
    for s, sex in zip(subjects, plan.sexes, strict=False):
        pl = realistic_placement(model, rest_vertices(model, s), base,
                                 np.random.default_rng([plan.seed, 3, s.index]), opts)
        placements[s.id] = pl
        np.savez(gdir / f"{s.id}.npz", betas=s.betas, phenotypes=s.phenotypes,
                 local_changes=s.local_changes, sex=sex, **pl.arrays())
        save_json(pl.markerset, gdir / f"{s.id}_markers.json", model="anny", num_faces=len(model.faces))
    workers = studio_workers(plan) if workers is None else max(1, int(workers))
    if workers > 1:
        _log(f"{len(plan.trials)} trials in {workers} worker processes")
        made = _in_workers(_trial_job, [(out, plan, i, placements, opts)
                                        for i in range(len(plan.trials))], workers)
    else:
        made = [generate_trial(out, plan, t, model, by_id, placements, opts) for t in plan.trials]
    infos = {t.seq_id: info for t, info in zip(plan.trials, made, strict=True)}
    meta = {"plan": plan_dict(plan), "trials": infos, "studio_source": source_hash(),
            "frame_convention": "gt row i = C3D sample i = C3D frame number first_frame + 1 + i "
                                "(first_frame 0-based, as formats.c3d.Markers)",
            "seconds": round(time.time() - t0, 1)}
    (out / "gt" / "session.json").write_text(json.dumps(meta, indent=1))
    recipe = out / "recipe.yaml"
    write_recipe(recipe, PL.recipe_dict(plan))
    _log(f"session {plan.session} written to {out} in {time.time() - t0:.0f} s")
    return recipe


def write_recipe(path: Path, recipe: dict, header: str = "") -> Path:
    text = yaml.safe_dump(recipe, sort_keys=False, allow_unicode=True, width=100)
    path.write_text((header + "\n" if header else "") + text)
    return path
