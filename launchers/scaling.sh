#!/usr/bin/env bash
# Data-parallel scaling of the training step: `umgen bench train` on 1 GPU, then on K GPUs through
# `umgen launch`, with the same per-rank batch; prints tokens/s and efficiency = tokens/s(K) / (K · tokens/s(1)).
#
#   launchers/scaling.sh configs/small.toml "1 2 4"     # the preset's own batch per rank (small: 4, paper: 1)
#   DEVICE=cpu launchers/scaling.sh configs/tiny.toml "1 2" --steps 2 --warmup 1
#
# UMGEN (the binary), DEVICE (cuda or cpu) and MASTER_PORT may be set; extra arguments go to `bench train`.
set -euo pipefail
config=${1:?usage: scaling.sh CONFIG "K1 K2 ..." [bench train args]}
counts=${2:?usage: scaling.sh CONFIG "K1 K2 ..." [bench train args]}
shift 2
umgen=${UMGEN:-umgen}
device=${DEVICE:-cuda}
port=${MASTER_PORT:-29500}
base=""
printf '%6s %14s %14s %11s\n' ranks tokens/s step_ms efficiency
for k in $counts; do
    if [ "$k" = 1 ]; then
        dev=$device; [ "$device" = cuda ] && dev=cuda:0
        out=$("$umgen" bench train --config "$config" --device "$dev" "$@")
    else
        out=$("$umgen" launch --nproc-per-node "$k" --master-port "$port" -- \
            bench train --config "$config" --device "$device" "$@")
        port=$((port + 1))
    fi
    tps=$(printf '%s\n' "$out" | awk '/^throughput/ {print $2}')
    ms=$(printf '%s\n' "$out" | awk '/^step/ {print $2}')
    if [ -z "$tps" ]; then
        echo "scaling.sh: no throughput in the output for $k rank(s):" >&2
        printf '%s\n' "$out" >&2
        exit 1
    fi
    [ "$k" = 1 ] && base=$tps
    if [ -n "$base" ]; then
        eff=$(awk -v t="$tps" -v b="$base" -v k="$k" 'BEGIN {printf "%.1f%%", 100 * t / (k * b)}')
    else
        eff="-"
    fi
    printf '%6s %14s %14s %11s\n' "$k" "$tps" "$ms" "$eff"
done
