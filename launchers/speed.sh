#!/usr/bin/env bash
# Training speed on one GPU, side by side with the PyTorch reference (docs/performance.md), in one run.
#
#   launchers/speed.sh [GPU] [TORCH_UMGEN_PY]       # default GPU 0; the reference is skipped without a path
#
# Runs, each under its own time limit so that one slow case cannot eat the others: the reference for the
# `small` and `paper` presets, `umgen bench train` for both presets in their `bf16-linear`, in f32 and in
# bf16 (`--set backbone.precision=…`), `small` once more on the named and on burn's matmul kernel (`--set
# train.kernels.matmul=named|burn`; the default is cuBLAS), `umgen-kernel-bench linear` and `attention` in
# both precisions (when KERNEL_BENCH names that binary or it is on the PATH), and 30 training steps of the `small` map and image VQ tokenizers on the bundled sample
# (their rasters/s). Prints the lines that
# matter at the end; full outputs go to $OUT (default ./speed-out). UMGEN names the binary (default:
# umgen); run from the repository root.
set -uo pipefail
gpu=${1:-0}
torch_py=${2:-}
umgen=${UMGEN:-umgen}
kernel_bench=${KERNEL_BENCH:-umgen-kernel-bench}
out=${OUT:-speed-out}
limit=${LIMIT:-240}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh" >/dev/null
mkdir -p "$out"
# shellcheck source=launchers/timed-runs.sh
source "$here/timed-runs.sh"
if [ -n "$torch_py" ]; then
    for p in small paper; do
        CUDA_VISIBLE_DEVICES=$gpu run "torch-$p" python3 "$torch_py" train --preset "$p" --device cuda
    done
fi
for p in small paper; do
    for prec in bf16-linear f32 bf16; do
        run "umgen-$p-$prec" "$umgen" bench train --preset "$p" --device "cuda:$gpu" --steps 10 --warmup 2 \
            --phases --set "backbone.precision=$prec"
    done
done
# The linear layers on the other kernels too: what cuBLAS (the default) gains over each.
for mm in named burn; do
    run "umgen-small-${mm}mm" "$umgen" bench train --preset small --device "cuda:$gpu" --steps 10 \
        --warmup 2 --set "train.kernels.matmul=$mm"
done
if command -v "$kernel_bench" >/dev/null; then
    run linear "$kernel_bench" linear --device "cuda:$gpu"
    for prec in f32 bf16; do
        run "attention-$prec" "$kernel_bench" attention --device "cuda:$gpu" --precision "$prec"
    done
else
    echo "== $kernel_bench not found: no kernel benches (cargo build --release -p umgen-kernel-bench --features cuda)"
fi
for m in map image; do
    rm -rf "$out/vq-$m"
    run "vq-$m" "$umgen" tokenizer train --config configs/small.toml --modality "$m" --data data/sumo-sample \
        --out "$out/vq-$m" --device "cuda:$gpu" --set "modality.$m.vq_train.steps=30" \
        --set "modality.$m.vq_train.log_every=10" --set "modality.$m.vq_train.checkpoint_every=100000"
done
echo
for f in "$out"/torch-*.txt; do [ -f "$f" ] && echo "$(basename "$f" .txt): $(grep -h '{' "$f" | tail -1)"; done
for f in "$out"/umgen-*.txt; do
    echo "$(basename "$f" .txt): $(grep -h -E '^(first step|step|throughput|peak memory)' "$f" | tr -s ' ' | paste -sd ';' -)"
done
for f in "$out"/attention-*.txt; do echo "-- $(basename "$f" .txt)"; grep -v INFO "$f" | tail -n 9; done
echo "-- linear"; grep -v -E 'INFO|WARN' "$out/linear.txt" | tail -n 26
for m in map image; do echo "vq-$m: $(grep -o 'step [0-9]*/30.*rasters_per_s [0-9.]*' "$out/vq-$m.txt" | sed 's/:.*rasters_per_s/: rasters\/s/' | tr '\n' ';')"; done
