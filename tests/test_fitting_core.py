"""The fitting core on a toy kinematic chain: compiled function cache, LM, robust loss, terms.

The chain is planar (angles, no rotation vectors) so it needs nothing from body/; the body
model's marker fit is tested in tests/test_marker_fit*.py.
"""
from __future__ import annotations

import os

import casadi as ca
import numpy as np
import pytest

from fitting import compiled, lm, robust, terms

N_LINK = 6
N_MARK = 18


def chain_markers(x, lengths, a, o, z):
    """x = [bx, by, theta (N)]; markers on links at fraction a, perpendicular offset o."""
    cs = isinstance(x, ca.SX)
    cos, sin = (ca.cos, ca.sin) if cs else (np.cos, np.sin)
    px, py, phi = x[0], x[1], 0
    joints = []
    for i in range(N_LINK):
        phi = phi + x[2 + i]
        joints.append((px, py, phi))
        px = px + lengths[i] * cos(phi)
        py = py + lengths[i] * sin(phi)
    rows = []
    for k in range(N_MARK):
        jx, jy, ph = joints[k % N_LINK]
        L = lengths[k % N_LINK]
        mx = jx + a[k] * L * cos(ph) - o[k] * sin(ph)
        my = jy + a[k] * L * sin(ph) + o[k] * cos(ph)
        rows.append([mx, my, z[k]])
    if cs:
        return ca.vertcat(*[ca.horzcat(*r) for r in rows])
    return np.array([[float(v) for v in r] for r in rows])


def chain_params():
    rng = np.random.default_rng(0)
    lengths = rng.uniform(0.2, 0.4, N_LINK)
    a = rng.uniform(0.2, 0.9, N_MARK)
    o = rng.uniform(-0.05, 0.05, N_MARK)
    z = rng.uniform(-0.05, 0.05, N_MARK)
    return lengths, a, o, z


def build_chain(mode="interpreted", cache=None, name="toy_chain"):
    """Residual function r = L_3d(markers(x), obs, vis); p = [obs (3K), vis (K)]."""
    lengths, a, o, z = chain_params()
    x = ca.SX.sym("x", 2 + N_LINK)
    p = ca.SX.sym("p", 4 * N_MARK)
    obs = ca.reshape(p[: 3 * N_MARK], 3, N_MARK).T
    vis = p[3 * N_MARK:]
    r = terms.L_3d(chain_markers(x, lengths, a, o, z), obs, vis)
    opts = compiled.CompileOptions(mode=mode, cache_dir=cache)
    return compiled.build(name, x, p, r, opts)


def make_p(obs, vis):
    o = np.where(vis[:, None] > 0, obs, 0.0)
    return np.concatenate([o.reshape(-1), vis])


def fd_jacobian(f, x, h=1e-6):
    f0 = f(x)
    J = np.zeros((len(f0), len(x)))
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (f(x + e) - f(x - e)) / (2 * h)
    return J


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("casadi_cache")


@pytest.fixture(scope="module")
def chain_compiled(cache):
    if compiled.find_compiler(compiled.CompileOptions()) is None:
        pytest.skip("no C compiler")
    return build_chain("compiled", cache)


def test_compiled_matches_interpreted_and_finite_differences(chain_compiled):
    rng = np.random.default_rng(1)
    fi = build_chain("interpreted")
    assert chain_compiled.compiled and not fi.compiled
    x = rng.normal(0, 0.5, 2 + N_LINK)
    obs = rng.normal(0, 1, (N_MARK, 3))
    vis = (rng.random(N_MARK) > 0.2).astype(float)
    p = make_p(obs, vis)
    r1, J1 = chain_compiled.dense(x, p)
    r2, J2 = fi.dense(x, p)
    np.testing.assert_allclose(r1, r2, atol=1e-12)
    np.testing.assert_allclose(J1, J2, atol=1e-12)
    lengths, a, o, z = chain_params()

    def f(xx):
        return terms.L_3d(chain_markers(xx, lengths, a, o, z), obs, vis)

    np.testing.assert_allclose(r1, f(x), atol=1e-12)
    np.testing.assert_allclose(J1, fd_jacobian(f, x), atol=1e-7)


