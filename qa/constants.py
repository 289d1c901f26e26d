"""Constants of the QA metrics (``qa.metrics``): keypoint groups, default thresholds and the
fixed parameters of the measurements. Units: metres, seconds, pixels unless named otherwise.

The default thresholds were calibrated on the clean bench session (8 sequences, keypoint
stride 6, 160 frames) and the demo session (2 sequences, full rate, 200 frames), against the
studio's ground truth: each threshold sits just above the largest value seen on the frames
whose fits are right (both people's KP65 body keypoints within 10 cm of the truth, partner
valid). Those frames are then flagged at 1.7 % (6 of 360, all ``wearer.marker_max_mm``: the
RFIN / LFIN marker 10-11 cm off in a grip, where the fitted fingers are 15-26 cm from the
truth: a real defect that the body-only truth check misses). Clean maxima on those frames:
marker max 31 mm (p98; 113 mm on those finger frames), per-view reprojection body 121 / hands
77 / face 52 px, cross-view body 45 / hands 43 / face 20 px, penetration 39 mm, volume 67 cm3,
self-penetration 35 mm, ground 6.5 mm, foot skate 1.1 m/s, jerk 662 m/s3, contact gap 3 mm,
closest distance outside contact 19 mm, sync offset 0 (all minima of the cost at 0).
"""
from __future__ import annotations

from formats import skeletons as S

# ---------------------------------------------------------------- KP65 keypoint groups
#: The face: nose, eyes, ears (KP65 has no other face points).
FACE = tuple(range(0, 5))
#: The body: shoulders, elbows, wrists, hips, knees, ankles and the six foot points.
BODY = tuple(range(5, len(S.BODY23)))
#: Both hands (21 + 21).
HANDS = tuple(range(S.LEFT_HAND.start, S.RIGHT_HAND.stop))
GROUPS = {"body": BODY, "hands": HANDS, "face": FACE}
#: Sub-groups whose median errors are combined per group (the worst of them): a group's error
#: is the largest median over its limbs, so that one limb off (a rotated forearm: 2-3 body
#: keypoints, one hand) shows though the group's overall median would hide it.
LIMBS = {
    "body": (
        tuple(S.kp65_index(n) for n in ("l_shoulder", "l_elbow", "l_wrist")),
        tuple(S.kp65_index(n) for n in ("r_shoulder", "r_elbow", "r_wrist")),
        tuple(S.kp65_index(n) for n in ("l_hip", "l_knee", "l_ankle")),
        tuple(S.kp65_index(n) for n in ("r_hip", "r_knee", "r_ankle")),
        tuple(S.kp65_index(n) for n in ("l_big_toe", "l_small_toe", "l_heel")),
        tuple(S.kp65_index(n) for n in ("r_big_toe", "r_small_toe", "r_heel")),
    ),
    "hands": (tuple(range(S.LEFT_HAND.start, S.LEFT_HAND.stop)),
              tuple(range(S.RIGHT_HAND.start, S.RIGHT_HAND.stop))),
    "face": (FACE,),
}
#: The cross-view reprojection figure (the median over the views) needs this many views.
MIN_VIEWS = 2
#: A limb needs this many confident detections in a view to count.
MIN_LIMB_POINTS = 2

# ---------------------------------------------------------------- sync
#: Time shifts (video frames) tried for each view.
SYNC_SHIFTS = tuple(range(-3, 4))
#: The best shift replaces 0 only when its gain over 0 is this many standard errors over the
#: person-frames (``qa.metrics._paired_z``). Session 31, bench store (8 sequences x 4 views, one
#: noise draw): the clean views' best nonzero shifts reach 1.2, the view delayed by 2 frames 3.1.
SYNC_MIN_Z = 2.5
#: Only detections whose projected person moves at least this much across the shifts count.
SYNC_MIN_MOTION_PX = 3.0
#: Per-detection errors are clipped here (a wrong detection counts as a miss, not more).
SYNC_CAP_PX = 25.0
#: Informative detections needed to estimate a view's shift.
SYNC_MIN_POINTS = 30
#: A view whose best shift still costs more (most detections a miss) is not judged. The
#: partner's detections fit worse than the wearer's (the Kick bench view delayed on purpose
#: costs 19 px at its best shift, with the partner in).
SYNC_MAX_COST_PX = 22.0
#: A view is judged only when its mean cost rises by at least SYNC_MIN_RISE (relative) from
#: the chosen shift to a shift SYNC_SENSE_FRAMES away on each side (the farthest tried up to
#: there): detections that do not follow the motion cannot say "in sync". Session 32's bench
#: (one noise draw): the Kick view delayed on purpose cost 17.7-18.2 px at every shift from -3
#: to 0 and read 0 (passing for in sync); the clean views rise 0-109 %, 11 of 32 by less than
#: 10 %. (A significance test of the rise, frame-clustered like SYNC_MIN_Z at 2.5, passed
#: only 13 of 32 on 20 frames and failed clear V's such as Posing's 50591643, 75 % up at z 1.4:
#: most frames of a view carry no timing, the few moving ones all of it.)
SYNC_SENSE_FRAMES = 2
SYNC_MIN_RISE = 0.10
SYNC_MARKER_RADIUS_M = 0.15  # a keypoint follows its nearest marker within this (sync)

