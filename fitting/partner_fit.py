"""Fit the partner (the person without markers) frame after frame from the four views (paper,
"3D Reconstruction in a Controlled Setup"; issue #15).

Per frame ``t`` the unknowns ``x_t = [r (3), T (3), theta ((Q-1)*3)]`` of the fit skeleton
(fitting/skinned.py; shape fixed from ``shape_fit``) minimise

    w_2d rho(L_2d) + w_theta L_theta + w_s L_s(x_t, x_{t-1}) + sum_extra w_e |r_e(x_t)|^2

- ``L_2d``: every KP65 keypoint of the partner detected in any view (body, feet, hands),
  confidence-weighted, with a Geman-McClure ``rho`` per observation (IRLS in ``fitting/lm.py``,
  as in the marker fit): a wrong detection in one view pulls with a bounded force. The
  residual function is ``fitting.reprojection.Reprojection``: the 65 KP65 slots
  (``body.joints.regressor(model, "kp65")`` -> ``fitting.skinned.regressed_coeffs``) posed
  with their exact Jacobian (``fitting.skinned.point_jacobian``) and projected with
  ``calib.project_jacobian``, in numpy (the CasADi graph of 65 slots over 52 joints was 17 MB
  of C and ran interpreted at ~8 ms per evaluation).
- ``L_theta`` (Gaussian + joint limits, ``fitting/priors.py``, with the spine's joints coupled
  so the trunk's bend is shared along it: ``SPINE_COUPLING_DEG``) and ``L_s`` (toward the
  previous frame) are quadratic terms / a box in numpy.
- The extra terms (``L_gp``, ``L_ic``, ``L_sc``, ``L_D``, ``L_N``) are the seam:
  :class:`ExtraTerm` hooks called before each of ``outer_rounds`` LM rounds with the current
  posed mesh (:class:`Posed`) choose the offending points (numpy: winding numbers, nearest
  points, the lowest vertices) and return :class:`Block` s: the points' slot coefficients
  ``H (N, Q, 4)`` and the paper's term (``fitting/terms.py``) as a function of their
  positions, with the targets fixed for the round. :class:`Augmented` appends the blocks' rows
  to the keypoint residual function; LM evaluates them exactly at every step, with
  the exact Jacobian of the points (``fitting.skinned.point_jacobian``: closed-form derivative of the
  reduced-tree skinning, no finite differences), so the graph stays fixed and only the
  offending points cost anything.

The first frame (and the first frame after more than ``reinit_after`` frames without enough
detections) starts from ``fitting.init_pose.init_pose`` (keypoints triangulated across the
views) with a graduated robust scale. The frames before the first one that could be
initialised (the partner hidden at the start: a hug) are then fitted backwards from it
(``backfill``). Frames with too few detections are held at the neighbouring solution and are
not valid; so are frames before the first one fitted, and frames whose median reprojection
error stays above ``max_reproj_px``.

Pure function over typed artifacts (no file I/O): :func:`fit_partner`; the stage adapter
``stages/partner_fit.py`` reads the files and saves the result.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Literal, Protocol

import numpy as np

from artifacts import REASON_CODE, BodyFit, ShapeFit
from artifacts.keypoints import PARTNER, Keypoints2D
from body.joints import regressor
from body.lbs import RestState, forward, rest_state
from body.model import BodyModel
from calib import project
from fitting import collision, lm, priors, robust, skinned, terms
from fitting.init_pose import InitOptions, init_pose
from fitting.marker_fit import GNC_FACTORS, pack, rewrap, unpack
from fitting.marker_graph import OBSERVED_WEIGHT, body_joints, observed_joints
from fitting.reprojection import Reprojection
from fitting.skinned import point_jacobian, subtree
from formats.skeletons import KP65, KP65_FLIP
from formats.skeletons import LEFT_HAND as S_LEFT_HAND
from formats.skeletons import RIGHT_HAND as S_RIGHT_HAND
from geometry import face_normals

# constants
# L_2d costs the mean squared pixel error (1/K per keypoint). L_ic: 1e4 per m^2 of each
# penetrating point (1 cm deep = 1 px^2). L_sc: 10x weaker (the studio's own truth motions
# put an elbow 15-50 mm into the own belly by the proxy's reckoning: at 1e4 L_sc pushed the
# fit away from the truth, MPJPE 26 -> 34 mm on Handshake frames). L_D: 1/P per matched facet
# pair of a region pair, so a region pair costs 1e5 x its mean squared centre gap: a 1 cm
# gap = 10 px^2, as much as ~3 px of 2D error on every keypoint. L_N: (1 + n1.n2)^2, 1/P per
# pair, 1e2: 60 degrees off opposite costs 25 px^2 (at 1e4 it overruled the 2D evidence and
# turned the body: Grab MPJPE 25 -> 84 mm; at 1e2 Grab/Handshake/HoldingHands 26.5/34/26.8 mm,
# against 25.3/34.4/29.2 without L_N). L_sil (fitting/silhouette.py: the partner's outline,
# only when the silhouettes stage's masks are given): realistic demo, partner MPJPE over 100
# frames without / at 3 / 10 / 30: Push 33.7 / 30.4 / 30.1 / 30.4 mm, Handshake 31.1 / 29.4
# / 28.5 / 28.6.
DEFAULT_WEIGHTS = {"L_2d": 1.0, "L_theta": 0.02, "L_s": 0.2, "L_gp": 1e5, "L_ic": 1e4,
                   "L_sc": 1e3, "L_D": 1e5, "L_N": 1e2, "L_sil": 10.0}
WIRED = ("L_2d", "L_theta", "L_s", "L_gp", "L_ic", "L_sc", "L_D", "L_N", "L_sil")  # terms evaluated
CONTACT_SELECTIONS = ("annotated", "all", "uniform")  # psi_D modes (contact_selection)
# L_theta's joint-limit hinge (fitting/priors.py limits), px^2 per rad^2 beyond a limit: at the
# Gaussian's weight (0.02) a limit cost nothing against the 2D term, and on the realistic demo
# the partner's clavicles reached 110-150 degrees (limit 35) in 18-42 % of frames, the spine
# 55-70 (limit 40), while the true motion stays within every limit
LIMIT_WEIGHT = 1e3
# L_G pulls a region pair only when its closest matched facets are nearer than this: a gap of
# tens of cm in an annotated contact frame means the annotation or the pose is off, and
# dragging the body there would overrule the 2D evidence (the frame is reported instead)
CONTACT_MAX_GAP_M = 0.6
# A contact frame whose annotated regions stay farther apart than this at the solution with L_G
# is fitted again without it (``FacetMatches.released``): the detections held the body off
# against L_G's weight, so the images say the annotated regions do not touch there (an
# annotated interval may hold such frames: the annotation is one frame's signature over the
# whole interval). Measured on session 36's bench store: with L_G, every contact frame of
# Grab, Handshake, Hit, HoldingHands, Kick, Posing and Push ends within 2 mm, Hug's hug frames
# (true gap 1-3 mm) within 1-25 mm, and Hug's frames whose true regions are 23-39 cm apart at
# 63-196 mm (all but frame 0, pulled to 22 mm). Released after the forward pass (not frame by
# frame inside it: a frame fitted without L_G starts the next, and two true hug frames then
# stayed 12-13 cm apart and went 76 -> 166 mm off): Hug's mpjpe 133.5 -> 123.4 mm, its
# penetration p95 96 -> 62 mm, the other classes unchanged (the bench protocol, on a copy of
# the partner_fit case's store)
CONTACT_RELEASE_M = 0.06
CONTACT_MARGIN_M = 0.002  # L_D pulls a partner facet centre this far outside the wearer's facet
CONTACT_FACETS_N = 50  # psi_D "uniform": facets drawn per region
EXTRA_TERMS = ("L_gp", "L_ic", "L_sc", "L_D", "L_N")
N_BODY = 23  # KP65 body keypoints (COCO-WholeBody order) counted for "enough detections"
FLIP_MIN_PX = 15.0  # check_views: a view this close to the estimate (median px) is kept as is
FLIP_RATIO = 0.5  # ... else mirrored / dropped when that fits at least twice as well
#: check_views' halves of the body, each mirrored back on its own: (the KP65 body keypoints
#: that judge it, every keypoint it moves): the head and arms with the hands; the legs
BODY_PARTS = ((np.arange(0, 11), np.r_[0:11, N_BODY:len(KP65)]),
              (np.arange(11, N_BODY), np.arange(11, N_BODY)))
# A hand detection (21 keypoints) outweighs the body's one wrist keypoint, so one wrong hand
# (another person's, a mirrored one) drags the whole arm: on the realistic demo's Push the
# partner's right hand detected 46-50 px off in one of the two views that saw it held the
# fitted arm 200-300 mm off the truth while the body keypoints of two views were 4-10 px from
# it (Push partner MPJPE 69 mm over frames 70-99; body keypoints alone 28). A hand whose wrist
# lies farther than this from the body-only solution's wrist is not that person's hand here.
HAND_GATE_PX = 25.0
# A body detection this far (median px) from the estimate while two other views agree with
# the estimate is not the partner (a bystander, an operator): the realistic demo's third
# person was taken for the partner 350 px away in one view for 25 frames
BYSTANDER_PX = 80.0
#: ... and the views that must agree with the estimate for that (Hug on the bench session: the
#: partner hidden behind the wearer is seen by one view at a time, and the bystander's 21
#: keypoints in another pulled the fit 1.25 m onto the bystander with two views required)
BYSTANDER_SUPPORT_VIEWS = 1
# the backward sweep after the forward pass (each frame re-solved tied to both neighbours):
# on the realistic bench session (stride 6) partner MPJPE 37.9 -> 32.6 mm pooled, better in
# 7 of 8 classes, penetration p95 36.8 -> 21.0 mm, for ~1.7x the fit's CPU; on the demo
# (stride 1, 100 frames) 33.2 -> 32.8
TEMPORAL_PASSES = 1
# LM rounds of a temporal re-solve: the frame starts at its forward solution, whose hooks'
# points it re-finds once (the forward pass's later rounds found them already)
TEMPORAL_ROUNDS = 1
# a joint of a valid frame is ground truth where keypoints moving with it were used in this
# many views (one view leaves its depth to the model: Push's right wrist seen by one view
# 45 px off, the other views' detections gated or a bystander's, was fitted 180-280 mm off)
MIN_VIEWS_OBSERVED = 2
#: A keypoint counts as observed in a view only where the fitted body agrees with its
#: detection within this many pixels: a detection the fit does not follow is no evidence of
#: where the fitted joint is. Two views that agree still leave a joint free along the line
#: where their rays nearly meet (CHI3D's diagonal cameras: 25 degrees apart), and one wrong
#: third view pulls it there: on the bench store of session 29 (stride 6, 8 classes), the
#: partner's body keypoints more than 10 cm off the truth in valid frames were 96; counting a
#: view with any detection, 13 of them were not observed; counting the views within 15 / 20 /
#: 25 / 35 px, 78 / 67 / 59 / 38 of them, for 245 / 145 / 101 / 54 more of the 3,239 right
#: ones (within 10 cm) not observed.
OBSERVED_PX = 20.0
#: A detection the solved frame lies farther than this from is an outlier: left out, and the
#: frame solved again. Geman-McClure (``sigma_keypoint_px`` 20) leaves such a keypoint a
#: small pull, but where the other views leave a joint free (two views 25 degrees apart) a
#: small pull moves it far. On the bench store of session 29 (stride 6, the 8 classes;
#: 0 = off / 50 / 35 / 25 px): partner MPJPE 31.3 / 30.1 / 29.2 / 29.3 mm, penetration p95
#: 29.6 / 29.5 / 20.7 / 21.1 mm, valid frames 10 cm off 0.234 / 0.222 / 0.204 / 0.181, valid
#: frames 0.906 / 0.900 / 0.887 / 0.863 (Posing 0.95 / 0.90 / 0.85 / 0.55: its views lose the
#: keypoints that made them count), fit CPU +0 / 9 / 15 / 28 %.
OUTLIER_PX = 35.0
#: L_theta's coupling of the trunk's joints (``fitting.priors.couple_chains``, SPINE_CHAIN):
#: consecutive spine joints differing by this (degrees, per axis) cost as much as a joint one
#: sigma from the prior's mean. The keypoints fix the shoulders and hips, not how the trunk's
#: bend is shared between spine05, spine03 and spine01: without it the partner's H36M spine
#: joint was 26-46 mm off (median per class) where the wearer's (markers on the trunk) is 10.
#: Bench store of session 32, partner MPJPE per class (Grab, Push, Kick, Hit, Handshake,
#: HoldingHands, Hug, Posing) at 0 / 15 / 25 deg: 26.8 / 20.7 / 22.9, 26.1 / 23.2 / 23.1,
#: 27.5 / 27.5 / 26.2, 18.5 / 18.7 / 18.6, 26.3 / 25.3 / 26.6, 22.2 / 22.8 / 22.4,
#: 136 / 118 / 127, 27.0 / 37.5 / 30.5 (Posing's left elbow, which two views read ~30 px apart
#: and the fit follows one or the other, changed sides); valid frames with a joint 10 cm off
#: 36 / 38 / 34 of 159-160; the spine joint 19-37 mm at 25 deg except Hug (Kick's 34 -> 37,
#: the one class it made worse). 3 and 8 deg on the
#: first four: 23.7 and 23.0 mm mean against 24.7 (22.5 at 15, 22.7 at 25); the neck chain
#: (neck01-head) coupled as well at 15: 23.0.
SPINE_COUPLING_DEG = 25.0
#: A view's detections of one keypoint that lie farther than this from the forward pass's fit
#: in the median over the sequence are that view's bias for that keypoint (the studio's
#: detector reads a wrist or a heel 20-40 px off in one view, frame after frame, the truth
#: agreeing: Geman-McClure and outlier_px leave such a keypoint its pull): they are left out,
#: and the forward pass runs again without them; per frame, the pass whose body explains the
#: detections left better (``robust_px_cost``) is kept. Bench store of session 33, the
#: partner's MPJPE per class (Grab, Push, Kick, Hit, Handshake, HoldingHands, Hug, Posing),
#: off / 20 / 25 px with that choice: 22.9 / 22.3 / 22.9, 23.1 / 24.2 / 23.2, 26.2 / 26.6 / 25.6,
#: 18.6 / 17.7 / 17.7, 26.6 / 27.0 / 26.4, 22.4 / 21.5 / 21.5, 127 / 139 / 123,
#: 30.5 / 28.5 / 26.2; valid frames with a joint 10 cm off 34 / 30 / 30 of 151. Without the
#: choice (the second pass kept whole): 25 px 22.9, 23.4, 25.9, 17.9, 26.4, 21.2, 124, 26.2
#: (33 frames 10 cm off); 20 px 22.1, 24.4, 27.9, 17.9, 27.5, 21.6, 140, 26.3 (29). The
#: fit's CPU: 1.7x (the forward pass twice where a pair is left out, in 7 of the 8 bench
#: sequences; the bench's fps_per_core 0.89 -> 0.52). Judging a view's bias also on the
#: keypoints check_views dropped as the wearer's (Grab's wrist, used in 6 of 20 frames) or on
#: every detection was measured on that store and not kept: it finds Grab's wrist (25.5 ->
#: 24.3 mm) but leaves out more (Posing's legs: 28.7 -> 30.2): the seven classes without Hug
#: 25.4 -> 25.5 mm (the bench's protocol, session 33's store).
RELIABILITY_PX = 25.0
# ... judged on at least this many fitted frames where the view detects the keypoint
RELIABILITY_MIN_FRAMES = 5
# the wearer's proxy mesh the occlusion rays are cast against (vertices; ~2x as many faces)
OCCLUDER_VERTICES = 600
GROUND_BAND_M = 0.01  # L_gp slots: candidates below the plane or within this above it
GROUND_K = 300  # L_gp candidates: the lowest vertices (both soles; 20 let a foot tilt under)
# the reasons (artifacts.body_fit.INVALID_REASONS) a frame of the partner fit can be not valid for
PARTNER_FIT_REASONS = ("too_few_keypoints", "held_before_first_keypoints", "poor_reprojection",
                       "too_few_views")
# a view sees the partner in a frame when it holds at least this many of its 23 body keypoints
# (after check_views); a fitted frame is valid only when ``min_valid_views`` views see it
VIEW_MIN_KEYPOINTS = 5
# a sequence whose partner keypoints were left out as the wearer's (the second pass's
# ``detect.refine.on_wearer`` and check_views' per-keypoint check) above this share of the
# partner's detected body keypoints is reported: the detector reads the wearer in the
# partner's place there (the bench's sequences: 0.3-5 %)
WEARER_DROP_WARN_SHARE = 0.10
#: A view that loses most of its partner keypoints to ``outlier_px`` in more than this share
#: of the solved frames is reported (the bench's sequences, session 30's run: Hug's views lose
#: most of them in 2, 4 and 2 of its 16 solved frames, where the partner hides behind the
#: wearer, and warn; HoldingHands and Kick in one frame of one view (5 %); the others in none)
OUTLIER_WARN_SHARE = 0.10
#: A view whose partner detection is dropped whole as somebody else (``bystander_px``) in more
#: than this share of the solved frames is reported: the partner was fitted without it there,
#: and a camera far off its calibration looks the same as an operator standing in the view
#: (the bench's, the demo's and the pose2sim recording's sequences, session 31's stores: no
#: view dropped in any frame; the keypoints stage drops an operator standing out of reach
#: before: ``detect.sequence.standing_far``)
BYSTANDER_WARN_SHARE = 0.25


@dataclass(frozen=True)
class PartnerFitOptions:
    """The partner fit's options (also the recipe's ``stages.partner_fit`` section).

    weights : per paper term (``fitting.terms.PARTNER_TERMS`` minus ``L_3d``); missing ones at
    their default (``DEFAULT_WEIGHTS``, the reasons beside it); 0 switches a term off.
    contact_selection : the paper's ``psi_D`` for ``L_D`` / ``L_N``: "annotated" (the
    signature's facets of each region pair; a pair without annotated facets uses "all"),
    "all" (every facet of both regions) or "uniform" (``contact_facets_n`` facets drawn per
    region, once per sequence, seed ``contact_seed``); contact_max_gap_m : a region pair
    whose closest matched facets are farther apart is not pulled in that frame (reported in
    ``contact_terms.pairs_too_far``); contact_release_m : a contact frame whose regions
    (:func:`region_distance`) stay farther apart than this at the solution with ``L_G`` is
    fitted again without it (``CONTACT_RELEASE_M``; ``contact_terms.frames_released``; 0: off).
    sigma_keypoint_px : Geman-McClure scale of a keypoint's 2D error, pixels;
    min_conf : detections below this confidence are ignored;
    min_keypoints / min_views : a frame is fitted when at least this many body keypoint
    detections (of the 23, over all views) in at least this many views are there;
    min_valid_views : a fitted frame is valid only when at least this many views (or every
    camera, when the rig has fewer) each see ``VIEW_MIN_KEYPOINTS`` of the partner's body
    keypoints after check_views (else ``too_few_views``): two views can always be fitted,
    and a wrong reading both share (the two people mixed, a hug seen from two sides) leaves
    no residual; a third view is the check (bench, session 24: the valid frames seen by two
    views were all more than 10 cm off: 6 of 6, Hug's 4 among them);
    reinit_after : after a run of more than this many frames without enough detections the
    next frame starts again from triangulation; max_iters / first_iters : LM iterations per
    round / for a (re)initialised frame; outer_rounds : LM rounds between which the extra
    terms re-detect their offending points; ftol : LM stops when a step lowers the cost by
    less than this fraction; max_reproj_px : a fitted frame whose median
    reprojection error is above this is not valid (``poor_reprojection``); use_hands : fit
    the fingers to the hand keypoints (52 fit joints; else the 22 body joints and the 23 body
    keypoints); ground_k : lowest vertices for L_gp; proxy_vertices : size of the proxy mesh
    of L_ic; max_frames : fit only the first N frames; check_views : mirror back a view's
    detection read left/right mirrored, drop one that is the wearer (:func:`check_views`);
    limit_weight : weight of L_theta's joint-limit hinge (px^2 per rad^2 beyond a limit of
    ``fitting.priors``; ``LIMIT_WEIGHT``, the reason beside it); hand_gate_px : each frame is
    first solved from the body keypoints alone, and a view's hand detection whose wrist lies
    farther than this from that body's wrist is not used (:func:`gate_hands`; 0: off, the
    hands enter at once); bystander_px : a view whose body detection lies farther than this
    (median) from the estimate while ``bystander_views`` other views agree with it is
    somebody else's and dropped (:func:`check_views`; 0: off); backfill : the frames before
    the first one that could be initialised are fitted backwards from it (each warm-started
    from and tied to the later neighbour, as the forward pass does with the earlier one);
    off, they are held at that frame's pose and not valid; occlusion : a keypoint the wearer's body hides in
    a view (the ray from the camera to the estimate's keypoint crosses the wearer's surface,
    ``fitting.occlusion``) is not used there: the detector guesses it (off: on the realistic
    demo it left Handshake at 31.0 mm against 31.1 and Push at 33.7 against 33.2, for 10 %
    more CPU; the detections that held the fit off were not hidden ones); temporal_passes : after the forward pass (each
    frame warm-started from and tied by L_s to the previous one), sweeps backwards over the
    sequence re-solving each frame tied to both its neighbours (0: none; ``TEMPORAL_PASSES``,
    the reason beside it); temporal_rounds : outer rounds of such a re-solve
    (``TEMPORAL_ROUNDS``); observed_px : a keypoint is observed in a frame (and what it moves
    with is ground truth there) where the fitted body lies within this many pixels of its
    detection in at least ``MIN_VIEWS_OBSERVED`` views (``OBSERVED_PX``, the reason beside
    it); outlier_px : after a frame's solve, a keypoint the fitted body lies farther than this
    from is left out and the frame solved once more without it (0: off; ``OUTLIER_PX``, the
    reason beside it); spine_coupling_deg : ``L_theta`` ties the trunk's bend to be shared
    along the spine's fitted joints at this sigma per axis (``fitting.priors.couple_chains``;
    0: off; ``SPINE_COUPLING_DEG``, the measurements beside it); reliability_px : after the
    forward pass, a view's detections of a keypoint that lie farther than this from the fit
    in the median over the sequence (:func:`unreliable_detections`) are left out of that view
    and the forward pass runs again without them, each frame keeping the pass that explains
    the detections left better (0: off; ``RELIABILITY_PX``, the measurements beside it; the
    report's ``detections_unreliable`` lists them)."""

    weights: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEIGHTS))
    sigma_keypoint_px: float = 20.0
    min_conf: float = 0.2
    min_keypoints: int = 12
    min_views: int = 2
    min_valid_views: int = 3
    reinit_after: int = 10
    max_iters: int = 10
    first_iters: int = 40
    outer_rounds: int = 3
    max_reproj_px: float = 25.0
    ftol: float = 1e-4
    use_hands: bool = True
    ground_k: int = GROUND_K
    proxy_vertices: int = 1500
    max_frames: int | None = None
    check_views: bool = True
    contact_selection: Literal["annotated", "all", "uniform"] = "annotated"
    contact_facets_n: int = CONTACT_FACETS_N
    contact_seed: int = 0
    contact_max_gap_m: float = CONTACT_MAX_GAP_M
    contact_release_m: float = CONTACT_RELEASE_M
    limit_weight: float = LIMIT_WEIGHT
    hand_gate_px: float = HAND_GATE_PX
    occlusion: bool = False
    temporal_passes: int = TEMPORAL_PASSES
    temporal_rounds: int = TEMPORAL_ROUNDS
    bystander_px: float = BYSTANDER_PX
    bystander_views: int = BYSTANDER_SUPPORT_VIEWS
    backfill: bool = True
    observed_px: float = OBSERVED_PX
    outlier_px: float = OUTLIER_PX
    spine_coupling_deg: float = SPINE_COUPLING_DEG
    reliability_px: float = RELIABILITY_PX

    def __post_init__(self):
        problems = []
        for name, v in self.weights.items():
            if name not in DEFAULT_WEIGHTS:
                problems.append(f"weights.{name}: unknown term (known: {', '.join(DEFAULT_WEIGHTS)})")
            elif not float(v) >= 0:
                problems.append(f"weights.{name}: must be >= 0, got {v}")
            elif name not in WIRED and float(v) > 0:
                problems.append(f"weights.{name}: not wired in this version of the partner fit "
                                f"(wired: {', '.join(WIRED)}); set it to 0")
        for name in ("limit_weight", "hand_gate_px", "bystander_px", "outlier_px",
                     "spine_coupling_deg", "reliability_px", "contact_release_m"):
            if not getattr(self, name) >= 0:
                problems.append(f"{name}: must be >= 0, got {getattr(self, name)}")
        for name in ("sigma_keypoint_px", "max_reproj_px", "observed_px"):
            if not getattr(self, name) > 0:
                problems.append(f"{name}: must be > 0, got {getattr(self, name)}")
        if not 0 <= self.min_conf <= 1:
            problems.append(f"min_conf: must be in [0, 1], got {self.min_conf}")
        if not self.contact_max_gap_m > 0:
            problems.append(f"contact_max_gap_m: must be > 0, got {self.contact_max_gap_m}")
        for name, lo in (("min_keypoints", 1), ("min_views", 2), ("min_valid_views", 1),
                         ("max_iters", 1),
                         ("first_iters", 1), ("outer_rounds", 1), ("reinit_after", 0),
                         ("ground_k", 1), ("proxy_vertices", 100), ("contact_facets_n", 1),
                         ("temporal_passes", 0), ("temporal_rounds", 1), ("bystander_views", 1)):
            if getattr(self, name) < lo:
                problems.append(f"{name}: must be >= {lo}, got {getattr(self, name)}")
        if self.max_frames is not None and self.max_frames < 1:
            problems.append(f"max_frames: must be >= 1, got {self.max_frames}")
        if self.contact_selection not in CONTACT_SELECTIONS:
            problems.append(f"contact_selection: must be one of {', '.join(CONTACT_SELECTIONS)}, "
                            f"got {self.contact_selection!r}")
        if problems:
            raise ValueError("; ".join(problems))
        w = dict(DEFAULT_WEIGHTS)
        w.update({k: float(v) for k, v in self.weights.items()})
        object.__setattr__(self, "weights", w)