def test_compile_cache_reused_and_corrupt_entry_rebuilt(chain_compiled, cache):
    lib = chain_compiled.library
    assert lib.parent == cache and lib.exists()
    mtime = lib.stat().st_mtime_ns
    again = build_chain("compiled", cache)
    assert again.library == lib and lib.stat().st_mtime_ns == mtime  # no recompile
    # A corrupt entry (a fresh folder: the loaded library must not be touched in place).
    other = cache / "corrupt"
    other.mkdir()
    (other / lib.name).write_bytes(b"not a shared library")
    rebuilt = build_chain("compiled", other)
    assert rebuilt.compiled and rebuilt.library == other / lib.name
    assert rebuilt.library.stat().st_size > 100
    x = np.zeros(2 + N_LINK)
    p = make_p(np.zeros((N_MARK, 3)), np.ones(N_MARK))
    np.testing.assert_allclose(rebuilt(x, p)[0], build_chain()(x, p)[0], atol=1e-12)


def test_no_compiler_falls_back_or_raises(tmp_path):
    x = ca.SX.sym("x", 2)
    p = ca.SX.sym("p", 1)
    r = ca.vertcat(x[0] * p, ca.sin(x[1]))
    opts = compiled.CompileOptions(mode="auto", compiler="no-such-cc", cache_dir=tmp_path)
    f = compiled.build("fallback", x, p, r, opts)
    assert not f.compiled
    np.testing.assert_allclose(f(np.array([2.0, 0.0]), np.array([3.0]))[0], [6.0, 0.0])
    with pytest.raises(RuntimeError, match="no C compiler"):
        compiled.build("fallback", x, p, r,
                       compiled.CompileOptions(mode="compiled", compiler="no-such-cc"))
    assert not any(tmp_path.iterdir())


def test_different_graphs_get_different_keys(cache):
    x = ca.SX.sym("x", 1)
    p = ca.SX.sym("p", 1)
    opts = compiled.CompileOptions(mode="compiled", cache_dir=cache)
    if compiled.find_compiler(opts) is None:
        pytest.skip("no C compiler")
    f1 = compiled.build("g", x, p, x * p, opts)
    f2 = compiled.build("g", x, p, x + p, opts)
    assert f1.library != f2.library
    assert f1(np.array([2.0]), np.array([3.0]))[0][0] == 6.0
    assert f2(np.array([2.0]), np.array([3.0]))[0][0] == 5.0


def _truth(rng):
    x = np.concatenate([rng.normal(0, 0.3, 2), rng.uniform(-1.0, 1.0, N_LINK)])
    lengths, a, o, z = chain_params()
    return x, chain_markers(x, lengths, a, o, z)


def test_lm_recovers_known_pose_from_its_markers(chain_compiled):
    rng = np.random.default_rng(2)
    for _ in range(3):
        x_true, obs = _truth(rng)
        x0 = x_true + rng.normal(0, 0.3, x_true.shape)
        res = lm.solve(chain_compiled, make_p(obs, np.ones(N_MARK)), x0)
        assert res.converged
        np.testing.assert_allclose(res.x, x_true, atol=1e-6)
        assert all(b <= a for a, b in zip(res.history, res.history[1:], strict=False))


