"""Cost of the attention policy's encoder: the full encoder vs. reading only 1 + k rows.

The decoder of :class:`~maipp_bench.algos.attention.AttentionPolicyNet` reads the current
node's and the k neighbours' embeddings; ``encode`` runs the last encoder layer's queries
and feed-forward on those rows only, through ``attend_rows`` (the layer's attention
without its sequence-first copies, the same bits). This script times, side by side in one
run and on the same inputs, the network with the full encoder followed by a gather (what
version 1 of the policy computed), with ``encode`` calling the layer's own
``nn.MultiheadAttention`` (until 2026-11-26), and with ``encode`` as it is, for the two
shapes that matter:

* ``train``: forward + backward of a PPO minibatch (256 decision rows);
* ``ti``: inference forward of one TI(8, 5) rollout step for 30 deciding agents (240 rows).

``--bf16`` adds a second table: the network as it is in float32 against the same network
under CPU autocast to bfloat16 (matrix products in bf16, weights kept in float32: what a
mixed-precision trainer would run), with the relative error of the logits and values
against float32 (a lead for training speed, not a setting of the trainer).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/policy_forward.py [--repeats 5] [--nodes 201] [--bf16]
"""

from __future__ import annotations

import argparse
import platform
from unittest import mock

import torch
from bench_timing import seconds_per_call
from torch import nn

from maipp_bench.algos import attention
from maipp_bench.algos.attention import AttentionConfig, AttentionPolicyNet


def layer_attention(attn: nn.MultiheadAttention, query: torch.Tensor,
                    kv: torch.Tensor) -> torch.Tensor:
    """What ``encode`` called before ``attend_rows``: the layer's own module
    (sequence-first inside); patched in for ``attention.attend_rows`` to compare."""
    return attn(query, kv, kv, need_weights=False)[0]


def full_encode(net: AttentionPolicyNet, x: torch.Tensor, read: torch.Tensor) -> torch.Tensor:
    """Every node through every layer, then the rows the decoder reads."""
    return net.encoder(x).gather(1, read.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--nodes", type=int, default=201)
    p.add_argument("--k", type=int, default=20)
    p.add_argument("--bf16", action="store_true",
                   help="also time float32 against bfloat16 autocast")
    args = p.parse_args()
    torch.manual_seed(0)
    net = AttentionPolicyNet(AttentionConfig())
    read_only = net.encode

    def inputs(b: int):
        return (torch.rand(b, args.nodes, 6), torch.rand(b, args.nodes, 32),
                torch.randint(0, args.nodes, (b,)), torch.rand(b, 1),
                torch.randint(0, args.nodes, (b, args.k)),
                torch.ones(b, args.k, dtype=torch.bool))

    train_in, ti_in = inputs(256), inputs(240)

    def train_step():
        logits, value, _ = net(*train_in)
        (logits.logsumexp(-1).sum() + value.sum()).backward()

    def ti_step():
        with torch.no_grad():
            net(*ti_in)

    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, "
          f"{torch.get_num_threads()} torch thread(s), N = {args.nodes}, k = {args.k}")
    print("| shape | full encoder (s) | read rows, layer's attention (s) | read rows, "
          "row attention (s) | speed-up over full | over layer's attention |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, fn in (("train: fwd + bwd, 256 rows", train_step),
                     ("ti: inference fwd, 240 rows", ti_step)):
        net.encode = lambda x, read: full_encode(net, x, read)  # noqa: E731
        full = seconds_per_call(fn, args.repeats)
        net.encode = read_only
        with mock.patch.object(attention, "attend_rows", layer_attention):
            layer = seconds_per_call(fn, args.repeats)
        fast = seconds_per_call(fn, args.repeats)
        print(f"| {name} | {full:.3f} | {layer:.3f} | {fast:.3f} | {full / fast:.1f}x | "
              f"{layer / fast:.2f}x |")
    if args.bf16:
        bf16_table(net, train_in, ti_in, args.repeats)


def relative_error(out: torch.Tensor, ref: torch.Tensor) -> float:
    """||out - ref|| / ||ref|| over the finite entries of ``ref`` (masked logits are -inf)."""
    keep = ref.isfinite()
    return float((out.float()[keep] - ref[keep]).norm() / ref[keep].norm())


def bf16_table(net: AttentionPolicyNet, train_in: tuple, ti_in: tuple, repeats: int) -> None:
    """Float32 against bfloat16 autocast, side by side on the same inputs; the backward
    pass runs outside autocast, as torch's AMP recipe has it."""
    def steps(precision: torch.dtype):
        on = precision == torch.bfloat16

        def train_step():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=on):
                logits, value, _ = net(*train_in)
                loss = logits.float().logsumexp(-1).sum() + value.float().sum()
            loss.backward()

        def ti_step():
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=on):
                net(*ti_in)

        return train_step, ti_step

    with torch.no_grad():
        logits, value, _ = net(*train_in)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            logits16, value16, _ = net(*train_in)
    print(f"\nbf16 autocast: relative error of the logits {relative_error(logits16, logits):.1e},"
          f" of the values {relative_error(value16, value):.1e} (256 rows)")
    print("| shape | float32 (s) | bf16 autocast (s) | speed-up |")
    print("|---|---:|---:|---:|")
    names = ("train: fwd + bwd, 256 rows", "ti: inference fwd, 240 rows")
    for name, f32_fn, b16_fn in zip(names, steps(torch.float32), steps(torch.bfloat16)):
        f32, b16 = seconds_per_call(f32_fn, repeats), seconds_per_call(b16_fn, repeats)
        print(f"| {name} | {f32:.3f} | {b16:.3f} | {f32 / b16:.2f}x |")

if __name__ == "__main__":
    main()
