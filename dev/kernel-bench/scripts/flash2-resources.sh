#!/usr/bin/env bash
# Registers and spills of the flash2 attention kernels on a machine without a GPU: compiles
# crates/cuda/src/kernels/flash2/flash2_warp.cu + flash2_tiles.cu + flash2_dq.cu + flash2.cu with NVRTC as umgen does (compute_80, fast math),
# then assembles the PTX for sm_90 with ptxas and prints each kernel's registers and spill bytes. With
# ARCH=90a, NVRTC targets compute_90a as on an H100 (the head size 64 kernels on `wgmma`) and ptxas sm_90a.
#
#   dev/kernel-bench/scripts/flash2-resources.sh [SOURCE]     # SOURCE: one joined file (as UMGEN_FLASH2_SOURCE takes;
#                                              # for norm.cu, temporal.cu or xent.cu: warp_device.cuh, then it)
#
# NVRTC and ptxas come from NVIDIA's PyPI wheels (nvidia-cuda-nvrtc-cu12, nvidia-cuda-nvcc-cu12), fetched
# once into $TOOLS (default ~/.cache/umgen/cuda-tools). Run from the repository root.
set -euo pipefail
tools=${TOOLS:-$HOME/.cache/umgen/cuda-tools}
here=crates/cuda/src/kernels/flash2
for pkg in nvidia-cuda-nvrtc-cu12 nvidia-cuda-nvcc-cu12; do
    if [ ! -d "$tools/$pkg" ]; then
        mkdir -p "$tools/$pkg"
        python3 -m pip download --no-deps -q "$pkg" -d "$tools/$pkg"
        (cd "$tools/$pkg" && unzip -q -o ./*.whl)
    fi
done
source_file=$(mktemp --suffix=.cu)
ptx=$(mktemp --suffix=.ptx)
trap 'rm -f "$source_file" "$ptx"' EXIT
if [ $# -ge 1 ]; then cp "$1" "$source_file"; else cat "$here/flash2_warp.cu" "$here/flash2_tiles.cu" "$here/flash2_dq.cu" "$here/flash2.cu" >"$source_file"; fi
arch=${ARCH:-80}
ARCH=$arch NVRTC=$(ls "$tools"/nvidia-cuda-nvrtc-cu12/nvidia/cuda_nvrtc/lib/libnvrtc.so.* | head -1) \
    python3 - "$source_file" "$ptx" <<'PY'
import ctypes, os, sys
lib = ctypes.CDLL(os.environ["NVRTC"])
prog = ctypes.c_void_p()
assert lib.nvrtcCreateProgram(ctypes.byref(prog), open(sys.argv[1], "rb").read(), b"flash2.cu", 0, None, None) == 0
opts = [b"--gpu-architecture=compute_" + os.environ["ARCH"].encode(), b"--use_fast_math"]
status = lib.nvrtcCompileProgram(prog, len(opts), (ctypes.c_char_p * len(opts))(*opts))
size = ctypes.c_size_t()
lib.nvrtcGetProgramLogSize(prog, ctypes.byref(size))
log = ctypes.create_string_buffer(size.value)
lib.nvrtcGetProgramLog(prog, log)
if status != 0:
    sys.exit("NVRTC failed:\n" + log.value.decode())
lib.nvrtcGetPTXSize(prog, ctypes.byref(size))
ptx = ctypes.create_string_buffer(size.value)
lib.nvrtcGetPTX(prog, ptx)
open(sys.argv[2], "wb").write(ptx.value)
PY
"$tools"/nvidia-cuda-nvcc-cu12/nvidia/cuda_nvcc/bin/ptxas -arch=sm_$([ "$arch" = 80 ] && echo 90 || echo "$arch") -v "$ptx" -o /dev/null 2>&1 |
    grep -E "Compiling entry|spill|registers" | paste - - - |
    sed -E "s/.*entry function 'umgen_flash2_([a-z0-9_]+)'.*([0-9]+ bytes stack frame), ([0-9]+ bytes spill stores), ([0-9]+ bytes spill loads).*Used ([0-9]+) registers.*/\1: \5 registers, \3, \4/"
