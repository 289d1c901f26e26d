"""geometry/: face normals and areas against trimesh, winding-number inside/outside against
analytic spheres and boxes (also with a hole), nearest points against trimesh, penetration
depth of overlapping spheres against the analytic overlap, facet-set contact distances."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import geometry as G


def _sphere(subdivisions=3, radius=1.0, centre=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices) + np.asarray(centre, float), np.asarray(s.faces)


def _random_points(rng, n, lo, hi):
    return rng.uniform(lo, hi, (n, 3))


# ------------------------------------------------------------------------------ normals, areas
def test_face_normals_and_areas_match_trimesh():
    rng = np.random.default_rng(0)
    V, F = _sphere(2)
    V = V * [1.0, 0.6, 1.7] + rng.normal(0, 0.02, V.shape)  # an uneven ellipsoid
    tm = trimesh.Trimesh(V, F, process=False)
    np.testing.assert_allclose(G.face_normals(V, F), tm.face_normals, atol=1e-12)
    np.testing.assert_allclose(G.face_areas(V, F), tm.area_faces, rtol=1e-12)
    raw = G.face_normals(V, F, unit=False)
    np.testing.assert_allclose(np.linalg.norm(raw, axis=1), 2 * tm.area_faces, rtol=1e-12)
    np.testing.assert_allclose(G.face_centroids(V, F), tm.triangles_center, atol=1e-12)
    # outward: the normals of a convex-ish closed mesh point away from its centre
    assert (np.einsum("td,td->t", G.face_normals(V, F), G.face_centroids(V, F)) > 0).all()


def test_face_normals_batched_over_frames_and_degenerate_is_zero():
    rng = np.random.default_rng(1)
    V, F = _sphere(1)
    Vs = V[None] + rng.normal(0, 0.05, (4, len(V), 3))
    n = G.face_normals(Vs, F)
    assert n.shape == (4, len(F), 3)
    for f in range(4):
        np.testing.assert_allclose(n[f], trimesh.Trimesh(Vs[f], F, process=False).face_normals,
                                   atol=1e-12)
    assert G.face_areas(Vs, F).shape == (4, len(F))
    # a collapsed triangle (two equal corners, or three collinear ones) has no direction
    Vd = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0.0]])
    Fd = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    nd = G.face_normals(Vd, Fd)
    np.testing.assert_array_equal(nd[:2], 0.0)
    np.testing.assert_allclose(nd[2], [0, 0, 1])


def test_face_normals_reject_bad_shapes():
    with pytest.raises(ValueError, match=r"vertices: expected \(\.\.\., V, 3\), got \(5, 2\)"):
        G.face_normals(np.zeros((5, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match=r"faces: expected \(T, 3\) int"):
        G.face_normals(np.zeros((5, 3)), np.array([[0.0, 1, 2]]))


def test_vertex_normals_of_a_sphere_are_radial():
    V, F = _sphere(3, radius=0.4, centre=(1.0, -2.0, 0.5))
    n = G.vertex_normals(V, F)
    radial = (V - [1.0, -2.0, 0.5]) / 0.4
    assert np.degrees(np.arccos(np.clip(np.einsum("vd,vd->v", n, radial), -1, 1))).max() < 1.0
    np.testing.assert_array_equal(G.VertexNormals(F, len(V))(V), n)
    # an unused vertex has no faces, hence no normal
    n2 = G.vertex_normals(np.vstack([V, [[9.0, 9, 9]]]), F)
    np.testing.assert_array_equal(n2[-1], 0.0)


# ------------------------------------------------------------------------------ inside / outside
def test_winding_number_inside_a_sphere_and_a_box():
    rng = np.random.default_rng(2)
    V, F = _sphere(3, radius=1.0, centre=(0.5, 0.0, 1.0))
    p = _random_points(rng, 3000, -1.0, 2.0)
    r = np.linalg.norm(p - [0.5, 0.0, 1.0], axis=1)
    clear = np.abs(r - 1.0) > 0.02  # the mesh's chords sag < 1.2 cm inside the true sphere
    assert clear.sum() > 2500 and (r < 1).sum() > 300
    np.testing.assert_array_equal(G.is_inside(p[clear], V, F), r[clear] < 1.0)
    w = G.winding_number(p[clear], V, F)
    np.testing.assert_allclose(w, (r[clear] < 1.0).astype(float), atol=0.02)

    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    q = _random_points(rng, 2000, -1.2, 1.2)
    truth = np.all(np.abs(q) < [1.0, 0.5, 0.25], axis=1)
    margin = np.min(np.abs(np.abs(q) - [1.0, 0.5, 0.25]), axis=1) > 1e-3
    assert truth[margin].sum() > 100
    np.testing.assert_array_equal(G.is_inside(q[margin], box.vertices, box.faces), truth[margin])


def test_exact_winding_number_agrees_with_libigl_and_adds_over_faces():
    """The numpy solid-angle sum equals libigl's winding number on a closed mesh and on an
    open part of it, and the parts' numbers add up to the whole's."""
    rng = np.random.default_rng(4)
    V, F = _sphere(3, radius=0.8, centre=(0.2, 0.1, 0.0))
    p = _random_points(rng, 300, -1.2, 1.2)
    w = G.winding_number_exact(p, V, F, chunk=5000)  # several chunks
    import igl

    np.testing.assert_allclose(w, igl.winding_number(V, F, p), atol=1e-9)
    half = G.face_centroids(V, F)[:, 0] > 0.2
    w1, w2 = G.winding_number_exact(p, V, F[half]), G.winding_number_exact(p, V, F[~half])
    np.testing.assert_allclose(w1 + w2, w, atol=1e-9)
    assert np.abs(w1).max() > 0.3  # an open part has non-integer numbers


def test_winding_number_tolerates_a_hole():
    """A sphere with a cap cut off (the faces within 35 degrees of +z): points well inside are
    still inside, points outside still outside, away from the hole."""
    rng = np.random.default_rng(3)
    V, F = _sphere(3)
    cen = G.face_centroids(V, F)
    keep = cen[:, 2] / np.linalg.norm(cen, axis=1) < np.cos(np.radians(35))
    Fh = F[keep]
    assert len(Fh) < len(F) - 50
    assert len(trimesh.Trimesh(V, Fh).outline().entities) >= 1  # really open
    d = rng.normal(size=(600, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.0, 2.0, 600)
    p = d * r[:, None]
    away = (d[:, 2] < np.cos(np.radians(60))) & (np.abs(r - 1) > 0.1)
    np.testing.assert_array_equal(G.is_inside(p[away], V, Fh), r[away] < 1.0)
    # the centre sees most of the sphere: still clearly inside
    assert 0.8 < G.winding_number(np.zeros((1, 3)), V, Fh)[0] < 0.99


# ------------------------------------------------------------------------------ nearest surface
def test_nearest_surface_matches_trimesh_closest_point():
    rng = np.random.default_rng(4)
    V, F = _sphere(2)
    V = V * [1.0, 0.5, 0.8]
    tm = trimesh.Trimesh(V, F, process=False)
    p = rng.normal(0, 1.0, (25, 3))
    near = G.nearest_surface(p, V, F)
    # trimesh's closest point on every triangle, brute force (its proximity query needs rtree)
    tris = tm.triangles
    cand = np.stack([trimesh.triangles.closest_point(tris, np.repeat(q[None], len(tris), 0))
                     for q in p])  # (N, T, 3)
    d_all = np.linalg.norm(cand - p[:, None], axis=2)
    tri = np.argmin(d_all, axis=1)
    cp, dist = cand[np.arange(len(p)), tri], d_all.min(axis=1)
    np.testing.assert_allclose(near.distance, dist, atol=1e-9)
    np.testing.assert_allclose(near.point, cp, atol=1e-9)
    # the face holds the closest point (or ties with trimesh's, on a shared edge or vertex)
    assert (near.face == tri).any()
    np.testing.assert_allclose(d_all[np.arange(len(p)), near.face], dist, atol=1e-9)
    with pytest.raises(ValueError, match=r"points: expected \(N, 3\), got \(4, 2\)"):
        G.nearest_surface(np.zeros((4, 2)), V, F)
    with pytest.raises(ValueError, match="faces: vertex index outside"):
        G.nearest_surface(p, V[:10], F)


# ------------------------------------------------------------------------------ penetration
@pytest.mark.parametrize("d", [1.5, 1.8])
def test_penetration_of_two_overlapping_spheres(d):
    """Unit icospheres with centres d apart along one of their vertex directions: the deepest
    point is 2 - d inside, each vertex's depth is 1 - its distance to the other centre."""
    V, F = _sphere(4)
    u = V[17] / np.linalg.norm(V[17])
    V0, V1 = V, V + d * u
    tol = 2e-3  # the polyhedron's faces sit up to ~1 mm inside the unit sphere
    deep = G.interpenetration(V0, V1, F)
    assert deep.depth == pytest.approx(2 - d, abs=tol)
    X = (V0, V1)[deep.body][deep.vertex]
    other_centre = (d * u, np.zeros(3))[deep.body]
    assert np.linalg.norm(X - other_centre) == pytest.approx(d - 1, abs=1e-9)
    inside = G.inside_points(V0, V1, F)
    for a, (ins, depth, face) in enumerate(inside):
        c_other = (d * u, np.zeros(3))[a]
        r = np.linalg.norm((V0, V1)[a] - c_other, axis=1)
        clear = np.abs(r - 1) > 3e-3
        truth = np.flatnonzero((r < 1) & clear)
        assert np.isin(truth, ins).all() and len(truth) > 10
        assert not np.isin(np.flatnonzero((r > 1) & clear), ins).any()
        np.testing.assert_allclose(depth, 1 - r[ins], atol=tol)
        assert (face >= 0).all() and (face < len(F)).all()
    dense = G.penetration_depths(V0, V1, F)
    np.testing.assert_array_equal(dense[inside[0].index], inside[0].depth)
    assert (np.delete(dense, inside[0].index) == 0).all()


