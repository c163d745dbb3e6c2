#!/usr/bin/env bash
# Data-parallel training on this machine's GPUs: one rank per GPU.
#
#   launchers/local.sh configs/small.toml            # every visible GPU
#   NGPUS=2 launchers/local.sh configs/small.toml --resume
#
# Extra arguments go to `umgen train`. UMGEN (the binary) and MASTER_PORT may be set.
set -euo pipefail
config=${1:?usage: local.sh CONFIG [train args...]}
shift
umgen=${UMGEN:-umgen}
here=$(cd "$(dirname "$0")" && pwd)
# NVRTC, CUDA headers and NCCL under the names the CUDA backend loads.
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh"
ngpus=${NGPUS:-$(nvidia-smi --list-gpus 2>/dev/null | wc -l)}
if [ "$ngpus" -lt 1 ]; then
    echo "local.sh: no GPU found (set NGPUS, or run umgen train --device cpu)" >&2
    exit 1
fi
exec "$umgen" launch --nproc-per-node "$ngpus" --master-port "${MASTER_PORT:-29500}" \
    -- train --config "$config" --device cuda "$@"
