"""TI(a, j) evaluation with the encoder's row attention against the layer's own.

``AttentionPolicyNet.encode`` calls :func:`~maipp_bench.algos.attention.attend_rows`, the
``nn.MultiheadAttention`` function for keys = values without its sequence-first copies
(the same bits in float32). This script plays the same protocol episodes (the suite's
first ``--instances`` instances, its first trial) with a learned TI method through both,
alternating which goes first over ``--pairs`` pairs, and reports the planning seconds and
whether every episode's Tr(P_f) is identical, both ways and to the committed board's spot
check of that row (the same episodes when ``--instances`` is the suite's 30).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/ti_row_attention.py --suite risk_aware \
        --method ours_ti --budgets 2 5
"""

from __future__ import annotations

from unittest import mock

from policy_forward import layer_attention
from ti_distinct_paths import ProtocolEpisodes, ti_parser

from maipp_bench.algos import attention


def main() -> None:
    p = ti_parser(__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=2)
    args = p.parse_args()
    episodes = ProtocolEpisodes(args)
    print(f"{args.pairs} pairs, alternating order")
    for setting in episodes.settings:
        walls: dict[str, float] = {"layer": 0.0, "rows": 0.0}
        traces = {}
        for i in range(args.pairs):
            for way in (("layer", "rows") if i % 2 == 0 else ("rows", "layer")):
                fn = layer_attention if way == "layer" else attention.attend_rows
                with mock.patch.object(attention, "attend_rows", fn):
                    out = episodes.play(setting)
                walls[way] += out["wall"] / args.pairs
                traces.setdefault(way, out["trace"])
                assert out["trace"] == traces[way], "a replay changed its own episodes"
        same = "identical" if traces["layer"] == traces["rows"] else "DIFFERENT"
        same += episodes.same_as_board(setting, traces["rows"])
        print(f"  {setting.key}: layer's attention {walls['layer']:6.1f} s | row attention "
              f"{walls['rows']:6.1f} s | {walls['layer'] / walls['rows']:.2f}x, Tr(P_f) {same}")


if __name__ == "__main__":
    main()
