"""Tolerances and magic numbers of the detect package (one place, see ARCHITECTURE.md)."""

#: Keypoints per person in the canonical KP65 layout (body 23, left hand 21, right hand 21).
N_KP = 65

#: Margin added on every side of the marker wearer's projected-marker box, as a fraction of
#: the box's larger side (markers sit on the skin; fingers, hair and shoes stick out).
BODY_MARGIN = 0.15

#: Hand crop: radius (metres) of the sphere around the hand centre whose projection sets the
#: hand box half-size. An adult hand is ~0.19 m long wrist to fingertip; the palm detector
#: wants context around it: on studio renders (wearer's hands, 56 crops) radius 0.10 / 0.14 /
#: 0.20 / 0.26 m found 32 / 42 / 43 / 46 hands at median errors 4.1 / 3.2 / 2.9 / 3.3 px and
#: p90 11.6 / 11.4 / 9.8 / 32.7 px (the largest crops start picking up the wrong hand).
HAND_RADIUS_M = 0.2

#: Hand centre = wrist + HAND_CENTRE_ALONG * (knuckles - wrist): the FIN marker (and the pose
#: detector's index/pinky points) sit on the knuckles, ~0.08 m from the wrist; the middle of
#: the hand with its fingers is ~0.1 m from the wrist.
HAND_CENTRE_ALONG = 1.2

#: Hand crop from 2D body keypoints (no markers): the hand centre is HAND_ALONG_FOREARM x
#: the elbow-to-wrist vector past the wrist (forearm ~0.26 m, hand centre ~0.09 m past the
#: wrist); half-side HAND_BOX_FROM_FOREARM x the forearm (~0.18 m / 0.26 m), at least
#: HAND_BOX_FROM_HEIGHT x the person's keypoint box height (~0.16 m / 1.6 m), and at least
#: MIN_HAND_BOX_PX / 2. Generous: the palm detector needs context around the hand.
HAND_ALONG_FOREARM = 0.35
HAND_BOX_FROM_FOREARM = 0.7
HAND_BOX_FROM_HEIGHT = 0.1
MIN_HAND_BOX_PX = 32.0

#: Smallest body crop side (pixels); below it the detector sees too few pixels anyway.
MIN_BODY_BOX_PX = 48.0

#: The paper's rule: a partner candidate keypoint is "close" to the marker wearer's keypoint
#: of the same type when nearer than NEAR_FRAC x the wearer's box height (pixels).
NEAR_FRAC = 0.04

#: A whole candidate is taken to be the marker wearer re-detected when at least this fraction
#: of its confident keypoints are "close" (above) to the wearer's keypoints of the same type.
SAME_PERSON_FRAC = 0.5

#: The partner rule's coherence guard: keypoints from a secondary candidate must lie within the
#: primary candidate's keypoint box grown by this fraction of its larger side.
COHERENT_MARGIN = 0.25

#: Keypoints with a confidence below this are treated as missing by the selection rules.
MIN_CONF = 0.1

#: Silhouette mask of the marker wearer, as fractions of the wearer's crop-box height (~1.3 x
#: the person's height): capsule radius along its bones and disc radius at its markers and
#: keypoints (~6 cm, a limb's radius), and the head disc around the face keypoints (~12 cm).
MASK_RADIUS_FRAC = 0.027
MASK_HEAD_FRAC = 0.055

#: The isolated wearer crop keeps discs of this radius (fraction of the crop-box height, ~28 cm)
#: around the wearer's markers and paints everything else.
ISOLATE_RADIUS_FRAC = 0.125

#: A partner candidate found in the painted image is dropped when more than this fraction of
#: its confident body keypoints lie on painted pixels (a person hallucinated from leftovers).
HALLUCINATED_FRAC = 0.5

#: Partner search: margin around the previous frame's partner box (fraction of its larger side).
TRACK_MARGIN = 0.25

#: A hand candidate is accepted when its wrist lies within HAND_ANCHOR_FRAC x the hand box side
#: of the expected wrist (projected wrist markers or pose wrist).
HAND_ANCHOR_FRAC = 0.6

#: The person found in the wearer's crop is accepted as the wearer when its keypoints lie
#: within ANCHOR_FRAC x the wearer's box height (median) of where the markers put them ...
ANCHOR_FRAC = 0.1

