# Sourced by benchmarks/train_2h.sh and benchmarks/final_choice.sh: the one check of a
# typed list of budgets (SELECT_BUDGETS, FINAL_BUDGETS), and the final choice's default.
FINAL_BUDGETS_DEFAULT="4 5"  # B = 5 is where most draws trail catnipp_ti; 4 beside it

check_budgets() {  # NAME VALUE: positive numbers, each once; exits the calling script
    local name=$1 b bs
    read -ra bs <<< "$2"
    for b in "${bs[@]}"; do
        [[ $b =~ ^[0-9]+([.][0-9]+)?$ ]] && [[ ! $b =~ ^0+([.]0+)?$ ]] \
            || { echo "${0##*/}: $name must be positive numbers, got '$b'" >&2; exit 2; }
    done
    ((${#bs[@]} >= 1)) && python -c "import sys; b = [float(x) for x in sys.argv[1:]]
sys.exit(len(set(b)) != len(b))" "${bs[@]}" \
        || { echo "${0##*/}: $name must name each budget once, got '$2'" >&2; exit 2; }
}
