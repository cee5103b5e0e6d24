"""Do `sga_rrt`'s episodes turn on the last bits of its trees? (docs/protocol.md, "`sga_rrt`
v3").

Plays a setting's first-trial episodes twice: as the method runs, and with every RRT
grown from a root (and kept path) moved by one unit in the last place, which moves every
tree node by a few ulps (the tree's shape stays unless a nearest-node choice sat on a
tie; not checked). An episode that differs between the two (beyond eval's 1e-9) turned
on last bits, as it would between two CPUs that round one operation differently.
``--pre-v3`` plays both with the rule `sga_rrt` v2 had for a point at a branch's end
(clamped onto the last padding vertex, the root, when the branch had two or more), for
the measurement points and the executed goal, to show what v3 changed; ``--moved``
counts the real measurement points that the v2 rule would put elsewhere.

Patches live in this process only (a diagnostic: the method and its fingerprint are
unchanged).

Usage:
    python benchmarks/sga_end_points.py --method sga_rrt_0.9_1.0 --setting budget=2.0 --episodes 30
    python benchmarks/sga_end_points.py --method sga_rrt_0.3_0.4 --setting budget=2.0 \\
        --episodes 30 --pre-v3 --moved
"""

from __future__ import annotations

import argparse
import contextlib
import math

import torch
from sga_band_edges import sga_target

import maipp_bench.algos.paths as paths
import maipp_bench.algos.sga_rrt as sga
from maipp_bench.protocol.runner import run_chunk

_V3_POINTS_AT = paths.points_at
REL = 1e-9  # eval's tolerance: beyond it an episode took other decisions


def v2_points_at(points: torch.Tensor, cum: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """`paths.points_at` as `sga_rrt` v2 had it: no cap at the last real vertex."""
    d = points.shape[-2]
    seg = torch.searchsorted(cum.contiguous(), dist.contiguous(), right=True).clamp(1, d - 1) - 1
    return paths.along_segments(points, cum, dist, seg)


@contextlib.contextmanager
def patched(rule_v2: bool, nudge: bool, moved: list[int] | None):
    """The v2 end-point rule and/or one-ulp roots for every tree grown inside; ``moved``
    (if given) collects how many real measurement points the two rules place differently."""
    grow, measure = sga.SGARRTPolicy._grow, sga.measurement_points

    def grow_nudged(self, root, key, chain=None, chain_mask=None):
        up = torch.tensor(float("inf"), dtype=root.dtype)
        root = torch.nextafter(root, up)
        if chain is not None:
            chain = torch.nextafter(chain, up)
        return grow(self, root, key, chain, chain_mask)

    def measure_counted(points, mask, since, spacing, max_points):
        pts, valid = measure(points, mask, since, spacing, max_points)
        if not rule_v2 and moved is None:
            return pts, valid
        paths.points_at = v2_points_at
        try:
            old, _ = measure(points, mask, since, spacing, max_points)
        finally:
            paths.points_at = _V3_POINTS_AT
        if moved is not None:
            moved[0] += int(((pts != old).any(-1) & valid).sum())
        return (old, valid) if rule_v2 else (pts, valid)

    sga.measurement_points = measure_counted
    if rule_v2:
        sga.points_at = v2_points_at  # the executed goal, found along the best branch
    if nudge:
        sga.SGARRTPolicy._grow = grow_nudged
    try:
        yield
    finally:
        sga.SGARRTPolicy._grow, sga.measurement_points = grow, measure
        sga.points_at = _V3_POINTS_AT


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="risk_aware")
    p.add_argument("--method", required=True, help="an sga_rrt_<a>_<b> method")
    p.add_argument("--setting", required=True, help="a setting key of the suite")
    p.add_argument("--episodes", type=int, default=30, help="the suite's first N instances")
    p.add_argument("--pre-v3", action="store_true", help="play with v2's end-point rule")
    p.add_argument("--moved", action="store_true",
                   help="count real measurement points the v2 rule places elsewhere")
    args = p.parse_args()
    suite, setting, spec = sga_target(p, args)
    seeds = list(suite.instance_seeds[: args.episodes])
    torch.set_num_threads(1)
    rule = "v2 (pre-v3)" if args.pre_v3 else "v3"
    played = {}
    for nudge in (False, True):
        moved = [0] if args.moved else None
        with torch.inference_mode(), patched(args.pre_v3, nudge, moved):
            played[nudge] = run_chunk(spec, suite.env_config(setting), seeds,
                                      suite.trial_seeds[0])
        if args.moved:
            print(f"{'one-ulp roots' if nudge else 'as run'}: {moved[0]} real measurement "
                  "points the v2 rule places elsewhere")
    differ = [(a["instance"], a["trace"], b["trace"])
              for a, b in zip(played[False], played[True])
              if not math.isclose(a["trace"], b["trace"], rel_tol=REL, abs_tol=REL)]
    mean = [sum(r["trace"] for r in played[n]) / len(seeds) for n in (False, True)]
    print(f"{args.suite} {args.method} {args.setting}, first trial, {len(seeds)} episodes, "
          f"end-point rule {rule}: {len(differ)} differ (beyond {REL:g}) with one-ulp roots "
          f"(mean Tr(P_f) {mean[0]:.4f} as run, {mean[1]:.4f} nudged)")
    for inst, a, b in differ:
        print(f"  instance {inst:>7}  {a:.4f}  nudged {b:.4f}")


if __name__ == "__main__":
    main()
