"""Levenberg-Marquardt in numpy around one (compiled) CasADi residual function.

The problem solved is

    min_x  sum_g rho_g(|r_g(x)|^2)  +  |A x - b|^2  +  |box(x)|^2

- ``r(x) = f(x, p)`` comes from a :class:`fitting.compiled.ResidualFunction` (the nonlinear
  terms: markers, keypoints); its rows are grouped (one marker = 3 rows) for the robust loss
  ``rho`` (IRLS, see ``fitting/robust.py``); rows outside any group are plain least squares.
- ``A x - b`` are the quadratic terms (pose prior, temporal smoothing): their normal
  equations ``A^T A`` and ``A^T b`` are added in numpy, never through CasADi.
- ``box`` is a hinge on chosen coordinates (joint limits): ``max(0, x - hi) + min(0, x - lo)``
  times a weight, Gauss-Newton on the active set.

Shapes: ``x (n,)``, ``r (m,)``, ``A (k, n)``, ``b (k,)``. The damping is Marquardt's
(``lambda * diag(H)`` with a floor) with a multiplicative up/down schedule.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fitting import robust
from fitting.compiled import ResidualFunction

# constants
DIAG_FLOOR = 1e-9  # floor on the damping diagonal (keeps unobserved coordinates solvable)
LAMBDA_MAX = 1e10


@dataclass(frozen=True)
class LMOptions:
    """Stopping and damping. ``ftol``: relative cost decrease that counts as converged;
    ``xtol``: step norm relative to |x|; ``gtol``: max |gradient|."""

    max_iters: int = 30
    lambda_init: float = 1e-3
    lambda_up: float = 10.0
    lambda_down: float = 0.3
    ftol: float = 1e-10
    xtol: float = 1e-10
    gtol: float = 1e-12


@dataclass(frozen=True)
class RobustGroups:
    """Rows of ``r`` grouped for a robust loss: ``rows (G, g)`` int indices (a group's rows
    form one error vector), ``loss`` name and scale ``sigma`` (residual units)."""

    rows: np.ndarray
    loss: robust.Loss = "geman_mcclure"
    sigma: float = 1.0


@dataclass(frozen=True)
class Quadratic:
    """A quadratic term ``|A x - b|^2`` stored as its normal equations:
    ``H = A^T A (n, n)``, ``g = A^T b (n,)``, ``c = b^T b``."""

    H: np.ndarray
    g: np.ndarray
    c: float

    @staticmethod
    def from_residual(A: np.ndarray, b: np.ndarray) -> Quadratic:
        A = np.asarray(A, dtype=float)
        b = np.asarray(b, dtype=float)
        return Quadratic(A.T @ A, A.T @ b, float(b @ b))

    @staticmethod
    def diagonal(n: int, idx: np.ndarray, w: np.ndarray, target: np.ndarray) -> Quadratic:
        """``sum_i w_i (x[idx_i] - target_i)^2`` without forming A."""
        H = np.zeros((n, n))
        g = np.zeros(n)
        idx = np.asarray(idx)
        w = np.broadcast_to(np.asarray(w, dtype=float), idx.shape)
        np.add.at(H, (idx, idx), w)
        np.add.at(g, idx, w * target)
        return Quadratic(H, g, float(np.sum(w * target * target)))

    def __add__(self, other: Quadratic) -> Quadratic:
        return Quadratic(self.H + other.H, self.g + other.g, self.c + other.c)

    def cost(self, x: np.ndarray) -> float:
        return float(x @ self.H @ x - 2.0 * self.g @ x + self.c)


@dataclass(frozen=True)
class Box:
    """Hinge on coordinates ``idx (k,)``: residual ``sqrt(w) * (max(0, x-hi) + min(0, x-lo))``."""

    idx: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    weight: float = 1.0

    def residual(self, x: np.ndarray) -> np.ndarray:
        v = x[self.idx]
        return np.sqrt(self.weight) * (np.maximum(0.0, v - self.hi) + np.minimum(0.0, v - self.lo))


@dataclass
class LMResult:
    """x (n,): solution; cost: final objective; iterations; converged; history: costs."""

    x: np.ndarray
    cost: float
    iterations: int
    converged: bool
    evaluations: int
    history: list[float] = field(default_factory=list)


class _Objective:
    """Evaluates cost, gradient and Gauss-Newton Hessian for one solve."""

    def __init__(self, fun, p, row_scale, groups, quad, box):
        self.fun = fun
        self.p = np.ascontiguousarray(p, dtype=float)
        self.scale = None if row_scale is None else np.asarray(row_scale, dtype=float)
        self.groups = groups
        self.quad = quad
        self.box = box
        flat = np.asarray(fun._flat)
        # a dense row-major Jacobian (the partner fit's numpy functions) is used as it comes
        self.dense = len(flat) == fun.n_r * fun.n_x and bool(np.all(flat == np.arange(len(flat))))
        self.J = None if self.dense else np.zeros((fun.n_r, fun.n_x))
        self.evaluations = 0

    def residual(self, x):
        r, jnz = self.fun(x, self.p)
        self.evaluations += 1
        r = r.copy()
        if self.scale is not None:
            r *= self.scale
        return r, jnz

    def cost_of(self, x, r):
        w_rows = np.ones_like(r)
        if self.groups is None:
            c = float(r @ r)
        else:
            c = 0.0
            grouped = np.zeros(len(r), dtype=bool)
            for gr in self.groups:
                s = np.sum(r[gr.rows] ** 2, axis=1)
                c += float(np.sum(robust.rho(s, gr.loss, gr.sigma)))
                w_rows[gr.rows] = robust.weight(s, gr.loss, gr.sigma)[:, None]
                grouped[gr.rows.ravel()] = True
            rest = r[~grouped]
            c += float(rest @ rest)
        if self.quad is not None:
            c += self.quad.cost(x)
        if self.box is not None:
            rb = self.box.residual(x)
            c += float(rb @ rb)
        return c, w_rows

    def normal_equations(self, x, r, jnz, w_rows):
        if self.dense:
            J = np.asarray(jnz).reshape(self.fun.n_r, self.fun.n_x)
        else:
            J = self.J
            J[...] = 0.0
            J.ravel()[self.fun._flat] = jnz
        sw = np.sqrt(w_rows)
        s = sw if self.scale is None else sw * self.scale
        keep = np.flatnonzero(s)  # rows of weight 0 (a missing keypoint) add nothing
        Jw = J[keep] * s[keep, None]
        H = Jw.T @ Jw
        g = Jw.T @ (r[keep] * sw[keep])
        if self.quad is not None:
            H += self.quad.H
            g += self.quad.H @ x - self.quad.g
        if self.box is not None:
            rb = self.box.residual(x)
            active = rb != 0
            i = self.box.idx[active]
            H[i, i] += self.box.weight
            g[i] += np.sqrt(self.box.weight) * rb[active]
        return H, g


def solve(
    fun: ResidualFunction,
    p: np.ndarray,
    x0: np.ndarray,
    *,
    row_scale: np.ndarray | None = None,
    groups: list[RobustGroups] | None = None,
    quad: Quadratic | None = None,
    box: Box | None = None,
    opts: LMOptions = LMOptions(),
) -> LMResult:
    """Minimise the objective of the module docstring from ``x0 (n,)``.

    fun, p : the residual function and its parameter vector (fixed during the solve).
    row_scale : (m,) multiplies residual rows (per-term sqrt weights, masks); None: 1.
    groups : robust row groups; rows in no group are plain least squares.
    quad, box : quadratic terms and joint-limit hinge in x.
    """
    obj = _Objective(fun, p, row_scale, groups, quad, box)
    x = np.array(x0, dtype=float)
    r, jnz = obj.residual(x)
    cost, w_rows = obj.cost_of(x, r)
    lam = opts.lambda_init
    history = [cost]
    converged = False
    it = 0
    while it < opts.max_iters:
        it += 1
        H, g = obj.normal_equations(x, r, jnz, w_rows)
        if np.max(np.abs(g)) < opts.gtol:
            converged = True
            break
        d = np.maximum(np.diag(H), DIAG_FLOOR)
        improved = False
        while lam < LAMBDA_MAX:
            Hd = H.copy()
            Hd[np.diag_indices_from(Hd)] += lam * d
            try:
                step = -np.linalg.solve(Hd, g)
            except np.linalg.LinAlgError:
                lam *= opts.lambda_up
                continue
            x_new = x + step
            r_new, jnz_new = obj.residual(x_new)
            cost_new, w_new = obj.cost_of(x_new, r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                improved = True
                break
            lam *= opts.lambda_up
        if not improved:
            converged = True  # no descent possible at any damping: a (local) minimum
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        small_step = np.linalg.norm(step) < opts.xtol * (np.linalg.norm(x) + opts.xtol)
        x, r, jnz, cost, w_rows = x_new, r_new, jnz_new.copy(), cost_new, w_new
        history.append(cost)
        lam = max(lam * opts.lambda_down, 1e-12)
        if rel < opts.ftol or small_step:
            converged = True
            break
    return LMResult(x=x, cost=cost, iterations=it, converged=converged,
                    evaluations=obj.evaluations, history=history)
