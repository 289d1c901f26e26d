"""fitting.priors: joint-limit classes, the Gaussian learned from samples, the default prior."""
from __future__ import annotations

import numpy as np
import pytest

from fitting import priors


def test_joint_classes_by_name():
    assert priors.joint_limit_deg("lowerarm02.L") == 35.0  # twist bone: tight
    assert priors.joint_limit_deg("lowerarm01.L") == 150.0  # elbow
    assert priors.joint_limit_deg("finger2-3.R") == 95.0
    assert priors.joint_limit_deg("spine03") == 40.0
    assert priors.joint_limit_deg("unknown_bone") == priors.DEFAULT_LIMIT_DEG
    lo, hi = priors.joint_limits(["spine03", "head"])
    np.testing.assert_allclose(hi, np.deg2rad([40, 40, 40, 60, 60, 60]))
    np.testing.assert_allclose(lo, -hi)


def test_learn_gaussian_recovers_covariance_and_whitens():
    rng = np.random.default_rng(0)
    n = 6
    L = np.tril(rng.normal(0, 0.1, (n, n)), -1) + 0.4 * np.eye(n)  # eigenvalues >> floor
    cov = L @ L.T
    mu = rng.normal(0, 0.5, n)
    X = rng.multivariate_normal(mu, cov, size=20000)
    g = priors.learn_gaussian(X, "test samples", shrinkage=0.0)
    np.testing.assert_allclose(g.mean, mu, atol=0.02)
    # A^T A = (cov + floor)^-1
    want = np.linalg.inv(cov + priors.VAR_FLOOR * np.eye(n))
    np.testing.assert_allclose(g.sqrt_precision.T @ g.sqrt_precision, want, rtol=0.05, atol=0.5)
    white = np.array([g.residual(x) for x in X[:5000]])
    np.testing.assert_allclose(np.cov(white, rowvar=False), np.eye(n), atol=0.08)
    assert g.source == "test samples"
    with pytest.raises(ValueError):
        priors.learn_gaussian(X[:1], "one sample")


def test_default_prior_says_where_it_comes_from():
    p = priors.default_prior(["spine03", "lowerarm01.L"])
    assert p.gaussian.mean.shape == (6,) and p.lo.shape == (6,)
    assert "no motion data" in p.source
    sig = 1 / np.diag(p.gaussian.sqrt_precision)
    np.testing.assert_allclose(sig, p.hi / 3)
    g = priors.learn_gaussian(np.random.default_rng(1).normal(size=(50, 6)), "fitted poses")
    assert priors.with_gaussian(p, g).source == "fitted poses"
    with pytest.raises(ValueError):
        priors.with_gaussian(p, priors.learn_gaussian(np.zeros((5, 3)) + np.arange(5)[:, None],
                                                      "wrong size"))


def test_a_bend_shared_along_a_chain_costs_nothing_extra_and_a_kink_does():
    names = ["spine05", "lowerarm01.L", "spine03", "spine01"]  # a chain need not be contiguous
    plain = priors.default_prior(names)
    sigma = np.deg2rad(15.0)
    p = priors.couple_chains(plain, (priors.SPINE_CHAIN, ("neck01", "head")), sigma)
    # two consecutive pairs of the spine, 3 axes each; the neck chain is not posed: no rows
    assert p.gaussian.sqrt_precision.shape == (12 + 6, 12)
    assert "spine05-spine03-spine01" in p.source and "neck01" not in p.source
    assert p.source.startswith(plain.source)
    np.testing.assert_array_equal(p.lo, plain.lo)

    def cost(prior, theta):
        return float(np.sum(prior.gaussian.residual(theta) ** 2))

    even = np.zeros(12)
    even[[0, 6, 9]] = 0.2  # the same bend about x at each spine joint
    assert cost(p, even) == pytest.approx(cost(plain, even))
    kink = np.zeros(12)
    kink[0] = 0.6  # the whole bend at the lowest joint
    # one pair differs by 0.6 rad about x
    assert cost(p, kink) - cost(plain, kink) == pytest.approx((0.6 / sigma) ** 2)
    elbow = np.zeros(12)
    elbow[3:6] = 0.5  # not in a chain: unchanged
    assert cost(p, elbow) == pytest.approx(cost(plain, elbow))
    # the minimum-norm way to make a given total bend is the even one, and the coupling makes
    # the kink dearer than the plain prior alone does
    assert cost(p, kink) / cost(p, even) > cost(plain, kink) / cost(plain, even)
    assert priors.couple_chains(plain, (priors.SPINE_CHAIN,), 0.0) is plain


def test_the_partner_fit_rejects_a_negative_spine_coupling():
    from fitting.partner_fit import PartnerFitOptions

    with pytest.raises(ValueError, match="spine_coupling_deg"):
        PartnerFitOptions(spine_coupling_deg=-1.0)
    assert PartnerFitOptions().spine_coupling_deg > 0
