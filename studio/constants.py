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

# ------------------------------------------------------------------------------------ realistic markers
# What a real, uncleaned optical capture looks like (``studio.mocap.RealismOptions``; off for the
# demo and bench presets, on for the ``markers`` preset). Marker names are classed by their
# Plug-in Gait stem (the name without its L/R side letter); names not listed are "bony".
#: Placement by hand: tangential slide of each marker from the template, standard deviation
#: (metres) per class, and its cap. Della Croce, Cappozzo & Kerrigan 1999 (Med Biol Eng Comput
#: 37:155) measured the inter-examiner precision of palpated pelvis / lower-limb landmarks at
#: 13-25 mm RMS; markers placed by eye along a segment (thigh, shank, upper arm, forearm wands,
#: back, the head band) vary more. The cap keeps a marker within ~2 sd; a slide that would leave
#: the marker's segment (dominant skinning bone group) is halved until it does not.
MARKER_PLACE_SLIDE_SD_M = {"bony": 0.015, "head": 0.02, "fleshy": 0.025, "pelvis_thigh": 0.02}
MARKER_PLACE_SLIDE_MAX_M = 0.05
MARKER_PLACE_HALVINGS = 5
#: Class of each Plug-in Gait stem for placement and offsets.
MARKER_PLACE_CLASS = {
    "FHD": "head", "BHD": "head",
    "C7": "bony", "CLAV": "bony", "STRN": "bony", "SHO": "bony", "ELB": "bony", "WRA": "bony",
    "WRB": "bony", "FIN": "bony", "ASI": "bony", "KNE": "bony", "ANK": "bony", "HEE": "bony",
    "TOE": "bony",
    "T10": "fleshy", "BAK": "fleshy", "UPA": "fleshy", "FRM": "fleshy", "TIB": "fleshy",
    "PSI": "pelvis_thigh", "THI": "pelvis_thigh",
}  # fmt: skip
#: Marker centre to skin distance (metres), uniform range per class: a 14 mm marker's radius
#: (7 mm) plus its base (~2 mm, MoSh/MoSh++ use 9.5 mm for all) plus what lies between base and
#: skin: the head band, a suit, the soft tissue of the pelvis and thigh (MoSh++ (Mahmood et al.
#: 2019) learns per-marker offsets for this reason).
MARKER_PLACE_OFFSET_M = {"head": (0.008, 0.012), "bony": (0.008, 0.014), "fleshy": (0.010, 0.018),
                         "pelvis_thigh": (0.012, 0.025)}
#: Soft-tissue artefact (STA): peak displacement (metres) of the joint-angle term per stem, and
#: the joints (``{s}``: the marker's side) whose local rotations drive it. Leardini et al. 2005
#: (Gait & Posture 21:212, STA review): thigh markers move 10-30 mm relative to the femur, shank
#: markers 5-15 mm, largest near the hip/knee in flexion; Cutti et al. 2005 and Hamming et al.
#: 2012: upper-arm / acromion skin markers 10-20 mm with arm elevation. Stems not listed (head
#: band, ankles, heels, toes, ASIS, sternum, wrist bar) get no STA.
MARKER_STA_AMPLITUDE_M = {"THI": 0.015, "TIB": 0.008, "UPA": 0.012, "FRM": 0.006, "PSI": 0.006,
                          "SHO": 0.008, "KNE": 0.004, "ELB": 0.003, "T10": 0.003, "BAK": 0.005}
