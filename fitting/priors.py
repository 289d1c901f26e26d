"""Pose prior for ``L_theta``: joint limits plus a Gaussian over the pose unknowns.

The paper's ``L_theta`` is the squared latent code of a normalizing flow trained on GHUM
poses. Neither GHUM, its flow, nor a motion-capture corpus (AMASS, CMU) can be obtained here,
so this prior is what can be justified from data that *is* here:

- **Joint limits** (``joint_limits``): symmetric bounds on each local rotation-vector
  component, by joint class (spine, knee, finger, twist bone...), in radians. They are
  anatomical ranges of motion rounded up (e.g. knee flexion ~150 deg, wrist ~80 deg); being
  per axis and symmetric they are loose on purpose: they stop wrapped or absurd solutions,
  not plausible ones. A hinge, zero inside the box.
- **Gaussian** (``GaussianPrior``): ``|A (theta - mu)|^2`` with ``A^T A`` the inverse
  covariance. ``learn_gaussian`` estimates it from pose samples with shrinkage toward a
  diagonal floor (a few hundred frames are enough). What it is learned from is recorded in
  ``GaussianPrior.source`` and in every fit report.

Which data: no motion corpus is available here, so :func:`default_prior` (what ``marker_fit``
uses unless given another) has a zero-mean Gaussian whose per-axis sigma is derived from the
joint-limit table (sigma = limit / 3): a maximum-entropy choice given the ranges, learned from
no motion data, and the reports say so. :func:`learn_gaussian` turns any pose array (AMASS
converted to this body model where licensed, or a session's own fitted poses) into a prior
learned from motion data; :func:`with_gaussian` swaps it in.

Shapes: the pose unknowns are ``theta: (P*3,)`` local rotation vectors of the P posed joints
(the root excluded), radians, flattened joint-major.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

# Joint classes: (name pattern, limit per axis in degrees). First match wins; matched against
# the lower-cased joint name. Twist bones (Anny's *01/*02 mid-segment bones) get a tight range:
# DESIGN.md found they need a stronger prior.
JOINT_CLASSES: tuple[tuple[str, float], ...] = (
    (r"(upperarm|lowerarm|upperleg|lowerleg)0?2|twist", 35.0),  # mid-segment twist bones
    (r"finger|thumb|index|middle|ring|pinky|metacarpal", 95.0),
    (r"toe", 45.0),
    (r"knee|lowerleg|shin|calf", 150.0),
    (r"elbow|lowerarm|forearm", 150.0),
    (r"wrist|hand", 80.0),
    (r"ankle|foot", 55.0),
    (r"hip|upperleg|thigh|pelvis", 120.0),
    (r"shoulder|upperarm", 130.0),
    (r"clavicle|collar|scapula", 35.0),
    (r"spine|chest|torso|abdomen|lumbar|thorax", 40.0),
    (r"neck", 50.0),
    (r"head", 60.0),
    (r"jaw", 25.0),
    (r"eye|oculi|brow|lip|tongue|oris|cheek|levator|risorius|temporalis|orbicularis|special",
     10.0),
)
DEFAULT_LIMIT_DEG = 90.0
SIGMA_FROM_RANGE = 1.0 / 3.0  # default Gaussian: sigma = limit / 3 per axis
SHRINKAGE = 0.1  # learn_gaussian: weight of the diagonal target
VAR_FLOOR = (np.deg2rad(2.0)) ** 2  # rad^2, so no direction is ever pinned


def joint_limit_deg(name: str) -> float:
    """The per-axis limit (degrees, symmetric) of a joint by its name."""
    low = name.lower()
    for pat, deg in JOINT_CLASSES:
        if re.search(pat, low):
            return deg
    return DEFAULT_LIMIT_DEG


def joint_limits(joint_names) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis bounds for the posed joints: ``(lo, hi)`` each ``(P*3,)`` radians."""
    hi = np.repeat(np.deg2rad([joint_limit_deg(n) for n in joint_names]), 3)
    return -hi, hi


@dataclass(frozen=True)
class GaussianPrior:
    """``|A (theta - mean)|^2`` over ``theta (n,)``: ``mean (n,)``, ``sqrt_precision A (k, n)``
    (``A^T A = Sigma^-1``; ``k > n`` when rows were appended, :func:`couple_chains`), radians;
    ``source`` says what it was learned from."""

    mean: np.ndarray
    sqrt_precision: np.ndarray
    source: str

    def residual(self, theta: np.ndarray) -> np.ndarray:
        return self.sqrt_precision @ (np.asarray(theta) - self.mean)


@dataclass(frozen=True)
class PosePrior:
    """What ``L_theta`` needs: the Gaussian and the limits over the pose unknowns.

    joint_names : (P,) the posed joints (theta is (P*3,)); lo, hi : (P*3,) radians;
    limit_idx : indices of theta that have limits (all, by default)."""

    joint_names: tuple[str, ...]
    gaussian: GaussianPrior
    lo: np.ndarray
    hi: np.ndarray
    limit_idx: np.ndarray

    @property
    def source(self) -> str:
        return self.gaussian.source


