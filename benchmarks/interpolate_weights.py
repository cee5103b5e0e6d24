"""Interpolate two policy files of one network: ``alpha * A + (1 - alpha) * B``.

The weight-space interpolation tried in docs/results.md ("Weight averaging"): a
fine-tune (A) and the network it started from (B). The output keeps A's file otherwise
(configs, curve, commands), so it loads wherever A does.

Usage:
    python benchmarks/interpolate_weights.py maipp_bench/checkpoints/ours.pt \\
        maipp_bench/checkpoints/ours_v3.pt --alpha 0.5 --out outputs/avg/avg50.pt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch


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
    a = torch.load(args.a, weights_only=False)
    b = torch.load(args.b, weights_only=False)
    if {k: v.shape for k, v in a["core"].items()} != {k: v.shape for k, v in b["core"].items()}:
        p.error(f"{args.a} and {args.b} hold different networks")
    out = dict(a)
    out["core"] = {k: args.alpha * a["core"][k] + (1 - args.alpha) * b["core"][k]
                   for k in a["core"]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, args.out)


if __name__ == "__main__":
    main()
