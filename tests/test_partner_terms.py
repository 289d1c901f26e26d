"""The partner fit's energy terms (``fitting/terms.py``: L_ic, L_sc, L_gp, L_D, L_N) and their
collision / contact geometry (``fitting/collision.py``).

Each term's CasADi Jacobian is checked against central differences of its numpy twin; small
Gauss-Newton loops (detection redone every iteration, as the partner fit will) check that each
term does its job: bodies pushed apart, an arm pushed out of the own belly, a mesh lifted onto
the floor, two facet patches pulled together with opposite normals.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import trimesh

from body import forward, rest_state
from body.regions import region_map
from body.rotations import rodrigues
from fitting import collision as C
from fitting import terms as T
from geometry import interpenetration, is_inside, nearest_surface

# ---------------------------------------------------------------------------- helpers


def _sx_like(a: np.ndarray, name: str):
    shape = a.shape if a.ndim == 2 else (a.shape[0], 1)
    return ca.SX.sym(name, *shape)


def _check_jacobian(f_np, f_cs, arrays, rtol=1e-6, atol=1e-8):
    """CasADi jacobian of f_cs(SX...) vs central differences of f_np(numpy...)."""
    syms = [_sx_like(a, f"x{i}") for i, a in enumerate(arrays)]
    expr = f_cs(*syms)
    xs = ca.vertcat(*[ca.vec(s) for s in syms])
    fun = ca.Function("f", [xs], [expr, ca.jacobian(expr, xs)])
    x0 = np.concatenate([a.reshape(-1, order="F") for a in arrays])

    def unpack(x):
        out, k = [], 0
        for a in arrays:
            out.append(x[k:k + a.size].reshape(a.shape, order="F"))
            k += a.size
        return out

    r_cs, J_cs = (np.asarray(v.full()) for v in fun(x0))
    r_np = np.asarray(f_np(*unpack(x0)))
    assert r_np.shape == (r_cs.shape[0],)
    np.testing.assert_allclose(r_cs[:, 0], r_np, rtol=1e-12, atol=1e-14)
    h = 1e-6
    J_fd = np.zeros((len(r_np), len(x0)))
    for i in range(len(x0)):
        e = np.zeros_like(x0)
        e[i] = h
        J_fd[:, i] = (np.asarray(f_np(*unpack(x0 + e))) - np.asarray(f_np(*unpack(x0 - e)))) / (2 * h)
    np.testing.assert_allclose(J_cs, J_fd, rtol=rtol, atol=atol)
    return J_cs


def _gauss_newton(x0, residual, iters=40, h=1e-6, damping=1e-9):
    """Minimise |residual(x)|^2 with forward-difference Jacobians; ``residual(x)`` redoes the
    detection at x and returns (r, frozen) where ``frozen(x)`` evaluates the same residual
    rows with the detection held fixed (as the symbolic graph does between detections)."""
    x = np.array(x0, float)
    for _ in range(iters):
        r, frozen = residual(x)
        if not len(r) or not np.any(r):
            break
        J = np.stack([(frozen(x + h * e) - r) / h for e in np.eye(len(x))], axis=1)
        H = J.T @ J
        x = x - np.linalg.solve(H + damping * np.eye(len(x)) * max(np.trace(H), 1.0), J.T @ r)
    return x


@pytest.fixture(scope="module")
def proxy(anny):
    return C.ProxyMesh.from_model(anny, 2000)


# ---------------------------------------------------------------------------- Jacobians


@pytest.mark.parametrize("term", [T.L_ic, T.L_sc, T.L_D])
def test_pull_terms_jacobian(term):
    rng = np.random.default_rng(1)
    p, t = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    w = rng.uniform(0.5, 1.5, 5)
    J = _check_jacobian(term, term, [p, t, w])
    # d r / d p is sqrt(w) I per point: the term pulls each point alone toward its target
    np.testing.assert_allclose(np.abs(J[:, :15]).sum(), 3 * np.sqrt(w).sum(), rtol=1e-9)


def test_L_gp_jacobian_and_hinge():
    rng = np.random.default_rng(2)
    normal = np.array([0.3, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    p = rng.normal(scale=0.1, size=(8, 3))
    d = p @ normal - 0.01
    p[np.abs(d) < 1e-3] += 0.01 * normal  # keep off the kink for the differences
    _check_jacobian(lambda q: T.L_gp(q, normal, 0.01), lambda q: T.L_gp(q, normal, 0.01), [p])
    r = T.L_gp(p, normal, 0.01)
    d = p @ normal - 0.01
    np.testing.assert_allclose(r[d < 0], d[d < 0])
    assert np.all(r[d >= 0] == 0)


def test_L_N_jacobian_and_value():
    rng = np.random.default_rng(3)
    tri1, tri2 = rng.normal(size=(4, 3, 3)), rng.normal(size=(4, 3, 3))
    w = rng.uniform(0.5, 1.5, 4)
    corners = [tri1[:, 0], tri1[:, 1], tri1[:, 2], tri2[:, 0], tri2[:, 1], tri2[:, 2], w]

    def f_np(a, b, c, a2, b2, c2, w):
        return T.L_N(np.stack([a, b, c], 1), np.stack([a2, b2, c2], 1), w)

    def f_cs(a, b, c, a2, b2, c2, w):
        return T.L_N((a, b, c), (a2, b2, c2), w)

    _check_jacobian(f_np, f_cs, corners)
    # the (P, 9) SX form gives the same expression
    s1, s2, sw = ca.SX.sym("a", 4, 9), ca.SX.sym("b", 4, 9), ca.SX.sym("w", 4, 1)
    f = ca.Function("f", [s1, s2, sw], [T.L_N(s1, s2, sw)])
    np.testing.assert_allclose(np.asarray(f(tri1.reshape(4, 9), tri2.reshape(4, 9), w).full())[:, 0],
                               T.L_N(tri1, tri2, w), rtol=1e-12)
    # phi_N = 1 + n1.n2: 0 for opposite normals, 2 for equal ones
    flipped = tri1[:, [0, 2, 1]]
    np.testing.assert_allclose(T.L_N(tri1, flipped, np.ones(4)), 0, atol=1e-12)
    np.testing.assert_allclose(T.L_N(tri1, tri1 + 1.0, np.ones(4)), 2, atol=1e-12)


def test_partner_terms_extend_terms():
    assert T.PARTNER_TERMS[:len(T.TERMS)] == T.TERMS
    assert set(T.PARTNER_TERMS) - set(T.TERMS) == {"L_sc", "L_ic", "L_gp", "L_D", "L_N"}
    assert all(callable(getattr(T, n)) for n in T.PARTNER_TERMS)


# ---------------------------------------------------------------------------- the proxy


def test_proxy_follows_the_skinned_mesh(anny, proxy):
    V0 = np.asarray(anny.v_template)
    F = np.asarray(anny.faces)
    assert 1500 <= proxy.num_vertices <= 2500
    # at rest the proxy vertices lie on the full surface, close to the decimated shape
    assert nearest_surface(proxy.points(V0), V0, F).distance.max() < 1e-9
    rng = np.random.default_rng(4)
    pose = np.zeros((1, anny.num_joints, 3))
    for name in ("upperarm01.L", "lowerarm01.R", "upperleg01.L", "spine03", "neck01"):
        pose[0, anny.joint_index(name)] = rng.normal(scale=0.4, size=3)
    out = forward(anny, np.zeros(0), pose, rodrigues(np.array([0.1, 0.2, 0.9]))[None],
                  np.array([[0.3, -0.1, 0.9]]))
    V = out.vertices[0]
    P = proxy.points(V)
    # the barycentric interpolation of the posed full mesh, written out; and still on its surface
    want = sum(proxy.bary[:, k, None] * V[proxy.corners[:, k]] for k in range(3))
    np.testing.assert_allclose(P, want, atol=1e-12)
    assert nearest_surface(P, V, F).distance.max() < 1e-9
    assert np.abs(P - proxy.points(V0)).max() > 0.1  # it did move with the pose
    # batched over frames
    np.testing.assert_allclose(proxy.points(np.stack([V0, V]))[1], P)
    # inside/outside of the proxy agrees with the full mesh near the body
    lo, hi = V.min(0) - 0.05, V.max(0) + 0.05
    Q = rng.uniform(lo, hi, size=(60000, 3))
    near = nearest_surface(Q, V, F).distance < 0.05
    Q = Q[near]
    agree = is_inside(Q, P, proxy.faces) == is_inside(Q, V, F)
    assert len(Q) > 3000 and agree.mean() > 0.99


# ---------------------------------------------------------------------------- L_ic


def _ic_residual(PA0, FA, PB, FB):
    """Both sums of L_ic for body A = points PA0 + x (x a translation) against body B."""

    def residual(x):
        PA = PA0 + x
        a_in_b, b_in_a = C.interpenetration(PA, PA, FA, PB, PB, FB)

        def frozen(y):
            QA = PA0 + y
            surf = (QA[FA[b_in_a.face]] * b_in_a.bary[..., None]).sum(1)  # slots on A
            return np.concatenate([
                T.L_ic(QA[a_in_b.index], a_in_b.target, np.ones(a_in_b.n)),
                T.L_ic(surf, b_in_a.target, np.ones(b_in_a.n))])

        return frozen(x), frozen

    return residual


def test_L_ic_pushes_two_bodies_apart(anny, proxy):
    """A ball (its own decimated proxy) pressed ~3 cm into Anny's belly is pushed out."""
    V0, F0 = np.asarray(anny.v_template), np.asarray(anny.faces)
    PB = proxy.points(V0)
    belly = (np.abs(V0[:, 0]) < 0.03) & (np.abs(V0[:, 2] - 0.15) < 0.03)
    ball = trimesh.creation.icosphere(4, radius=0.1)
    bp = C.ProxyMesh.from_mesh(ball.vertices, ball.faces, 300)
    centre = np.array([0.0, V0[belly, 1].min() - 0.1 + 0.03, 0.15])
    PA0 = bp.points(ball.vertices) + centre
    a_in_b, b_in_a = C.interpenetration(PA0, PA0, bp.faces, PB, PB, proxy.faces)
    assert 0.02 < a_in_b.deepest < 0.04 and b_in_a.n > 0
    x = _gauss_newton(np.zeros(3), _ic_residual(PA0, bp.faces, PB, proxy.faces))
    PA = PA0 + x
    a_in_b, b_in_a = C.interpenetration(PA, PA, bp.faces, PB, PB, proxy.faces)
    assert max(a_in_b.deepest, b_in_a.deepest) < 1e-3
    assert -0.04 < x[1] < -0.02 and abs(x[0]) < 0.005  # moved forward, out of the belly
    # the full meshes: what is left is the proxy's own approximation (~3 mm)
    assert interpenetration(ball.vertices + centre + x, V0, ball.faces, F0).depth < 0.005
    # starting apart nothing moves
    PA_far = PA0 + np.array([0.0, -0.05, 0.0])
    assert C.interpenetration(PA_far, PA_far, bp.faces, PB, PB, proxy.faces)[0].n == 0
    assert np.all(_gauss_newton(np.zeros(3), _ic_residual(PA_far, bp.faces, PB, proxy.faces)) == 0)


