"""fitting.occlusion: keypoints another body hides from a camera (rays against its mesh)."""
from __future__ import annotations

import numpy as np


def _box(centre, size):
    import trimesh

    b = trimesh.creation.box(size)
    return np.asarray(b.vertices) + np.asarray(centre, float), np.asarray(b.faces)


def test_points_behind_a_body_are_hidden_and_points_before_or_beside_it_are_not():
    from calib import look_at
    from fitting.occlusion import hidden

    cam = look_at("c", [4.0, 0.0, 1.0], [0.0, 0.0, 1.0], (1000, 1000), (450, 450), 900, 900)
    V, F = _box([1.0, 0.0, 1.0], (0.3, 0.5, 1.0))  # a slab between the camera and the origin
    pts = np.array([[0.0, 0.0, 1.0],     # behind the slab: hidden
                    [0.0, 0.1, 1.3],     # behind it, off-centre: hidden
                    [2.0, 0.0, 1.0],     # between the camera and the slab: seen
                    [0.0, 1.5, 1.0],     # beside it: seen
                    [0.0, 0.0, 2.5],     # above its top edge (ray passes over it): seen
                    [1.14, 0.0, 1.0],    # 1 cm behind its surface facing the camera: seen
                    [np.nan, 0.0, 0.0]])  # unknown: never hidden
    got = hidden([cam], pts, V, F)[0]
    assert got.tolist() == [True, True, False, False, False, False, False]
    assert hidden([cam], pts[5:6], V, F, margin_m=0.0)[0, 0]  # without the margin it is


def test_ray_hits_agree_with_a_sphere_in_closed_form():
    import trimesh

    from fitting.occlusion import ray_hits

    m = trimesh.creation.icosphere(4, 0.3)
    rng = np.random.default_rng(0)
    O = np.array([3.0, 0.2, 0.1])
    P = rng.uniform(-0.8, 0.8, (400, 3))
    P = P[np.linalg.norm(P, axis=1) > 0.32]
    got = ray_hits(O, P, m.vertices, m.faces, margin_m=0.0, chunk=5000)  # several chunks
    D = P - O
    a, b, c = (D * D).sum(1), 2 * (D @ O), O @ O - 0.09
    disc = b * b - 4 * a * c
    t1 = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    want = (disc > 0) & (t1 > 0) & (t1 < 1)
    grazing = np.abs(disc) < 0.05 * a  # where the icosphere and the sphere may differ
    assert want.sum() >= 10
    assert np.all((got == want) | grazing)
