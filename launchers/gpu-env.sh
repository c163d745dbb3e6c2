#!/usr/bin/env bash
# Source this on a GPU machine before running a CUDA build of umgen:   . launchers/gpu-env.sh
#
# umgen's CUDA backend compiles kernels with NVRTC at run time (it needs the toolkit's headers) and talks
# NCCL through cudarc, which looks for `libnccl.so` but not the `libnccl.so.2` that NCCL packages install.
# This script finds both libraries and exposes them under the names cudarc loads. `umgen doctor` checks
# the result. Safe to source from scripts under `set -euo pipefail`: a lookup that finds nothing is not an
# error here.
_umgen_lib="${TMPDIR:-/tmp}/umgen-cudalib-$(id -u)"
mkdir -p "$_umgen_lib"
_nvrtc=$(ls /usr/local/cuda*/targets/x86_64-linux/lib/libnvrtc.so.1[0-9] 2>/dev/null | sort -V | tail -1 || true)
[ -z "$_nvrtc" ] && _nvrtc=$(find / -xdev -name "libnvrtc.so.1[0-9]" 2>/dev/null | grep -v stubs | head -1 || true)
_nccl=$(ls /usr/lib/x86_64-linux-gnu/libnccl.so.2 2>/dev/null || find / -xdev -name "libnccl.so.2" 2>/dev/null | head -1 || true)
_cuda_root=$(ls -d /usr/local/cuda-1[0-9]* 2>/dev/null | sort -V | tail -1 || true)
if [ -n "$_cuda_root" ]; then export CUDA_PATH="${CUDA_PATH:-$_cuda_root}"; fi
if [ -n "$_nvrtc" ]; then
  ln -sf "$_nvrtc" "$_umgen_lib/libnvrtc.so"
  export LD_LIBRARY_PATH="$_umgen_lib:$(dirname "$_nvrtc"):${LD_LIBRARY_PATH:-}"
else
  echo "gpu-env.sh: NVRTC not found (install the CUDA toolkit)" >&2
fi
if [ -n "$_nccl" ]; then
  ln -sf "$_nccl" "$_umgen_lib/libnccl.so"
  case ":${LD_LIBRARY_PATH:-}:" in *":$_umgen_lib:"*) ;; *) export LD_LIBRARY_PATH="$_umgen_lib:${LD_LIBRARY_PATH:-}" ;; esac
else
  echo "gpu-env.sh: NCCL not found (multi-GPU training needs it)" >&2
fi
# NVLink multicast (NVLS) stays off: it needs exclusive fabric resources that shared hosts do not grant.
export NCCL_NVLS_ENABLE="${NCCL_NVLS_ENABLE:-0}"
echo "gpu-env.sh: CUDA_PATH=${CUDA_PATH:-none} nvrtc=${_nvrtc:-none} nccl=${_nccl:-none}" >&2
unset _umgen_lib _nvrtc _nccl _cuda_root