# ---------------------------------------------------------------------------- the seam


@dataclass(frozen=True, eq=False)
class Block:
    """One extra term's offending points, chosen between LM rounds: ``name`` (a paper term),
    ``H (N, Q, 4)`` their slot coefficients (points on the skinned surface), and
    ``residual(pos (N, 3)) -> (r (m,), dr (m, 3), point (m,))`` the term (``fitting/terms.py``,
    unweighted), each row's derivative in the position of the one point it depends on, and
    that point's index; or, for rows that depend on ``k`` points each (a facet normal: its 3
    corners), ``dr (m, k, 3)`` and ``point (m, k)``; evaluated exactly at every LM evaluation
    (the targets found by the hook stay fixed within a round)."""

    name: str
    H: np.ndarray
    residual: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

    @property
    def points(self) -> int:
        return len(self.H)

    def evaluate(self, skel, u, x, sub=None) -> tuple[np.ndarray, np.ndarray]:
        """(r (m,), J (m, n)) at unknowns x (chain rule through :func:`point_jacobian`)."""
        return self.rows(*point_jacobian(skel, u, self.H, x, sub))

    def rows(self, pos: np.ndarray, Jp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(r (m,), J (m, n)) from the points' positions (N, 3) and Jacobian (N, 3, n)."""
        r, dr, point = self.residual(pos)
        if np.ndim(dr) == 2:
            return r, np.einsum("ma,max->mx", dr, Jp[point])
        return r, np.einsum("mka,mkax->mx", dr, Jp[point])


class Posed:
    """The partner's current state inside a frame's solve, with what hooks need lazily:
    ``x (n,)``, ``vertices (V, 3)`` (``body.forward``), ``slots(vertex_ids, weights)``: slot
    coefficients (N, Q, 4) of points ``sum_m weights[n, m] * vertex[vertex_ids[n, m]]``
    (a proxy vertex: its face corners and barycentric coordinates)."""

    def __init__(self, ctx: _BodyCtx, x: np.ndarray, frame: int):
        self.ctx, self.x, self.frame = ctx, np.asarray(x, float), frame
        self._V = None

    @property
    def vertices(self) -> np.ndarray:
        if self._V is None:
            self._V = self.ctx.posed_vertices(self.x)
        return self._V

    def slots(self, vertex_ids: np.ndarray, weights: np.ndarray) -> np.ndarray:
        return np.einsum("nm,nmqc->nqc", np.asarray(weights, float),
                         self.ctx.vertex_H(np.asarray(vertex_ids, np.int64)))


class ExtraTerm(Protocol):
    """A term that enters between LM rounds: ``name`` (its weight's key) and
    ``__call__(posed) -> list[Block]`` (empty when nothing offends)."""

    name: str

    def __call__(self, posed: Posed) -> list[Block]: ...


@dataclass
class GroundTerm:
    """``L_gp``: of the ``k`` lowest vertices (``fitting.collision.ground_candidates``) those
    below the plane ``normal . x = offset`` or less than ``GROUND_BAND_M`` above it, as slots,
    each ``min(0, normal . p - offset)`` (``fitting.terms.L_gp``); only when one is below."""

    normal: np.ndarray
    offset: float
    k: int = collision.GROUND_K
    name: str = "L_gp"

    def __call__(self, posed: Posed) -> list[Block]:
        V = posed.vertices
        n = np.asarray(self.normal, float)
        idx = collision.ground_candidates(V, n, self.offset, self.k)
        d = V[idx] @ n - self.offset
        if not np.any(d < 0):
            return []
        idx = idx[d < GROUND_BAND_M]  # below, or near enough to get there within the round

        def residual(pos):
            r = terms.L_gp(pos, n, self.offset)
            return r, np.where((r < 0)[:, None], n[None], 0.0), np.arange(len(pos))

        return [Block(self.name, posed.slots(idx[:, None], np.ones((len(idx), 1))), residual)]


def _pull_residual(targets: np.ndarray, term=terms.L_ic):
    """Residual of ``L_ic`` (or ``term`` = ``terms.L_sc``) toward fixed targets (N, 3) and its
    derivative."""
    N = len(targets)
    dr = np.tile(np.eye(3), (N, 1))  # row 3i + a: d/dp_i[a]
    point = np.repeat(np.arange(N), 3)

    def residual(pos):
        return term(pos, targets, np.ones(N)), dr, point

    return residual


class InterpenetrationTerm:
    """``L_ic`` against the wearer's posed body, both sums (``fitting.collision
    .interpenetration`` on the proxy meshes): partner proxy points inside the wearer pushed
    to the wearer's surface, and the partner's surface pushed past the wearer's proxy points
    inside it. ``wearer_vertices``: per fitted frame the wearer's mesh (V, 3) or None."""

    name = "L_ic"

    def __init__(self, proxy: collision.ProxyMesh, wearer_vertices):
        self.proxy = proxy
        self.wearer = wearer_vertices
        self._wp: dict[int, np.ndarray | None] = {}

    def wearer_points(self, f: int):
        if f not in self._wp:
            V = None if self.wearer is None else self.wearer[f]
            self._wp = {f: None if V is None else self.proxy.points(V)}  # one frame at a time
        return self._wp[f]

    def __call__(self, posed: Posed) -> list[Block]:
        Pb = self.wearer_points(posed.frame)
        if Pb is None:
            return []
        pr = self.proxy
        Pa = pr.points(posed.vertices)
        a_in_b, b_in_a = collision.interpenetration(Pa, Pa, pr.faces, Pb, Pb, pr.faces)
        out = []
        if a_in_b.n:
            H = posed.slots(pr.corners[a_in_b.index], pr.bary[a_in_b.index])
            out.append(Block(self.name, H, _pull_residual(a_in_b.target)))
        if b_in_a.n:  # the nearest point of the partner's proxy surface: 3 proxy vertices
            tri = pr.faces[b_in_a.face]  # (n, 3) proxy vertex ids
            vids = pr.corners[tri].reshape(b_in_a.n, 9)
            w = (b_in_a.bary[:, :, None] * pr.bary[tri]).reshape(b_in_a.n, 9)
            out.append(Block(self.name, posed.slots(vids, w), _pull_residual(b_in_a.target)))
        return out


class SelfCollisionTerm:
    """``L_sc``: the partner's proxy points inside its own body, counting only the parts that
    are not neighbours of the point's region (``fitting.collision.self_collisions`` on
    ``proxy.points(posed.vertices)``; the proxy needs regions: ``ProxyMesh.from_model``).
    Each penetrating proxy point is pulled to its nearest point on the non-neighbouring own
    proxy surface (the paper's ``NN(V_l, M)``), pushed ``collision.MARGIN_M`` beyond it, the
    target fixed for the round as ``L_ic``'s: ``terms.L_sc(p, target, 1)`` (3n,), metres.
    (A target riding on the own surface, both points moving, was tried: on an elbow folded
    into the belly it moved the body twice as far and left 0.6 mm where this leaves none.)"""

    name = "L_sc"

    def __init__(self, proxy: collision.ProxyMesh):
        self.proxy = proxy

    def __call__(self, posed: Posed) -> list[Block]:
        pr = self.proxy
        col = collision.self_collisions(pr, pr.points(posed.vertices))
        if not col.n:
            return []
        H = posed.slots(pr.corners[col.index], pr.bary[col.index])
        return [Block(self.name, H, _pull_residual(col.target, terms.L_sc))]


def contact_selection(contact, rmap, mode: str = "annotated", n: int = CONTACT_FACETS_N,
                      rng: np.random.Generator | None = None):
    """The paper's ``psi_D`` for every region pair of ``contact`` (a
    ``fitting.contact_signature.ContactAnnotation``, person 0 = the wearer, person 1 = the
    partner): ``(selection, modes)``, selection one ``(wearer facets, partner facets)`` int64
    pair per row of ``contact.region_pairs``, modes the mode used for each. ``"annotated"``
    falls back to ``"all"`` for a pair without annotated facets; ``"uniform"`` draws ``n``
    facets per region with ``rng`` (default ``np.random.default_rng(0)``)."""
    from fitting.contact_signature import select_facets

    R = len(contact.region_pairs)
    if mode == "uniform":
        rng = np.random.default_rng(0) if rng is None else rng
        return select_facets(contact, rmap, mode, n, rng), [mode] * R
    if mode != "annotated":
        return select_facets(contact, rmap, mode), [mode] * R
    full = None
    sel, modes = [], []
    for r in range(R):
        fp = contact.facets_of_pair(r)
        if len(fp):
            sel.append((np.unique(fp[:, 0]), np.unique(fp[:, 1])))
            modes.append("annotated")
            continue
        full = select_facets(contact, rmap, "all") if full is None else full
        sel.append(full[r])
        modes.append("all")
    return sel, modes


class FacetMatches:
    """The nearest-facet matches of ``Phi_D`` between the wearer's and the partner's selected
    facets at the current pose, shared by the ``L_D`` and ``L_N`` terms (computed once per
    :class:`Posed`).

    contact : the ``ContactAnnotation``; frames : (F,) the fit's video frame numbers
    (``Posed.frame`` indexes them; ``contact.active`` takes video frames); wearer_vertices :
    per fit frame the wearer's posed mesh (V, 3) or None; faces : (T, 3) the model's faces;
    selection : :func:`contact_selection`'s per-pair ``(wearer facets, partner facets)``.

    ``__call__(posed)`` -> None outside the contact interval or without the wearer's mesh,
    else ``(face_w (P,), face_p (P,), weight (P,), wearer vertices (V, 3))``: per region pair
    both directions of ``collision.match_facets`` (every wearer facet with its nearest partner
    facet, then every partner facet with its nearest wearer facet), ``weight = 1 / P_k`` for
    the ``P_k`` matches of region pair k (a region pair's terms are means over its matches;
    region pairs add up)."""

    def __init__(self, contact, frames: np.ndarray, wearer_vertices, faces: np.ndarray,
                 selection: list[tuple[np.ndarray, np.ndarray]], max_gap_m: float = np.inf):
        self.contact, self.frames = contact, np.asarray(frames, np.int64)
        self.wearer, self.faces, self.selection = wearer_vertices, np.asarray(faces), selection
        self.max_gap_m = float(max_gap_m)
        self.too_far: set[tuple[int, int]] = set()  # (fit frame, region pair) not pulled
        self.released: dict[int, float] = {}  # fit frame -> its regions' distance with L_G,
        # fitted without it (contact_release_m)
        self._last = (None, None)

    def active(self, f: int) -> bool:
        """L_G applies at fit frame index ``f``: its video frame is in the contact interval,
        the wearer's mesh is there and the frame is not ``released``."""
        return (self.wearer is not None and self.wearer[f] is not None
                and self.contact.active(int(self.frames[f])) and f not in self.released)

    def __call__(self, posed: Posed):
        if self._last[0] is posed:
            return self._last[1]
        out = None
        if self.active(posed.frame):
            VW, VP = self.wearer[posed.frame], posed.vertices
            fw, fp, w = [], [], []
            for k, (s_w, s_p) in enumerate(self.selection):
                a, b = collision.match_facets(VW, self.faces, s_w, VP, self.faces, s_p)
                gap = np.linalg.norm(VW[self.faces[a]].mean(1) - VP[self.faces[b]].mean(1), axis=1)
                if not gap.min() <= self.max_gap_m:  # the annotation or the pose is off
                    self.too_far.add((int(posed.frame), k))
                    continue
                self.too_far.discard((int(posed.frame), k))
                fw.append(a)
                fp.append(b)
                w.append(np.full(len(a), 1.0 / len(a)))
            if fw:
                out = (np.concatenate(fw), np.concatenate(fp), np.concatenate(w), VW)
        self._last = (posed, out)
        return out


class ContactTerm:
    """One half of ``L_G = L_D + L_N`` in the contact frames (``name`` "L_D" or "L_N"; the two
    share one :class:`FacetMatches`). With the matched facet pairs (wearer facet ``f_w``,
    partner facet ``f_p``, weight ``1 / P_k``), the wearer fixed:

    - ``L_D``: the partner facets' centres (each a point: the mean of its 3 corner vertices)
      pulled to the wearer facets' centres, ``terms.L_D(c_p, c_w, w)`` (3P,), metres;
    - ``L_N``: the partner facets' unit normals turned opposite to the wearer's,
      ``terms.L_N(tri_w, tri_p, w)`` = ``sqrt(w)(1 + n_w . n_p)`` (P,), dimensionless; each
      row depends on the partner facet's 3 corners (exact derivative of the unit normal:
      :func:`normal_residual`)."""

    def __init__(self, name: str, matches: FacetMatches):
        if name not in ("L_D", "L_N"):
            raise ValueError(f"name: expected 'L_D' or 'L_N', got {name!r}")
        self.name, self.matches = name, matches

    def __call__(self, posed: Posed) -> list[Block]:
        m = self.matches(posed)
        if m is None:
            return []
        fw, fp, w, VW = m
        F = self.matches.faces
        if self.name == "L_D":
            H = posed.slots(F[fp], np.full((len(fp), 3), 1.0 / 3.0))
            # the target: the wearer's facet centre, CONTACT_MARGIN_M out along its normal
            # (touching, not coincident: a centre pulled onto a curved surface takes the
            # facets around it through the other body, and L_ic then fights L_D)
            tri = VW[F[fw]]
            target = tri.mean(1) + CONTACT_MARGIN_M * face_normals(VW, F[fw])
            return [Block(self.name, H, centre_residual(target, w))]
        H = posed.slots(F[fp].reshape(-1, 1), np.ones((3 * len(fp), 1)))
        return [Block(self.name, H, normal_residual(VW[F[fw]], w))]


def centre_residual(targets: np.ndarray, weights: np.ndarray):
    """``L_D`` of points (P, 3) toward fixed facet centres ``targets`` (P, 3), per-pair
    ``weights`` (P,): ``residual(pos) -> (terms.L_D(pos, targets, w) (3P,), dr (3P, 3),
    point (3P,))``."""
    P = len(targets)
    sw = np.sqrt(np.asarray(weights, float))
    dr = np.repeat(sw, 3)[:, None] * np.tile(np.eye(3), (P, 1))
    point = np.repeat(np.arange(P), 3)

    def residual(pos):
        return terms.L_D(pos, targets, weights), dr, point

    return residual


def normal_residual(tri_fixed: np.ndarray, weights: np.ndarray):
    """``L_N`` of triangles whose corners are the points (3P, 3) (triangle i = points 3i,
    3i + 1, 3i + 2, outward order) against fixed triangles ``tri_fixed`` (P, 3, 3):
    ``residual(pos) -> (r (P,), dr (P, 3, 3), point (P, 3))`` with ``r = terms.L_N(tri_fixed,
    tri, w) = sqrt(w)(1 + n_1 . n)`` and its exact derivative in the three corners: with
    ``N = (b - a) x (c - a)``, ``n = N / |N|`` and ``g = sqrt(w) (I - n n^T) n_1 / |N|``,
    ``dr/da = g x (c - b)``, ``dr/db = (c - a) x g``, ``dr/dc = g x (b - a)``. Degenerate
    triangles (|N| = 0) give NaN rows."""
    P = len(tri_fixed)
    n1 = terms.facet_normals(np.asarray(tri_fixed, float))
    w = np.asarray(weights, float)
    sw = np.sqrt(w)
    point = np.arange(3 * P).reshape(P, 3)

    def residual(pos):
        tri = np.asarray(pos, float).reshape(P, 3, 3)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        u, v = b - a, c - a
        N = np.cross(u, v)
        L = np.linalg.norm(N, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = terms.L_N(tri_fixed, tri, w)
            n = N / L
            g = sw[:, None] * (n1 - (n * n1).sum(1, keepdims=True) * n) / L
        dr = np.stack([np.cross(g, c - b), np.cross(v, g), np.cross(g, u)], axis=1)
        return r, dr, point

    return residual


class Augmented:
    """The graph's residual function with the extra blocks' rows appended (the interface of
    ``fitting.compiled.ResidualFunction`` that ``fitting.lm.solve`` uses): the blocks are
    evaluated in numpy at every call, with exact dense Jacobian rows."""

    def __init__(self, base, blocks: list[Block], body: _BodyCtx):
        self.base, self.blocks, self.body = base, blocks, body
        self.sizes = [len(b.residual(np.zeros((b.points, 3)))[0]) for b in blocks]
        self.n_x, self.n_p = base.n_x, base.n_p
        self.n_r = base.n_r + sum(self.sizes)
        extra = np.arange(base.n_r, self.n_r)
        self._flat = np.concatenate([base._flat, (extra[:, None] * self.n_x
                                                  + np.arange(self.n_x)).reshape(-1)])
        self.compiled = base.compiled
        self._H = np.concatenate([b.H for b in blocks]) if blocks else None  # one FK per call
        self._pattern = (skinned.JacobianPattern(body.skel, self._H, body.sub) if blocks
                         else None)
        self._at = np.cumsum([0] + [b.points for b in blocks])

    def rows(self) -> list[tuple[str, slice]]:
        out, o = [], self.base.n_r
        for b, m in zip(self.blocks, self.sizes, strict=True):
            out.append((b.name, slice(o, o + m)))
            o += m
        return out

    def __call__(self, x, p):
        r0, j0 = self.base(x, p)
        t0 = time.perf_counter()
        rs, js = [r0], [j0]
        if self.blocks:
            pos, Jp = point_jacobian(self.body.skel, self.body.u, self._H, x, self.body.sub,
                                     self._pattern)
            for b, a, e in zip(self.blocks, self._at[:-1], self._at[1:], strict=True):
                r, J = b.rows(pos[a:e], Jp[a:e])
                rs.append(r)
                js.append(J.reshape(-1))
        self.body.jacobian_s += time.perf_counter() - t0
        return np.concatenate(rs), np.concatenate(js)


# ---------------------------------------------------------------------------- the solver


class _BodyCtx:
    """The partner's fixed shape on the fit skeleton: rest state, offsets, vertex slots."""

    def __init__(self, model: BodyModel, betas, rest: RestState, skel: skinned.FitSkeleton):
        self.model, self.betas, self.rest, self.skel = model, betas, rest, skel
        self.u, _ = skinned.reduced_offsets(model, rest, skel)
        self.sub = subtree(skel)
        self._H: dict[int, np.ndarray] = {}
        self.jacobian_s = 0.0  # extra terms' exact Jacobians inside LM, seconds
        self.hook_s = 0.0  # the hooks (posing the mesh, finding offending points), seconds

    def posed_vertices(self, x: np.ndarray) -> np.ndarray:
        pose, R, T = unpack(self.skel, self.model.num_joints, x[None])
        return forward(self.model, self.betas, pose, R, T, rest=self.rest).vertices[0]

    def vertex_H(self, vids: np.ndarray) -> np.ndarray:
        """(..., Q, 4) slot coefficients of mesh vertices ``vids`` (...), cached."""
        flat = vids.reshape(-1)
        new = np.unique(flat[[int(v) not in self._H for v in flat]]) if len(flat) else flat
        if len(new):
            H = skinned.vertex_coeffs(self.model, self.rest, self.skel, self.model.weights[new],
                                      self.rest.vertices[0, new])
            self._H.update(zip(new.tolist(), H, strict=True))
        return np.stack([self._H[int(v)] for v in flat]).reshape(vids.shape
                                                                  + (len(self.skel.joints), 4))


class PartnerSolver:
    """Everything fixed over a sequence: the keypoint graph, its packed parameters, the prior,
    the options and the extra terms."""

    def __init__(self, reproj: Reprojection, body: _BodyCtx, prior: priors.PosePrior,
                 opts: PartnerFitOptions, extra=()):
        self.reproj, self.body, self.opts, self.extra = reproj, body, opts, list(extra)
        C, K = reproj.C, reproj.K
        self.p = np.zeros(0)
        w = opts.weights
        n = reproj.n_x
        pose_idx = np.arange(6, n)
        g = prior.gaussian
        self.quad_prior = terms.quadratic_L_theta(n, pose_idx, g.mean, g.sqrt_precision, w["L_theta"])
        self.box = terms.box_L_theta(pose_idx, prior.lo, prior.hi, prior.limit_idx,
                                     opts.limit_weight)
        self.row_scale = np.full(2 * C * K, np.sqrt(w["L_2d"]))
        self.rows_k = np.arange(2 * C * K).reshape(C * K, 2)

    def groups(self, conf, factor=1.0):
        kk = max(int(np.count_nonzero(np.asarray(conf) > 0)), 1)
        return [lm.RobustGroups(self.rows_k, "geman_mcclure", factor * self.opts.sigma_keypoint_px
                                * np.sqrt(self.opts.weights["L_2d"] / kk))]

    def blocks(self, x, frame) -> list[Block]:
        """The extra terms' offending points at unknowns x (hooks on the posed mesh)."""
        posed = Posed(self.body, x, frame)
        out = []
        t0 = time.perf_counter()
        for term in self.extra:
            if self.opts.weights.get(term.name, 0) > 0:
                out.extend(term(posed))
        self.body.hook_s += time.perf_counter() - t0
        return out

    def solve(self, x0, uv, conf, frame: int, x_prev=None, first=False, s_scale=1.0,
              extra=True, rounds_max=None):
        """One frame: uv (C, K, 2) pixels, conf (C, K) (0 = missing). Rounds of LM; before
        each the hooks choose the offending points, which LM then evaluates exactly
        (:class:`Augmented`). ``L_s`` ties x to ``x_prev`` at ``s_scale`` times its weight (the
        temporal pass: 2 x the neighbours' mean = the sum over both neighbours, up to a
        constant); extra=False: L_2d and the priors alone, one round; rounds_max: at most this
        many rounds (default ``outer_rounds``). Returns (LMResult, the
        blocks of the last round (their terms are reported at the solution; the hooks are
        not called again after it), rounds)."""
        self.reproj.set_observations(uv, conf)
        quad = self.quad_prior
        if x_prev is not None and self.opts.weights["L_s"] > 0:
            quad = quad + terms.quadratic_L_s(len(x0), np.arange(len(x0)), x_prev,
                                              s_scale * self.opts.weights["L_s"])
        x = np.asarray(x0, float)
        res, rounds = None, 0
        extra = extra and bool(self.extra)
        blocks = self.blocks(x, frame) if (extra and not first) else []
        n_rounds = (self.opts.outer_rounds if rounds_max is None else rounds_max) if extra else 1
        for k in range(n_rounds):
            if k > 0 and not blocks:
                break
            fun, scale = self.reproj, self.row_scale
            if blocks:
                fun = Augmented(self.reproj, blocks, self.body)
                scale = np.concatenate([scale] + [np.full(m, np.sqrt(self.opts.weights[b.name]))
                                                  for b, m in zip(blocks, fun.sizes, strict=True)])
            for fct in (GNC_FACTORS if (first and k == 0) else (1.0,)):
                res = lm.solve(fun, self.p, x, row_scale=scale, groups=self.groups(conf, fct),
                               quad=quad, box=self.box,
                               opts=lm.LMOptions(max_iters=self.opts.first_iters if first
                                                 else self.opts.max_iters, ftol=self.opts.ftol))
                x = res.x
            rounds += 1
            if k + 1 < n_rounds:  # the next round's points
                blocks = self.blocks(x, frame)
        return res, blocks, rounds


# ---------------------------------------------------------------------------- one sequence


def _partner_keypoints(keypoints: Keypoints2D, cams, frames, kidx, min_conf):
    """(uv (F, C, K, 2), conf (F, C, K)) of the partner at the fit's frames, cameras by id."""
    kp = np.asarray(keypoints.person(PARTNER), float)[[keypoints.camera(c.name) for c in cams]]
    kf = np.asarray(keypoints.frames)
    pos = np.searchsorted(kf, frames)
    full = kp[:, pos].copy()  # (C, F, 65, 3)
    full[..., 2] = np.where(full[..., 2] >= min_conf, full[..., 2], 0.0)
    kp = full[:, :, kidx]
    return np.transpose(kp[..., :2], (1, 0, 2, 3)), np.transpose(kp[..., 2], (1, 0, 2)), full


def contact_warnings(report: dict) -> list[str]:
    """The report's warning when contact frames were fitted without ``L_G`` (``contact_terms``
    ``frames_released``, :data:`CONTACT_RELEASE_M`): the annotated interval holds frames whose
    annotated regions the images keep apart, or the fit is wrong there. None otherwise."""
    ct = report.get("contact_terms") or {}
    rel = ct.get("frames_released") or []
    if not rel:
        return []
    gaps = ct.get("released_gap_m") or []
    span = f" ({min(gaps) * 1000:.0f}-{max(gaps) * 1000:.0f} mm)" if gaps else ""
    return [f"contact: {len(rel)} of the {ct.get('frames', '?')} fitted frames of the annotated "
            f"contact interval kept the annotated regions apart with L_G{span} and were fitted "
            f"without it (video frames {', '.join(map(str, rel))}): the images hold them apart "
            "there, so the annotation's interval may be too long, or the fit is wrong there; "
            "check the interval and those frames' overlays"]


def wearer_drop_warnings(detected: int, dropped_check: int, dropped_second: int = 0,
                         share: float = WEARER_DROP_WARN_SHARE) -> list[str]:
    """The report's warning when many partner keypoints were left out as the wearer's.

    detected : the partner's body keypoints the fit was given (after the second pass);
    dropped_check : of those, dropped by :func:`check_views`' per-keypoint wearer check;
    dropped_second : left out before, by the second pass (``detect.refine.on_wearer``).
    Returns one line when the dropped share of ``detected + dropped_second`` exceeds ``share``
    (none otherwise, and none with nothing detected)."""
    total = int(detected) + int(dropped_second)
    n = int(dropped_check) + int(dropped_second)
    if total <= 0 or n <= share * total:
        return []
    return [f"{n} of {total} partner body keypoints ({100.0 * n / total:.0f} %, more than "
            f"{100.0 * share:.0f} %) lay on the wearer's joint of the same name and were left out "
            f"(second pass {int(dropped_second)}, check_views {int(dropped_check)}): the detector "
            "reads the wearer in the partner's place; check the partner's overlays"]


def outlier_warnings(rejected: dict, views: list[str],
                     share: float = OUTLIER_WARN_SHARE) -> list[str]:
    """The report's warnings for a view that lost most of its keypoints to ``outlier_px``.

    rejected : the report's ``keypoints_rejected_as_outliers`` (``frames_view_lost_most``
    per view, ``frames_solved``, ``outlier_px``); views : the cameras' names.
    Returns a line per view that lost most (more than half) of its partner keypoints in more
    than ``share`` of the solved frames: the other views fit a body it does not see, so its
    calibration or sync is off, or it reads somebody else."""
    n = int(rejected.get("frames_solved") or 0)
    out = []
    for name, k in zip(views, rejected.get("frames_view_lost_most") or (), strict=False):
        if n > 0 and k > share * n:
            out.append(f"view {name}: in {k} of {n} solved frames ({100.0 * k / n:.0f} %, more "
                       f"than {100.0 * share:.0f} %) most of its partner keypoints lay more than "
                       f"{rejected.get('outlier_px')} px from the body the other views fit and "
                       "were left out: its calibration or sync may be off, or it reads "
                       "somebody else; check that view's overlays")
    return out


def unreliable_warnings(unreliable: dict, share: float = 0.5) -> list[str]:
    """The report's warnings for a view most of whose body keypoints were left out as that
    view's bias (``reliability_px``): more than ``share`` of the partner's ``N_BODY`` body
    keypoints. unreliable : the report's ``detections_unreliable``."""
    out = []
    for name, kps in (unreliable.get("per_view") or {}).items():
        n = sum(1 for k in kps if k in KP65[:N_BODY])
        if n > share * N_BODY:
            out.append(f"view {name}: {n} of the partner's {N_BODY} body keypoints lay more "
                       f"than {unreliable.get('reliability_px')} px from the fitted body in the "
                       "median over the sequence and were left out of the fit: its calibration "
                       "or sync may be off, or it reads somebody else; check that view's overlays")
    return out


def view_warnings(report: dict, views: list[str]) -> list[str]:
    """The warnings a partner fit's ``report`` (:func:`fit_partner`) raises about single views:
    :func:`outlier_warnings`, :func:`unreliable_warnings` and :func:`bystander_warnings`, in
    that order. views : the cameras' names."""
    rejected = report["keypoints_rejected_as_outliers"]
    return (outlier_warnings(rejected, views) + unreliable_warnings(report["detections_unreliable"])
            + bystander_warnings(report["views_dropped_as_bystander_per_view"],
                                 rejected["frames_solved"], views))


def bystander_warnings(dropped, solved: int, views: list[str],
                       share: float = BYSTANDER_WARN_SHARE) -> list[str]:
    """The report's warnings for a view whose partner detection was dropped whole as somebody
    else (``check_views``' ``far``) in more than ``share`` of the ``solved`` frames.

    dropped : per view, the frames it was dropped in (the report's
    ``views_dropped_as_bystander_per_view``); views : the cameras' names."""
    out = []
    for name, k in zip(views, dropped or (), strict=False):
        if solved > 0 and k > share * solved:
            out.append(f"view {name}: in {int(k)} of {solved} solved frames ({100.0 * k / solved:.0f}"
                       f" %, more than {100.0 * share:.0f} %) the partner's detection lay far "
                       "from the body the other views fit and the view was left out whole as "
                       "somebody else: the partner was fitted without it there. A bystander "
                       "or an operator in that view, or its calibration or sync is off; check "
                       "that view's overlays")
    return out


def check_views(cams, pred: np.ndarray, uv: np.ndarray, conf: np.ndarray, flip: np.ndarray,
                other: np.ndarray | None = None, min_px: float = FLIP_MIN_PX,
                ratio: float = FLIP_RATIO, far_px: float = 0.0,
                support: int = BYSTANDER_SUPPORT_VIEWS) -> ViewCheck:
    """Cross-view consistency of one frame's partner detections against a 3D body.

    pred : (K, 3) the partner's keypoints from the current estimate (the previous frame's
    solution, or this frame's); uv (C, K, 2), conf (C, K) the detections; flip : (K,) the
    left/right mirror of the K keypoints (``formats.skeletons.KP65_FLIP``); other : (K, 3) the
    marker wearer's keypoints (from ``marker_fit``) or None. Per view, ``e`` is the median
    pixel distance of the detected body keypoints to ``pred``'s projection:

    - a view whose detection lies farther than ``far_px`` (> 0) from ``pred`` while at least
      ``support`` other views lie within it is somebody else (a bystander, an operator) and
      dropped (conf 0; ``far``);
    - a view whose detection lies nearer the wearer's projected keypoints than the partner's
      (``e_other < ratio * e``, ``e > min_px``; an identity swap) is dropped (conf 0);
    - a view whose detection read mirrored fits ``pred`` better (``e_flip < ratio * e`` and
      ``e > min_px``) is mirrored back (a person seen from behind read as seen from the
      front: the fit must not follow it);
    - in a view kept as it is or mirrored back, each half of the body (:data:`BODY_PARTS`:
      the head and arms with the hands, the legs) is judged the same way on its own (a view
      whose legs alone read mirrored is mirrored back as a whole, its median held by the 12
      leg keypoints of 23, and its arms then mirrored back alone): the detector mirrors the
      upper body alone of a partner seen from behind while the legs stay right (bench,
      Posing, view 60457274 from frame 54 on: the shoulders, elbows and wrists swapped), and
      the whole view's median, held by the legs, does not see it;
    - in a view kept, each body keypoint is judged on its own against the wearer: one that
      lies nearer the wearer's projected keypoint of the same name (either side) than the
      estimate's (``d_other < ratio * d``, ``d > min_px``) is the wearer's joint read as the
      partner's and dropped (conf 0; bench, Posing: a second-pass crop put the partner's left
      elbow on the wearer's elbow, 80-110 px from the truth, at confidence 0.4-0.9). A joint
      near the wearer's other joints (a hand on the wearer's chest, Push) is kept.

    Returns a :class:`ViewCheck` (copies)."""
    uv, conf = np.array(uv, float), np.array(conf, float)
    flip = np.asarray(flip)
    C, K = conf.shape
    body = np.arange(min(K, N_BODY))
    flipped, dropped, far = np.zeros(C, bool), np.zeros(C, bool), np.zeros(C, bool)

    def med(c, target, perm, idx=body):
        """Median px distance of view c's detections ``perm``-ed to ``target``'s projection,
        over the keypoints ``idx`` (NaN with fewer than 4 detected)."""
        ok = conf[c, perm][idx] > 0
        if ok.sum() < 4:
            return np.nan
        d = np.linalg.norm(uv[c, perm][idx][ok] - project(cams[c], target[idx][ok]), axis=-1)
        return float(np.median(d))

    ident = np.arange(K)
    e = np.array([med(c, pred, ident) for c in range(C)])
    if far_px > 0:
        near = e <= far_px
        for c in np.flatnonzero(e > far_px):
            if np.count_nonzero(np.delete(near, c)) >= support:
                conf[c] = 0.0
                far[c] = True
    for c in range(C):
        if far[c] or not e[c] > min_px:
            continue
        if other is not None:
            e_other = min(med(c, other, ident), med(c, other, flip))
            if e_other < ratio * e[c]:
                conf[c] = 0.0
                dropped[c] = True
                continue
        if med(c, pred, flip) < ratio * e[c]:
            uv[c], conf[c] = uv[c, flip], conf[c, flip]
            flipped[c] = True
    parts = np.zeros((C, len(BODY_PARTS)), bool)
    kp_dropped = np.zeros((C, K), bool)
    kept = ~(far | dropped | flipped)
    # the halves also of a view mirrored back as a whole: a view whose legs alone read
    # mirrored (12 of the 23 body keypoints) has its median held by them and is mirrored as a
    # whole, which mirrors its right arms; the arms are then mirrored back on their own
    for c in np.flatnonzero(kept | flipped):
        for p, (judged, moved) in enumerate(BODY_PARTS):
            judged = judged[judged < K]
            ep = med(c, pred, ident, judged)
            if ep > min_px and med(c, pred, flip, judged) < ratio * ep:
                moved = moved[moved < K]
                uv[c, moved], conf[c, moved] = uv[c, flip[moved]], conf[c, flip[moved]]
                parts[c, p] = True
    if other is not None:
        for c in np.flatnonzero(kept):
            ok = conf[c, body] > 0
            d = np.linalg.norm(uv[c, body] - project(cams[c], pred[body]), axis=-1)
            po = project(cams[c], other[body])
            d_other = np.minimum(np.linalg.norm(uv[c, body] - po, axis=-1),
                                 np.linalg.norm(uv[c, body] - po[flip[body]], axis=-1))
            bad = ok & (d > min_px) & (d_other < ratio * d)
            conf[c, body[bad]] = 0.0
            kp_dropped[c, body[bad]] = True
    return ViewCheck(uv, conf, flipped, dropped, far, parts, kp_dropped)


@dataclass(frozen=True)
class ViewCheck:
    """What :func:`check_views` made of one frame's detections: ``uv (C, K, 2)``, ``conf (C,
    K)`` after it, and per view ``flipped``, ``dropped`` (the wearer), ``far`` (somebody
    else), (C,) bool each."""

    uv: np.ndarray
    conf: np.ndarray
    flipped: np.ndarray
    dropped: np.ndarray
    far: np.ndarray
    parts_flipped: np.ndarray  # (C, 2) bool: the upper / lower half mirrored back alone (in a
    # view mirrored back as a whole: that half mirrored again, as it was read)
    keypoints_dropped: np.ndarray  # (C, K) bool: the wearer's joints read as the partner's

    @property
    def changed(self) -> bool:
        return bool(self.flipped.any() or self.dropped.any() or self.far.any()
                    or self.parts_flipped.any() or self.keypoints_dropped.any())


#: KP65 rows of each hand's wrist (the hand detector's) and the body's wrist, left and right
HAND_WRISTS = ((KP65.index("l_hand_wrist"), KP65.index("l_wrist"), S_LEFT_HAND),
               (KP65.index("r_hand_wrist"), KP65.index("r_wrist"), S_RIGHT_HAND))


def gate_hands(cams, pred: np.ndarray, uv: np.ndarray, conf: np.ndarray,
               gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop the hand detections that are not the estimate's hands.

    pred : (65, 3) keypoints of a solution fitted from the body keypoints alone; uv (C, 65,
    2), conf (C, 65) the detections. A view's hand (21 keypoints) whose wrist keypoint lies
    farther than ``gate_px`` from ``pred``'s body wrist (projected) is dropped (conf 0); a
    hand whose wrist was not detected is judged by the median of its keypoints against
    ``pred``'s hand keypoints, at twice the gate (the fingers of a body-only solution are
    the prior's). Returns ``(conf (C, 65) copy, gated (C, 2) bool)`` (left, right)."""
    conf = np.array(conf, float)
    C = conf.shape[0]
    gated = np.zeros((C, 2), bool)
    for c in range(C):
        for side, (hw, bw, sl) in enumerate(HAND_WRISTS):
            seen = conf[c, sl] > 0
            if not seen.any():
                continue
            if conf[c, hw] > 0:
                d = np.linalg.norm(uv[c, hw] - project(cams[c], pred[bw][None])[0])
                bad = d > gate_px
            else:
                P = project(cams[c], pred[sl][seen])
                bad = np.median(np.linalg.norm(uv[c, sl][seen] - P, axis=-1)) > 2 * gate_px
            if bad:
                conf[c, sl] = 0.0
                gated[c, side] = True
    return conf, gated


def wearer_posed(model: BodyModel, wearer: BodyFit, frames: np.ndarray, chunk: int = 64):
    """The wearer's posed body at video ``frames``: ``(vertices, joints)``, two lists with per
    frame (V, 3) / (J, 3) (NaN-free) or None where the wearer's fit has no such frame
    (``body.lbs.posed_at``)."""
    from body.lbs import posed_at

    return posed_at(model, wearer, frames, chunk)


def wearer_keypoints(posed, R) -> np.ndarray:
    """(F, K, 3) the wearer's keypoints (regressor ``R`` (K, V + J)) from
    :func:`wearer_posed`'s ``(vertices, joints)``; NaN where the wearer has no frame."""
    V, J = posed
    out = np.full((len(V), R.shape[0], 3), np.nan)
    for f, (v, j) in enumerate(zip(V, J, strict=True)):
        if v is not None:
            out[f] = R @ np.concatenate([v, j])
    return out


def wearer_vertices(model: BodyModel, wearer: BodyFit, frames: np.ndarray):
    """(F, V, 3) the wearer's posed mesh at video ``frames`` (NaN-free; frames the wearer's
    fit does not have: None in the returned list)."""
    return wearer_posed(model, wearer, frames)[0]


def reprojection_px(cams, pts: np.ndarray, uv: np.ndarray, conf: np.ndarray) -> np.ndarray:
    """(C, K) pixel error of model keypoints ``pts (K, 3)`` against detections, NaN where
    not detected."""
    err = np.stack([np.linalg.norm(project(c, pts) - uv[i], axis=-1) for i, c in enumerate(cams)])
    return np.where(conf > 0, err, np.nan)


def robust_px_cost(cams, pts: np.ndarray, uv: np.ndarray, conf: np.ndarray,
                   sigma_px: float) -> float:
    """The detections' robust cost of model keypoints ``pts (K, 3)``: the sum over views and
    keypoints of ``conf * rho(e^2)`` with L_2d's Geman-McClure ``rho`` (``fitting.robust``)."""
    e = np.nan_to_num(reprojection_px(cams, pts, uv, conf), nan=0.0)
    return float(np.sum(conf * robust.rho(e ** 2, "geman_mcclure", sigma_px)))


def unreliable_detections(cams, pts: list, uv: np.ndarray, conf: np.ndarray, max_px: float,
                          min_frames: int = RELIABILITY_MIN_FRAMES) -> np.ndarray:
    """(C, K) the (view, keypoint) pairs whose detections lie farther than ``max_px`` from
    the fitted keypoints ``pts`` (per frame ``(K, 3)``, None: not fitted) in the median over
    the frames that have both, judged where there are at least ``min_frames`` of them."""
    F, C, K = conf.shape
    err = np.full((F, C, K), np.nan)
    for f, p in enumerate(pts):
        if p is not None:
            err[f] = reprojection_px(cams, p, uv[f], conf[f])
    n = np.isfinite(err).sum(axis=0)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(n[None] > 0, err, 0.0), axis=0)
    return (n >= min_frames) & (med > max_px)


def _contact_report(extra, frames) -> dict:
    """The report's ``contact_terms`` from the contact matches: ``pairs_too_far``, the fit
    frames (video numbers) where a region pair was farther than ``contact_max_gap_m`` at the
    last evaluation and so not pulled, per region pair index;
    ``frames_released`` and their ``released_gap_m``: the contact frames fitted without
    ``L_G`` (``contact_release_m``)."""
    m = contact_matches(extra)
    if m is None:
        return {}
    out: dict[str, list[int]] = {}
    for f, k in sorted(m.too_far):
        out.setdefault(str(k), []).append(int(frames[f]))
    return {"max_gap_m": m.max_gap_m, "pairs_too_far": out,
            "frames_released": [int(frames[f]) for f in sorted(m.released)],
            "released_gap_m": [round(m.released[f], 4) for f in sorted(m.released)]}


def contact_matches(extra) -> FacetMatches | None:
    """The :class:`FacetMatches` the contact terms among ``extra`` share (None: no L_G)."""
    return next((t.matches for t in extra if isinstance(t, ContactTerm)), None)


def extra_terms(model: BodyModel, frames: np.ndarray, wearer_V, contact=None, ground=None,
                opts: PartnerFitOptions = PartnerFitOptions(), rmap=None,
                silhouettes=None) -> tuple[list, dict]:
    """The extra terms of a sequence whose weight is > 0, in the order ``L_gp``, ``L_ic``,
    ``L_sc``, ``L_D``, ``L_N``, and the report's ``contact_terms`` entry.

    frames : (F,) the fit's video frames; wearer_V : per fit frame the wearer's mesh (V, 3) or
    None (:func:`wearer_vertices`), or None without a wearer; contact : a
    ``ContactAnnotation`` or None; ground : ``(normal, offset)`` or None; rmap : the region
    map the annotation's region ids index (default ``body.regions.region_map(model)``).
    ``L_sc`` needs nothing else; ``L_ic`` the wearer; ``L_D`` / ``L_N`` the wearer and an
    annotation with contact (active in its interval only). ``contact_terms``: ``terms`` (the
    contact terms built), ``selection`` (the ``psi_D`` option), and when built
    ``frames`` (fit frames in the interval with the wearer's mesh) and ``pairs`` (per region
    pair: ``regions`` [wearer, partner], the ``selection`` used, ``facets`` [wearer, partner]
    selected); else ``why_not``."""
    w = opts.weights
    extra: list = []
    if ground is not None and w["L_gp"] > 0:
        extra.append(GroundTerm(np.asarray(ground[0], float), float(ground[1]), opts.ground_k))
    use_ic = wearer_V is not None and w["L_ic"] > 0
    if use_ic or w["L_sc"] > 0:
        proxy = collision.ProxyMesh.from_model(model, opts.proxy_vertices)
        if use_ic:
            extra.append(InterpenetrationTerm(proxy, wearer_V))
        if w["L_sc"] > 0:
            extra.append(SelfCollisionTerm(proxy))
    want = [n for n in ("L_D", "L_N") if w[n] > 0]
    info: dict = {"terms": [], "selection": opts.contact_selection}
    if not want:
        info["why_not"] = "weights L_D and L_N are 0"
    elif contact is None:
        info["why_not"] = "no contact annotation"
    elif not contact.has_contact:
        info["why_not"] = "the annotation has no contact"
    elif wearer_V is None:
        info["why_not"] = "no wearer fit"
    else:
        if rmap is None:
            from body.regions import region_map

            rmap = region_map(model)
        sel, modes = contact_selection(contact, rmap, opts.contact_selection,
                                       opts.contact_facets_n,
                                       np.random.default_rng(opts.contact_seed))
        matches = FacetMatches(contact, frames, wearer_V, np.asarray(model.faces), sel,
                               opts.contact_max_gap_m)
        extra.extend(ContactTerm(n, matches) for n in want)
        info.update(terms=want, frames=int(sum(matches.active(f) for f in range(len(frames)))),
                    pairs=[{"regions": list(map(str, contact.region_names[k])),
                            "selection": modes[k], "facets": [int(len(a)), int(len(b))]}
                           for k, (a, b) in enumerate(sel)])
    if silhouettes is not None and w["L_sil"] > 0:  # L_sil: a fitting.silhouette.SilhouetteInput
        from fitting.silhouette import silhouette_term

        extra.append(silhouette_term(model, frames, silhouettes, opts.proxy_vertices))
    return extra, info


def _observed_summary(model: BodyModel, fit: BodyFit) -> dict:
    """How much of the valid frames' body the evidence observed (:attr:`BodyFit.observed`):
    per joints3d_25 joint the share of valid frames it is ground truth in, and the share of
    valid frames with every joint observed."""
    from fitting.marker_graph import fit_points_observed
    from formats.skeletons import JOINTS3D_25

    v = np.asarray(fit.valid, bool)
    if not v.any():
        return {"frames_all_observed": None, "per_joint": {}}
    pts = fit_points_observed(model, fit)[v]
    return {"frames_all_observed": float(pts.all(axis=1).mean()),
            "per_joint": {n: round(float(pts[:, i].mean()), 3) for i, n in enumerate(JOINTS3D_25)}}


def seed_poses(start: BodyFit | None, skel, frames: np.ndarray) -> list[np.ndarray | None]:
    """Per frame of ``frames`` (F,): the unknowns x (the fit's packing: global rotation
    vector, translation, the fitted joints' rotation vectors) of ``start``'s pose at that
    frame where ``start`` has it and it is valid there, else None (None everywhere without
    ``start``).

    Why: the stage fits twice, before and after the second detection pass, and the second
    fit started each sequence afresh from the triangulated detections. A start triangulated
    from detections whose legs one view reads mirrored puts the legs crossed (bench, Kick,
    on one machine's mediapipe answers: the second start's knees 107-161 mm off, the first's
    15-24), and the fit cannot uncross them through each other; check_views then mirrors the
    right views' legs to match (40 of 80 view-halves), and all 20 frames, their knees and
    ankles 28-41 cm off, were published as valid. The first fit's pose, chosen on the first
    detections (around which the second pass cropped), does not depend on that
    triangulation."""
    out: list[np.ndarray | None] = [None] * len(frames)
    if start is None:
        return out
    X = pack(skel, start.body_pose, start.global_orient, start.transl)
    pos = {int(f): i for i, f in enumerate(np.asarray(start.frames, np.int64))}
    valid = np.asarray(start.valid, bool)
    for k, f in enumerate(np.asarray(frames, np.int64)):
        i = pos.get(int(f))
        if i is not None and valid[i]:
            out[k] = X[i]
    return out


def fit_partner(model: BodyModel, shape: ShapeFit, keypoints: Keypoints2D, cams,
                wearer: BodyFit | None = None, contact=None, ground=None,
                opts: PartnerFitOptions = PartnerFitOptions(), progress=None,
                log=None, silhouettes=None, start: BodyFit | None = None) -> tuple[BodyFit, dict]:
    """The partner's motion over the keypoints' video frames.

    model : BodyModel; shape : the partner's own :class:`artifacts.ShapeFit` (betas held
    fixed); keypoints : :class:`artifacts.Keypoints2D` (person 1 = the partner; its frames are
    the frames fitted; ``opts.max_frames`` keeps the first N); cams : ``calib.Camera`` per
    view (matched to the keypoints' views by id); wearer : the marker wearer's
    :class:`artifacts.BodyFit` (``L_ic``; None: no collision term); contact : a
    ``fitting.contact_signature.ContactAnnotation`` (``L_D`` / ``L_N`` in its interval, with
    the wearer; what was used: ``report["contact_terms"]``, :func:`extra_terms`); ground :
    ``(normal (3,), offset)`` of the
    ground plane (``L_gp``; None: none); progress : iterable wrapper; log : ``log(str)``;
    start : an earlier fit of the partner over these frames (the stage's first fit, before
    the second detection pass): a start frame (the first, a re-initialisation) that it
    fitted validly starts from its pose there (:func:`seed_poses`) instead of from
    ``init_pose``'s triangulation of this fit's detections; counted in the report's
    ``initialisations_from_start``.

    Returns the :class:`artifacts.BodyFit` (no marker fields) and a report dict whose
    ``per_frame`` entry holds arrays (the stage writes them to ``terms.npz``): ``reproj_px
    (F, C)`` median error per view, ``detections (F,)``, ``term_cost (F, T)`` the weighted
    cost of each term at the solution, ``term_active (F, T)``, ``term_points (F, T)``
    (offending points of the extra terms), names in ``report["terms"]``.
    """
    log = log or (lambda _msg: None)
    frames = np.asarray(keypoints.frames, np.int64)
    if opts.max_frames:
        frames = frames[: opts.max_frames]
    F, C = len(frames), len(cams)
    betas = np.asarray(shape.betas, float)
    rest = rest_state(model, betas)
    skel = skinned.fit_skeleton(model, None if opts.use_hands else body_joints(model))
    kidx = np.arange(len(KP65) if opts.use_hands else N_BODY)
    R_kp = regressor(model, "kp65")[kidx]
    Hk = skinned.regressed_coeffs(model, rest, skel, R_kp)
    uv, conf, kp_raw = _partner_keypoints(keypoints, cams, frames, kidx, opts.min_conf)
    body = _BodyCtx(model, betas, rest, skel)

    posed = None if wearer is None else wearer_posed(model, wearer, frames)
    WV = None if posed is None else posed[0]
    if silhouettes is not None:  # L_sil: the masks (artifacts.silhouettes) and the cameras
        from fitting.silhouette import SilhouetteInput

        silhouettes = SilhouetteInput(silhouettes, list(cams))
    rmap = None
    if contact is not None and WV is not None:  # one region map for L_G and the release
        from body.regions import region_map

        rmap = region_map(model)
    extra, contact_info = extra_terms(model, frames, WV, contact, ground, opts, rmap=rmap,
                                      silhouettes=silhouettes)
    t0 = time.perf_counter()
    reproj = Reprojection(skel, body.u, Hk, cams, body.sub)
    t_build = time.perf_counter() - t0
    prior = priors.couple_chains(priors.default_prior(skel.names[1:]), (priors.SPINE_CHAIN,),
                                 np.deg2rad(opts.spine_coupling_deg))
    solver = PartnerSolver(reproj, body, prior, opts, extra)
    names = ["L_2d", "L_theta", "L_s"] + [t.name for t in extra]

    flipK = np.asarray(KP65_FLIP)[kidx]
    WK = None if posed is None else wearer_keypoints(posed, R_kp)
    seeds = seed_poses(start, skel, frames)
    X = np.zeros((F, skel.n))
    reason = np.zeros(F, np.int8)
    err_px = np.full((F, C), np.nan)
    agree = np.zeros((F, C, len(kidx)), bool)  # the fitted keypoint within observed_px
    flipped = np.zeros((F, C), bool)
    dropped = np.zeros((F, C), bool)
    far = np.zeros((F, C), bool)
    halves = np.zeros((F, C, len(BODY_PARTS)), bool)
    on_wearer_n = np.zeros((F, C), np.int64)
    gated = np.zeros((F, C, 2), bool)
    gate = opts.use_hands and opts.hand_gate_px > 0
    hidden_n = np.zeros((F, C), np.int64)
    rejected_n = np.zeros((F, C), np.int64)  # keypoints left out as outliers of the solve
    uv_in, conf_in = uv.copy(), conf.copy()
    uv_pre, conf_pre = uv.copy(), np.zeros_like(conf)  # what each frame's solve used, before outlier_px
    unreliable = np.zeros((C, len(kidx)), bool)
    kept_first = []  # frames whose first forward pass was kept (reliability_px)
    occluder = None
    if opts.occlusion and WV is not None:
        from fitting.occlusion import hidden

        occluder = collision.ProxyMesh.from_mesh(model.v_template, np.asarray(model.faces),
                                                 OCCLUDER_VERTICES)

    def slots(x):
        return skinned.slot_positions_np(skel, body.u, Hk, x)

    def occluded(f, x):
        """(C, K) the partner's keypoints at x that the wearer hides in each view."""
        if WV[f] is None:
            return np.zeros((C, len(kidx)), bool)
        return hidden(cams, slots(x), occluder.points(WV[f]), occluder.faces)

    def record(f, x, blocks, x_ref, s_scale=1, e=None):
        """Frame f's solution x and the terms at it (L_s against x_ref, None: none; e: its
        reprojection_px against uv[f], conf[f] when already known)."""
        X[f] = x
        cost[f], active[f], npts[f] = 0.0, False, 0
        if e is None:
            e = reprojection_px(cams, slots(x), uv[f], conf[f])
        with np.errstate(all="ignore"):
            err_px[f] = [np.nanmedian(r) if np.isfinite(r).any() else np.nan for r in e]
            agree[f] = np.nan_to_num(e, nan=np.inf) <= opts.observed_px
        reason[f] = 0 if np.nanmedian(e) <= opts.max_reproj_px else REASON_CODE["poor_reprojection"]
        s2 = solver.row_scale[0] ** 2
        r2 = np.sum(((np.nan_to_num(e) ** 2) * conf[f]) / max(int((conf[f] > 0).sum()), 1))
        cost[f, 0] = s2 * r2
        g = prior.gaussian
        cost[f, 1] = opts.weights["L_theta"] * float(np.sum((g.sqrt_precision @ (x[6:] - g.mean)) ** 2))
        if x_ref is not None:
            cost[f, 2] = s_scale * opts.weights["L_s"] * float(np.sum((x - x_ref) ** 2))
        active[f, :3] = True, True, x_ref is not None
        for b in blocks:
            j = names.index(b.name)
            r = b.residual(skinned.slot_positions_np(skel, body.u, b.H, x))[0]  # no Jacobian
            cost[f, j] += opts.weights[b.name] * float(r @ r)
            active[f, j] = True
            npts[f, j] += b.points

    cost = np.zeros((F, len(names)))
    active = np.zeros((F, len(names)), bool)
    npts = np.zeros((F, len(names)), np.int64)
    det = (conf[:, :, :N_BODY] > 0).sum((1, 2))
    views = (conf[:, :, :N_BODY] > 0).any(2).sum(1)
    enough = (det >= opts.min_keypoints) & (views >= opts.min_views)

    def checked(f, x, uvf, cf):
        """``check_views`` of frame f's detections against the partner at x, its findings
        recorded."""
        vc = check_views(cams, slots(x), uvf, cf, flipK, None if WK is None else WK[f],
                         far_px=opts.bystander_px, support=opts.bystander_views)
        if vc.changed:
            flipped[f] |= vc.flipped
            dropped[f] |= vc.dropped
            far[f] |= vc.far
            halves[f] |= vc.parts_flipped
            on_wearer_n[f] += vc.keypoints_dropped.sum(-1)
        return vc

    matches = contact_matches(extra) if opts.contact_release_m > 0 else None
    faces = np.asarray(model.faces)
    regions = contact_regions(model, contact, rmap) if matches is not None else []
    per_frame_state = (flipped, dropped, far, halves, on_wearer_n, gated, hidden_n, rejected_n)

    def release_contact():
        """The contact frames whose annotated regions the forward pass left farther apart than
        ``contact_release_m`` with ``L_G`` (the detections held them off) fitted again without
        it, in order, each from its detections as they came (before this frame's checks) and
        warm-started from and tied to the frame before (``FacetMatches.released``). Decided
        on the whole pass, not frame by frame inside it: a frame fitted without L_G is the
        next frame's start, from which L_G cannot bring touching regions back together."""
        gaps = {f: region_distance(WV[f], body.posed_vertices(X[f]), faces, regions)
                for f in range(F) if active[f, 0] and matches.active(f)}
        for f in sorted(g for g, d in gaps.items() if d > opts.contact_release_m):
            matches.released[f] = gaps[f]
            uv[f], conf[f] = uv_in[f], np.where(unreliable, 0.0, conf_in[f])
            for a in per_frame_state:
                a[f] = 0
            prev = f > 0 and active[f - 1, 0]
            fit_frame(f, X[f - 1] if prev else X[f], X[f - 1] if prev else None,
                      seeded=not prev)

    def fit_frame(f, x0, x_ref, seeded=False):
        """Frame f solved from x0 (tied to x_ref by L_s; None: a start frame, whose views are
        not checked against an estimate unless x0 is ``seeded``: an earlier fit's pose) and
        recorded; returns its solution."""
        start = x_ref is None
        uvf, cf = uv[f], conf[f]
        if opts.check_views and (seeded or not start):  # against the neighbouring frame's
            # solution (or the earlier fit's pose at a start frame)
            vc = checked(f, x0, uvf, cf)
            uvf, cf = vc.uv, vc.conf
        first = start
        if gate or occluder is not None:  # a first solve from the body keypoints alone
            cb = cf.copy()
            if gate:
                cb[:, N_BODY:] = 0.0
            if occluder is not None and not start:  # what the wearer hides, by the last frame
                cb[occluded(f, x0)] = 0.0
            res, _, _ = solver.solve(x0, uvf, cb, f, x_ref, first=first, extra=False)
            if occluder is not None:  # ... and by this frame's body
                hid = occluded(f, res.x) & (cf > 0)
                cf = np.where(hid, 0.0, cf)
                hidden_n[f] = hid.sum(axis=1)
            if gate:  # the hands that are not that body's hands left out
                cf, gated[f] = gate_hands(cams, slots(res.x), uvf, cf, opts.hand_gate_px)
            x0, first = res.x, False
        res, blocks, nr = solver.solve(x0, uvf, cf, f, x_ref, first=first)
        rounds.append(nr)
        if opts.check_views:  # and against this frame's own solution
            vc = checked(f, res.x, uvf, cf)
            if vc.changed:
                uvf, cf = vc.uv, vc.conf
                res, blocks, _ = solver.solve(res.x, uvf, cf, f, x_ref)
        e = None  # the solution's reprojection, kept for record() while it still holds
        uv_pre[f], conf_pre[f] = uvf, cf
        if opts.outlier_px > 0:  # a detection the solution lies far from: left out, solved again
            e = reprojection_px(cams, slots(res.x), uvf, cf)
            far_px = np.nan_to_num(e, nan=0.0) > opts.outlier_px
            if far_px.any():
                cf = np.where(far_px, 0.0, cf)
                rejected_n[f] = far_px.sum(axis=1)
                res, blocks, _ = solver.solve(res.x, uvf, cf, f, x_ref)
                e = None
        uv[f], conf[f] = uvf, cf
        x = rewrap(res.x)
        iters.append(res.iterations)
        record(f, x, blocks, x_ref, e=e)
        return x

    x_prev, miss, first_fit, inits, iters, rounds, t_rounds = None, 0, None, 0, [], [], []
    n_seeded = 0
    backfilled = 0
    from threadpoolctl import threadpool_limits

    def forward_pass(it):
        """Each frame warm-started from and tied to the previous one (a start frame from the
        earlier fit's pose or from triangulation), then the frames before the first fitted
        one backwards."""
        nonlocal x_prev, miss, first_fit, inits, n_seeded, backfilled
        x_prev, miss, first_fit = None, 0, None
        for f in it:
            start = x_prev is None or miss > opts.reinit_after
            x0, from_start = x_prev, False
            if enough[f] and start and seeds[f] is not None:  # the earlier fit's pose here
                x0, from_start = seeds[f], True
                n_seeded += 1
            elif enough[f] and start:
                kpi = kp_raw[:, f].copy()
                if gate:  # from the body alone (a wrong hand triangulated drags the arm)
                    kpi[:, N_BODY:, 2] = 0.0
                init = init_pose(model, betas, cams, kpi, skel, InitOptions())
                x0 = init.x if init.ok else None
                if not init.ok:
                    log(f"frame {int(frames[f])}: no initialisation ({init.reason})")
                else:
                    inits += 1
            if not enough[f] or x0 is None:
                if x_prev is not None:
                    X[f] = x_prev
                    reason[f] = REASON_CODE["too_few_keypoints"]
                else:
                    reason[f] = REASON_CODE["held_before_first_keypoints"]
                miss += 1
                continue
            x = fit_frame(f, x0, None if start else x_prev, seeded=from_start)
            miss = 0
            first_fit = f if first_fit is None else first_fit
            x_prev = x
        if first_fit and opts.backfill:  # the frames before the first initialised one, backwards
            x_next, miss = X[first_fit], 0
            for f in reversed(range(first_fit)):
                if miss > opts.reinit_after:
                    break
                if not enough[f]:
                    X[f] = x_next
                    reason[f] = REASON_CODE["too_few_keypoints"]
                    miss += 1
                    continue
                x_next, miss, first_fit = fit_frame(f, x_next, x_next), 0, f
                backfilled += 1
            reason[:first_fit] = REASON_CODE["held_before_first_keypoints"]  # a run at the start

    it = range(F) if progress is None else progress(range(F), total=F, desc="partner_fit")
    t0, c0 = time.perf_counter(), time.thread_time()
    with threadpool_limits(limits=1):
        forward_pass(it)
        if opts.reliability_px > 0 and F >= 3:  # a view's biased keypoint left out, and again
            unreliable = unreliable_detections(
                cams, [slots(X[f]) if active[f, 0] else None for f in range(F)], uv_pre,
                conf_pre, opts.reliability_px)
            if unreliable.any():
                uv[:], conf[:] = uv_in, conf_in
                conf[:, unreliable] = 0.0
                for arr in (flipped, dropped, far, halves, on_wearer_n, gated, hidden_n,
                            rejected_n, agree, active):  # what the report says: the last pass
                    arr[:] = 0
                reason[:] = 0
                X1 = X.copy()
                forward_pass(range(F))
                for f in np.flatnonzero(active[:, 0]):  # per frame, the pass that explains
                    # the detections left better (the second may have found a worse basin)
                    c1, c2 = (robust_px_cost(cams, slots(x), uv[f], conf[f],
                                             opts.sigma_keypoint_px) for x in (X1[f], X[f]))
                    if c1 < c2:  # recorded again at that pose (tied to the frame before)
                        ref = X[f - 1] if f > 0 and active[f - 1, 0] else None
                        record(f, X1[f], solver.blocks(X1[f], f), ref)
                        kept_first.append(int(f))
        if matches is not None and F >= 2:
            release_contact()
        if opts.temporal_passes and F >= 3:  # both directions: each frame against both neighbours
            for _ in range(opts.temporal_passes):
                for f in reversed(range(F)):
                    nb = [X[g] for g in (f - 1, f + 1) if 0 <= g < F and active[g, 0]]
                    if not active[f, 0] or not nb:
                        continue
                    ref = np.mean(nb, axis=0)
                    res, blocks, nr = solver.solve(X[f], uv[f], conf[f], f, ref, s_scale=len(nb),
                                                   rounds_max=opts.temporal_rounds)
                    iters.append(res.iterations)
                    t_rounds.append(nr)
                    record(f, rewrap(res.x), blocks, ref, len(nb))
            for f in range(1, F):  # a held frame holds its predecessor's final pose
                if not active[f, 0] and reason[f] == REASON_CODE["too_few_keypoints"]:
                    X[f] = X[f - 1]
    t_fit, c_fit = time.perf_counter() - t0, time.thread_time() - c0
    if first_fit is not None:
        X[:first_fit] = X[first_fit]
    body_pose, R, T = unpack(skel, model.num_joints, X)
    # a joint is ground truth only where keypoints that move with it were used in two views
    # that the fitted body agrees with (observed_px)
    # (agree is set only where a frame is solved, and only where its detection is kept)
    seen = agree.sum(axis=1) >= MIN_VIEWS_OBSERVED  # (F, K)
    kp_seen = np.zeros((F, len(KP65)), bool)
    kp_seen[:, kidx] = seen
    observed = observed_joints(model, skel, (), np.zeros((F, 0), bool),
                               skinned.support_of(Hk, OBSERVED_WEIGHT), seen)
    out = BodyFit(body_pose=body_pose, global_orient=R, transl=T, betas=betas, frames=frames,
                  valid=reason == 0, invalid_reason=reason, observed=observed,
                  keypoints_observed=kp_seen)
    reasons = out.reasons()
    n_fit = int(np.count_nonzero(active[:, 0]))
    with np.errstate(all="ignore"):
        rp = {"median": float(np.nanmedian(err_px)) if np.isfinite(err_px).any() else None,
              "per_view_median": [float(np.nanmedian(err_px[:, c])) if np.isfinite(err_px[:, c]).any()
                                  else None for c in range(C)]}
    report = {
        "frames": F, "first_fitted_frame": None if first_fit is None else int(frames[first_fit]),
        "frames_valid": reasons["fitted"],
        "frames_not_valid": {n: reasons[n] for n in PARTNER_FIT_REASONS},
        "initialisations": inits, "initialisations_from_start": n_seeded,
        "frames_backfilled": backfilled, "terms": names, "weights": dict(opts.weights),
        "reprojection_px": rp, "hands": bool(opts.use_hands), "fitted_joints": list(skel.names),
        "prior": prior.source, "build_s": round(t_build, 3),
        "fit_s": round(t_fit, 3), "fit_cpu_s": c_fit, "extra_jacobian_s": round(body.jacobian_s, 3),
        "extra_hooks_s": round(body.hook_s, 3),
        "fps": round(n_fit / max(t_fit, 1e-9), 2),
        "mean_iterations": float(np.mean(iters)) if iters else 0.0,
        # LM rounds per frame (hooks re-run between them): forward pass, temporal pass
        "mean_rounds": float(np.mean(rounds)) if rounds else 0.0,
        "mean_rounds_temporal": float(np.mean(t_rounds)) if t_rounds else 0.0,
        "contact_frames": 0 if contact is None or not contact.has_contact else int(np.count_nonzero(
            (frames >= contact.interval[0]) & (frames <= contact.interval[1]))),
        "contact_terms": {**contact_info, **_contact_report(extra, frames)},
        "frames_with": {n: int(active[:, i].sum()) for i, n in enumerate(names)},
        "views_mirrored_back": int(flipped.sum()), "views_dropped_as_wearer": int(dropped.sum()),
        "views_dropped_as_bystander": int(far.sum()),
        "views_dropped_as_bystander_per_view": [int(v) for v in far.sum(axis=0)],
        "view_halves_mirrored_back": {"upper": int(halves[..., 0].sum()),
                                      "lower": int(halves[..., 1].sum())},
        "keypoints_dropped_as_wearer": {"keypoints": int(on_wearer_n.sum()),
                                        "views": int((on_wearer_n > 0).sum())},
        "body_keypoints_detected": int(det.sum()),
        "joints_observed": _observed_summary(model, out),
        "keypoints_hidden_by_wearer": int(hidden_n.sum()) if occluder is not None else None,
        "keypoints_rejected_as_outliers": {
            "keypoints": int(rejected_n.sum()), "outlier_px": opts.outlier_px or None,
            # per view, the frames where it lost most of its keypoints to the rule (only a
            # solved frame loses any)
            "frames_view_lost_most": [int(v) for v in (
                rejected_n > (conf > 0).sum(axis=2)).sum(axis=0)],
            "frames_solved": n_fit},
        "hands_gated": {"views": int(gated.sum()), "gate_px": opts.hand_gate_px if gate else None},
        "detections_unreliable": {
            "reliability_px": opts.reliability_px or None, "pairs": int(unreliable.sum()),
            "frames_kept_from_first_pass": len(kept_first),
            "per_view": {c.name: [KP65[k] for k in kidx[unreliable[i]]]
                         for i, c in enumerate(cams) if unreliable[i].any()}},
        "per_frame": {"reproj_px": err_px, "views_seeing": views_seeing(conf),
                      "views_flipped": flipped, "views_dropped": dropped, "views_bystander": far, "halves_flipped": halves,
                      "keypoints_on_wearer": on_wearer_n, "hands_gated": gated, "keypoints_hidden": hidden_n,
                      "keypoints_rejected": rejected_n,
                      "detections": det, "term_cost": cost,
                      "term_active": active, "term_points": npts, "frames": frames},
    }
    return apply_min_valid_views(out, report, opts.min_valid_views, C)


def views_seeing(conf: np.ndarray) -> np.ndarray:
    """(F,) int: per frame the views that hold at least ``VIEW_MIN_KEYPOINTS`` of the
    partner's body keypoints; conf (F, C, K) (0 = not used)."""
    return ((np.asarray(conf)[:, :, :N_BODY] > 0).sum(2) >= VIEW_MIN_KEYPOINTS).sum(1)


def apply_min_valid_views(fit: BodyFit, report: dict, min_valid_views: int,
                          cameras: int) -> tuple[BodyFit, dict]:
    """The fit with its valid frames seen by fewer than ``required`` =
    ``min(min_valid_views, cameras)`` views (``report["per_frame"]["views_seeing"]``; a rig of
    fewer cameras needs every camera) made not valid, ``too_few_views``, and the report's
    counts to match (``frames_valid``, ``frames_not_valid``, ``valid_views_required``). A
    frame not valid for another reason keeps it; one judged ``too_few_views`` before is
    judged again at ``required``."""
    import dataclasses

    required = min(int(min_valid_views), int(cameras))
    seeing = np.asarray(report["per_frame"]["views_seeing"])
    few = REASON_CODE["too_few_views"]
    reason = np.asarray(fit.invalid_reason).copy()
    reason[reason == few] = 0
    reason[(reason == 0) & (seeing < required)] = few
    out = dataclasses.replace(fit, valid=reason == 0, invalid_reason=reason)
    reasons = out.reasons()
    return out, {**report, "frames_valid": reasons["fitted"],
                 "frames_not_valid": {n: reasons[n] for n in PARTNER_FIT_REASONS},
                 "valid_views_required": required}


# ---------------------------------------------------------------------------- figures


def contact_regions(model: BodyModel, contact=None, rmap=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The faces of each annotated region pair of ``contact`` (wearer region, partner region;
    ``body.regions.region_map(model)`` unless ``rmap``): ``psi_D`` in mode "all"
    (``fitting.contact_signature.select_facets``); [] without a contact."""
    if contact is None or not contact.has_contact:
        return []
    from body.regions import region_map
    from fitting.contact_signature import select_facets

    return select_facets(contact, region_map(model) if rmap is None else rmap, "all")


def region_distance(V_wearer: np.ndarray, V_partner: np.ndarray, faces: np.ndarray,
                    regions: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """The contact distance of two posed meshes (metres): the mean over the region pairs
    (:func:`contact_regions`) of the smallest facet distance between the two regions
    (``geometry.facet_distances``)."""
    from geometry import facet_distances

    return float(np.mean([facet_distances(V_wearer, faces, a, V_partner, faces, b).a_to_b.min()
                          for a, b in regions]))


def contact_figures(model: BodyModel, partner: BodyFit, wearer: BodyFit | None, contact=None,
                    ground=None, rmap=None) -> dict[str, np.ndarray]:
    """Per-frame figures of a fit (metres): ``penetration_m (F,)`` deepest interpenetration
    of the two posed meshes (``geometry.interpenetration``; NaN without the wearer),
    ``contact_m (F,)`` in the contact interval (NaN outside): mean over the annotated region
    pairs of the smallest facet distance between the two regions (wearer region, partner
    region; ``geometry.facet_distances``), ``ground_m (F,)`` depth of the lowest partner
    vertex below the ground plane (0 above; NaN without a plane)."""
    from geometry import interpenetration

    F = partner.num_frames
    VP = forward(model, np.asarray(partner.betas, float), partner.body_pose,
                 partner.global_orient, partner.transl).vertices
    faces = np.asarray(model.faces)
    pen = np.full(F, np.nan)
    con = np.full(F, np.nan)
    gnd = np.full(F, np.nan)
    WV = wearer_vertices(model, wearer, partner.frames) if wearer is not None else [None] * F
    sel = contact_regions(model, contact, rmap)
    for i, f in enumerate(np.asarray(partner.frames)):
        if WV[i] is not None:
            pen[i] = interpenetration(VP[i], WV[i], faces).depth
            if sel and contact.interval[0] <= f <= contact.interval[1]:
                con[i] = region_distance(WV[i], VP[i], faces, sel)
        if ground is not None:
            d = VP[i] @ np.asarray(ground[0], float) - float(ground[1])
            gnd[i] = max(0.0, -float(d.min()))
    return {"penetration_m": pen, "contact_m": con, "ground_m": gnd}


# ---------------------------------------------------------------------------- shape from views

#: KP65 bones whose length the shape from the views matches (rest pose, model keypoints):
#: upper and lower arms and legs, shoulder and hip widths, both sides of the torso
SHAPE_BONES = (("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("r_shoulder", "r_elbow"),
               ("r_elbow", "r_wrist"), ("l_hip", "l_knee"), ("l_knee", "l_ankle"),
               ("r_hip", "r_knee"), ("r_knee", "r_ankle"), ("l_shoulder", "r_shoulder"),
               ("l_hip", "r_hip"), ("l_shoulder", "l_hip"), ("r_shoulder", "r_hip"))
SHAPE_RIDGE = 1e-4  # m^2 per unit beta^2: keeps the betas the bones do not determine at 0


@dataclass(frozen=True)
class ViewShape:
    """The shape estimated from the views: ``betas``, the observed and fitted bone lengths
    (metres, :data:`SHAPE_BONES` order; NaN: not seen), the frames used and the rms bone
    error before / after (mm)."""

    betas: np.ndarray
    bones_observed_m: np.ndarray
    bones_fitted_m: np.ndarray
    frames_used: int
    rms_before_mm: float
    rms_after_mm: float

    def report(self) -> dict:
        def r(a):
            return [None if not np.isfinite(v) else round(float(v), 4) for v in a]

        return {"source": "views", "frames_used": self.frames_used,
                "bones": ["-".join(b) for b in SHAPE_BONES],
                "bones_observed_m": r(self.bones_observed_m),
                "bones_fitted_m": r(self.bones_fitted_m),
                "bone_rms_mean_shape_mm": round(self.rms_before_mm, 1),
                "bone_rms_mm": round(self.rms_after_mm, 1)}


def observed_bones(keypoints: Keypoints2D, cams, person: int = PARTNER, frames: int = 20,
                   min_conf: float = 0.5) -> tuple[np.ndarray, int]:
    """(B,) median length of each :data:`SHAPE_BONES` bone (metres) over the first ``frames``
    frames where the person is seen in >= 2 views, from the keypoints triangulated per frame
    (linear DLT, ``calib.dlt.triangulate_points``), and the frames used."""
    from calib.dlt import triangulate_points

    idx = {n: i for i, n in enumerate(KP65)}
    ci = [keypoints.camera(c.name) for c in cams]
    kp = np.asarray(keypoints.person(person), float)[ci]  # (C, F, 65, 3)
    lens, used = [], 0
    for f in range(kp.shape[1]):
        ok = kp[:, f, :N_BODY, 2] >= min_conf
        if (ok.sum(1) >= 6).sum() < 2:
            continue
        X = triangulate_points(cams, kp[:, f, :N_BODY, :2], ok)
        lens.append([np.linalg.norm(X[idx[a]] - X[idx[b]]) for a, b in SHAPE_BONES])
        used += 1
        if used >= frames:
            break
    if not lens:
        return np.full(len(SHAPE_BONES), np.nan), 0
    L = np.array(lens, float)
    seen = np.isfinite(L).any(axis=0)
    out = np.full(L.shape[1], np.nan)
    out[seen] = np.nanmedian(L[:, seen], axis=0)
    return out, used


def shape_from_views(model: BodyModel, keypoints: Keypoints2D, cams, person: int = PARTNER,
                     frames: int = 20, ridge: float = SHAPE_RIDGE) -> ViewShape:
    """Betas whose rest-pose keypoint bones (:data:`SHAPE_BONES`) match the bones seen in
    the views (:func:`observed_bones`, the first ``frames`` frames where the person is seen),
    Gauss-Newton with a ridge toward the mean shape. The keypoints are exactly linear in the
    betas (``v_template + shapedirs @ betas``, the same for the joints, then the KP65
    regressor); a bone length is not, hence the iterations."""
    idx = {n: i for i, n in enumerate(KP65)}
    obs, used = observed_bones(keypoints, cams, person, frames)
    S = model.num_betas
    R = regressor(model, "kp65")
    A0 = R @ np.concatenate([model.v_template, model.joint_template])  # (65, 3)
    D = np.concatenate([np.asarray(model.shapedirs, float)[:, :, :S],
                        np.asarray(model.joint_shapedirs, float)[:, :, :S]])  # (V+J, 3, S)
    Ad = np.einsum("kn,nds->kds", R.toarray() if hasattr(R, "toarray") else R, D)  # (65, 3, S)
    ia = np.array([idx[a] for a, _ in SHAPE_BONES])
    ib = np.array([idx[b] for _, b in SHAPE_BONES])
    ok = np.isfinite(obs)
    b = np.zeros(S)

    def bones(beta):
        P = A0 + Ad @ beta
        d = P[ia] - P[ib]
        return np.linalg.norm(d, axis=1), d

    L0, _ = bones(b)
    if ok.sum() >= 4:
        for _ in range(8):
            L, d = bones(b)
            J = np.einsum("bd,bds->bs", d / L[:, None], Ad[ia] - Ad[ib])[ok]
            r = (L - obs)[ok]
            H = J.T @ J + ridge * np.eye(S)
            step = np.linalg.solve(H, -(J.T @ r + ridge * b))
            b = b + step
            if np.abs(step).max() < 1e-6:
                break
    L1, _ = bones(b)

    def rms(L):
        return float(np.sqrt(np.mean((L - obs)[ok] ** 2)) * 1000) if ok.any() else float("nan")

    return ViewShape(betas=b, bones_observed_m=obs, bones_fitted_m=L1, frames_used=used,
                     rms_before_mm=rms(L0), rms_after_mm=rms(L1))
