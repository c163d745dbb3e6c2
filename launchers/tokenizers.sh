#!/usr/bin/env bash
# A config's map and image VQ tokenizers, trained side by side on this machine's GPUs (half of them each,
# data-parallel through `umgen launch`), then evaluated on the dataset's held-out split.
#
#   launchers/tokenizers.sh configs/small.toml data/sumo-sample              # until vq_train.steps
#   MINUTES=25 launchers/tokenizers.sh configs/small.toml data/sumo-sample  # stop after 25 minutes
#
# The tokenizers go to OUT/tokenizer-<modality> (OUT defaults to runs/<config name>, which is where
# configs/small.toml's `modality.<name>.tokenizer` points); rerunning resumes them. Extra arguments go to
# every `tokenizer train` (e.g. --set modality.map.vq_train.batch_size=8). With one GPU the tokenizers
# train one after the other. Also read: UMGEN (the binary), NGPUS, MODALITIES ("map image"), MASTER_PORT
# (first of two, default 29510), EVAL_SPLIT (test), EVAL_FRAMES (256). Logs: OUT/tokenizer-<modality>.log.
set -euo pipefail
usage="usage: tokenizers.sh CONFIG DATA [tokenizer train args...]"
config=${1:?$usage}
data=${2:?$usage}
shift 2
umgen=${UMGEN:-umgen}
out=${OUT:-runs/$(basename "$config" .toml)}
read -r -a modalities <<<"${MODALITIES:-map image}"
here=$(cd "$(dirname "$0")" && pwd)
# NVRTC, CUDA headers and NCCL under the names the CUDA backend loads.
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh" >/dev/null
ngpus=${NGPUS:-$(nvidia-smi --list-gpus 2>/dev/null | wc -l)}
if [ "$ngpus" -lt 1 ]; then
    echo "tokenizers.sh: no GPU found (set NGPUS, or run umgen tokenizer train --device cpu)" >&2
    exit 1
fi
mkdir -p "$out"

one() { # modality first-gpu gpu-count port train-args...
    local m=$1 first=$2 n=$3 port=$4 gpus log
    shift 4
    gpus=$(seq -s, "$first" $((first + n - 1)))
    log="$out/tokenizer-$m.log"
    echo "tokenizers.sh: $m on GPU $gpus, log $log" >&2
    CUDA_VISIBLE_DEVICES=$gpus "$umgen" launch --nproc-per-node "$n" --master-port "$port" -- tokenizer train \
        --config "$config" --modality "$m" --data "$data" --out "$out/tokenizer-$m" --device cuda \
        ${MINUTES:+--time-limit "$MINUTES"} "$@" >"$log" 2>&1 || { echo "tokenizers.sh: $m failed, see $log" >&2; return 1; }
    CUDA_VISIBLE_DEVICES=$first "$umgen" tokenizer eval --config "$config" --modality "$m" --data "$data" \
        --tokenizer "$out/tokenizer-$m" --split "${EVAL_SPLIT:-test}" --frames "${EVAL_FRAMES:-256}" \
        --device cuda:0 >>"$log" 2>&1 || { echo "tokenizers.sh: evaluating $m failed, see $log" >&2; return 1; }
}

port=${MASTER_PORT:-29510}
status=0
if [ "$ngpus" -lt 2 ] || [ "${#modalities[@]}" -ne 2 ]; then
    for m in "${modalities[@]}"; do one "$m" 0 "$ngpus" "$port" "$@" || status=1; done
else
    half=$(((ngpus + 1) / 2))
    one "${modalities[0]}" 0 "$half" "$port" "$@" &
    first=$!
    one "${modalities[1]}" "$half" $((ngpus - half)) $((port + 1)) "$@" || status=1
    wait "$first" || status=1
fi
for m in "${modalities[@]}"; do
    echo "== $m ($out/tokenizer-$m)"
    sed -n '/tokenizer .* on [0-9]* frames/,$p' "$out/tokenizer-$m.log" | grep -v ' INFO ' || true
done
exit "$status"