#: ... and its size (keypoint spread) within this factor of the anchors' spread; position and
#: size are judged together (an ellipse with these two semi-axes, detect.people.wearer_check).
#: On the studio bench (wearer crops, every 15th frame) correct detections measured anchor
#: errors 0.021-0.065 x box height (10-90 %) and sizes 0.93-1.06 (5-95 %), extremes 0.88 /
#: 1.14; the partner lined up in front of the wearer: 0.094-0.12 and 1.16-1.27.
WEARER_SCALE_TOL = 1.18

#: ... and is rejected as mirrored when its left/right-swapped keypoints lie nearer the anchors
#: by more than FLIP_MARGIN_FRAC x the box height (profile views, where left and right
#: overlap in the image, stay within the margin).
FLIP_MARGIN_FRAC = 0.02

#: The partner counts as found when at least MIN_PARTNER_KP body keypoints have a confidence
#: of at least ACCEPT_CONF; otherwise the tracked search falls back to the whole image.
MIN_PARTNER_KP = 8
ACCEPT_CONF = 0.5

#: ... and when those keypoints span at least this fraction of the wearer's crop-box height
#: (a standing adult's keypoints span ~0.65 of it; a skeleton crumpled onto the visible bits
#: of an occluded partner spans far less).
MIN_PARTNER_SPAN_FRAC = 0.3

#: Cross-view check (detect/multiview.py): RANSAC inlier threshold, pixels. Detector noise on
#: studio renders is ~5 px median, ~20 px p90; a mixed or mirrored skeleton misses by 40+.
CROSS_VIEW_PX = 25.0

#: A person keeps its keypoints in a view unless fewer than MIN_KEPT_FRAC of its confident
#: body keypoints there survive the cross-view check and the partner/wearer guard AND at most
#: MAX_LEFTOVER_KP are left (detect.sequence.mostly_dropped): then the detection mixed both
#: people and the leftovers are as likely the other's. On the bench session (every 10th frame)
#: 0.5 alone removed 4 of the 7 swapped views at a cost of 0.3 / 2 points of the wearer's /
#: partner's body detection rate (0.8: 6 of 7, 7 / 5 points); with at most 8 (or 7) leftovers
#: the same 4 went at 0.4 / 0.7 points; at most 6 removed only 2 of them.
MIN_KEPT_FRAC = 0.5
MAX_LEFTOVER_KP = 8

#: ... and only when the leftovers look like the other person's (detect.sequence.
#: leftovers_look_swapped), as fractions of the wearer's crop-box height: the wearer's lie
#: (median) farther than LEFTOVER_OFF_ANCHOR_FRAC from its marker anchors (a correct wearer
#: lies 0.027 from them, median), the partner's nearer than LEFTOVER_ON_WEARER_FRAC to one of
#: the wearer's markers. On the bench session the mostly-dropped partners whose leftovers were
#: its own lay 0.058-0.11 from the wearer's markers, those that were the wearer's 0.019-0.044.
LEFTOVER_OFF_ANCHOR_FRAC = 0.03
LEFTOVER_ON_WEARER_FRAC = 0.05

#: A hand crop is run only when its expected wrist lies in the image and at least this
#: fraction of the crop's area does (detect.people.hand_crop_useful): a hand mostly out of the
#: picture is not found anyway, and each hand call costs as much as ~0.6 pose calls.
MIN_HAND_BOX_INSIDE = 0.5

#: The head centre needs at least this many of the four head markers seen (their mean is then
#: within ~8 cm of the centre, the markers sitting ~10 cm from it; on the bench session one
#: head marker is unseen in up to 40 % of a sequence's frames).
MIN_HEAD_MARKERS = 2

#: The partner's face keypoints, triangulated over the views, must lie farther than this
#: (metres) from the wearer's head centre (mean of its head markers): a nearer "partner"
#: nose or ear is the wearer's (detect.sequence.cross_view_guard; in 2D the partner's face in
#: front of the wearer's head lies as near as the wearer's own). On the bench truth the
#: wearer's own face keypoints lie 0.11 m (median) and up to 0.177 m from that centre, the
#: partner's at least 0.29 m (Hug; 0.55 m and more elsewhere); cheek to cheek they could come
#: within ~0.15 m, and are then dropped too. 0.1 m (a skull's radius) caught only part of the
#: wearer's face taken for the partner's (a swapped view at stride 1, Hug frame 30).
PARTNER_FACE_HEAD_M = 0.18

