"""Interpolate two policy files of one network: ``alpha * A + (1 - alpha) * B``.

The weight-space interpolation tried in docs/results.md ("Weight averaging"): a
fine-tune (A) and the network it started from (B). The output keeps A's file otherwise
(configs, curve, commands), so it loads wherever A does.

Usage:
    python benchmarks/interpolate_weights.py maipp_bench/checkpoints/ours_v4.pt \\
        maipp_bench/checkpoints/ours_v3.pt --alpha 0.5 --out outputs/avg/avg50.pt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from maipp_bench.algos.checkpoint import average_policies


def main() -> None:
    """Write the interpolated policy file."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--alpha", type=float, required=True, help="weight of A, in [0, 1]")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    if not 0.0 <= args.alpha <= 1.0:
        p.error(f"--alpha {args.alpha}: must be in [0, 1]")
    mixed = average_policies([args.a, args.b], weights=[args.alpha, 1 - args.alpha])
    out = torch.load(args.a, weights_only=False) | {"core": mixed["core"]}  # A's file
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, args.out)


if __name__ == "__main__":
    main()
