"""Tolerances and magic numbers of the calib package (one place, see ARCHITECTURE.md)."""

#: Newton iterations and stopping tolerance (normalized image units) for point undistortion.
UNDISTORT_MAX_ITERS = 30
UNDISTORT_TOL = 1e-14

#: Grid (per image side) of sample pixels used to fit one distortion model to another.
CONVERSION_GRID = 41

#: CHI3D frames are 900 x 900; the CHI3D camera JSON carries no image size.
CHI3D_IMAGE_SIZE = (900, 900)

#: Number of scalars in the packed camera vector (see calib.camera.camera_vector).
CAM_VECTOR_SIZE = 21
