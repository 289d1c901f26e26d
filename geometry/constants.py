"""Tolerances of the mesh geometry, in one place (metres)."""

#: A triangle whose edge cross product is shorter than this (twice its area, m^2) is
#: degenerate: its face normal is the zero vector.
DEGENERATE_CROSS = 1e-15
#: Vertex normals: sums of face normals shorter than this are left unnormalised (isolated
#: vertices get a zero normal).
VERTEX_NORMAL_EPS = 1e-12
#: A point is inside a closed (or nearly closed) mesh where its generalized winding number
#: exceeds this (1 inside, 0 outside; holes blur it smoothly).
INSIDE_WINDING = 0.5