def test_penetration_apart_and_across_topologies():
    V, F = _sphere(2)
    assert G.interpenetration(V, V + [3.0, 0, 0], F) == G.Deepest(0.0, -1, -1)
    # a unit box (other faces) spanning x = 0.5 .. 1.5 pushed into a unit sphere turned so
    # that one of its vertices is the pole (1, 0, 0)
    S, Fs = _sphere(4)
    T = trimesh.geometry.align_vectors(S[17], [1.0, 0, 0])
    S = S @ T[:3, :3].T
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    B, Fb = np.asarray(box.vertices) + [1.0, 0, 0], np.asarray(box.faces)
    # the pole is 0.5 from every side of the box it is in: the deepest point
    deep = G.interpenetration(S, B, Fs, Fb)
    assert deep.body == 0 and deep.vertex == 17 and deep.depth == pytest.approx(0.5, abs=1e-9)
    # the box's four inner corners are inside the sphere, sqrt(0.75) from its centre
    ins_box = G.inside_points(S, B, Fs, Fb)[1]
    assert sorted(ins_box.index.tolist()) == sorted(np.flatnonzero(B[:, 0] < 1).tolist())
    np.testing.assert_allclose(ins_box.depth, 1 - np.sqrt(0.75), atol=2e-3)
    per = G.interpenetration_per_frame(np.stack([V, V]),
                                       np.stack([V + [3.0, 0, 0], V + [1.5, 0, 0]]), F)
    assert per[0] == 0 and per[1] == pytest.approx(0.5, abs=0.02)


