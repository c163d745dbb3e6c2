#!/usr/bin/env bash
# A model's rollouts from scratch in one run on one GPU: train, export, generate one step ahead and a long
# rollout from held-out contexts, evaluate both against the real split (docs/results.md's recipe).
#
#   launchers/rollout-study.sh CONFIG OUT [DEVICE]
#
# DEVICE is umgen's device (default cuda:0; `cpu` runs configs/tiny.toml in minutes).
#
# OUT receives run/ (checkpoints), bundle/, one/ and long/ (each with eval/report.md) and summary.txt (the
# held-out losses, the one-step L2 against its baselines, and the long rollout's "Against the targets"
# table). Environment:
#   UMGEN     the binary (default: umgen on PATH)
#   DATA      the dataset (default data/sumo-sample); its train split trains, SPLIT (default test) evaluates
#   STEPS     training steps (default 2000)
#   SETS      more `--set KEY=VALUE` arguments for training, e.g. "--set backbone.track_follow=true"
#   CONTEXTS  held-out contexts (default $DATA:$SPLIT:64:8), FRAMES the rollout's length (default 60 = 30 s)
#   DRAW      the long rollout's sampling (default control.md's long-rollout draw), SEED (default 1)
#   GEN       more arguments for the long rollout only, e.g. "--map-memory"
# Run from the repository root (the config's relative paths are the repository's).
set -euo pipefail
usage="usage: launchers/rollout-study.sh CONFIG OUT [DEVICE]"
config=${1:?$usage}
out=${2:?$usage}
device=${3:-cuda:0}
umgen=${UMGEN:-umgen}
data=${DATA:-data/sumo-sample}
split=${SPLIT:-test}
steps=${STEPS:-2000}
contexts=${CONTEXTS:-$data:$split:64:8}
frames=${FRAMES:-60}
seed=${SEED:-1}
read -r -a sets <<<"${SETS:-}"
read -r -a gen <<<"${GEN:-}"
read -r -a draw <<<"${DRAW:---top-k 5 --top-k-of agent=64 --top-p-of agent=0.8 --top-p-rest-of agent}"
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh" >/dev/null
mkdir -p "$out"
[ -e "$out/run" ] && { echo "$out/run exists: choose another OUT" >&2; exit 2; }
t0=$(date +%s)
stage() { echo "== $(($(date +%s) - t0)) s: $*"; }

stage "train $config, $steps steps"
if ! "$umgen" train --config "$config" --device "$device" --set train.data="$data" --set train.steps="$steps" \
    --set train.out_dir="$out/run" --set train.val_every="$((steps / 2 > 0 ? steps / 2 : 1))" "${sets[@]}" \
    >"$out/train.log" 2>&1; then
    tail -n 20 "$out/train.log" >&2
    echo "training failed: $out/train.log" >&2
    exit 1
fi
grep -E "val/loss" "$out/train.log" || true
stage "export"
"$umgen" export --checkpoint "$out/run" --out "$out/bundle" --dtype bf16
stage "one step ahead, greedy, recorded ego"
"$umgen" generate --bundle "$out/bundle" --device "$device" --contexts "$contexts" --frames 1 --recorded-ego \
    --top-k 1 --out "$out/one"
stage "rollout of $frames frames"
"$umgen" generate --bundle "$out/bundle" --device "$device" --contexts "$contexts" --frames "$frames" \
    "${draw[@]}" --seed "$seed" "${gen[@]}" --out "$out/long"
for g in one long; do
    stage "eval $g"
    "$umgen" eval --generated "$out/$g" --reference "$data" --split "$split" >"$out/$g.eval.log" 2>&1 ||
        { echo "eval of $g failed: $out/$g.eval.log" >&2; exit 1; }
done
stage "done"
{
    echo "# $config, $steps steps on $data; $contexts, $frames frames"
    echo "held-out loss by step:"
    grep -h '"val/loss"' "$out/run/metrics.jsonl" | grep -o -E '"(step|val/loss)": ?[0-9.e+-]+' |
        grep -o -E '[0-9.e+-]+$' | paste -d' ' - - | awk '{ printf "  %d: %.4f\n", $1, $2 }' || true
    echo
    # One step ahead against constant acceleration from the recorded state (the acceptance's bar), and the
    # long rollout's verdicts.
    grep -A 2 '^| horizon (s) | model mean | const. acc.' "$out/one/eval/report.md" || true
    echo
    sed -n '/^## Against the targets/,$p' "$out/long/eval/report.md" | sed '/^## [^A]/,$d'
} | tee "$out/summary.txt"
