"""Event-driven asynchronous motion on the roadmap (PROTOCOL, "Roadmap, motion, budget").

Agents move along straight edges at unit speed. Simulated time jumps to the next arrival;
the agents that arrive (ties included) decide, the others keep moving. Each agent measures
at the start and then every ``sample_spacing`` of travelled distance, carrying the leftover
across edges. Everything here is a pure function of tensors batched over [envs, agents].
"""

from __future__ import annotations

import torch

# Arrival ties and budget fits are decided with this slack (distances are float64).
EPS = 1e-9


def edge_points(
    src: torch.Tensor, dst: torch.Tensor, length: torch.Tensor, along: torch.Tensor
) -> torch.Tensor:
    """Points at distance ``along [..., R]`` from ``src [..., 2]`` towards ``dst [..., 2]``.

    ``length [...]`` is the edge length; zero-length edges give ``src``.
    """
    frac = along / torch.where(length > 0, length, 1.0).unsqueeze(-1)
    return src.unsqueeze(-2) + (dst - src).unsqueeze(-2) * frac.unsqueeze(-1)


def sample_offsets(
    since_sample: torch.Tensor, travel: torch.Tensor, spacing: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where along a leg of length ``travel`` the measurements fall.

    Args:
        since_sample: ``[E, m]`` distance travelled since each agent's last measurement.
        travel: ``[E, m]`` distance travelled in this leg (0 for resting agents).
        spacing: measurement spacing (0.2).

    Returns:
        ``offsets [E, m, R]`` (distance into the leg), ``valid [E, m, R]`` and the new
        ``since_sample [E, m]``; ``R`` is the largest count in the batch.
    """
    total = since_sample + travel
    count = torch.floor(total / spacing + EPS).to(torch.int64)
    count = torch.where(travel > 0, count, torch.zeros_like(count))
    r = int(count.max()) if count.numel() else 0
    j = torch.arange(r, device=travel.device, dtype=travel.dtype)
    offsets = spacing * (j + 1) - since_sample.unsqueeze(-1)
    valid = j.to(torch.int64) < count.unsqueeze(-1)
    rest = torch.clamp(total - count.to(total.dtype) * spacing, min=0.0)
    return offsets, valid, torch.where(travel > 0, rest, since_sample)


def reachability(adjacent: torch.Tensor) -> torch.Tensor:
    """Connected components as a reachability matrix ``[E, m, m]`` (transitive closure by
    repeated squaring; reflexive)."""
    m = adjacent.shape[-1]
    eye = torch.eye(m, dtype=torch.bool, device=adjacent.device)
    reach = (adjacent | eye).to(torch.float32)
    hops = 1
    while hops < m:
        reach = ((reach @ reach) > 0).to(torch.float32)
        hops *= 2
    return reach > 0
