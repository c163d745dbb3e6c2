#!/usr/bin/env bash
# Training against the PyTorch reference, eager and compiled, on one GPU in one run: the comparison of
# docs/performance.md's "Training now" table.
#
#   launchers/training-parity.sh TORCH_UMGEN_PY [GPU]
#
# For the `small` and `paper` presets: PyTorch eager and compiled (dev/kernel-bench/scripts/torch-time-step.py:
# the median of 10 timed steps, tokens/s and the peak allocation), then umgen's step ($TRAIN_BENCH --preset P:
# the median of 20 steps of `small`, 3 of `paper`, after 2 warm-up steps) with the pool it reserved, the live
# set at its peak and the MFU. With ALTERNATE=KEY=V1,V2 each preset's steps also take turns between those
# values of a kernel choice in one process (umgen-kernel-bench's `--alternate`, one step a turn). Ends with a table: umgen's
# tokens/s over each PyTorch mode's, and umgen's pool against PyTorch eager's peak allocation.
#
# TRAIN_BENCH: the command whose `--preset P --device cuda:GPU --steps N --warmup 2` times umgen's step
# (default `umgen-kernel-bench train`; `umgen bench train` works too, without ALTERNATE). SETS: more
# `--set KEY=VALUE` arguments for umgen. PRESETS (default "small paper"), OUT (default ./parity-out),
# LIMIT (seconds a run may take, default 600). Run from the repository root.
set -uo pipefail
torch_py=${1:?usage: launchers/training-parity.sh TORCH_UMGEN_PY [GPU]}
gpu=${2:-0}
read -r -a bench <<<"${TRAIN_BENCH:-umgen-kernel-bench train}"
read -r -a sets <<<"${SETS:-}"
presets=${PRESETS:-small paper}
out=${OUT:-parity-out}
limit=${LIMIT:-600}
here=$(cd "$(dirname "$0")" && pwd)
timer="$here/../dev/kernel-bench/scripts/torch-time-step.py"
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh" >/dev/null
mkdir -p "$out"
# shellcheck source=launchers/timed-runs.sh
source "$here/timed-runs.sh"
steps_of() { [ "$1" = paper ] && echo 3 || echo 20; }
for p in $presets; do
    for mode in eager compiled; do
        flag=()
        [ "$mode" = compiled ] && flag=(--compile)
        CUDA_VISIBLE_DEVICES=$gpu run "torch-$p-$mode" python3 "$timer" "$torch_py" --preset "$p" "${flag[@]}" \
            --timed 10 --steps 1
    done
    run "umgen-$p" "${bench[@]}" --preset "$p" --device "cuda:$gpu" --steps "$(steps_of "$p")" --warmup 2 "${sets[@]}"
    if [ -n "${ALTERNATE:-}" ]; then
        # Turns of one step each: twice the plain run's steps, so that each value gets as many.
        run "alternate-$p" "${bench[@]}" --preset "$p" --device "cuda:$gpu" --steps "$((2 * $(steps_of "$p")))" \
            --warmup 4 --alternate "$ALTERNATE" "${sets[@]}"
    fi
done
# The numbers: PyTorch's "… X ms a step …, peak allocation Y GiB", umgen's "step X ms", "peak memory X GiB
# reserved", "live at peak X GiB" and "MFU X%".
first() { grep -h -o -E "$1" "$2" 2>/dev/null | head -1 | grep -o -E '[0-9]+(\.[0-9]+)?' | head -1; }
echo
echo "| preset | umgen step ms | pool GiB | live at peak GiB | MFU % | eager ms (peak GiB) | compiled ms (peak GiB) | umgen ÷ eager | umgen ÷ compiled | pool ≤ eager peak |"
echo "|---|---|---|---|---|---|---|---|---|---|"
for p in $presets; do
    u="$out/umgen-$p.txt" e="$out/torch-$p-eager.txt" c="$out/torch-$p-compiled.txt"
    step=$(first '^step +[0-9.]+ ms' "$u")
    pool=$(first '[0-9.]+ GiB reserved' "$u")
    live=$(first '^live at peak +[0-9.]+ GiB' "$u")
    mfu=$(first 'MFU [0-9.]+%' "$u")
    em=$(first '[0-9.]+ ms a step \(median' "$e") ep=$(first 'peak allocation [0-9.]+ GiB' "$e")
    cm=$(first '[0-9.]+ ms a step \(median' "$c") cp=$(first 'peak allocation [0-9.]+ GiB' "$c")
    # Same tokens a step on both sides, so the tokens/s ratio is the inverse ratio of the steps.
    awk -v p="$p" -v s="$step" -v pool="$pool" -v live="$live" -v mfu="$mfu" -v em="$em" -v ep="$ep" \
        -v cm="$cm" -v cp="$cp" 'function r(a, b) { return (a == "" || b == "") ? "-" : sprintf("%.2f×", a / b) }
        function v(a) { return a == "" ? "-" : a }
        BEGIN {
            fits = (pool == "" || ep == "") ? "-" : (pool + 0 <= ep + 0 ? "yes" : "no")
            printf "| %s | %s | %s | %s | %s | %s (%s) | %s (%s) | %s | %s | %s |\n", p, v(s), v(pool), v(live),
                v(mfu), v(em), v(ep), v(cm), v(cp), r(em, s), r(cm, s), fits
        }'
done
for f in "$out"/alternate-*.txt; do
    [ -f "$f" ] && { echo "-- $(basename "$f" .txt)"; grep -v -E 'INFO|WARN' "$f" | tail -n 6; }
done
