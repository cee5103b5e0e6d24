"""The attention policy network: shapes, masking, Laplacian encoding, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from maipp_bench.algos.attention import (
    AttentionConfig,
    AttentionPolicyNet,
    feature_columns,
    laplacian_encoding,
)
from maipp_bench.envs import MAIPPConfig, MAIPPEnv


@pytest.fixture(scope="module")
def obs():
    env = MAIPPEnv(MAIPPConfig(n_agents=2, budget=1.0, n_nodes=40, k_neighbors=8),
                   batch_size=[3])
    td = env.reset()
    return env, td


def test_laplacian_encoding_matches_numpy(obs):
    env, _ = obs
    rm = env.episode.roadmap
    pe = laplacian_encoding(rm.neighbors, rm.neighbor_valid, dim=8)
    assert pe.shape == (3, 41, 8)
    # Independent check: symmetric normalised Laplacian eigenvectors with numpy.
    nbr, valid = rm.neighbors[0].numpy(), rm.neighbor_valid[0].numpy()
    a = np.zeros((41, 41))
    for i in range(41):
        a[i, nbr[i][valid[i]]] = 1
    a = ((a + a.T) > 0).astype(float)
    d = 1 / np.sqrt(a.sum(1))
    lap = np.eye(41) - d[:, None] * a * d[None, :]
    w, v = np.linalg.eigh(lap)
    assert abs(w[0]) < 1e-9  # connected graph: one zero eigenvalue
    for j in range(8):  # eigenvectors up to sign (eigenvalues here are distinct)
        col = pe[0, :, j].numpy()
        assert min(np.abs(col - v[:, j + 1]).max(), np.abs(col + v[:, j + 1]).max()) < 1e-8


@pytest.mark.parametrize("feature_set", ["ours", "catnipp"])
def test_policy_never_picks_a_masked_slot(obs, feature_set):
    env, td = obs
    torch.manual_seed(0)
    cols = feature_columns(feature_set)
    net = AttentionPolicyNet(AttentionConfig(n_features=len(cols), pe_dim=8))
    rm = env.episode.roadmap
    pe = laplacian_encoding(rm.neighbors, rm.neighbor_valid, dim=8).float()
    o = td["agents", "observation"]
    x = o["node_features"][:, 0, :, cols].float()
    mask = torch.rand(3, 8) < 0.5
    mask[:, 3] = True
    logits, value, state = net(x, pe, o["current_node"][:, 0], o["budget"][:, 0].float(),
                               o["neighbors"][:, 0], mask)
    assert logits.shape == (3, 8) and value.shape == (3, 1) and state[0].shape == (3, 128)
    assert torch.isinf(logits[~mask]).all() and torch.isfinite(logits[mask]).all()
    assert (logits[mask].abs() <= 10).all()
    samples = torch.distributions.Categorical(logits=logits).sample((500,))
    assert mask.gather(1, samples.T).all()
    assert mask[torch.arange(3), logits.argmax(-1)].all()
    (logits[mask].sum() + value.sum()).backward()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)


def test_unknown_feature_set_is_refused():
    with pytest.raises(ValueError, match="valid"):
        feature_columns("nope")


@pytest.mark.parametrize("layers", [1, 2])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_encoder_read_at_decoder_rows_equals_full_encoder(layers, dtype, tol):
    # The decoder reads 1 + k node embeddings; running the last layer's queries and
    # feed-forward on those rows only must be the same function as the full encoder.
    torch.manual_seed(0)
    net = AttentionPolicyNet(AttentionConfig(encoder_layers=layers)).to(dtype)
    x = torch.randn(5, 41, 128, dtype=dtype)
    read = torch.randint(0, 41, (5, 9))
    read[:, 1] = read[:, 0]  # a repeated index is read twice, as any gather would
    full = net.encoder(x).gather(1, read.unsqueeze(-1).expand(-1, -1, 128))
    torch.testing.assert_close(net.encode(x, read), full, rtol=tol, atol=tol)
    with torch.no_grad():  # the inference fast path of nn.TransformerEncoder as well
        full = net.encoder(x).gather(1, read.unsqueeze(-1).expand(-1, -1, 128))
        torch.testing.assert_close(net.encode(x, read), full, rtol=tol, atol=tol)