def _sqrt_precision(cov: np.ndarray) -> np.ndarray:
    """A with A^T A = cov^-1 (A = L^-1 from cov = L L^T)."""
    L = np.linalg.cholesky(cov)
    return np.linalg.inv(L)


def learn_gaussian(samples: np.ndarray, source: str, shrinkage: float = SHRINKAGE) -> GaussianPrior:
    """Mean and shrunk covariance of pose samples.

    samples : (N, n) pose vectors (local rotation vectors, radians), N >= 2.
    source : a sentence naming the data (kept in reports).
    shrinkage : Sigma = (1 - s) * sample covariance + s * diag(sample variances), plus a floor.
    """
    X = np.asarray(samples, dtype=float)
    if X.ndim != 2 or len(X) < 2:
        raise ValueError(f"learn_gaussian: expected (N >= 2, n) samples, got {X.shape}")
    mu = X.mean(axis=0)
    S = np.cov(X, rowvar=False).reshape(X.shape[1], X.shape[1])
    cov = (1.0 - shrinkage) * S + shrinkage * np.diag(np.diag(S))
    cov += VAR_FLOOR * np.eye(len(mu))
    return GaussianPrior(mu, _sqrt_precision(cov), source)


def default_prior(joint_names) -> PosePrior:
    """Joint limits plus a zero-mean Gaussian with sigma = limit / 3 per axis (see module doc:
    derived from the range-of-motion table, not from motion data)."""
    names = tuple(joint_names)
    lo, hi = joint_limits(names)
    sigma = np.maximum(hi * SIGMA_FROM_RANGE, np.sqrt(VAR_FLOOR))
    g = GaussianPrior(np.zeros(len(hi)), np.diag(1.0 / sigma),
                      "no motion data: zero mean, sigma = joint-limit / 3 per axis "
                      "(fitting/priors.py JOINT_CLASSES)")
    return PosePrior(names, g, lo, hi, np.arange(len(hi)))


#: Chains of joints that bend together (a spine's vertebrae share a bend between them): the
#: fitted joints of Anny's trunk, pelvis to chest. Anny's pose-0 joint frames are all aligned
#: with the body (``body/lbs.py``: G_j = I at rest), so a bend shared evenly over a chain is
#: equal local rotation vectors (exactly for bends about one axis, to first order otherwise).
SPINE_CHAIN = ("spine05", "spine03", "spine01")


def couple_chains(prior: PosePrior, chains, sigma_rad: float) -> PosePrior:
    """The prior with, per chain of joints (names; those not posed are skipped) and per pair
    of consecutive posed joints ``a, b`` in it, the rows ``(theta_a - theta_b) / sigma_rad``
    appended to the Gaussian's ``sqrt_precision``: a bend is shared over the chain unless the
    evidence says otherwise (a chain's joints differing by ``sigma_rad`` per axis cost as much
    as one joint ``sigma`` from the mean). Keypoints on the shoulders and hips fix the trunk's
    total bend but not how it is shared between the vertebrae, so without this the fit puts it
    wherever the per-joint prior is weakest. ``sigma_rad`` <= 0: the prior unchanged."""
    if not sigma_rad > 0:
        return prior
    names = list(prior.joint_names)
    n = len(prior.lo)
    rows, used = [], []
    for chain in chains:
        posed = [names.index(j) for j in chain if j in names]
        for a, b in zip(posed[:-1], posed[1:], strict=True):
            for ax in range(3):
                r = np.zeros(n)
                r[3 * a + ax], r[3 * b + ax] = 1.0 / sigma_rad, -1.0 / sigma_rad
                rows.append(r)
        if len(posed) > 1:
            used.append("-".join(names[i] for i in posed))
    if not rows:
        return prior
    g = prior.gaussian
    A = np.concatenate([np.asarray(g.sqrt_precision, float), np.asarray(rows)], axis=0)
    src = (f"{g.source}; chains bending together ({', '.join(used)}): consecutive joints "
           f"coupled at sigma {np.rad2deg(sigma_rad):.1f} deg per axis")
    return with_gaussian(prior, GaussianPrior(g.mean, A, src))


def with_gaussian(prior: PosePrior, gaussian: GaussianPrior) -> PosePrior:
    """The same limits with another Gaussian (e.g. one from :func:`learn_gaussian`)."""
    if gaussian.mean.shape != prior.lo.shape:
        raise ValueError(f"Gaussian over {gaussian.mean.shape} for pose {prior.lo.shape}")
    return PosePrior(prior.joint_names, gaussian, prior.lo, prior.hi, prior.limit_idx)