def test_lm_with_gaps_and_a_swapped_label(chain_compiled):
    """Warm start (as frame to frame), 1 mm noise, two gaps, two labels swapped."""
    lengths, a, o, z = chain_params()
    rng = np.random.default_rng(3)
    for _ in range(3):
        x_true, clean = _truth(rng)
        obs = clean + rng.normal(0, 0.001, clean.shape)
        vis = np.ones(N_MARK)
        vis[[1, 7]] = 0.0  # gaps
        obs[1] = np.nan  # gap values may be NaN in the C3D: make_p zeroes them
        swapped = obs.copy()
        swapped[[3, 8]] = obs[[8, 3]]  # two labels swapped
        x0 = x_true + rng.normal(0, 0.05, x_true.shape)
        p = make_p(swapped, vis)
        rows = np.arange(3 * N_MARK).reshape(N_MARK, 3)
        gm = lm.solve(chain_compiled, p, x0,
                      groups=[lm.RobustGroups(rows, "geman_mcclure", sigma=0.01 / np.sqrt(N_MARK))])
        l2 = lm.solve(chain_compiled, p, x0)
        err_gm = np.abs(chain_markers(gm.x, lengths, a, o, z) - clean).max()
        err_l2 = np.abs(chain_markers(l2.x, lengths, a, o, z) - clean).max()
        assert err_gm < 0.005, err_gm
        assert err_l2 > 5 * err_gm, (err_l2, err_gm)
        # The swapped markers stand out in the robust fit's residuals.
        resid = np.linalg.norm(chain_markers(gm.x, lengths, a, o, z) - swapped, axis=1)
        assert set(np.argsort(np.nan_to_num(resid))[-2:]) == {3, 8}


@pytest.mark.parametrize("loss", ["geman_mcclure", "huber"])
def test_robust_weight_is_derivative_of_rho(loss):
    s = np.array([0.0, 0.3, 1.0, 4.0, 25.0])
    h = 1e-6
    d = (robust.rho(s + h, loss, 1.5) - robust.rho(np.maximum(s - h, 0), loss, 1.5)) / (
        (s + h) - np.maximum(s - h, 0))
    np.testing.assert_allclose(robust.weight(s, loss, 1.5), d, rtol=1e-4)
    assert robust.rho(np.array([1e6]), "geman_mcclure", 1.5)[0] <= 1.5 ** 2


def _cs_jacobian(term, args_cs, x_sym, arg_vals):
    f = ca.Function("t", [x_sym], [ca.jacobian(term(*args_cs), x_sym)])
    return np.array(f(arg_vals))


def test_L_3d_jacobian_vs_finite_differences():
    rng = np.random.default_rng(4)
    K = 5
    m = ca.SX.sym("m", K, 3)
    obs = rng.normal(size=(K, 3))
    vis = np.array([1, 0, 1, 1, 0.5])
    msym = ca.reshape(ca.SX.sym("v", 3 * K), K, 3)
    vec = ca.reshape(msym, -1, 1)
    J = _cs_jacobian(terms.L_3d, (msym, ca.DM(obs), ca.DM(vis)), vec, rng.normal(size=3 * K))
    x0 = rng.normal(size=3 * K)
    fd = fd_jacobian(lambda v: terms.L_3d(v.reshape(3, K).T, obs, vis), x0)
    np.testing.assert_allclose(J, fd, atol=1e-8)
    del m
    # value: |r|^2 = 1/K_vis sum_i vis_i |m_i - M_i|^2 (K_vis counts markers with vis > 0)
    mv = x0.reshape(3, K).T
    r = terms.L_3d(mv, obs, vis)
    want = np.sum(vis * np.sum((mv - obs) ** 2, axis=1)) / 4
    assert np.isclose(r @ r, want)


def test_L_2d_jacobian_vs_finite_differences():
    rng = np.random.default_rng(5)
    N = 7
    obs = rng.normal(size=(N, 2)) * 100
    conf = np.array([0.9, 0, 0.5, 1, 0.2, 0, 0.7])
    sym = ca.SX.sym("u", 2 * N)
    uv = ca.reshape(sym, N, 2)
    J = _cs_jacobian(terms.L_2d, (uv, ca.DM(obs), ca.DM(conf)), sym, np.zeros(2 * N))
    fd = fd_jacobian(lambda v: terms.L_2d(v.reshape(2, N).T, obs, conf), rng.normal(size=2 * N))
    np.testing.assert_allclose(J, fd, atol=1e-8)
    r = terms.L_2d(obs + 1.0, obs, conf)
    assert np.isclose(r @ r, 2 * conf.sum() / 5)


