#!/bin/bash
# Every figure docs/results.md writes up for a shipped two-hour draw, from its committed
# cards: wall stamps, per-stage throughput, the held-out choices, the protocol score and
# its margins against the baselines, and the counts over all draws.
#
# Usage: bash benchmarks/draw_figures.sh docs/cards/PREFIX [docs/cards/PREVIOUS_PREFIX]
#   PREVIOUS_PREFIX (the draw before) adds stage3_minutes.py's side-by-side calibration.
#   The counts come from draw_rate.py, which reads docs/results.md's table of draws: add
#   the draw's row first, or they are the counts before it.
set -euo pipefail
P=${1:?usage: draw_figures.sh docs/cards/PREFIX [docs/cards/PREVIOUS_PREFIX]}
cd "$(dirname "$0")/.."  # PREFIX paths are relative to the repository root
[ -f "$P.json" ] || { echo "draw_figures.sh: no card $P.json (ship the draw first)" >&2; exit 2; }
py() { echo "+ python $*"; python "$@"; }
show() { echo "+ $1"; python -c "import json,sys; d=json.load(open(sys.argv[1])); d.pop('curve', None); print(json.dumps(d, indent=1))" "$1"; }

cat "${P}_wall.txt"
for s in "${P}_stages12.jsonl" "${P}_m1_stages12.jsonl"; do
  [ -f "$s" ] && py benchmarks/train_throughput.py --card "$s" --split stages
done
[ $# -ge 2 ] && py benchmarks/stage3_minutes.py --calibrate "$2" "$P"
for f in "${P}_start_choice.json" "${P}_deadline.json" "${P}_choice.json" "$P.json"; do
  [ -f "$f" ] && show "$f"
done
# The docs' "kept X by D" and "N standard errors" of each held-out choice.
for f in "${P}_start_choice.json" "${P}_choice.json"; do
  [ -f "$f" ] && py benchmarks/select_snapshot.py --show "$f"
done
# The stage-3 snapshot card set aside by the final choice carries run_continued_to.
for f in "$P.json" "${P}_stage3_start.json" "${P}_stage3_avg.json"; do
  [ -f "$f" ] && py benchmarks/train_throughput.py --card "$f"
done
[ -f "${P}_score.txt" ] && cat "${P}_score.txt"
if [ -d "${P}_board" ]; then
  py benchmarks/board_table.py --suite risk_aware --leaderboards "${P}_board"
  py benchmarks/board_diff.py --suite risk_aware --method ours_ti --method-from "${P}_board" \
    --against sga_rrt_0.3_0.4 greedy catnipp_ti catnipp_greedy oracle
fi
[ -d "${P}_b5_results" ] && py benchmarks/paired_subset.py --subset "${P}_b5_results" \
  --results docs/cards/catnipp_ti_risk_aware_b5_results --method ours_ti --against catnipp_ti
echo "(draw_rate.py counts the rows of docs/results.md's table of draws; add this draw's row first)"
py benchmarks/draw_rate.py
