"""Cameras, distortion, projection (numpy + CasADi), calibration files, triangulation, pycolmap.

```python
from calib import Camera, project
cam = Camera(name, f=(fx, fy), c=(cx, cy), k=(k1, k2, k3), p=(p1, p2), R=(3,3), T=(3,),
             width, height, model="h36m")       # X_cam = (X_world - T) @ R.T
uv = project(cam, X_world)                      # (..., 3) -> (..., 2) pixels
```
"""
from calib.camera import (
    DISTORTION_MODELS,
    Camera,
    cam_from_world,
    camera_vector,
    distort,
    look_at,
    normalized_from_pixels,
    project,
    project_cs,
    project_jacobian,
    rays_from_pixels,
    undistort,
    undistort_pixels,
    world_to_cam,
)

__all__ = [
    "DISTORTION_MODELS",
    "Camera",
    "cam_from_world",
    "camera_vector",
    "distort",
    "look_at",
    "normalized_from_pixels",
    "project",
    "project_cs",
    "project_jacobian",
    "rays_from_pixels",
    "undistort",
    "undistort_pixels",
    "world_to_cam",
]
