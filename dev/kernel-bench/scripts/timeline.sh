#!/usr/bin/env bash
# A training step's GPU timeline without Nsight Systems (docs/performance.md): when each kernel ran, how much
# of each step the GPU was busy and where it idled, and what the host did meanwhile (driver calls, waits).
#
#   dev/kernel-bench/scripts/timeline.sh build DIR                  # on a machine with gcc: DIR/libtimeline.so + libcupti.so.13
#   dev/kernel-bench/scripts/timeline.sh run DIR [bench train args] # on the GPU machine: runs `umgen bench train` under it
#
# `build` compiles dev/kernel-bench/scripts/timeline/timeline.c, a CUDA injection library on CUPTI's activity API, against
# CUPTI 13.0 from NVIDIA's PyPI wheels (fetched once into $TOOLS, default ~/.cache/umgen/cuda-tools) and puts
# the matching libcupti beside it, so the GPU machine needs neither a compiler nor CUPTI. `run` loads it
# through CUDA_INJECTION64_PATH, writes the CSV to $OUT (default ./timeline.csv) and prints
# dev/kernel-bench/scripts/timeline/timeline.py's summary; default arguments: --preset small --steps 6 --warmup 2.
# UMGEN names the binary (default: umgen on the PATH). Run from the repository root.
set -euo pipefail
mode=${1:-}
dir=${2:-}
[ -n "$mode" ] && [ -n "$dir" ] || { sed -n 2,14p "$0" >&2; exit 2; }
shift 2
here=$(cd "$(dirname "$0")" && pwd)
case "$mode" in
build)
    tools=${TOOLS:-$HOME/.cache/umgen/cuda-tools}
    for pkg in nvidia-cuda-cupti nvidia-cuda-runtime nvidia-cuda-crt; do
        if [ ! -d "$tools/$pkg-13" ]; then
            mkdir -p "$tools/$pkg-13"
            python3 -m pip download --no-deps -q "$pkg==13.0.*" -d "$tools/$pkg-13"
            (cd "$tools/$pkg-13" && unzip -q -o ./*.whl)
        fi
    done
    mkdir -p "$dir"
    gcc -O2 -Wall -Werror -shared -fPIC -o "$dir/libtimeline.so" "$here/timeline/timeline.c" \
        -I"$tools/nvidia-cuda-cupti-13/nvidia/cu13/include" \
        -I"$tools/nvidia-cuda-runtime-13/nvidia/cu13/include" \
        -I"$tools/nvidia-cuda-crt-13/nvidia/cu13/include" \
        -L"$tools/nvidia-cuda-cupti-13/nvidia/cu13/lib" -l:libcupti.so.13 -Wl,-rpath,'$ORIGIN'
    cp "$tools/nvidia-cuda-cupti-13/nvidia/cu13/lib/libcupti.so.13" "$dir/"
    echo "built $dir/libtimeline.so"
    ;;
run)
    dir=$(cd "$dir" && pwd)
    out=${OUT:-timeline.csv}
    # shellcheck source=/dev/null
    [ -f "$here/../../../launchers/gpu-env.sh" ] && source "$here/../../../launchers/gpu-env.sh" >/dev/null
    [ $# -gt 0 ] || set -- --preset small --steps 6 --warmup 2
    CUDA_INJECTION64_PATH="$dir/libtimeline.so" UMGEN_TIMELINE="$out" \
        "${UMGEN:-umgen}" bench train --device cuda:0 "$@" 2>&1 | grep -E "^(step|host|error)" || true
    python3 "$here/timeline/timeline.py" "$out"
    ;;
*)
    sed -n 2,14p "$0" >&2
    exit 2
    ;;
esac