MARKER_STA_JOINTS = {
    "THI": ("upperleg01.{s}", "lowerleg01.{s}"), "TIB": ("lowerleg01.{s}", "foot.{s}"),
    "UPA": ("upperarm01.{s}", "lowerarm01.{s}"), "FRM": ("lowerarm01.{s}", "lowerarm02.{s}", "wrist.{s}"),
    "PSI": ("upperleg01.{s}", "spine05"), "SHO": ("upperarm01.{s}", "clavicle.{s}"),
    "KNE": ("lowerleg01.{s}",), "ELB": ("lowerarm01.{s}",), "T10": ("spine03", "spine02"),
    "BAK": ("upperarm01.{s}", "clavicle.{s}"),
}  # fmt: skip
#: Joint rotation (radians) at which the joint-angle term reaches ~76 % (tanh 1) of its peak,
#: and the share of the STA along the surface normal (skin slides more than it lifts).
MARKER_STA_ANGLE_REF_RAD = 1.0
MARKER_STA_NORMAL_SHARE = 0.3
#: Damped wobble after accelerations: a mass-spring-damper of the soft tissue driven by the
#: marker's acceleration (relative displacement x'' + 2 zeta w x' + w^2 x = -gain a). Wakeling &
#: Nigg 2001 (J Appl Physiol 90:412): thigh / calf soft-tissue vibration after heel strike at
#: 10-20 Hz (larger masses lower), damping ratio ~0.2-0.5, displacements of a few mm. gain =
#: STA amplitude x MARKER_WOBBLE_GAIN_PER_M: a thigh marker (15 mm) swings ~6 mm under a
#: 100 m/s^2 acceleration (a fast kick).
MARKER_WOBBLE_HZ = 12.0
MARKER_WOBBLE_DAMPING = 0.3
MARKER_WOBBLE_GAIN_PER_M = 22.0
#: Total STA cap (metres).
MARKER_STA_MAX_M = 0.03
#: Labelling faults of an uncleaned Vicon Nexus auto-labelled trial (no published rates; chosen
#: so a 5 s trial has one or two of each): label swaps of two markers closer than
#: SWAP_MAX_DIST_M for SWAP_LEN samples, ghosts (a label jumps to a reflection GHOST_DIST_M
#: away and stays there GHOST_LEN samples), 1-sample spikes of SPIKE_M. Rates per minute.
MARKER_SWAPS_PER_MIN = 15.0
MARKER_SWAP_LEN = (5, 20)
MARKER_SWAP_MAX_DIST_M = 0.15
MARKER_GHOSTS_PER_MIN = 15.0
MARKER_GHOST_LEN = (2, 8)
MARKER_GHOST_DIST_M = (0.1, 1.0)
MARKER_SPIKES_PER_MIN = 25.0
MARKER_SPIKE_M = (0.02, 0.08)
#: Occlusions of a real capture are longer than the demo's (samples at 120 Hz: up to ~0.8 s).
MARKER_REAL_GAP_LEN = (5, 100)
#: Unlabelled points (``*12``...) in the file: how many, and the share of samples they show.
MARKER_UNLABELLED = 3
MARKER_UNLABELLED_VISIBLE = 0.25
#: Analog channels at this multiple of the point rate (Vicon: 1000 Hz analog for 100 Hz
#: points), a 0.6 x 0.4 m force plate (AMTI-sized) with amplifier offsets (N) and noise (N),
#: EMG noise (V).
ANALOG_RATIO = 10
FORCE_PLATE_SIZE_M = (0.6, 0.4)
FORCE_OFFSET_N = 15.0
FORCE_NOISE_N = 2.0
EMG_NOISE_V = 2e-5
#: Body density (kg / m^3) for the force plate's body weight from the mesh volume.
BODY_DENSITY = 1010.0
#: First frame (0-based C3D frame of sample 0) of a capture that was trimmed in Nexus.
FIRST_FRAME_RANGE = (50, 4000)
#: Static calibration trial: seconds, arm abduction (radians from hanging), sway amplitude
#: (radians of tilt about the ankles, ~5 mm at the pelvis) and frequency range (Hz).
STATIC_S = 2.0
STATIC_ARM_ABDUCTION_RAD = (0.5, 0.8)
STATIC_SWAY_RAD = 0.005
STATIC_SWAY_HZ = (0.15, 0.5)
#: The marker-only preset: mocap rate (Hz), movement trial length range (s), the rate of the
#: (never rendered) timeline the motion synthesis checks contact on.
MARKERS_HZ = 120.0
MARKERS_TRIAL_S = (4.0, 6.0)
MARKERS_CHECK_FPS = 30.0
#: Mocap before the motion's first checked frame (s; a multiple of 1 / MARKERS_HZ).
MARKERS_LEAD_S = 0.1

