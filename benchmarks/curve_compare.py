"""Two training curves side by side: how many leading updates agree in every field but
wall time (a seed replayed), the wall-time ratio at the end of that stretch, and one
field's mean over windows of each curve: windows of updates, or of env frames
(``--frames-bin``) to compare runs of different batch sizes.

Curves are run folders, ``curve.jsonl`` files or checkpoint cards, as
``python -m maipp_bench.curves`` reads them. ``--key update_s`` is derived: the seconds
of each update (the step of the cumulative ``wall_s``). Fields that are means over the
episodes that ended in an update (``trace_final``, ``traps``) are averaged weighted by
those episodes, so that updates in which none ended (NaN: with ``reset_every`` > 1 the
first updates after a fresh start) count nothing.

Usage:
    python benchmarks/curve_compare.py docs/cards/ours_2h_intent_seed2.json \
        docs/cards/ours_2h_intent_seed2_lr3e-5.json --key reward_per_decision --window 10
    python benchmarks/curve_compare.py docs/cards/ours_gpu_h200_seed0.json \
        docs/cards/ours_2h_intent_seed3_lr3e-5_stages12.jsonl --frames-bin 100000
"""

from __future__ import annotations

import argparse
import math

from maipp_bench.curves import read_curve


def values(rows: list[dict], key: str) -> list[float]:
    if key == "update_s":
        walls = [0.0] + [r["wall_s"] for r in rows]
        return [b - a for a, b in zip(walls, walls[1:])]
    return [r[key] for r in rows]


PER_EPISODE = ("trace_final", "traps")  # means over the episodes ended in the update


def weights(rows: list[dict], key: str) -> list[float]:
    """Each update's weight in a window mean: the episodes that ended in it for
    :data:`PER_EPISODE` fields (the step of the cumulative ``episodes``), else 1."""
    if key not in PER_EPISODE:
        return [1.0] * len(rows)
    ended = [0] + [r["episodes"] for r in rows]
    return [float(b - a) for a, b in zip(ended, ended[1:])]


def window_means(rows: list[dict], key: str, window: int, frames_bin: int) -> dict[str, float]:
    """Mean of ``key`` per ``window`` updates, or per ``frames_bin`` env frames if given."""
    groups: dict[str, list[tuple[float, float]]] = {}
    for i, (row, v, w) in enumerate(zip(rows, values(rows, key), weights(rows, key))):
        if frames_bin:
            end = ((row["frames"] - 1) // frames_bin + 1) * frames_bin
            label = f"<={end // 1000}k"
        else:
            label = f"{i // window * window + 1}-"
        groups.setdefault(label, []).append((v, w))
    return {label: (sum(v * w for v, w in vw if w) / total if (total := sum(w for _, w in vw))
                    else math.nan) for label, vw in groups.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--key", default="reward_per_decision")
    p.add_argument("--window", type=int, default=10, help="updates per window")
    p.add_argument("--frames-bin", type=int, default=0, help="env frames per window "
                   "(instead of --window)")
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
    unit = f"{args.frames_bin} frames" if args.frames_bin else f"{args.window} updates"
    for name, rows in (("a", a), ("b", b)):
        means = window_means(rows, args.key, args.window, args.frames_bin)
        print(f"{name}: mean {args.key} per {unit}: "
              + " ".join(f"{label} {m:.4f}" for label, m in means.items()))


if __name__ == "__main__":
    main()
