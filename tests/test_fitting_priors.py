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
