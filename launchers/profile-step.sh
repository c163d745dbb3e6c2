#!/usr/bin/env bash
# Where one training step's kernel time goes, by kind of kernel (docs/performance.md).
#
#   launchers/profile-step.sh [GPU] [PRESET] [bench train arguments...]   # default GPU 0, preset small
#
# Runs `umgen bench train` once for 3 steps, so that every kernel of a steady step is compiled (and kept in
# the kernel cache), then once for a single step with cubecl's per-kernel profiling log
# (CUBECL_DEBUG_LOG=FILE CUBECL_DEBUG_OPTION=profile: every kernel is synced and timed, so that step runs
# slower than an unprofiled one while each kernel's own time stays right), and sums the kernel times by
# kind: the named matmul kernel (train.matmul = "named"), burn's matmul kernels, fused element-wise, fused
# and plain reductions, copies, the rest by name. cuBLAS's kernels (train.matmul = "cublas", the default)
# are not cubecl's and are not in the log: their time shows as cubecl's `wait` kernel, which holds cubecl's
# stream until the product is done; pass `--set train.matmul=named` to see the products by name. The log
# stays in $OUT (default ./profile-out). UMGEN names the binary (default: umgen); run from the repository
# root.
set -uo pipefail
gpu=${1:-0}
preset=${2:-small}
shift $(($# < 2 ? $# : 2))
umgen=${UMGEN:-umgen}
out=${OUT:-profile-out}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=/dev/null
[ -f "$here/gpu-env.sh" ] && source "$here/gpu-env.sh" >/dev/null
mkdir -p "$out"
"$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 2 --warmup 1 "$@" >"$out/warm.txt" 2>&1 ||
    { echo "warm-up run failed; see $out/warm.txt" >&2; exit 1; }
rm -f "$out/kernels.log"
CUBECL_DEBUG_LOG="$out/kernels.log" CUBECL_DEBUG_OPTION=profile \
    "$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 1 --warmup 0 "$@" >"$out/profiled.txt" 2>&1 ||
    { echo "profiled run failed; see $out/profiled.txt" >&2; exit 1; }
python3 - "$out/kernels.log" <<'PY'
import collections, re, sys
unit = {'ns': 1e-6, 'µs': 1e-3, 'us': 1e-3, 'ms': 1.0, 's': 1e3}
line = re.compile(r'^\|\s*([0-9.]+)(ns|µs|us|ms|s)\s*\|\s*(.*)$')
def kind(name):
    if 'TensorMapArgs' in name: return 'matmul, named kernel (TMA)'
    if 'Matmul' in name: return "matmul, burn's kernels"
    if 'ElemwiseFuse' in name: return 'fused element-wise'
    if 'Reduce' in name: return 'reductions'
    if 'Copy' in name: return 'copies'
    return name.split('|')[0].strip()
ms, launches = collections.Counter(), collections.Counter()
for text in open(sys.argv[1], errors='replace'):
    m = line.match(text.strip())
    if m:
        k = kind(m.group(3))
        ms[k] += float(m.group(1)) * unit[m.group(2)]
        launches[k] += 1
total = sum(ms.values())
if not total:
    sys.exit(f'no kernel timings in {sys.argv[1]}')
print(f'{total:.1f} ms of kernel time in {sum(launches.values())} launches')
for k, v in ms.most_common(24):
    print(f'{v:9.1f} ms {100 * v / total:5.1f} % {launches[k]:6d} launches  {k}')
PY
