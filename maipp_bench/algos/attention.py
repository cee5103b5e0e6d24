"""The paper's attention policy network (encoder-decoder with a pointer head).

Paper Sec. III-C and the reference code: node features embedded to 128 dims plus a
Laplacian positional encoding (32 eigenvectors of the symmetric normalised Laplacian of
the roadmap); pre-LayerNorm self-attention over all nodes; a decoder that concatenates the
remaining budget and the interest threshold to the current node's embedding and projects
back to 128, runs an LSTM cell over the agent's trajectory, attends over the k neighbour
slots and scores them with a pointer head (10 tanh clipping, masked logits); a value head.

Only the network lives here; training (issue 5) wires it to TorchRL.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from maipp_bench.envs.maipp_env import NODE_FEATURES
from maipp_bench.envs.roadmap import laplacian_encoding  # noqa: F401  (re-exported)

# Which node features each method sees (paper: ours adds risk and intent to CAtNIPP's).
FEATURE_SETS: dict[str, tuple[str, ...]] = {
    "ours": ("x", "y", "interest_mean", "interest_std", "risk_ucb", "intent"),
    "catnipp": ("x", "y", "interest_mean", "interest_std"),
}


def feature_columns(feature_set: str) -> list[int]:
    """Column indices of ``NODE_FEATURES`` used by a feature set (ValueError if unknown)."""
    if feature_set not in FEATURE_SETS:
        raise ValueError(f"unknown feature set {feature_set!r}; valid: {sorted(FEATURE_SETS)}")
    return [NODE_FEATURES.index(name) for name in FEATURE_SETS[feature_set]]


@dataclass(frozen=True)
class AttentionConfig:
    """Network sizes (reference code: 128 dims, 4 heads, feed-forward 512, 32 PE dims)."""

    n_features: int = len(FEATURE_SETS["ours"])
    embed_dim: int = 128
    heads: int = 4
    ff_dim: int = 512
    encoder_layers: int = 1
    pe_dim: int = 32
    clip: float = 10.0


class AttentionPolicyNet(nn.Module):
    """Masked pointer logits over the k neighbour slots, and a state value.

    Example:
        >>> net = AttentionPolicyNet(AttentionConfig(n_features=4, encoder_layers=1))
        >>> x, pe = torch.rand(2, 30, 4), torch.rand(2, 30, 32)
        >>> cur, nbr = torch.zeros(2, dtype=torch.long), torch.randint(0, 30, (2, 6))
        >>> mask = torch.ones(2, 6, dtype=torch.bool)
        >>> logits, value, state = net(x, pe, cur, torch.rand(2, 1), nbr, mask)
        >>> logits.shape, value.shape
        (torch.Size([2, 6]), torch.Size([2, 1]))
    """

    def __init__(self, cfg: AttentionConfig = AttentionConfig(), threshold: float = 0.4):
        super().__init__()
        d = cfg.embed_dim
        self.cfg, self.threshold = cfg, threshold
        self.embed = nn.Linear(cfg.n_features, d)
        self.pos = nn.Linear(cfg.pe_dim, d)
        layer = nn.TransformerEncoderLayer(d, cfg.heads, cfg.ff_dim, dropout=0.0,
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, cfg.encoder_layers,
                                             enable_nested_tensor=False)
        self.current = nn.Linear(d + 2, d)  # + remaining budget, interest threshold
        self.lstm = nn.LSTMCell(d, d)
        self.cross = nn.MultiheadAttention(d, cfg.heads, batch_first=True)
        self.query = nn.Linear(d, d)
        self.key = nn.Linear(d, d)
        self.value_head = nn.Linear(d, 1)

    def forward(
        self,
        features: torch.Tensor,
        pos_enc: torch.Tensor,
        current: torch.Tensor,
        budget: torch.Tensor,
        neighbors: torch.Tensor,
        mask: torch.Tensor,
        state: tuple[torch.Tensor, torch.Tensor] | None = None,
        positions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Logits ``[B, k]`` (masked slots -inf), value ``[B, 1]``, new LSTM state.

        Args:
            features: ``[B, N, F]`` node features (a feature set's columns).
            pos_enc: ``[B, N, pe_dim]`` Laplacian encoding of the roadmap.
            current: ``[B]`` current node index.
            budget: ``[B, 1]`` remaining budget fraction.
            neighbors: ``[B, k]`` node index of each slot.
            mask: ``[B, k]`` bool feasibility mask (at least one True per row).
            state: LSTM ``(h, c)`` of the agent's trajectory so far, ``[B, 128]`` each.
            positions: ``self.pos(pos_enc)`` ``[B, N, d]``, for a caller that already has
                it (TI's rollouts keep one roadmap for all their steps); ``pos_enc`` is
                then not read.
        """
        read = torch.cat([current.unsqueeze(-1), neighbors], -1)  # [B, 1 + k]
        if positions is None:
            positions = self.pos(pos_enc)
        h = self.encode(self.embed(features) + positions, read)  # [B, 1 + k, d]
        cur, nbr = h[:, 0], h[:, 1:]
        thr = torch.full_like(budget, self.threshold)
        cur = self.current(torch.cat([cur, budget, thr], -1))
        state = self.lstm(cur, state)
        q = state[0]
        ctx, _ = self.cross(q.unsqueeze(1), nbr, nbr, key_padding_mask=~mask)
        ctx = ctx.squeeze(1) + q
        scores = (self.query(ctx).unsqueeze(1) * self.key(nbr)).sum(-1)
        # float32 under autocast too (identity otherwise): bf16 would round logits near
        # the clip to ~0.04, noise in PPO's ratio between collection and loss
        logits = self.cfg.clip * torch.tanh(scores.float() / math.sqrt(h.shape[-1]))
        logits = logits.masked_fill(~mask, -torch.inf)
        return logits, self.value_head(ctx), state

    def encode(self, x: torch.Tensor, read: torch.Tensor) -> torch.Tensor:
        """The encoder's output ``[B, R, d]`` at the node indices ``read`` ``[B, R]`` only.

        The decoder reads 1 + k of the N node embeddings, so the last layer runs its
        queries and feed-forward on those rows alone (keys and values still span all
        nodes): the same function as ``self.encoder(x)[read]`` in a quarter to a fifth of
        the time for one layer over 201 nodes (``benchmarks/policy_forward.py``; tested
        against the full encoder). Written for the pre-LN, dropout-free layers built above.
        """
        *full, last = self.encoder.layers
        for layer in full:
            x = layer(x)
        rows = read.unsqueeze(-1).expand(-1, -1, x.shape[-1])
        kv = last.norm1(x)
        y = x.gather(1, rows)
        y = y + attend_rows(last.self_attn, kv.gather(1, rows), kv)
        return y + last.linear2(last.activation(last.linear1(last.norm2(y))))


