#!/usr/bin/env bash
# The compute goal's GPU form (docs/results.md): the ours recipe from scratch on one lent
# GPU inside ONE device call (a command runs at most 10 minutes and a session has 15 minutes
# of device time, start-up included), every choice fixed before it starts:
#   one stage, the paper's PPO defaults (Adam 1e-4, minibatch 256, 8 epochs) with the
#   paper's TI(8, 5) intents in collection from the first update, N_ENVS envs of 160 steps
#   per update; no held-out evaluation; the policy file is the last update.
# On the GPU collection is bound by launch latency, not by envs (docs/performance.md: 64 and
# 256 envs collect in 8 and 13 s), so a wide batch costs little more per update than a
# narrow one; learning grows with it. But per env frame 128 envs learned far less than the
# CPU's 8-16 in the first run (2026-11-26, docs/results.md "The recipe on one lent GPU"):
# PPO's progress comes from the number of updates. So N_ENVS defaults to 16 since then
# (the CPU recipe's stage 2-3 width; 128 in that first run), chosen from its training curves.
# Usage: bash benchmarks/train_gpu.sh OUT_DIR [SEED] [MINUTES] [N_ENVS] [OVERRIDE ...]
# MINUTES is train's max_minutes (update time; start-up and saves come on top, and the
# update that crosses it still ends). Further arguments are Hydra overrides and win over
# the script's (a CPU smoke test: device=cpu env=tiny; no intents: algo.intent_rollouts=0).
set -euo pipefail
OUT=${1:?usage: train_gpu.sh OUT_DIR [SEED] [MINUTES] [N_ENVS] [OVERRIDE ...]}
SEED=${2:-0}
MINUTES=${3:-6.5}
N_ENVS=${4:-16}
[[ $SEED =~ ^[0-9]+$ ]] || { echo "train_gpu.sh: SEED must be an integer, got '$SEED'" >&2; exit 2; }
[[ $MINUTES =~ ^[0-9]+([.][0-9]+)?$ ]] && [[ ! $MINUTES =~ ^0+([.]0+)?$ ]] \
    || { echo "train_gpu.sh: MINUTES must be a positive number, got '$MINUTES'" >&2; exit 2; }
[[ $N_ENVS =~ ^[1-9][0-9]*$ ]] \
    || { echo "train_gpu.sh: N_ENVS must be a positive integer, got '$N_ENVS'" >&2; exit 2; }
mkdir -p "$OUT"
echo "start $(date -u +%FT%TZ)" | tee "$OUT/wall.txt"
python -m maipp_bench.train algo=ours device=cuda threads=1 \
    seed="$SEED" n_envs="$N_ENVS" algo.intent_rollouts=8 algo.intent_depth=5 \
    max_minutes="$MINUTES" total_updates=100000 checkpoint_every=1 eval_every=0 \
    progress=false hydra.run.dir="$OUT/run" export="$OUT/policy.pt" export_from=last \
    "export_note='benchmarks/train_gpu.sh: the last update, fixed before the run'" "${@:5}"
echo "end $(date -u +%FT%TZ)" | tee -a "$OUT/wall.txt"