def test_L_theta_and_L_s_normal_equations_match_their_residuals():
    rng = np.random.default_rng(6)
    n, npose = 12, 9
    pose_idx = np.arange(3, 12)
    mean = rng.normal(0, 0.1, npose)
    A = np.tril(rng.normal(size=(npose, npose))) + 3 * np.eye(npose)
    limit_idx = np.array([0, 4, 8])
    lo, hi = np.array([-0.2, -0.1, 0.0]), np.array([0.3, 0.2, 0.1])
    x = rng.normal(0, 0.5, n)
    w = 2.5
    r = np.sqrt(w) * terms.L_theta(x[pose_idx], mean, A, lo, hi, limit_idx)
    q = terms.quadratic_L_theta(n, pose_idx, mean, A, w)
    box = terms.box_L_theta(pose_idx, lo, hi, limit_idx, w)
    assert np.isclose(r @ r, q.cost(x) + np.sum(box.residual(x) ** 2))
    # CasADi twin and its Jacobian vs finite differences
    th = ca.SX.sym("th", npose)
    f = ca.Function("f", [th], [terms.L_theta(th, mean, A, lo, hi, limit_idx)])
    np.testing.assert_allclose(np.array(f(x[pose_idx])).ravel(),
                               terms.L_theta(x[pose_idx], mean, A, lo, hi, limit_idx), atol=1e-12)
    Jcs = np.array(ca.Function("j", [th], [ca.jacobian(f(th), th)])(x[pose_idx]))
    fd = fd_jacobian(lambda t: terms.L_theta(t, mean, A, lo, hi, limit_idx), x[pose_idx])
    np.testing.assert_allclose(Jcs, fd, atol=1e-7)
    # The LM gradient of prior + box equals the finite-difference gradient of |r|^2.
    obj = lm._Objective(_Zero(n), np.zeros(0), None, None, q, box)
    H, g = obj.normal_equations(x, np.zeros(0), np.zeros(0), np.zeros(0))
    gfd = fd_jacobian(lambda xx: np.atleast_1d(
        w * np.sum(terms.L_theta(xx[pose_idx], mean, A, lo, hi, limit_idx) ** 2)), x)[0]
    np.testing.assert_allclose(2 * g, gfd, atol=1e-5)
    # L_s
    prev = rng.normal(size=n)
    ws = np.linspace(1, 2, n)
    qs = terms.quadratic_L_s(n, np.arange(n), prev, ws)
    rs = np.sqrt(ws) * terms.L_s(x, prev)
    assert np.isclose(rs @ rs, qs.cost(x))
    np.testing.assert_allclose(fd_jacobian(lambda xx: terms.L_s(xx, prev), x), np.eye(n),
                               atol=1e-9)


class _Zero:
    """A residual function with no rows (for testing the numpy terms alone)."""

    def __init__(self, n):
        self.n_r, self.n_x = 0, n
        self._flat = np.zeros(0, dtype=np.int64)


def test_cache_dir_env_override(tmp_path, monkeypatch):
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path))
    assert compiled.cache_dir(compiled.CompileOptions()) == tmp_path
    assert compiled.cache_dir(compiled.CompileOptions(cache_dir=tmp_path / "x")) == tmp_path / "x"
    monkeypatch.delenv(compiled.CACHE_ENV)
    assert compiled.cache_dir(compiled.CompileOptions()) == compiled.DEFAULT_CACHE
    assert os.fspath(compiled.DEFAULT_CACHE).endswith(os.path.join("assets", "cache", "casadi"))


def test_auto_mode_interprets_huge_sources(tmp_path):
    x = ca.SX.sym("x", 2)
    p = ca.SX.sym("p", 1)
    r = ca.vertcat(x[0] * p, ca.sin(x[1]))
    opts = compiled.CompileOptions(mode="auto", cache_dir=tmp_path, max_source_mb=1e-6)
    msgs = []
    f = compiled.build("huge", x, p, r, opts, log=msgs.append)
    assert not f.compiled and "interpreted" in msgs[0]
    assert not list(tmp_path.glob("*.so"))
    if compiled.find_compiler(opts) is not None:
        forced = compiled.build("huge", x, p, r, compiled.CompileOptions(
            mode="compiled", cache_dir=tmp_path, max_source_mb=1e-6))
        assert forced.compiled
