"""Polyline helpers: points along padded paths land on the path, never on its padding."""

from __future__ import annotations

import math

import pytest
import torch

from maipp_bench.algos.paths import measurement_points, points_at, polyline_lengths


def _padded(vertices: list[list[float]], pad: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A polyline padded as RRT branches are: extra vertices repeat the root, masked out."""
    pts = torch.tensor(vertices + [vertices[0]] * pad, dtype=torch.float64)
    mask = torch.tensor([True] * len(vertices) + [False] * pad)
    return pts, mask


def _staircase(n: int, step: float = 0.1) -> list[list[float]]:
    """n segments of length ``step`` turning left and right: its computed length is n * step
    only up to a few ulps, as an RRT branch's is."""
    out, x, y = [[0.13, 0.27]], 0.13, 0.27
    for i in range(n):
        angle = 0.3 if i % 2 else -0.45
        x, y = x + step * math.cos(angle), y + step * math.sin(angle)
        out.append([x, y])
    return out


@pytest.mark.parametrize("pad", [0, 1, 3])
@pytest.mark.parametrize("ulps", [-2, 0])
def test_point_at_the_end_lands_on_the_end(pad: int, ulps: int) -> None:
    verts = _staircase(10)
    pts, mask = _padded(verts, pad)
    cum = polyline_lengths(pts, mask)
    total = float(cum.max())
    dist = torch.tensor([total + ulps * math.ulp(total)], dtype=torch.float64).clamp_max(total)
    got = points_at(pts, cum, dist)[0]
    assert torch.allclose(got, torch.tensor(verts[-1], dtype=torch.float64), atol=1e-12), got


@pytest.mark.parametrize("pad", [1, 3])
def test_padding_never_moves_a_point(pad: int) -> None:
    verts = _staircase(7)
    bare, bare_mask = _padded(verts, 0)
    pts, mask = _padded(verts, pad)
    total = float(polyline_lengths(bare, bare_mask).max())
    dist = torch.linspace(0.0, total, 23, dtype=torch.float64)
    a = points_at(bare, polyline_lengths(bare, bare_mask), dist)
    b = points_at(pts, polyline_lengths(pts, mask), dist)
    assert torch.equal(a, b)


def test_points_inside_interpolate_their_segment() -> None:
    pts, mask = _padded([[0.0, 0.0], [0.3, 0.0], [0.3, 0.4]], 2)
    dist = torch.tensor([0.15, 0.3, 0.5], dtype=torch.float64)
    got = points_at(pts, polyline_lengths(pts, mask), dist)
    want = torch.tensor([[0.15, 0.0], [0.3, 0.0], [0.3, 0.2]], dtype=torch.float64)
    assert torch.allclose(got, want, atol=1e-15)


@pytest.mark.parametrize("pad", [0, 4])
def test_measurement_at_a_branch_end_counts_whatever_its_last_bits(pad: int) -> None:
    """A branch of ten steps measured every 0.2 from a fresh sample, its computed length a
    few ulps short of 1.0 (as an RRT branch's may be): the fifth point, at 1.0, is kept (the
    1e-12 allowance) and lands at the branch's end on any padding, not on the root."""
    verts = _staircase(10, step=0.09999999999999999)
    pts, mask = _padded(verts, pad)
    assert float(polyline_lengths(pts, mask).max()) < 1.0  # the case under test
    got, valid = measurement_points(pts, mask, torch.tensor(0.0, dtype=torch.float64), 0.2, 6)
    assert valid.tolist() == [True] * 5 + [False]
    assert torch.allclose(got[4], torch.tensor(verts[-1], dtype=torch.float64), atol=1e-12)


def test_zero_length_path_lands_on_its_vertex() -> None:
    pts, mask = _padded([[0.4, 0.6]], 3)
    pts[1:] = torch.tensor([0.9, 0.1], dtype=torch.float64)  # padding elsewhere than the root
    dist = torch.tensor([0.0, 0.2], dtype=torch.float64)
    got = points_at(pts, polyline_lengths(pts, mask), dist)
    assert torch.equal(got, torch.tensor([[0.4, 0.6], [0.4, 0.6]], dtype=torch.float64))


def test_a_batch_of_differently_padded_paths() -> None:
    """Each row finds its own last real vertex."""
    rows = [_padded(_staircase(n), 8 - n) for n in (2, 5, 8)]
    pts = torch.stack([r[0] for r in rows])
    mask = torch.stack([r[1] for r in rows])
    cum = polyline_lengths(pts, mask)
    got = points_at(pts, cum, cum.amax(-1, keepdim=True))[:, 0]
    want = torch.stack([r[0][n] for r, n in zip(rows, (2, 5, 8))])
    assert torch.allclose(got, want, atol=1e-12)