# ---------------------------------------------------------------------------- L_sc


def test_L_sc_pushes_the_forearm_out_of_the_belly(anny, proxy):
    rest = rest_state(anny, np.zeros(0))
    ids = [anny.joint_index("upperarm01.L"), anny.joint_index("lowerarm01.L")]

    def points(x):
        pose = np.zeros((1, anny.num_joints, 3))
        pose[0, ids] = x.reshape(2, 3)
        out = forward(anny, None, pose, np.eye(3)[None], np.zeros((1, 3)), rest=rest)
        return proxy.points(out.vertices[0])

    # the left arm folded across the front, the forearm ~3 cm deep in the belly
    x0 = np.array([0.0, 0.5, 0.0, 0.0, 0.0, -1.5])
    c = C.self_collisions(proxy, points(x0))
    rmap = region_map(anny)
    names = {rmap.names[r] for r in proxy.vertex_region[c.index]}
    assert c.deepest > 0.02 and "l_forearm_front" in names and names & {"l_abdomen", "r_abdomen"}
    # the rest pose has no self-collision (the elbow crease and armpits are neighbours)
    assert C.self_collisions(proxy, points(np.zeros(6))).n == 0

    def residual(x):
        col = C.self_collisions(proxy, points(x))
        Fp = proxy.faces

        def frozen(y):
            P = points(y)
            surf = (P[Fp[col.face]] * col.bary[..., None]).sum(1)  # the target moves with the body
            target = surf + (col.target - (points(x)[Fp[col.face]] * col.bary[..., None]).sum(1))
            return T.L_sc(P[col.index], target, np.ones(col.n))

        return frozen(x), frozen

    x = _gauss_newton(x0, residual, iters=30)
    assert C.self_collisions(proxy, points(x)).deepest < 1e-3
    assert np.linalg.norm(x - x0) < 1.0  # pushed out, not thrown away