# ------------------------------------------------------------------------------------ the lab
#: The realistic studio (studio.lab): the room (half size and height, metres; texture
#: resolution), its colours (RGB 0-255).
ROOM_HALF_M = 5.5
ROOM_HEIGHT_M = 3.3
FLOOR_TEXTURE_PX = 2048
WALL_TEXTURE_PPM = 180.0
FLOOR_TILE_M = 0.5
FLOOR_TILE_RGB = (168, 166, 160)
MAT_RGB = (30, 70, 170)
WALKWAY_RGB = (38, 38, 42)
WALL_RGB = (226, 222, 212)
SKIRTING_RGB = (110, 105, 100)
WINDOW_RGB = (185, 200, 215)
DOOR_RGB = (150, 120, 90)
CEILING_RGB = (215, 215, 212)
#: The second camera rig on tripods: azimuth offset from the midpoints between the main
#: cameras (rad) and distance from the centre (m).
TRIPOD_AZIMUTH_OFFSET_RAD = 0.35
TRIPOD_RADIUS_M = (4.1, 4.6)
#: The bystander (an operator): distance from the room's centre (m) of the candidate spots,
#: the least distance from any subject's root at any frame (m), the slow turn (rad).
BYSTANDER_RADIUS_M = (3.1, 3.7)
BYSTANDER_MIN_DIST_M = 2.2
BYSTANDER_TURN_RAD = 0.35
#: Skin tones and hair colours the people are drawn with (RGB).
SKIN_TONES = ((241, 200, 170), (224, 178, 148), (198, 145, 110), (160, 110, 80), (115, 78, 55),
              (80, 55, 40))
HAIR_RGB = ((30, 22, 18), (70, 45, 25), (120, 85, 50), (190, 160, 110), (110, 110, 110))
#: Per camera look: exposure gain, white-balance multipliers of red and blue, vignetting,
#: sensor noise sd (8-bit DN at mid grey), JPEG quality of the compression pass (H.264's
#: artefacts stand-in, upper bound exclusive), shutter (fraction of the frame interval).
LOOK_GAIN = (0.82, 1.12)
LOOK_WB = (0.92, 1.08)
LOOK_VIGNETTE = (0.12, 0.3)
LOOK_NOISE_SD = (1.5, 3.0)
LOOK_JPEG_QUALITY = (72, 86)
LOOK_SHUTTER = (0.3, 0.5)
#: Motion blur (studio.lab.motion_blur): the motion field's grid (px), the least motion that
#: is blurred (px), the spacing of the samples along the motion (px) and their most.
BLUR_CELL_PX = 6
BLUR_MIN_PX = 0.5
BLUR_STEP_PX = 1.5
BLUR_MAX_SAMPLES = 9
#: Every BLUR_VERTEX_STRIDE-th vertex of a body places the motion field.
BLUR_VERTEX_STRIDE = 2
#: Sensor noise: unit noise fields drawn once per session and read at random offsets.
NOISE_BANK = 3
NOISE_BANK_MARGIN_PX = 64
#: Calibration error (the recipe's calibration against the truth): the RMS reprojection
#: error (px) of points in CALIB_VOLUME_M (x, y, z ranges, metres), drawn per camera; the
#: shape of the error (sd of the centre (m), orientation (deg), focal (relative), principal
#: point (px)) before it is scaled to that RMS.
CALIB_ERROR_PX = (0.3, 0.5)
CALIB_VOLUME_M = ((-1.5, 1.5), (-1.5, 1.5), (0.0, 2.0))
CALIB_CENTRE_SD_M = 0.004
CALIB_ROT_SD_DEG = 0.003
CALIB_FOCAL_REL_SD = 0.0003
CALIB_PRINCIPAL_SD_PX = 0.1
#: The share of the centre error's image shift at the volume's centre that the orientation error
#: compensates (a calibration trades them; 1: the centre keeps its pixel exactly).
CALIB_COMPENSATION = 0.6
#: The realistic studio's video codecs, first available wins (H.264 where OpenCV has an
#: encoder for it).
REALISTIC_CODECS = ("avc1", "mp4v")
#: The realistic presets' camera out of sync: this fraction of a frame late (the last camera).
DESYNC_FRAMES = 0.3
#: Frames of the clean plate video (the empty room; noise differs between frames).
CLEAN_PLATE_FRAMES = 10
#: The bystander's clothing (the realistic studio's third person).
BYSTANDER_CLOTHING = {"shirt": (200, 200, 195), "sleeve": (60, 60, 65), "trousers": (45, 50, 70),
                      "shoes": (90, 60, 40)}

# Sequences of a session are made in parallel worker processes (one per core, at most one per
# sequence; MOCAP_STUDIO_WORKERS overrides, 1: in this process) when they have at least this
# many video frames: a worker's start (imports, the body model, the renderer) costs ~5 s, the
# bench preset's sequences (120 frames) 55-155 s each
PARALLEL_MIN_FRAMES = 50
# ... and a marker session's trials, when it has two motion trials or more with at least this
# many mocap samples in all (the markers preset: 2,636 samples, trials 15-43 s each)
PARALLEL_MIN_SAMPLES = 1000
