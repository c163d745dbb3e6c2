#!/usr/bin/env bash
# Generation speed of umgen's engine next to the PyTorch reference, on one GPU, in one run (the numbers of
# docs/performance.md's generation table): `umgen bench generate` for the `small` and `paper` presets at
# batch 1 and larger batches, then `torch_umgen.py infer-graph` (the OAR step replayed as a CUDA graph) and
# `infer-scaling` (eager, KV cache) at the same history lengths.
#
#   launchers/generate-speed.sh [UMGEN] [TORCH_UMGEN_PY] [OUT_DIR] [PRESETS]
#
# UMGEN: a CUDA build of umgen (default target/release/umgen); TORCH_UMGEN_PY: the PyTorch reference's
# script (default ./torch_umgen.py, from the shared benchmarks); OUT_DIR (default generate-speed): one log per run and summary.txt;
# PRESETS (default "small paper"): the presets measured (each takes about five minutes).
# Run it from the repository root on the GPU machine, after `. launchers/gpu-env.sh`.
set -euo pipefail
umgen=${1:-target/release/umgen}
torch=${2:-torch_umgen.py}
out=${3:-generate-speed}
presets=${4:-small paper}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,clocks.sm --format=csv,noheader | tee "$out/gpu.txt"
for preset in $presets; do
  case $preset in
    small) ts=1,8 batches=1,16,128 rollout=60 ;;
    paper) ts=1,20 batches=1,16 rollout=60 ;;
  esac
  "$umgen" bench generate --preset "$preset" --device cuda:0 --history "$ts" --batch "$batches" --frames 3 \
    --rollout "$rollout" 2>&1 | tee "$out/umgen-$preset.txt"
  python3 "$torch" infer-graph --preset "$preset" --ts "$ts" 2>&1 | tee "$out/torch-graph-$preset.jsonl"
  python3 "$torch" infer-scaling --preset "$preset" --ts "$ts" --max-tokens 256 --models umgen 2>&1 \
    | tee "$out/torch-eager-$preset.jsonl"
done
{
  echo "== umgen (engine)"
  grep -hE "^(config|start| +[0-9]+ +[0-9]+ |rollout)" "$out"/umgen-*.txt
  echo "== PyTorch"
  grep -h '"mode"' "$out"/torch-*.jsonl
} | tee "$out/summary.txt"
