"""Polyline helpers shared by path planners: resampling and measurement points along paths."""

from __future__ import annotations

import torch


def polyline_lengths(points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Cumulative arc length at each vertex of ``points [..., D, 2]`` (``mask``: vertex real)."""
    seg = (points[..., 1:, :] - points[..., :-1, :]).norm(dim=-1)
    seg = seg * (mask[..., 1:] & mask[..., :-1])
    return torch.nn.functional.pad(torch.cumsum(seg, -1), (1, 0))


def points_at(points: torch.Tensor, cum: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Points at arc lengths ``dist [..., R]`` along polylines ``points [..., D, 2]``.

    ``cum`` is :func:`polyline_lengths`: padding vertices after the last real one repeat its
    length. A distance at (or past) the end lands on the last real vertex, not on padding:
    whether a measurement sits exactly at a branch's end or a few ulps short of it must not
    move it to wherever the padding lies (the root, for RRT branches).
    """
    d = points.shape[-2]
    # The first vertex at the full length: the last real one (or, after zero-length
    # final segments, one at the same place). Real vertices come first.
    last = (cum < cum[..., -1:]).sum(-1, keepdim=True)
    idx = torch.searchsorted(cum.contiguous(), dist.contiguous(), right=True)
    return along_segments(points, cum, dist, torch.minimum(idx, last).clamp(1, d - 1) - 1)


def along_segments(
    points: torch.Tensor, cum: torch.Tensor, dist: torch.Tensor, seg: torch.Tensor
) -> torch.Tensor:
    """Points at arc lengths ``dist [..., R]`` on segments ``seg [..., R]`` (segment i joins
    vertices i and i + 1) of polylines ``points [..., D, 2]``, clamped to the segment."""
    start = cum.gather(-1, seg)
    length = cum.gather(-1, seg + 1) - start
    a = points.gather(-2, seg.unsqueeze(-1).expand(*seg.shape, 2))
    b = points.gather(-2, (seg + 1).unsqueeze(-1).expand(*seg.shape, 2))
    # A zero-length segment (only a zero-length path's) has no direction: stay at its start.
    frac = ((dist - start) / torch.where(length > 0, length, torch.inf)).clamp(0, 1)
    return a + (b - a) * frac.unsqueeze(-1)


def measurement_points(
    points: torch.Tensor, mask: torch.Tensor, since: torch.Tensor, spacing: float,
    max_points: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where an agent that has travelled ``since`` since its last measurement would measure
    along polylines ``points [..., D, 2]``: ``[..., R, 2]`` and a mask (R = max_points)."""
    cum = polyline_lengths(points, mask)
    total = cum.amax(-1, keepdim=True)
    j = torch.arange(max_points, device=points.device, dtype=points.dtype)
    dist = spacing * (j + 1) - since.unsqueeze(-1)
    valid = dist <= total + 1e-12
    return points_at(points, cum, torch.minimum(dist, total)), valid
