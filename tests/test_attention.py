"""The attention policy network: shapes, masking, Laplacian encoding, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from maipp_bench.algos.attention import (
    AttentionConfig,
    AttentionPolicyNet,
    attend_rows,
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


def test_laplacian_encoding_signs_do_not_hang_on_rounding(monkeypatch):
    """A symmetric roadmap (a path) has eigenvectors whose largest entries tie in magnitude
    with opposite signs; rounding, which differs with the batch and the device, must not
    pick the sign (it once did: a held-out episode played differently in another batch)."""
    n = 6  # path 0 - 1 - ... - 5: neighbour slots (i - 1, i + 1)
    idx = torch.arange(n)
    neighbors = torch.stack([(idx - 1).clamp_min(0), (idx + 1).clamp_max(n - 1)], -1)[None]
    valid = torch.stack([idx > 0, idx < n - 1], -1)[None]
    eigh = torch.linalg.eigh
    encodings = []
    for favoured in (slice(0, n // 2), slice(n // 2, n)):  # 1e-13: far below SIGN_TIE
        def rounded(lap, favoured=favoured):
            w, v = eigh(lap)
            v = v.clone()
            v[..., favoured, :] *= 1 + 1e-13
            return w, v

        monkeypatch.setattr(torch.linalg, "eigh", rounded)
        encodings.append(laplacian_encoding(neighbors, valid, dim=4))
    monkeypatch.undo()
    tied = encodings[0].abs()[0, :3] - encodings[0].abs()[0, 3:].flip(0)
    assert tied.abs().max() < 1e-9  # the path's vectors are (anti)symmetric: ties
    assert torch.allclose(encodings[0], encodings[1], rtol=0, atol=1e-12)
    peak = encodings[0].abs().amax(1, keepdim=True)
    first = (encodings[0].abs() >= peak - 1e-9).to(torch.uint8).argmax(1)
    assert (encodings[0][0, first[0], torch.arange(4)] > 0).all()  # the first tied entry


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


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-6), (torch.float64, 1e-12)])
def test_row_attention_is_the_layers_own(dtype, tol):
    # attend_rows skips nn.MultiheadAttention's sequence-first copies. Under MKL's default
    # kernels its float32 outputs are the layer's very bits; under the CPU-independent ones
    # the suite runs (tests/conftest.py) products of another layout round apart by ~1e-7.
    # The committed TI rows' recompute is checked directly (test_leaderboards.py).
    torch.manual_seed(0)
    attn = nn.MultiheadAttention(128, 4, batch_first=True).to(dtype)
    q = torch.randn(6, 9, 128, dtype=dtype)
    kv = torch.randn(6, 41, 128, dtype=dtype, requires_grad=True)
    with torch.no_grad():
        torch.testing.assert_close(attend_rows(attn, q, kv),
                                   attn(q, kv, kv, need_weights=False)[0], rtol=tol, atol=tol)
    out, ref = attend_rows(attn, q, kv), attn(q, kv, kv, need_weights=False)[0]
    torch.testing.assert_close(out, ref, rtol=tol, atol=tol)
    # Training differentiates through it: the same gradients.
    g = torch.randn_like(out)
    wrt = [kv, attn.in_proj_weight, attn.in_proj_bias, attn.out_proj.weight]
    grad_tol = max(tol, 1e-5)  # backward passes may sum in another order
    for got, want in zip(torch.autograd.grad(out, wrt, g), torch.autograd.grad(ref, wrt, g)):
        torch.testing.assert_close(got, want, rtol=grad_tol, atol=grad_tol)


def test_row_attention_under_bf16_autocast_is_the_layers_within_rounding():
    # algo.precision=bf16 runs it under autocast, where the key/value bias is added in
    # the product's bf16: close to the layer's own bf16 output and to float32's, with
    # gradients that still reach the bias.
    torch.manual_seed(0)
    attn = nn.MultiheadAttention(128, 4, batch_first=True)
    with torch.no_grad():
        attn.in_proj_bias.normal_()  # a bias large enough to matter
    q, kv = torch.randn(6, 9, 128), torch.randn(6, 41, 128)
    exact = attn(q, kv, kv, need_weights=False)[0]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = attend_rows(attn, q, kv)
        ref = attn(q, kv, kv, need_weights=False)[0]
    assert out.dtype == torch.bfloat16
    for got in (out, ref):
        rel = ((got.float() - exact).norm() / exact.norm()).item()
        assert 0 < rel < 2e-2
    (grad,) = torch.autograd.grad(out.float().sum(), attn.in_proj_bias)
    assert grad[256:].abs().sum() > 0  # the value bias moves the output (keys' cannot)


@pytest.mark.parametrize("layer", [dict(batch_first=False), dict(bias=False),
                                   dict(add_bias_kv=True), dict(add_zero_attn=True),
                                   dict(kdim=64, vdim=64), dict(dropout=0.1)])
def test_row_attention_refuses_layers_it_does_not_compute(layer):
    attn = nn.MultiheadAttention(128, 4, **{"batch_first": True, **layer})
    with pytest.raises(ValueError, match="attend_rows computes"):
        attend_rows(attn, torch.randn(2, 3, 128), torch.randn(2, 5, 128))


def test_a_given_position_embedding_replaces_the_encoding(obs):
    # TI's rollouts embed the roadmap's encoding once and pass it for every step.
    env, td = obs
    torch.manual_seed(0)
    net = AttentionPolicyNet(AttentionConfig(n_features=4, pe_dim=8))
    rm = env.episode.roadmap
    pe = laplacian_encoding(rm.neighbors, rm.neighbor_valid, dim=8).float()
    o = td["agents", "observation"]
    args = (o["current_node"][:, 0], o["budget"][:, 0].float(), o["neighbors"][:, 0],
            torch.ones(3, 8, dtype=torch.bool))
    x = o["node_features"][:, 0, :, feature_columns("catnipp")].float()
    with torch.no_grad():
        want = net(x, pe, *args)
        got = net(x, None, *args, positions=net.pos(pe))
    assert all(torch.equal(a, b) for a, b in zip(want[:2] + want[2], got[:2] + got[2]))