def test_broad_phase_spares_only_meshes_that_cannot_hold_each_other(monkeypatch):
    """geometry.apart: two closed spheres farther apart than their edges are spared the
    winding numbers; spheres a hair apart, crossing, nested (a small one inside a big one, no
    crossing) or open (a hole) are not, and inside_points gives what the exact test gives."""
    from geometry import queries as Q

    V, F = _sphere(3)
    edge = Q.max_edge(V, F)
    assert Q.is_closed(F) and not Q.is_closed(F[1:])
    assert Q.apart(V, F, V + [2.0 + 2.5 * edge, 0, 0], F)  # gap wider than two edges
    assert not Q.apart(V, F, V + [2.0 + 0.5 * edge, 0, 0], F)  # vertices within reach
    assert not Q.apart(V, F, V + [1.5, 0, 0], F)  # crossing
    assert not Q.apart(V, F[1:], V + [3.0, 0, 0], F)  # open: winding numbers can lie
    small = 0.2 * V + [0.1, 0, 0]  # nested: no vertex near the big sphere's
    assert not Q.apart(V, F, small, F)
    ins = G.inside_points(V, small, F)
    assert len(ins[1].index) == len(small)  # every vertex of the small sphere is inside
    # the spared case gives what the winding numbers give: nothing inside
    far = V + [2.0 + 2.5 * edge, 0, 0]
    spared = G.inside_points(V, far, F)
    monkeypatch.setattr(Q, "apart", lambda *a: False)
    exact = G.inside_points(V, far, F)
    for a, b in zip(spared, exact, strict=True):
        assert len(a.index) == len(b.index) == 0


