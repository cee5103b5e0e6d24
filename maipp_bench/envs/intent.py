"""Trajectory intents: Gaussians over teammates' future nodes (paper Sec. III-B, PROTOCOL).

An agent broadcasts (mean, covariance) fitted to the nodes of its sampled future
trajectories; a teammate turns the intents it has received into one feature per roadmap
node: the sum of their densities at the node, divided by its maximum over the nodes.
"""

from __future__ import annotations

import math

import torch


def fit_intent(
    points: torch.Tensor, mask: torch.Tensor, cov_floor: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit the intent Gaussian to sampled nodes (ref: centroid, sample covariance + floor I).

    Args:
        points: ``[..., P, 2]`` node positions of all sampled trajectories.
        mask: bool ``[..., P]``: which points are real.
        cov_floor: variance added on the diagonal ((1/28)^2 in the reference code).

    Returns:
        ``mean [..., 2]`` and ``cov [..., 2, 2]``; the unbiased sample covariance (as
        ``numpy.cov``) is used, zero when fewer than two points are given.
    """
    w = mask.to(points.dtype).unsqueeze(-1)
    n = w.sum(-2)  # [..., 1]
    mean = (points * w).sum(-2) / n.clamp_min(1.0)
    d = (points - mean.unsqueeze(-2)) * w
    scatter = d.transpose(-1, -2) @ d
    cov = scatter / (n - 1.0).clamp_min(1.0).unsqueeze(-1)
    eye = torch.eye(2, dtype=points.dtype, device=points.device)
    return mean, cov + cov_floor * eye


def check_intent(mean: torch.Tensor, cov: torch.Tensor, which: torch.Tensor) -> None:
    """Raise ``ValueError`` unless every selected intent is finite, symmetric and PD."""
    if not bool(which.any()):
        return
    m, c = mean[which], cov[which]
    bad = ~torch.isfinite(m).all(-1) | ~torch.isfinite(c).flatten(-2).all(-1)
    bad |= (c - c.transpose(-1, -2)).abs().amax((-1, -2)) > 1e-9 * c.abs().amax((-1, -2))
    det = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0]
    bad |= (c[..., 0, 0] <= 0) | (det <= 0)
    if bool(bad.any()):
        where = which.nonzero()[bad].tolist()
        raise ValueError(
            "('agents', 'intent'): covariance must be finite, symmetric and positive "
            f"definite and the mean finite; offending [env, agent] = {where}"
        )


def intent_feature(
    nodes: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, valid: torch.Tensor
) -> torch.Tensor:
    """Per-node intent feature for every receiving agent.

    Args:
        nodes: ``[E, N, 2]`` roadmap node positions.
        mean: ``[E, m, m, 2]``: intent of teammate ``b`` as held by agent ``a`` at ``[a, b]``.
        cov: ``[E, m, m, 2, 2]``.
        valid: bool ``[E, m, m]``: agent ``a`` holds an intent of ``b`` (never ``a == b``).

    Returns:
        ``[E, m, N]``: summed densities normalised by their maximum (0 with no intents).
    """
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    det = (a * c - b * b).clamp_min(torch.finfo(cov.dtype).tiny)
    d = nodes[:, None, None, :, :] - mean.unsqueeze(-2)  # [E, m, m, N, 2]
    dx, dy = d[..., 0], d[..., 1]
    quad = (c.unsqueeze(-1) * dx * dx - 2 * b.unsqueeze(-1) * dx * dy
            + a.unsqueeze(-1) * dy * dy) / det.unsqueeze(-1)
    dens = torch.exp(-0.5 * quad) / (2 * math.pi * torch.sqrt(det)).unsqueeze(-1)
    total = (dens * valid.unsqueeze(-1)).sum(-2)  # [E, m, N]
    peak = total.amax(-1, keepdim=True)
    return torch.where(peak > 0, total / torch.where(peak > 0, peak, 1.0), 0.0)
