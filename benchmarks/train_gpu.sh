#!/usr/bin/env bash
# The compute goal's GPU form (docs/results.md): the ours recipe from scratch on one lent
# GPU inside ONE device call (a command runs at most 10 minutes and a session has 15 minutes
# of device time, start-up included), every choice fixed before it starts:
#   one stage, the paper's PPO defaults (Adam 1e-4, minibatch 256, 8 epochs) with the
#   paper's TI(8, 5) intents in collection from the first update, 2,560 env frames per
#   update as N_ENVS envs of 2560 / N_ENVS steps, every env starting fresh episodes every
#   160 env steps (reset_every = 160 / steps); no held-out evaluation; the policy file is
#   the last update.
# On the GPU an env step costs about the same at any width (bound by launches on the
# host), so the update's frames are cheapest as few wide steps: 128 envs x 20 steps took
# 2.3 s an update against 10.4 s for 16 x 160 (2026-12-04, H200, docs/performance.md
# "A fifth lent GPU: wide, short batches"). The frames per update and the steps between fresh starts are
# what 16 x 160 collects (PPO's progress comes from the number of updates: the first GPU
# run's 128 x 160 = 20,480-frame updates learned far less per frame, 2026-11-26,
# docs/results.md "The recipe on one lent GPU"). N_ENVS=16 is the recipe of the runs of
# 2026-11-26 (16 x 160, a fresh start every update). A run with 128 x 20 that restarted
# episodes every update (before reset_every existed) trained on their first 20 steps only.
# Usage: bash benchmarks/train_gpu.sh OUT_DIR [SEED] [MINUTES] [N_ENVS] [OVERRIDE ...]
# N_ENVS (default 128) must divide 2560 with a step count that divides 160: 16, 32, 64,
# 128, 256, 512, ... MINUTES is train's max_minutes (update time; start-up and saves come
# on top, and the update that crosses it still ends). Further arguments are Hydra
# overrides and win over the script's (a CPU smoke test: device=cpu env=tiny; no
# intents: algo.intent_rollouts=0).
set -euo pipefail
OUT=${1:?usage: train_gpu.sh OUT_DIR [SEED] [MINUTES] [N_ENVS] [OVERRIDE ...]}
SEED=${2:-0}
MINUTES=${3:-6.5}
N_ENVS=${4:-128}
[[ $SEED =~ ^[0-9]+$ ]] || { echo "train_gpu.sh: SEED must be an integer, got '$SEED'" >&2; exit 2; }
[[ $MINUTES =~ ^[0-9]+([.][0-9]+)?$ ]] && [[ ! $MINUTES =~ ^0+([.]0+)?$ ]] \
    || { echo "train_gpu.sh: MINUTES must be a positive number, got '$MINUTES'" >&2; exit 2; }
[[ $N_ENVS =~ ^[1-9][0-9]*$ ]] \
    || { echo "train_gpu.sh: N_ENVS must be a positive integer, got '$N_ENVS'" >&2; exit 2; }
STEPS=$((2560 / N_ENVS))
((N_ENVS * STEPS == 2560 && STEPS > 0 && 160 % STEPS == 0)) \
    || { echo "train_gpu.sh: N_ENVS must divide 2560 frames per update into steps that divide 160 (e.g. 16, 32, 64, 128, 256), got '$N_ENVS'" >&2; exit 2; }
RESET=$((160 / STEPS))
mkdir -p "$OUT"
echo "start $(date -u +%FT%TZ)" | tee "$OUT/wall.txt"
python -m maipp_bench.train algo=ours device=cuda threads=1 \
    seed="$SEED" n_envs="$N_ENVS" steps_per_batch="$STEPS" reset_every="$RESET" \
    algo.intent_rollouts=8 algo.intent_depth=5 \
    max_minutes="$MINUTES" total_updates=100000 checkpoint_every="$RESET" eval_every=0 \
    progress=false hydra.run.dir="$OUT/run" export="$OUT/policy.pt" export_from=last \
    "export_note='benchmarks/train_gpu.sh: the last update, fixed before the run'" "${@:5}"
echo "end $(date -u +%FT%TZ)" | tee -a "$OUT/wall.txt"