# ---------------------------------------------------------------------------- L_gp


def test_L_gp_lifts_a_mesh_onto_the_floor(anny):
    V0 = np.asarray(anny.v_template)
    normal, offset = np.array([0.0, 0.0, 1.0]), 0.0
    below = V0 - np.array([0.0, 0.0, V0[:, 2].min() + 0.04])  # lowest vertex 4 cm below z = 0

    def residual_of(V):
        def residual(x):
            idx = C.ground_candidates(V + x, normal, offset, k=C.GROUND_K)

            def frozen(y):
                return T.L_gp((V + y)[idx], normal, offset)

            return frozen(x), frozen

        return residual

    x = _gauss_newton(np.zeros(3), residual_of(below))
    assert abs((below + x)[:, 2].min() - offset) < 1e-3
    assert abs(x[0]) < 1e-9 and abs(x[1]) < 1e-9  # lifted along the normal only
    above = below + np.array([0.0, 0.0, 0.06])  # 2 cm above the floor: untouched
    assert np.all(_gauss_newton(np.zeros(3), residual_of(above)) == 0)
    idx = C.ground_candidates(below, normal, offset, k=5)
    np.testing.assert_array_equal(np.sort(below[idx, 2]), np.sort(below[:, 2])[:5])


# ---------------------------------------------------------------------------- L_D, L_N


