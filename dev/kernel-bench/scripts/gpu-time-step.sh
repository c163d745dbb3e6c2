#!/usr/bin/env bash
# A steady training step's GPU time by kernel, from Nsight Compute (docs/performance.md).
#
#   dev/kernel-bench/scripts/gpu-time-step.sh [GPU] [PRESET] [bench train arguments...]   # default GPU 0, preset small
#
# `profile-step.sh` times kernels through cubecl's profiling mode, which syncs around every kernel and
# overstated burn-fusion's element-wise kernels (a kernel that took 25 ms off its sum left the step as it
# was). This script instead runs `umgen bench train` under `ncu` with one metric,
# `gpu__time_duration` (each kernel's own duration, the kernels as a normal run compiles them, cuBLAS's
# included), for one step and for two, and prints the second run less the first: a steady step's GPU time
# in all and by kernel. Compare the total with the step time `bench train` reports: equal means the step
# is the GPU's. It takes a few minutes (ncu replays every kernel). The CSVs stay in $OUT (default
# ./gpu-time-out). It prints the step by kernel family (kernel_families.py, as torch-time-step.py
# prints the PyTorch reference) and its largest kernels. UMGEN names the binary (default: umgen), NCU the profiler (default: ncu on the PATH,
# else /usr/local/cuda/bin/ncu); run from the repository root.
set -uo pipefail
gpu=${1:-0}
preset=${2:-small}
shift $(($# < 2 ? $# : 2))
umgen=${UMGEN:-umgen}
out=${OUT:-gpu-time-out}
ncu=${NCU:-$(command -v ncu || echo /usr/local/cuda/bin/ncu)}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=/dev/null
[ -f "$here/../../../launchers/gpu-env.sh" ] && source "$here/../../../launchers/gpu-env.sh" >/dev/null
[ -x "$ncu" ] || { echo "no Nsight Compute at $ncu (set NCU)" >&2; exit 1; }
mkdir -p "$out"
# Compile every kernel once, so that the profiled runs time kernels, not NVRTC.
"$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 2 --warmup 1 "$@" >"$out/warm.txt" 2>&1 ||
    { echo "warm-up run failed; see $out/warm.txt" >&2; exit 1; }
for steps in 1 2; do
    "$ncu" --metrics gpu__time_duration.sum --csv --print-units base \
        "$umgen" bench train --preset "$preset" --device "cuda:$gpu" --steps 1 --warmup $((steps - 1)) "$@" \
        >"$out/ncu-$steps.csv" 2>"$out/ncu-$steps.err" ||
        { echo "profiled run failed; see $out/ncu-$steps.err" >&2; exit 1; }
done
python3 - "$out/ncu-1.csv" "$out/ncu-2.csv" "$here" <<'PY'
import collections, csv, sys
sys.path.insert(0, sys.argv[3])
from kernel_families import summary
def load(path):
    rows = [l for l in open(path, errors='replace') if l.startswith('"')]
    total, by, n = 0.0, collections.Counter(), collections.Counter()
    for row in csv.DictReader(rows):
        if row.get('Metric Name') != 'gpu__time_duration.sum':
            continue
        ms = float(row['Metric Value'].replace(',', '')) / 1e6
        name = row['Kernel Name'].split('(')[0].split('<')[0][:64]
        total += ms
        by[name] += ms
        n[name] += 1
    if not by:
        sys.exit(f'no kernel durations in {path}')
    return total, by, n
(t1, b1, n1), (t2, b2, n2) = load(sys.argv[1]), load(sys.argv[2])
print(f'first step {t1:.1f} ms of GPU time; a steady step (the second) {t2 - t1:.1f} ms')
by, n = b2 - b1, n2 - n1
print(summary(dict(by), dict(n), top=30))
PY
