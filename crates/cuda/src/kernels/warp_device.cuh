// The warp- and block-level primitives of the CUDA C kernels in this crate (`norm/norm.cu`,
// `temporal/temporal.cu`, `xent/xent.cu`, `adamw/adamw.cu`, `lookup/lookup.cu`, …) on the GPU.
// `side::kernel_source` puts this before a kernel's source for NVRTC (which resolves no includes); on the
// host `warp_emulator.h` defines the same names.
#define DEV static __device__ __forceinline__
#define KERNEL extern "C" __global__ void __launch_bounds__(256)
// A kernel whose registers are held to what `n` blocks of 256 threads on one SM leave it.
#define KERNEL_RESIDENT(n) extern "C" __global__ void __launch_bounds__(256, n)
// NVRTC has no <math.h>.
#define NEG_INF __int_as_float(0xff800000)
typedef unsigned short u16;
typedef unsigned int u32;
DEV float bits_float(u32 u) { return __uint_as_float(u); }
DEV u32 float_bits(float f) { return __float_as_uint(f); }
DEV int lane_id() { return threadIdx.x & 31; }
DEV int warp_id() { return threadIdx.x >> 5; }
DEV int warps_per_block() { return blockDim.x >> 5; }
DEV long long block_x() { return blockIdx.x; }
DEV long long blocks() { return gridDim.x; }
DEV long long warp_index() { return (long long)blockIdx.x * (blockDim.x >> 5) + (threadIdx.x >> 5); }
DEV float warp_sum(float x) {
    for (int m = 16; m > 0; m >>= 1) x += __shfl_xor_sync(0xffffffffu, x, m);
    return x;
}
DEV float warp_max(float x) {
    for (int m = 16; m > 0; m >>= 1) x = fmaxf(x, __shfl_xor_sync(0xffffffffu, x, m));
    return x;
}
DEV float from_lane(float x, int lane) { return __shfl_sync(0xffffffffu, x, lane); }
DEV float from_xor(float x, int mask) { return __shfl_xor_sync(0xffffffffu, x, mask); }
DEV void warp_sync() { __syncwarp(); }
#define SHARED __shared__
DEV int thread_id() { return threadIdx.x; }
DEV int threads() { return blockDim.x; }
DEV void sync_block() { __syncthreads(); }
DEV int atomic_add(int* p, int v) { return atomicAdd(p, v); }