def _bumpy_patch(n=13, size=0.12):
    u = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(u, u)
    Z = 0.01 * np.sin(70 * X + 0.3) * np.cos(50 * Y) + 2.0 * X * X - 1.0 * X * Y
    V = np.stack([X, Y, Z], -1).reshape(-1, 3)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            F += [(a, b, d), (a, d, c)]
    return V, np.array(F)


def test_L_D_and_L_N_pull_annotated_facets_together():
    V1, F1 = _bumpy_patch()
    V2r, F2 = V1.copy(), F1[:, [0, 2, 1]]  # the touching surface: same shape, facing the other way
    sel = np.arange(len(F1))  # the annotated facets: the whole patch
    # a rigid transform away from contact: 3 cm off along the normal, turned 0.08 rad, shifted
    # in the plane by less than half a facet (identical grids have ICP fixed points a whole
    # facet apart, where all but the border facets match exactly)
    true = np.array([0.06, -0.05, 0.04, 0.003, -0.002, 0.03])

    def place(x):
        return V2r @ rodrigues(x[:3]).T + x[3:]

    def residual(x):
        V2 = place(x)
        f1, f2 = C.match_facets(V1, F1, C.psi_D(sel, "annotated", annotated=sel), V2, F2,
                                C.psi_D(sel, "annotated", annotated=sel))
        w = np.ones(len(f1)) / len(f1)

        def frozen(y):
            W = place(y)
            return np.concatenate([T.L_D(V1[F1[f1]].mean(1), W[F2[f2]].mean(1), w),
                                   0.01 * T.L_N(V1[F1[f1]], W[F2[f2]], w)])

        return frozen(x), frozen

    def figures(x):
        V2 = place(x)
        f1, f2 = C.match_facets(V1, F1, sel, V2, F2, sel)
        d = np.linalg.norm(V1[F1[f1]].mean(1) - V2[F2[f2]].mean(1), axis=1)
        n1, n2 = T.facet_normals(V1[F1[f1]]), T.facet_normals(V2[F2[f2]])
        return d.mean(), (n1 * n2).sum(1).mean()

    d0, dot0 = figures(true)
    assert d0 > 0.02 and dot0 > -0.999
    x = _gauss_newton(true, residual, iters=60)
    d, dot = figures(x)
    assert d < 1e-4 and dot < -0.99999


def test_psi_D_and_contact_pairs(anny):
    rmap = region_map(anny)
    V, F = np.asarray(anny.v_template), np.asarray(anny.faces)
    r = rmap.names.index("l_palm")
    faces = rmap.faces_of(r)
    assert np.array_equal(C.psi_D(faces, "all"), faces)
    u = C.psi_D(faces, "uniform", n=10, rng=np.random.default_rng(0))
    assert len(u) == 10 and len(np.unique(u)) == 10 and set(u) <= set(faces)
    with pytest.raises(ValueError, match="mode"):
        C.psi_D(faces, "some")
    with pytest.raises(ValueError, match="annotated"):
        C.psi_D(faces, "annotated")
    # a region matched against itself on the same mesh: every facet finds itself, both ways
    fp = C.contact_pairs(V, F, rmap, V, F, rmap, [(r, r)])
    assert fp.n == 2 * len(faces)
    np.testing.assert_array_equal(fp.face_1, fp.face_2)
    # two regions: matches stay inside the selected regions, first the one way then the other
    r2 = rmap.names.index("r_palm")
    fp = C.contact_pairs(V, F, rmap, V + np.array([0.0, -0.05, 0.0]), F, rmap, [(r, r2)],
                         mode="uniform", n=20, rng=np.random.default_rng(1))
    assert fp.n == 40 and set(rmap.face_region[fp.face_1]) == {r}
    assert set(rmap.face_region[fp.face_2]) == {r2} and np.all(fp.pair == 0)
