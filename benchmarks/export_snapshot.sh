#!/usr/bin/env bash
# A training checkpoint or one of its kept snapshots as a policy file with its JSON card
# (python -m maipp_bench.train ... export=), for the held-out choices of train_2h.sh and
# final_choice.sh: SNAPSHOT is RUN/checkpoint.pt (the run's last update) or
# RUN/snapshots/update_NNNN.pt (that update, read through RUN/checkpoint.pt's config).
# The card goes beside OUT_PT (OUT_PT with .json); NOTE says how the update was chosen.
# Usage: bash benchmarks/export_snapshot.sh SNAPSHOT OUT_PT EXPORT_DIR NOTE
set -euo pipefail
SNAPSHOT=${1:?usage: export_snapshot.sh SNAPSHOT OUT_PT EXPORT_DIR NOTE}
OUT_PT=${2:?usage: export_snapshot.sh SNAPSHOT OUT_PT EXPORT_DIR NOTE}
EXPORT_DIR=${3:?usage: export_snapshot.sh SNAPSHOT OUT_PT EXPORT_DIR NOTE}
NOTE=${4:?usage: export_snapshot.sh SNAPSHOT OUT_PT EXPORT_DIR NOTE}
if [[ $SNAPSHOT =~ ^(.*)/snapshots/update_0*([0-9]+)\.pt$ ]]; then
    RUN=${BASH_REMATCH[1]} FROM=${BASH_REMATCH[2]}
else
    RUN=$(dirname "$SNAPSHOT") FROM=last
fi
python -m maipp_bench.train algo=ours total_updates=0 threads=2 progress=false \
    resume="$RUN/checkpoint.pt" export="$OUT_PT" export_from="$FROM" \
    hydra.run.dir="$EXPORT_DIR" "export_note='$NOTE'"
