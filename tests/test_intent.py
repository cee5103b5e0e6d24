"""Intent Gaussians and the node intent feature against direct numpy computations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from maipp_bench.envs.intent import check_intent, fit_intent, intent_feature

FLOOR = (1.0 / 28.0) ** 2


def test_fit_intent_matches_numpy_with_masks():
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(4, 3, 40, 2, generator=gen, dtype=torch.float64)
    mask = torch.rand(4, 3, 40, generator=gen) < 0.6
    mask[0, 0] = True  # all points
    mask[1, 1, :] = False
    mask[1, 1, :2] = True  # exactly two points
    mean, cov = fit_intent(pts, mask, FLOOR)
    assert mean.shape == (4, 3, 2) and cov.shape == (4, 3, 2, 2)
    for i in range(4):
        for j in range(3):
            sel = pts[i, j][mask[i, j]].numpy()
            ref_mean = np.mean(sel, axis=0)
            ref_cov = np.cov(sel.T) + FLOOR * np.eye(2)
            np.testing.assert_allclose(mean[i, j].numpy(), ref_mean, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(cov[i, j].numpy(), ref_cov, rtol=1e-10, atol=1e-14)


def test_fit_intent_single_point_gives_floor():
    pts = torch.tensor([[[0.3, 0.7], [0.9, 0.1]]], dtype=torch.float64)
    mask = torch.tensor([[True, False]])
    mean, cov = fit_intent(pts, mask, FLOOR)
    assert torch.allclose(mean, torch.tensor([[0.3, 0.7]], dtype=torch.float64))
    assert torch.allclose(cov, FLOOR * torch.eye(2, dtype=torch.float64).unsqueeze(0))


def _density(x, mean, cov):
    d = x - mean
    inv = np.linalg.inv(cov)
    quad = np.einsum("ni,ij,nj->n", d, inv, d)
    return np.exp(-0.5 * quad) / (2 * np.pi * np.sqrt(np.linalg.det(cov)))


def test_intent_feature_matches_numpy():
    gen = torch.Generator().manual_seed(1)
    e, m, n = 2, 3, 60
    nodes = torch.rand(e, n, 2, generator=gen, dtype=torch.float64)
    mean = torch.rand(e, m, m, 2, generator=gen, dtype=torch.float64)
    a = torch.randn(e, m, m, 2, 2, generator=gen, dtype=torch.float64) * 0.1
    cov = a @ a.transpose(-1, -2) + 0.01 * torch.eye(2, dtype=torch.float64)
    valid = torch.rand(e, m, m, generator=gen) < 0.7
    valid &= ~torch.eye(m, dtype=torch.bool)
    valid[0, 0] = False  # agent 0 of env 0 holds no intents: feature 0
    valid[0, 1, 0] = True
    feat = intent_feature(nodes, mean, cov, valid)
    assert feat.shape == (e, m, n)
    for i in range(e):
        for r in range(m):
            total = np.zeros(n)
            for s in range(m):
                if valid[i, r, s]:
                    total += _density(nodes[i].numpy(), mean[i, r, s].numpy(), cov[i, r, s].numpy())
            ref = total / total.max() if total.max() > 0 else total
            np.testing.assert_allclose(feat[i, r].numpy(), ref, rtol=1e-10, atol=1e-12)
    assert torch.all(feat[0, 0] == 0)
    assert torch.allclose(feat[0, 1].max(), torch.tensor(1.0, dtype=torch.float64))


@pytest.mark.parametrize(
    "cov",
    [
        [[1.0, 2.0], [2.0, 1.0]],  # indefinite
        [[0.0, 0.0], [0.0, 1.0]],  # singular
        [[1.0, 0.5], [0.0, 1.0]],  # not symmetric
        [[float("nan"), 0.0], [0.0, 1.0]],
    ],
)
def test_check_intent_rejects_bad_covariance(cov):
    mean = torch.zeros(1, 2, 2, dtype=torch.float64)
    c = torch.eye(2, dtype=torch.float64).expand(1, 2, 2, 2).clone()
    c[0, 1] = torch.tensor(cov, dtype=torch.float64)
    which = torch.tensor([[True, True]])
    with pytest.raises(ValueError, match="positive"):
        check_intent(mean, c, which)
    # Not selected: not checked.
    check_intent(mean, c, torch.tensor([[True, False]]))
