"""One small robust Levenberg-Marquardt, shared by the planar essential matrix's refinement and
the planar homography's (docs/theory.md sections 3.2 and 3.4)."""

from __future__ import annotations

import numpy as np

__all__ = ["LMFit", "robust_lm"]


class LMFit:
    """Result of :func:`robust_lm`: parameters ``x`` (P,), residuals ``fun`` (M,) at ``x``, robust ``cost``."""

    __slots__ = ("x", "fun", "cost")

    def __init__(self, x, fun, cost):
        self.x, self.fun, self.cost = x, fun, cost


def robust_lm(fun, x0, f_scale: float, iters: int = 15) -> LMFit:
    """Levenberg-Marquardt with Cauchy IRLS weights for 1-2 parameters.

    Hand-written because scipy.optimize.least_squares spends ~3 ms per call in overhead at this size
    (measured), several times the work itself, and this runs at every control step.
    """
    x = np.asarray(x0, dtype=float).copy()
    f = fun(x)
    c2 = f_scale * f_scale

    def robust_cost(r):
        return float(np.sum(np.log1p(r * r / c2)))

    cost, mu, h = robust_cost(f), 1e-3, 1e-6
    for _ in range(iters):
        w = 1.0 / (1.0 + f * f / c2)  # Cauchy IRLS weights
        J = np.empty((len(f), len(x)))
        for j in range(len(x)):
            xj = x.copy()
            xj[j] += h
            J[:, j] = (fun(xj) - f) / h
        Jw = J * w[:, None]
        A, g = Jw.T @ J, Jw.T @ f
        improved = False
        for _ in range(8):
            try:
                dx = -np.linalg.solve(A + mu * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            f_new = fun(x + dx)
            c_new = robust_cost(f_new)
            if c_new < cost:
                x, f, improved = x + dx, f_new, True
                mu = max(mu / 3.0, 1e-9)
                converged = cost - c_new < 1e-6 * cost or np.max(np.abs(dx)) < 1e-7
                cost = c_new
                break
            mu *= 10.0
        if not improved or converged:
            break
    return LMFit(x, f, cost)