def attend_rows(attn: nn.MultiheadAttention, query: torch.Tensor,
                kv: torch.Tensor) -> torch.Tensor:
    """``attn(query, kv, kv)[0]`` without the module's sequence-first layout: the same bits
    in float32 on CPU (tested) with no copy of the transposed input or of the ``[B, N, 2d]``
    key and value projections (a quarter of a training pass, 1/7 of a TI pass).

    Args:
        attn: the layer whose weights are used: ``batch_first=True``, in-projection bias,
            one embedding size, no ``add_bias_kv`` / ``add_zero_attn``, and no dropout
            while training (what the encoder builds; anything else is a ValueError).
        query: ``[B, R, d]`` rows that attend.
        kv: ``[B, N, d]`` rows attended over (keys and values are the same tensor).
    """
    if not (attn.batch_first and attn._qkv_same_embed_dim and attn.in_proj_bias is not None
            and attn.bias_k is None and not attn.add_zero_attn
            and not (attn.training and attn.dropout > 0)):
        raise ValueError("attend_rows computes a batch-first nn.MultiheadAttention with an "
                         "in-projection bias, one embedding size, no add_bias_kv / "
                         "add_zero_attn and no dropout while training")
    b, r, d = query.shape
    n, heads = kv.shape[1], attn.num_heads
    w, bias = attn.in_proj_weight, attn.in_proj_bias
    q = nn.functional.linear(query, w[:d], bias[:d]).view(b, r, heads, d // heads)
    # nn.MultiheadAttention projects keys and values with one matmul, then adds the bias.
    # The bias takes the product's dtype first: under bf16 autocast an in-place add of a
    # float32 bias into the bf16 product took longer on CPU than the matmul itself
    # (docs/performance.md); a no-op cast in float32, whose bits stay the module's.
    k_v = torch.matmul(kv, w[d:].t())
    k_v.add_(bias[d:].to(k_v.dtype))
    k, v = k_v.view(b, n, 2, heads, d // heads).permute(2, 0, 3, 1, 4).unbind(0)
    out = nn.functional.scaled_dot_product_attention(q.transpose(1, 2), k, v)
    return attn.out_proj(out.transpose(1, 2).reshape(b, r, d))
