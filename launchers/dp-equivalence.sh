#!/usr/bin/env bash
# Data-parallel equivalence on one machine's GPUs: six steps of the tiny model in the linear regime
# (train.eps = 1, lr 0.3: AdamW is then a momentum SGD, its update linear in the gradient), one rank at
# batch 8 against the same global batch split over ranks and micro-batches, and ranks that shard the
# optimizer state (train.shard_optimizer) against the same ranks unsharded, also across a stop and a
# resume that turns sharding off; prints each run's largest parameter difference and relative L2 against
# the references (docs/training.md, "Equivalence").
#
#   launchers/dp-equivalence.sh                 # UMGEN=path/to/umgen (CUDA build), OUT=runs/equivalence
set -euo pipefail
umgen=${UMGEN:-umgen}
out=${OUT:-runs/equivalence}
gpus=$(nvidia-smi -L | wc -l)
devices=$(seq -s, -f 'cuda:%g' 0 $((gpus - 1)))
mkdir -p "$out"
"$umgen" tokenize --config configs/tiny.toml --data data/sumo-sample --out "$out/tokens" --device "$devices"
common=(--set "train.tokens=$out/tokens" --set train.steps=6 --set train.eps=1 --set train.lr=0.3
    --set train.warmup=0 --set train.checkpoint_every=6)
run() { # NAME RANKS BATCH ACCUM [SHARD [train args...]]
    local args=(train --config configs/tiny.toml "${common[@]}" --set "train.batch_size=$3"
        --set "train.grad_accum=$4" --set "train.out_dir=$out/$1"
        --set "train.shard_optimizer=${5:-false}" "${@:6}")
    [[ " ${*:6} " == *" --resume "* ]] || rm -rf "${out:?}/$1"
    if [ "$2" = 1 ]; then
        "$umgen" "${args[@]}" --device cuda:0
    else
        "$umgen" launch --nproc-per-node "$2" -- "${args[@]}" --device cuda
    fi
}
run one 1 8 1
run again 1 8 1
run accum 1 4 2
run ranks2 2 4 1
run ranks2-accum 2 2 2
run ranks2-sharded 2 4 1 true
# Stopped after step 1 with sharding on, resumed with it off: the checkpoint holds the whole state.
run ranks2-resumed 2 4 1 true --time-limit 1e-6
run ranks2-resumed 2 4 1 false --resume
if [ "$gpus" -ge 4 ]; then
    run ranks4 4 2 1
    run ranks4-sharded 4 2 1 true
fi
python3 - "$out" <<'PY'
import json, os, struct, sys
import numpy as np
out = sys.argv[1]
def weights(name):
    b = open(f"{out}/{name}/checkpoints/step-000000006/model.safetensors", "rb").read()
    n = struct.unpack("<Q", b[:8])[0]
    head = json.loads(b[8:8 + n])
    return {k: np.frombuffer(b[8 + n + v["data_offsets"][0]: 8 + n + v["data_offsets"][1]], np.float32)
            for k, v in head.items() if k != "__metadata__"}
def compare(ref, names):
    r = weights(ref)
    print(f"against {ref}:")
    for name in names:
        if not os.path.isdir(f"{out}/{name}"):
            continue
        w = weights(name)
        d = {k: np.abs(w[k].astype(np.float64) - a) for k, a in r.items()}
        worst = max(float(x.max()) for x in d.values())
        rel = np.sqrt(sum(float((x ** 2).sum()) for x in d.values())
                      / sum(float((a.astype(np.float64) ** 2).sum()) for a in r.values()))
        print(f"  {name:14s} largest {worst:.1e}  relative L2 {rel:.1e}")
compare("one", ["again", "accum", "ranks2", "ranks4"])
compare("accum", ["ranks2", "ranks2-accum"])
compare("ranks2", ["ranks2-sharded", "ranks2-resumed"])
if os.path.isdir(f"{out}/ranks4"):
    compare("ranks4", ["ranks4-sharded"])
PY