# ------------------------------------------------------------------------------ facet distances
def test_facet_distances_between_two_squares():
    """Unit squares at z = 0 (A) and z = h shifted by 2 in x (B): from each A facet centroid
    (cx, cy) the nearest point of B is on its edge x = 2, sqrt((2 - cx)^2 + h^2) away, and the
    other way from x = 1."""
    h = 0.3
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
    Fs = np.array([[0, 1, 2], [0, 2, 3]])
    A, B = sq, sq + [2.0, 0, h]
    fd = G.facet_distances(A, Fs, [0, 1], B, Fs, [0, 1])
    ca, cb = G.face_centroids(A, Fs), G.face_centroids(B, Fs)
    np.testing.assert_allclose(fd.a_to_b, np.hypot(2 - ca[:, 0], h), atol=1e-12)
    np.testing.assert_allclose(fd.b_to_a, np.hypot(cb[:, 0] - 1, h), atol=1e-12)
    assert fd.total() == pytest.approx(fd.a_to_b.sum() + fd.b_to_a.sum())
    # on top of each other, B's facet 1 only (the half over y > x): A's facet 1 is right
    # under it, A's facet 0 (centroid (2/3, 1/3)) reaches it at the diagonal, sqrt(2)/6 away
    fd2 = G.facet_distances(A, Fs, [0, 1], sq + [0, 0, h], Fs, [1])
    np.testing.assert_allclose(fd2.a_to_b, [np.hypot(h, np.sqrt(2) / 6), h], atol=1e-12)
    assert (fd2.a_nearest == 1).all()
    np.testing.assert_allclose(fd2.b_to_a, h, atol=1e-12)
    assert fd2.b_nearest.tolist() == [1]
    with pytest.raises(ValueError, match="must not be empty"):
        G.facet_distances(A, Fs, [], B, Fs, [0])


def test_geometry_imports_no_project_package():
    from tests.conftest import REPO
    from tests.test_layering import imported_modules

    project = {"stages", "body", "calib", "formats", "fitting", "studio", "recipes", "detect",
               "bench", "pipeline", "drawing", "artifacts"}
    files = sorted((REPO / "geometry").glob("*.py"))
    assert len(files) >= 3
    assert {f.name: sorted(imported_modules(f) & project) for f in files
            if imported_modules(f) & project} == {}
