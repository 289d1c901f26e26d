"""Triangle-mesh geometry shared by the body models, the fits and the studio (numpy, scipy,
libigl, trimesh only; imports no project package).

- ``geometry.mesh``: :func:`face_normals` (the one face-normal function), :func:`face_areas`,
  :func:`face_centroids`, :func:`vertex_normals`, :class:`VertexNormals`.
- ``geometry.queries``: :func:`winding_number`, :func:`winding_number_exact`, :func:`is_inside`, :func:`nearest_surface`,
  :func:`points_inside`, :func:`penetration_depths`, :func:`inside_points`,
  :func:`deepest_inside`, :func:`interpenetration`, :func:`interpenetration_per_frame`,
  :func:`facet_distances`.
"""
from geometry.mesh import VertexNormals, face_areas, face_centroids, face_normals, vertex_normals
from geometry.queries import (
    Deepest,
    FacetDistances,
    Inside,
    Nearest,
    deepest_inside,
    facet_distances,
    inside_points,
    interpenetration,
    interpenetration_per_frame,
    is_inside,
    nearest_surface,
    penetration_depths,
    points_inside,
    winding_number,
    winding_number_exact,
)

__all__ = [
    "Deepest", "FacetDistances", "Inside", "Nearest", "VertexNormals", "deepest_inside",
    "face_areas", "face_centroids", "face_normals", "facet_distances", "inside_points",
    "interpenetration", "interpenetration_per_frame", "is_inside", "nearest_surface",
    "penetration_depths", "points_inside", "vertex_normals", "winding_number",
    "winding_number_exact",
]
