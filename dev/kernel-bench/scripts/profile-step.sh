#!/usr/bin/env bash
# Where one training step's kernel time goes, by kind of kernel (docs/performance.md).
#
#   dev/kernel-bench/scripts/profile-step.sh [GPU] [PRESET] [bench train arguments...]   # default GPU 0, preset small
#
# Runs `umgen bench train` once for 3 steps, so that every kernel of a steady step is compiled (and kept in
# the kernel cache), then twice with cubecl's per-kernel profiling log (CUBECL_DEBUG_LOG=FILE
# CUBECL_DEBUG_OPTION=profile: every kernel is synced and timed, so those steps run slower than unprofiled
# ones while each kernel's own time stays right), for one step and for two; the second log less the first
# is a steady step (the first step also draws the lazily initialised parameters and the embedding tables),
# and the script sums that step's kernel times by kind (the first step's total is printed too): the named
# matmul kernel (train.kernels.matmul = "named"), burn's matmul kernels, fused element-wise, fused and plain
# reductions, copies, the rest by name. cuBLAS's kernels (train.kernels.matmul = "cublas", the default)
# are not cubecl's and are not in the log: their time shows as cubecl's `wait` kernel, which holds cubecl's
# stream until the product is done; pass `--set train.kernels.matmul=named` to see the products by name. The logs
# stay in $OUT (default ./profile-out). UMGEN names the binary (default: umgen); run from the repository
# root.
set -uo pipefail
gpu=${1:-0}
preset=${2:-small}
shift $(($# < 2 ? $# : 2))
umgen=${UMGEN:-umgen}
out=${OUT:-profile-out}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=/dev/null
[ -f "$here/../../../launchers/gpu-env.sh" ] && source "$here/../../../launchers/gpu-env.sh" >/dev/null
mkdir -p "$out"
"$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 2 --warmup 1 "$@" >"$out/warm.txt" 2>&1 ||
    { echo "warm-up run failed; see $out/warm.txt" >&2; exit 1; }
for steps in 1 2; do
    rm -f "$out/kernels-$steps.log"
    CUBECL_DEBUG_LOG="$out/kernels-$steps.log" CUBECL_DEBUG_OPTION=profile \
        "$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 1 --warmup $((steps - 1)) "$@" \
        >"$out/profiled-$steps.txt" 2>&1 ||
        { echo "profiled run failed; see $out/profiled-$steps.txt" >&2; exit 1; }
done
python3 - "$out/kernels-1.log" "$out/kernels-2.log" <<'PY'
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
def sums(path):
    ms, launches = collections.Counter(), collections.Counter()
    for text in open(path, errors='replace'):
        m = line.match(text.strip())
        if m:
            k = kind(m.group(3))
            ms[k] += float(m.group(1)) * unit[m.group(2)]
            launches[k] += 1
    if not ms:
        sys.exit(f'no kernel timings in {path}')
    return ms, launches
(ms1, n1), (ms2, n2) = sums(sys.argv[1]), sums(sys.argv[2])
print(f'first step: {sum(ms1.values()):.1f} ms of kernel time in {sum(n1.values())} launches')
# Counter subtraction drops kinds that are not positive, which only the first step's have.
ms, launches = ms2 - ms1, n2 - n1
total = sum(ms.values())
print(f'a steady step (the second): {total:.1f} ms of kernel time in {sum(launches.values())} launches')
for k, v in ms.most_common(24):
    print(f'{v:9.1f} ms {100 * v / total:5.1f} % {launches[k]:6d} launches  {k}')
PY