# ---------------------------------------------------------------- geometry
#: Penetrating volume: grid cell edge (m) and the largest grid (cells); a larger overlap gets
#: coarser cells.
VOLUME_CELL_M = 0.005
VOLUME_MAX_CELLS = 40_000
#: Unexpected contact: the two meshes' closest distance is measured up to this (farther frames
#: report NEAR_M).
NEAR_M = 0.10
#: Foot skate: a foot vertex within this of the floor is in contact.
FOOT_CONTACT_M = 0.02
#: Foot regions (``body.regions`` names, both sides) whose vertices are the foot.
FOOT_REGIONS = ("sole", "heel", "toes")
#: Unexpected contact: frames within this many video frames of the annotated interval count as
#: expected (approach and release).
CONTACT_MARGIN_FRAMES = 10
#: Jerk: the third difference is taken on fit frames at least this far apart (seconds).
JERK_DT_S = 0.1
#: Proxy mesh size for self-penetration (``fitting.collision.ProxyMesh``).
PROXY_VERTICES = 2000

# ---------------------------------------------------------------- default thresholds
MARKER_MAX_MM = 40.0
MARKERS_REPAIRED = 0.5  # any marker repaired by the cleaning step near the frame flags it
MARKER_MEDIAN_MM = 15.0
REPROJ_BODY_PX = 130.0
REPROJ_HANDS_PX = 80.0
REPROJ_FACE_PX = 55.0
REPROJ_VIEWS_BODY_PX = 48.0
REPROJ_VIEWS_HANDS_PX = 45.0
REPROJ_VIEWS_FACE_PX = 21.0
SYNC_MAX_FRAMES = 0  # any shift the check finds is flagged (0 on every clean view of the bench and the demo)
PENETRATION_MM = 40.0
PENETRATION_VOLUME_CM3 = 70.0
SELF_PENETRATION_MM = 40.0
GROUND_PENETRATION_MM = 10.0
FOOT_SKATE_M_S = 1.2
CONTACT_GAP_MM = 20.0
UNEXPECTED_CONTACT_MM = 5.0
JERK_M_S3 = 1000.0
MERGE_GAP_FRAMES = 2
MIN_CONF = 0.3
NOT_VALID = 0.5  # <person>.not_valid is 1.0 / 0.0, flagged above this

# ---------------------------------------------------------------- withholding (stage export)
#: The QA reasons (``QAOptions`` threshold fields, i.e. ``qa.metrics.threshold_name`` of a
#: flagged metric) that mean the FIT is wrong for that person and frame: a frame flagged by
#: one of them is published not valid (``valid/<action>.json`` reason ``qa:<name>``; recipe
#: ``stages.export.withhold``, this is its default). Why each one:
FIT_WRONG = {
    "marker_max_mm": "a marker the fitted surface misses by > 40 mm: the body part carrying it "
                     "is off (the clean session's only flags are fingers fitted 15-26 cm off)",
    "marker_median_mm": "the body as a whole is off its own markers",
    "reproj_views_body_px": "a keypoint off in at least two views: a fit error shows in most "
                            "views, a bad detection in one",
    "reproj_views_hands_px": "a hand off in at least two views (the hands are part of the truth)",
    "reproj_views_face_px": "the head off in at least two views",
    "penetration_mm": "one body deep inside the other: at least one of the two poses is wrong",
    "penetration_volume_cm3": "a volume inside both bodies: at least one of the two is wrong",
    "self_penetration_mm": "limbs through the person's own body: not a pose a body takes",
    "ground_penetration_mm": "the body below the floor it stands on",
    "contact_gap_mm": "the annotated contact regions apart in an annotated contact frame: the "
                      "fits contradict the annotation",
    "unexpected_contact_mm": "the bodies touching or interpenetrating outside the annotated "
                             "interval: the annotation says they are apart",
    "jerk_m_s3": "a keypoint's third difference no body produces: the frame is off its "
                 "neighbours",
}
#: The QA reasons that do not say the fit is wrong (flagged for a reviewer, published valid
#: unless listed in ``stages.export.withhold``). Why each one:
NOT_FIT_WRONG = {
    "markers_repaired": "input side: the cleaning repaired the capture around the frame; the fit "
                        "on the repaired capture may be right (its residuals say)",
    "sync_max_frames": "input side: a camera out of sync; the wearer's fit does not use the "
                       "videos and a partner fit it spoils shows in the cross-view reprojection",
    "reproj_body_px": "one view off altogether: a detection or camera problem as often as a fit "
                      "error (the cross-view figures judge the fit)",
    "reproj_hands_px": "one view off altogether (hands): see reproj_body_px",
    "reproj_face_px": "one view off altogether (face): see reproj_body_px",
    "foot_skate_m_s": "feet really slide and pivot on the floor; a look, not a verdict",
}
#: The pair reasons (both people): the metric is of the two bodies together.
PAIR_REASONS = ("penetration_mm", "penetration_volume_cm3", "contact_gap_mm",
                "unexpected_contact_mm")
#: The fit-wrong reasons that do not withhold a person fitted to markers (the marker wearer) when
#: the other person is fitted from the video alone (stage export, option ``trust_markers``):
#: the cross-view reprojection (the wearer's fit does not use the videos: its keypoints off
#: in two views say the detections are wrong, an occlusion, not the fit; its marker reasons
#: judge its fit) and the pair reasons (one of the two bodies is wrong: the one no marker
#: holds). Measured on the realistic bench session (160 frames, studio truth): these reasons
#: withheld 35 wearer frames, none of them with a joint more than 10 cm off the truth (no
#: wearer frame there is); the partner frames they flagged stay withheld.
MARKER_FIT_SPARED = PAIR_REASONS + ("reproj_views_body_px", "reproj_views_hands_px",
                                    "reproj_views_face_px")
