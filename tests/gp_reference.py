"""Independent float64 references used by the tests (no maipp_bench code).

A dense Gaussian process with the Matern 3/2 kernel written out from its formula,
k(r) = s2 (1 + sqrt(3) r / l) exp(-sqrt(3) r / l), solved with a float64 Cholesky factor of
K(X, X) + noise I, exactly as PROTOCOL "Beliefs" defines the belief.
"""

from __future__ import annotations

import math

import torch

F64 = torch.float64


def matern32_cov(a: torch.Tensor, b: torch.Tensor, length_scale: float = 0.25,
                 variance: float = 1.0) -> torch.Tensor:
    """Matern nu=3/2 covariance between ``a [P, 2]`` and ``b [Q, 2]`` (float64)."""
    a, b = a.to(F64), b.to(F64)
    dx = a[:, None, 0] - b[None, :, 0]
    dy = a[:, None, 1] - b[None, :, 1]
    r = torch.sqrt(dx * dx + dy * dy)
    s = math.sqrt(3.0) * r / length_scale
    return variance * (1.0 + s) * torch.exp(-s)


def dense_gp(x: torch.Tensor, y: torch.Tensor, query: torch.Tensor, noise: float = 1e-4,
             length_scale: float = 0.25, variance: float = 1.0):
    """Posterior mean ``[Q, C]`` and variance ``[Q]`` of a zero-mean GP given ``x [n, 2]``,
    ``y [n, C]`` (or ``[n]``), at ``query [Q, 2]``; ``n = 0`` gives the prior."""
    query = query.to(F64)
    y = y.to(F64)
    if y.dim() == 1:
        y = y[:, None]
    nq = query.shape[0]
    if x.shape[0] == 0:
        return (torch.zeros(nq, y.shape[-1], dtype=F64),
                torch.full((nq,), float(variance), dtype=F64))
    k_xx = matern32_cov(x, x, length_scale, variance)
    k_xx = k_xx + noise * torch.eye(x.shape[0], dtype=F64)
    chol = torch.linalg.cholesky(k_xx)
    k_xq = matern32_cov(x, query, length_scale, variance)
    alpha = torch.cholesky_solve(y, chol)
    mean = k_xq.T @ alpha
    v = torch.linalg.solve_triangular(chol, k_xq, upper=False)
    var = variance - (v * v).sum(0)
    return mean, var


def trace_in_region(mean: torch.Tensor, var: torch.Tensor, beta: float = 1.0,
                    threshold: float = 0.4) -> torch.Tensor:
    """Tr(P) over X_I = {mu + beta sigma >= threshold}, written out with a Python mask."""
    sd = torch.sqrt(torch.clamp(var, min=0.0))
    region = (mean + beta * sd) >= threshold
    return var.clamp(min=0.0)[region].sum()
