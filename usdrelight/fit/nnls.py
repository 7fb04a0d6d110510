"""Non-negative least squares in normal form: the exact solve under the light fit's linear model."""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import nnls


def nnls_normal(G: np.ndarray, r: np.ndarray) -> np.ndarray:
    """argmin_{x >= 0} x^T G x - 2 r^T x for a symmetric PSD G (a least-squares problem in normal form)."""
    q = len(r)
    if q == 0:
        return np.zeros(0)
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    live = d > 0
    x = np.zeros(q)
    if not live.any():
        return x
    Gn = G[np.ix_(live, live)] / np.outer(d[live], d[live])
    Gn[np.diag_indices_from(Gn)] += 1e-9
    R = np.linalg.cholesky(Gn).T
    y = solve_triangular(R, r[live] / d[live], trans="T")
    sol, _ = nnls(R, y, maxiter=50 * q)
    x[live] = sol / d[live]
    return x
