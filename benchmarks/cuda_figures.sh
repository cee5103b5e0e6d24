#!/usr/bin/env bash
# The CUDA figures of docs/performance.md, in one call on a GPU machine:
#   bash benchmarks/cuda_figures.sh OUT_DIR [SECTION ...]
# Sections (default: all): check, env32, env64, profile, train, precision, shape. Each writes JSON and a log to OUT_DIR; a
# section that fails is reported and the next one still runs.
# - check: the CUDA tests (`pytest -m cuda`: the env, every method, training on CUDA).
# - env32, env64: benchmarks/env_throughput.py on CUDA in float32 / float64, for each E
#   of $ENVS (default 1024 4096 16384 32768).
# - profile: benchmarks/cuda_profile.py at E = 16384.
# - train: benchmarks/train_throughput.py on CUDA: ours at 64 and 256 envs, mappo at 64.
# - precision: the update of benchmarks/train_gpu.sh (ours, 16 envs, TI(8, 5) intents in
#   collection) in float32 and in bf16 (algo.precision), side by side, and their ratio.
# - shape: the same update's 2,560 env frames as 16 envs x 160 steps (train_gpu.sh's
#   width until 2026-12-04), 64 x 40 and 128 x 20 (its default since), side by side: collection on the GPU costs about the
#   same per env step at any width (bound by launches on the host), so fewer, wider steps
#   should shorten an update; their ratios to the first.
# Needs maipp_bench's dependencies importable (on a machine without network, install
# wheels first: docs/performance.md gives the command used).
set -u
out=${1:?usage: cuda_figures.sh OUT_DIR [SECTION ...]}
shift
sections=${*:-check env32 env64 profile train precision}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
py=${PYTHON:-python3}

run() {  # run NAME CMD...: tee the log, report failure, go on
    local name=$1
    shift
    echo "=== $name: $*"
    local t0=$SECONDS
    if "$@" > >(tee "$out/$name.log") 2>&1; then
        echo "=== $name ok ($((SECONDS - t0)) s)"
    else
        echo "=== $name FAILED ($((SECONDS - t0)) s)"
    fi
}

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/gpu.txt"
$py -c "import torch, torchrl, tensordict; print('torch', torch.__version__, 'torchrl', \
torchrl.__version__, 'tensordict', tensordict.__version__, torch.cuda.get_device_name())" \
    | tee -a "$out/gpu.txt"

for s in $sections; do
    case $s in
    check)
        run check_cuda $py -m pytest -q -p no:cacheprovider -m cuda tests ;;
    env32 | env64)  # one process per E: a batch too large for the card fails alone
        dt=float${s#env}
        for e in ${ENVS:-1024 4096 16384 32768}; do
            run "env_${dt}_$e" $py benchmarks/env_throughput.py --device cuda --dtype $dt \
                --envs $e --warmup 150 --steps 100 --ref-steps 150 --repeats 3 \
                --out "$out/env_${dt}_$e.json"
        done ;;
    profile)
        run profile $py benchmarks/cuda_profile.py --envs 16384 --out "$out/profile.txt" ;;
    train)
        for job in "ours 64 3" "ours 256 2" "mappo 64 2"; do  # algo, n_envs, timed updates
            set -- $job
            run "train_$1_$2" $py benchmarks/train_throughput.py algo=$1 device=cuda \
                n_envs=$2 --updates $3 --out "$out/train_$1_$2.json"
        done ;;
    precision)
        rm -f "$out"/train_ours_16_{float32,bf16}.json  # no ratio from an earlier call's files
        for p in float32 bf16; do
            run "train_ours_16_$p" $py benchmarks/train_throughput.py algo=ours device=cuda \
                threads=1 n_envs=16 algo.intent_rollouts=8 algo.intent_depth=5 \
                algo.precision=$p --updates 2 --out "$out/train_ours_16_$p.json"
        done
        run precision_ratio $py benchmarks/train_throughput.py \
            --ratio "$out/train_ours_16_float32.json" "$out/train_ours_16_bf16.json" ;;
    shape)
        shapes=${SHAPES:-"16x160 64x40 128x20"}
        for sh in $shapes; do
            rm -f "$out/shape_$sh.json"
            run "shape_$sh" $py benchmarks/train_throughput.py algo=ours device=cuda \
                threads=1 n_envs=${sh%x*} steps_per_batch=${sh#*x} algo.intent_rollouts=8 \
                algo.intent_depth=5 --updates 2 --out "$out/shape_$sh.json"
        done
        base=${shapes%% *}
        for sh in ${shapes#* }; do
            run "shape_ratio_$sh" $py benchmarks/train_throughput.py \
                --ratio "$out/shape_$base.json" "$out/shape_$sh.json"
        done ;;
    *) echo "unknown section $s" ;;
    esac
done
