"""Constants of the CHI3D benchmark protocol (the public tools' ``util/eval_util.py``)."""
from __future__ import annotations

#: H36M 17 -> the public code's J17 order; its first 14 are the LSP joints, entry 14 the pelvis.
H36M_TO_J17 = (6, 5, 4, 1, 2, 3, 16, 15, 14, 11, 12, 13, 8, 10, 0, 7, 9)
NUM_LSP = 14
PELVIS_J17 = 14          # position of the H36M pelvis (joint 0) in H36M_TO_J17
PELVIS_H36M = 0          # the translation error is the distance of joint 0
MM_PER_M = 1000.0        # figures are reported in mm (the data are in metres)
IOU_EPS = 1e-12          # added to a union area (two empty boxes -> IoU 0, not NaN)
PROCRUSTES_EPS = 1e-12   # a prediction with (nearly) zero spread: scale 0 (maps to the truth's mean)

#: metric names, in the order of the table
JOINT_METRICS = ("mpjpe", "pa_mpjpe", "transl_err")
VERTEX_METRICS = ("mpvpe", "pa_mpvpe")
METRICS = JOINT_METRICS + VERTEX_METRICS

#: optional per-action files of a CHI3D-layout subject folder that the evaluator reads
VALID_DIR = "valid"          # valid/<action>.json: {"valid": (P, F) or (F,) bools}, truth only
VERTICES_DIR = "vertices"    # vertices/<action>.npz: vertices (P, F, V, 3), root (P, F, 3) metres
JOINTS_DIR = "joints3d_25"
SMPLX_DIR = "smplx"
ANNY_DIR = "anny"            # anny/<action>.json: Anny parameters (formats.anny_json)
CAMERAS_DIR = "camera_parameters"
CONTACT_FILE = "interaction_contact_signature.json"
DEFAULT_JSON = "evaluation.json"