#: A partner detection whose feet, back-projected onto the floor, stand farther than this
#: (metres, along the floor) from the wearer's markers' centre is somebody else (an operator,
#: a bystander): close interaction keeps the partner within reach. On the bench truth every
#: partner joint stays within 1.04 m of the wearer's root (HoldingHands; 0.65-0.94 m in the
#: other classes) and the bystander at least 2.22 m away (detect.sequence.standing_far). On
#: session 21's bench keypoints (the detector's raw partner slots, 8 sequences, stride 6) every
#: reach from 1.0 to 2.5 m caught all 79 views whose partner slot held somebody else; the
#: partner's own detections flagged: 17 views at 1.0 m, 5 at 1.5, 4 at 2.0, 3 at 2.5 (the
#: feet of poor detections, two of them 83-97 px off), and 3.0 m caught only 47 of the 79.
PARTNER_REACH_M = 2.0
#: The height above the floor (m) of the ankle and heel keypoints those feet are read from.
FOOT_HEIGHT_M = 0.07

#: Identity check (detect/identity.py): each view's detection of a person judged as a whole
#: skeleton (medians over its body keypoints, pixels). A pair of views is consistent on the
#: keypoints its triangulation reprojects into both within IDENTITY_PAIR_PX, at least
#: IDENTITY_MIN_KP of them and IDENTITY_PAIR_FRAC of those both observe (a detection can be
#: half wrong: the legs of a partner hidden in a hug); another view supports it within
#: IDENTITY_VIEW_PX (the cross-view check's threshold). Without a consistent pair in the
#: frame, a view is judged against the skeleton of the frames within
#: IDENTITY_WINDOW_FRAMES video frames either side (25 = 0.5 s at 50 fps) at
#: IDENTITY_TIME_PX (the person moved meanwhile). Rays meeting at less than
#: IDENTITY_MIN_ANGLE_DEG are not triangulated: the bench rig's opposite cameras meet at
#: 25-31 degrees and, paired, "confirmed" the partner's made-up skeleton in hugs (its
#: neighbours meet at 82-88). A detection whose distance to the other person's reference is
#: under IDENTITY_AMBIGUOUS_RATIO x that to its own is a swap: 1.25 left the profile view of
#: HoldingHands frame 80 (a wearer halfway to the partner, 26 / 30 px) and 2.0 dropped 6
#: wearer views for none more; mirrored when, mirrored, it fits under IDENTITY_FLIP_RATIO x
#: as labelled (the bench metric's rule) and by IDENTITY_FLIP_MIN_PX.
IDENTITY_PAIR_PX = 15.0
IDENTITY_PAIR_FRAC = 0.5
IDENTITY_VIEW_PX = 25.0
IDENTITY_TIME_PX = 50.0
IDENTITY_WINDOW_FRAMES = 25
IDENTITY_MIN_ANGLE_DEG = 45.0
IDENTITY_AMBIGUOUS_RATIO = 1.5
IDENTITY_FLIP_RATIO = 0.5
IDENTITY_FLIP_MIN_PX = 5.0
IDENTITY_MIN_KP = 4

#: The partner's second pass (detect.refine): a body keypoint of the person found in the crop
#: that lies farther than REFINE_WEARER_MIN_PX from the first fit's projection and nearer the
#: wearer's detected keypoint of the same name (either side) than REFINE_WEARER_RATIO x that
#: distance is the wearer's joint read as the partner's, and dropped. Bench, Posing (session
#: 23): the crops of the two views that had lost the partner put its left elbow on the
#: wearer's elbow (1-8 px from the wearer's detection, 80-110 px from the truth, confidence
#: 0.4-0.9) and the fit followed them along the depth the two other, opposite, views leave
#: free (0.25-0.4 m); dropping them took Posing from 48.6 to 32.1 mm and left the other
#: classes within 0.2 mm (87 keypoints dropped over the 8 sequences).
REFINE_WEARER_MIN_PX = 15.0
REFINE_WEARER_RATIO = 0.5
