"""Magic numbers of the synthetic capture studio, in one place (metres, seconds, pixels)."""

# ------------------------------------------------------------------------------------ timing
#: Video frame rate (CHI3D: 50 fps) and marker capture rate (Vicon, may differ from video).
VIDEO_FPS = 50.0
MOCAP_HZ = 100.0
#: The C3D's first frame is at this video time (seconds): mocap starts a little before the
#: video and ends a little after it. Must be a multiple of 1 / MOCAP_HZ.
SYNC_OFFSET_S = -0.12
#: Extra mocap after the last video frame, seconds.
MOCAP_TAIL_S = 0.1

# ------------------------------------------------------------------------------------ cameras
#: CHI3D camera serials and image size.
CAMERA_NAMES = ("50591643", "58860488", "60457274", "65906101")
IMAGE_SIZE = (900, 900)
#: Camera placement around the capture volume: azimuths (deg, jittered), distance and height
#: ranges (metres) of the camera centres, focal length range (pixels), the point they look at.
CAMERA_AZIMUTHS_DEG = (40.0, 130.0, 220.0, 310.0)
CAMERA_AZIMUTH_JITTER_DEG = 8.0
CAMERA_DISTANCE_M = (3.9, 4.4)
CAMERA_HEIGHT_M = (1.5, 2.3)
CAMERA_LOOKAT_M = (0.0, 0.0, 0.95)
CAMERA_LOOKAT_JITTER_M = 0.12
CAMERA_FOCAL_PX = (1080.0, 1180.0)
CAMERA_PRINCIPAL_JITTER_PX = 8.0
#: Mild Human3.6M-model distortion: k1, k2, k3 ranges and |p| bound.
CAMERA_K_RANGE = ((-0.16, -0.06), (0.02, 0.12), (-0.02, 0.02))
CAMERA_P_ABS = 6e-4

# ------------------------------------------------------------------------------------ look
#: Skin and clothing colours (the renderer's background, floor and lights: drawing.constants).
SKIN_RGB = (224, 178, 148)
#: Clothing palettes per person: shirt, sleeves, trousers, shoes (RGB 0-255). Person 0 is
#: the first subject of the session (blue/grey), person 1 the second (red/olive).
CLOTHING = (
    {"shirt": (40, 90, 200), "sleeve": (70, 130, 230), "trousers": (35, 40, 60), "shoes": (20, 20, 20)},
    {"shirt": (210, 50, 40), "sleeve": (240, 110, 60), "trousers": (90, 110, 40), "shoes": (240, 240, 235)},
)

# ------------------------------------------------------------------------------------ scans
SCAN_POINTS = 60000
SCAN_NOISE_M = 0.002
SCAN_HOLE_RADIUS_M = 0.055
SCAN_SOLE_HEIGHT_M = 0.03
SCAN_DENSITY_CONTRAST = 6.0

# ------------------------------------------------------------------------------------ markers
#: Standard deviation of the marker noise per axis (metres): ~1 mm 3D RMS.
MARKER_NOISE_SD_M = 0.001 / 3 ** 0.5
#: Fraction of markers that get occlusion gaps, gaps per affected marker, run length (samples).
MARKER_GAP_FRACTION = 0.3
MARKER_GAPS_PER_MARKER = (1, 3)
MARKER_GAP_LEN = (5, 50)
#: Per-subject marker placement differs from the nominal set: tangential slide and offset
#: change (metres), standard deviations.
MARKER_SLIDE_SD_M = 0.004
MARKER_OFFSET_SD_M = 0.001

# ------------------------------------------------------------------------------------ subjects
#: Random anny body sliders per subject (count, |value| bound).
SUBJECT_SLIDERS = 12
SUBJECT_SLIDER_RANGE = 0.5

# ------------------------------------------------------------------------------------ motion
#: IK iterations per sample and synthesis passes (IK -> measure -> correct).
IK_ITERS = 10
SYNTH_PASSES = 4
#: At a contact the surfaces are pressed together by this much (metres): soft tissue.
CONTACT_PRESS_M = 0.0015
#: Interpenetration outside the contacts deeper than this is resolved by pushing apart,
#: plus a margin; the push is smoothed over this many master samples.
PENETRATION_TOL_M = 0.002
SEPARATION_MARGIN_M = 0.003
SEPARATION_SMOOTH = 6
#: Vertices this close to the other body's bounding box are checked for penetration.
NEAR_M = 0.05
#: Broad phase: the most flesh around any joint (metres); IK is re-solved where a correction
#: moved a target by more than REFINE_TOL_M.
FLESH_M = 0.16
REFINE_TOL_M = 0.0003
#: Vertices nearer than this to the other body get exact (libigl) signed distances.
EXACT_BAND_M = 0.008
EXACT_PATCH_K = 12
#: Limb interpenetration is undone by IK goals on at most this many points (distinct bones)
#: per contact and sample, with this weight.
REPEL_POINTS = 3
REPEL_WEIGHT = 0.7

# ------------------------------------------------------------------------------------ contact
#: Surfaces closer than this (metres) touch (contact interval); annotated facets have their
#: centroid this close to the other surface; 3-6 of them per signature.
TOUCH_M = 0.005
SIGNATURE_DIST_M = 0.006
SIGNATURE_PAIRS = (3, 6)
#: What a sequence's true motion must achieve (``studio.contact.MotionCheck.ok``): no true
#: interpenetration deeper than MAX_TRUE_PENETRATION_M in any video frame, and each contact
#: touching (gap < TOUCH_M) in at least MIN_TOUCHING of the frames where it is fully held.
#: A draw that misses is drawn again from the next random stream, up to MOTION_ATTEMPTS draws
#: (then the best one is kept and the session says so).
MAX_TRUE_PENETRATION_M = 0.005
MIN_TOUCHING = 0.75
MOTION_ATTEMPTS = 4

# ------------------------------------------------------------------------------------ placement
#: The pair is rotated by a random heading and shifted by up to this much (metres).
PAIR_SHIFT_M = 0.25
#: Scan: random heading, shift (metres) of the subject in the scanner's frame.
SCAN_SHIFT_M = 0.3
#: After the passes: where a limb is still deeper than PENETRATION_MAX_M inside the other
#: body, its repulsion goals are made stronger (doubled, up to REPEL_GAIN_MAX times their
#: weight), then its target is moved out by that depth; RETREAT_ROUNDS rounds in all.
PENETRATION_MAX_M = 0.003
RETREAT_ROUNDS = 6
REPEL_GAIN_MAX = 4.0
#: Over-relaxation of the gap corrections (the IK follows a moved target only partly).
REFINE_GAIN = 1.3
LIMB_NEAR_M = 0.03
#: Then, where a limb is still inside, the contact gives way: its weight is scaled by
#: GIVE_WAY_FACTOR there, up to GIVE_WAY_ROUNDS times.
GIVE_WAY_ROUNDS = 0
GIVE_WAY_FACTOR = 0.85
#: An interaction takes at least this long (seconds); shorter videos show its middle part.
MIN_SCENARIO_S = 2.4
#: IK solutions are smoothed over time with a Gaussian of this many master samples.
IK_SMOOTH_SAMPLES = 1.5
#: Vertices with no vertex of the other body this close (metres) are far from it (outside).
FAR_M = 0.08
#: Regions (name suffixes) whose touches a signature skips when there are others (not for kick).
INCIDENTAL_REGIONS = ("foot_top", "sole", "heel", "toes")
