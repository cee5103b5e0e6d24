"""Two training curves side by side: how many leading updates agree in every field but
wall time (a seed replayed), the wall-time ratio at the end of that stretch, and one
field's mean over windows of updates of each curve.

Curves are run folders, ``curve.jsonl`` files or checkpoint cards, as
``python -m maipp_bench.curves`` reads them.

Usage:
    python benchmarks/curve_compare.py docs/cards/ours_2h_intent_seed2.json \
        docs/cards/ours_2h_intent_seed2_lr3e-5.json --key reward_per_decision --window 10
"""

from __future__ import annotations

import argparse

from maipp_bench.curves import read_curve


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--key", default="reward_per_decision")
    p.add_argument("--window", type=int, default=10)
    args = p.parse_args()
    a, b = read_curve(args.a), read_curve(args.b)
    same = 0
    for ra, rb in zip(a, b):
        if {k: v for k, v in ra.items() if k != "wall_s"} != \
                {k: v for k, v in rb.items() if k != "wall_s"}:
            break
        same += 1
    print(f"first {same} updates agree in every field but wall_s "
          f"(of {len(a)} and {len(b)})")
    if same:
        print(f"  wall_s at update {a[same - 1]['update']}: {a[same - 1]['wall_s']:.0f} s "
              f"and {b[same - 1]['wall_s']:.0f} s (b / a = "
              f"{b[same - 1]['wall_s'] / a[same - 1]['wall_s']:.3f})")
    w = args.window
    for name, rows in (("a", a), ("b", b)):
        means = [sum(r[args.key] for r in rows[i:i + w]) / len(rows[i:i + w])
                 for i in range(0, len(rows), w)]
        print(f"{name}: mean {args.key} per {w} updates: "
              + " ".join(f"{m:.4f}" for m in means))


if __name__ == "__main__":
    main()
