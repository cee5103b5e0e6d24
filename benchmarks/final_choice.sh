#!/usr/bin/env bash
# FINAL=1 of benchmarks/train_2h.sh (2026-11-27; docs/results.md, "The final choice"): the
# run's policy file is chosen on held-out episodes at B = 4 and 5 (training's held-out
# seeds, never the protocol's) between two candidates, instead of being stage 3's uniform
# average by rule:
#   start.pt  stage 3's own start (the stage-2 update it fine-tuned): stage 3 lost ground
#             at B = 4-5 in one of the four bf16 draws scored against their start;
#   avg.pt    the uniform average of all of stage 3's snapshots (train_2h.sh's output),
#             the reference, which wins ties.
# B = 4-5 because B = 5 is where most draws trail or tie catnipp_ti and where stage 3
# moved the scores most; the score is the geometric mean over the two budgets of the mean
# Tr(P_f) (benchmarks/select_snapshot.py). The episodes are held-out seeds 160-223 (from
# FINAL_FIRST): SELECT=1 chose the start on seeds 0-159, which would favour it. Two
# candidates x 2 budgets x 64 episodes take about 4 minutes on the two cores. The
# chosen file and its card are copied to OUT_DIR/final.pt / final.json; the scores, with
# the choice's seconds, go to OUT_DIR/final_select.json. Runs on a finished train_2h.sh
# output too (the run's training is not touched), so that older draws can be re-scored.
# Run from the folder train_2h.sh ran in (the card's paths are relative to it).
# HELDOUT_SET: the held-out episode set (default 2; 1 replays the choices made before
# 2026-11-27's session 40 on one shared roadmap).
# FINAL_BUDGETS (default "4 5"; 2026-12-06): the budgets it scores on. Three of the eight
# WIDE=8 draws that missed to the fifty-sixth did so at B = 2 alone, which nothing after
# the start choice scores; "2 4 5" adds it.
# Usage: [FINAL_EPISODES=64] [FINAL_FIRST=160] [FINAL_BUDGETS="4 5"] [HELDOUT_SET=2] bash benchmarks/final_choice.sh OUT_DIR
set -euo pipefail
OUT=${1:?usage: final_choice.sh OUT_DIR}
EPISODES=${FINAL_EPISODES:-64}
FIRST=${FINAL_FIRST:-160}
HELDOUT_SET=${HELDOUT_SET:-2}
source "$(dirname "$0")/budgets.sh"
FINAL_BUDGETS=${FINAL_BUDGETS:-$FINAL_BUDGETS_DEFAULT}
check_budgets FINAL_BUDGETS "$FINAL_BUDGETS"
read -ra BUDGETS <<< "$FINAL_BUDGETS"
[[ $HELDOUT_SET == 1 || $HELDOUT_SET == 2 ]] \
    || { echo "final_choice.sh: HELDOUT_SET must be 1 or 2, got '$HELDOUT_SET'" >&2; exit 2; }
HERE=$(dirname "$0")
[[ -f $OUT/avg.json && -d $OUT/stage3/snapshots ]] \
    || { echo "final_choice.sh: $OUT is not a finished train_2h.sh run (no avg.json or stage3/snapshots/)" >&2; exit 2; }
# Stage 3's start, as its card records it.
START=$(python -c 'import json, sys; print(json.load(open(sys.argv[1])).get("init", {}).get("path", ""))' \
    "$OUT/avg.json")
[[ -f $START ]] || { echo "final_choice.sh: stage 3's start $START (as $OUT/avg.json records it) is not" \
    "there; run from the folder train_2h.sh ran in" >&2; exit 2; }
# The start as a policy file with its card: a snapshot of stage 2, or its last update.
bash "$HERE/export_snapshot.sh" "$START" "$OUT/start.pt" "$OUT/export_start" \
    "benchmarks/final_choice.sh: stage 3 of $OUT started from this network"
CHOSEN=$(python "$HERE/select_snapshot.py" --candidates "$OUT/start.pt" "$OUT/avg.pt" \
    --method ours_ti --budget "${BUDGETS[@]}" --episodes "$EPISODES" --first "$FIRST" --workers 2 \
    --heldout-set "$HELDOUT_SET" \
    --out "$OUT/final_select.json" | tail -1)
cp "$CHOSEN" "$OUT/final.pt"
cp "${CHOSEN%.pt}.json" "$OUT/final.json"
echo "final $CHOSEN $(date -u +%FT%TZ)" | tee -a "$OUT/wall.txt"
