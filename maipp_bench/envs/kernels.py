"""Stationary covariance kernels, registered by name (``MAIPPConfig.kernel``)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

# A kernel maps distances r >= 0 (any shape) to correlations in [0, 1]; the belief
# multiplies by the prior variance. Adding a kernel is one function and one entry.
KernelFn = Callable[[torch.Tensor, float], torch.Tensor]


# In-place arithmetic on fresh temporaries: these run on millions of distances per step.
def matern12(r: torch.Tensor, length_scale: float) -> torch.Tensor:
    return (r * (-1.0 / length_scale)).exp_()


def matern32(r: torch.Tensor, length_scale: float) -> torch.Tensor:
    s = r * (math.sqrt(3.0) / length_scale)
    e = torch.neg(s).exp_()
    return s.add_(1.0).mul_(e)


def matern52(r: torch.Tensor, length_scale: float) -> torch.Tensor:
    s = r * (math.sqrt(5.0) / length_scale)
    e = torch.neg(s).exp_()
    return (s * s).div_(3.0).add_(s).add_(1.0).mul_(e)


def rbf(r: torch.Tensor, length_scale: float) -> torch.Tensor:
    return torch.exp(-0.5 * (r / length_scale) ** 2)


KERNELS: dict[str, KernelFn] = {
    "matern12": matern12,
    "matern32": matern32,
    "matern52": matern52,
    "rbf": rbf,
}


def pairwise_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distances between point sets ``a [..., P, 2]`` and ``b [..., Q, 2]``.

    Computed from coordinate differences (not the |a|^2 + |b|^2 - 2ab expansion) so that
    duplicate points give exactly zero, which the exactness tests rely on. On CUDA the
    differences are written out: ``cdist``'s CUDA kernel reduces each pair with a thread
    block, which took 62% of a step's device time at E = 16384 for these 2-D points
    (``benchmarks/cuda_profile.py``). The CPU keeps ``cdist``, whose bits the committed
    leaderboards hold.
    """
    if a.is_cuda:
        return (a.unsqueeze(-2) - b.unsqueeze(-3)).square_().sum(-1).sqrt_()  # [..., P, Q]
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")
