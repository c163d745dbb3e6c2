// The warp- and warpgroup-level primitives of the flash2 kernels on the GPU (`mma.sync`, `ldmatrix`, quad
// shuffles; Hopper's `wgmma` where NVRTC targets sm_90a), compiled before `flash2_tiles.cu` and `flash2.cu`
// (`flash2.rs` joins them). The host emulator (`flash2_emulator.cpp`) defines the same names instead.

#ifndef UMGEN_EMULATED
typedef unsigned int u32;
typedef unsigned short u16;
#define DEV __device__ __forceinline__
// At most 128 registers a thread, so that two blocks of 8 warps share an SM: the key/value-gradient kernel
// spills about 500 bytes a thread for it and still runs 10 % faster than with 254 registers and one block
// (H100, docs/decisions/005-training-attention-flash2.md).
#define KERNEL extern "C" __global__ void __launch_bounds__(256, 2)
#define SHARED __shared__
#define ALIGNED __align__(16)

// The softmax's base-2 exponent and logarithm as single approximate instructions, what `--use_fast_math`
// makes of exp2f and log2f: the kernels are also compiled by cubecl (`train.kernels.stream = "cubecl"`),
// which passes NVRTC no such option, and the precise exp2f adds range handling to every score.
DEV float fast_exp2(float x) {
    float y;
    asm("ex2.approx.ftz.f32 %0, %1;" : "=f"(y) : "f"(x));
    return y;
}
DEV float fast_log2(float x) {
    float y;
    asm("lg2.approx.ftz.f32 %0, %1;" : "=f"(y) : "f"(x));
    return y;
}
#define exp2f fast_exp2
#define log2f fast_log2

// c += a · b on the tensor cores: a 16×16 (row-major fragments), b 16×8, c 16×8 f32.
DEV void mma(float* c, const u32* a, const u32* b) {
    asm volatile(
        "mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, "
        "{%0,%1,%2,%3};\n"
        : "+f"(c[0]), "+f"(c[1]), "+f"(c[2]), "+f"(c[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b[0]), "r"(b[1]));
}

DEV u32 shared_address(const u16* p) {
    u32 s;
    asm("{ .reg .u64 a; cvta.to.shared.u64 a, %1; cvt.u32.u64 %0, a; }" : "=r"(s) : "l"(p));
    return s;
}

// Four 8×8 matrices of 16-bit elements; lane l gives the address of row (l & 7) of matrix (l >> 3).
DEV void ldsm4(u32* r, const u16* p) {
    asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0,%1,%2,%3}, [%4];\n"
                 : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
                 : "r"(shared_address(p)));
}

// The same, each matrix transposed.
DEV void ldsm4t(u32* r, const u16* p) {
    asm volatile("ldmatrix.sync.aligned.m8n8.x4.trans.shared.b16 {%0,%1,%2,%3}, [%4];\n"
                 : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3])
                 : "r"(shared_address(p)));
}

DEV float quad_max(float x) {
    x = fmaxf(x, __shfl_xor_sync(0xffffffffu, x, 1));
    return fmaxf(x, __shfl_xor_sync(0xffffffffu, x, 2));
}

DEV float quad_sum(float x) {
    x += __shfl_xor_sync(0xffffffffu, x, 1);
    return x + __shfl_xor_sync(0xffffffffu, x, 2);
}

// x of lane `lane` of this warp.
DEV float from_lane(float x, int lane) { return __shfl_sync(0xffffffffu, x, lane); }

DEV int lane_id() { return threadIdx.x & 31; }
DEV int warp_id() { return threadIdx.x >> 5; }
DEV int thread_id() { return threadIdx.x; }
DEV int threads() { return blockDim.x; }
DEV int block_x() { return blockIdx.x; }
// The flattened (batch, head) index: the grid's y and z (y holds at most 65,535).
DEV int block_y() { return blockIdx.y + 65535 * blockIdx.z; }
DEV void sync_block() { __syncthreads(); }
// A block's dynamic shared memory (sized at launch), here `n` elements of `type` at most.
#define DYNAMIC_SHARED(type, name, n) extern __shared__ __align__(16) type name[]
#endif


#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
typedef unsigned long long u64;
#define TILE_ALIGNED __align__(1024)

// The descriptor of a B operand in shared memory at `p` (PTX ISA, "Matrix Descriptor Format"): rows of 128
// bytes with the 128-byte swizzle (`at_tile`), groups of 8 rows 1,024 bytes apart, tiles aligned to 1,024
// bytes so that the swizzle's rows are the tile's. The PTX ISA's tables give the 8-row stride as the stride
// offset for K-major operands and the leading offset for N-major ones (whose other offset, the next 64
// columns, N = 64 never uses): both are set.
DEV u64 wg_descriptor(const u16* p) {
    u64 a = shared_address(p);
    return ((a & 0x3FFFFull) >> 4) | ((u64)(1024 >> 4) << 16) | ((u64)(1024 >> 4) << 32) | (1ull << 62);
}

// The accumulator operands of an m64n64 (8 tiles) and an m64n32 (4 tiles) product: asm outputs, PTX names.
#define WG_ACC4(d, j) "+f"(d[j][0]), "+f"(d[j][1]), "+f"(d[j][2]), "+f"(d[j][3])
#define WG_ACC32(d) WG_ACC4(d, 0), WG_ACC4(d, 1), WG_ACC4(d, 2), WG_ACC4(d, 3)
#define WG_ACC64(d) WG_ACC32(d), WG_ACC4(d, 4), WG_ACC4(d, 5), WG_ACC4(d, 6), WG_ACC4(d, 7)
#define WG_D32 "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15}"
#define WG_D64                                                                                            \
    "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, " \
    "%22, %23, %24, %25, %26, %27, %28, %29, %30, %31}"

// d (64 × 64 per warpgroup, this warp's 16 rows as 8 accumulator tiles) += a · B; B K-major (`TB` 0:
// B[k][n] at row n of the tile) or N-major (`TB` 1: at row k).
template <int TB>
DEV void wgmma_n64(float (*d)[4], const u32* a, u64 desc) {
    asm volatile(
        "{\n.reg .pred p;\nsetp.ne.b32 p, %37, 0;\n"
        "wgmma.mma_async.sync.aligned.m64n64k16.f32.bf16.bf16 "
        WG_D64 ", "
        "{%32, %33, %34, %35}, %36, p, 1, 1, %38;\n}\n"
        : WG_ACC64(d)
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "l"(desc), "r"(1), "n"(TB));
}

// The same with N = 32 (4 accumulator tiles).
template <int TB>
DEV void wgmma_n32(float (*d)[4], const u32* a, u64 desc) {
    asm volatile(
        "{\n.reg .pred p;\nsetp.ne.b32 p, %21, 0;\n"
        "wgmma.mma_async.sync.aligned.m64n32k16.f32.bf16.bf16 "
        WG_D32 ", "
        "{%16, %17, %18, %19}, %20, p, 1, 1, %22;\n}\n"
        : WG_ACC32(d)
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "l"(desc), "r"(1), "n"(TB));
}

// The same with A read from shared memory too (K-major, `desc_a`): no A registers. ptxas (12.9 and the
// H100 driver's) gave the registers of a loop-invariant A fragment to the next `wgmma`'s A fragment, so the
// operands that stay the same across a kernel's loop (queries, keys, values, output gradients of the
// block's rows) are read from their tile in shared memory instead.
template <int TB>
DEV void wgmma_n64_ss(float (*d)[4], u64 desc_a, u64 desc) {
    asm volatile(
        "{\n.reg .pred p;\nsetp.ne.b32 p, %34, 0;\n"
        "wgmma.mma_async.sync.aligned.m64n64k16.f32.bf16.bf16 "
        WG_D64 ", "
        "%32, %33, p, 1, 1, 0, %35;\n}\n"
        : WG_ACC64(d)
        : "l"(desc_a), "l"(desc), "r"(1), "n"(TB));
}

template <int TB>
DEV void wgmma_n32_ss(float (*d)[4], u64 desc_a, u64 desc) {
    asm volatile(
        "{\n.reg .pred p;\nsetp.ne.b32 p, %18, 0;\n"
        "wgmma.mma_async.sync.aligned.m64n32k16.f32.bf16.bf16 "
        WG_D32 ", "
        "%16, %17, p, 1, 1, 0, %19;\n}\n"
        : WG_ACC32(d)
        : "l"(desc_a), "l"(desc), "r"(1), "n"(TB));
}

// acc += A · B over one step of 16 along k, A being rows [64 w, 64 w + 64) of `rows` (the tile of the block's
// rows, `at_tile` layout) for this thread's warpgroup w, and B as in `wg_mma`.
template <int NT, bool MN>
DEV void wg_mma_ss(float (*acc)[4], const u16* rows, const u16* tile, int k0) {
    u64 desc_a = wg_descriptor(rows + 64 * 64 * (warp_id() >> 2) + k0);
    u64 desc = wg_descriptor(MN ? tile + 64 * k0 : tile + k0);
    if constexpr (NT == 8)
        wgmma_n64_ss<MN ? 1 : 0>(acc, desc_a, desc);
    else
        wgmma_n32_ss<MN ? 1 : 0>(acc, desc_a, desc);
}

// acc (this warp's 16 rows × 8 · NT) += a · B over one step of 16 along k: B[k][n] = tile[n][k0 + k] (K-major,
// `MN` false) or tile[k0 + k][n] (`MN` true); `tile` in the `at_tile` layout of rows of 64.
template <int NT, bool MN>
DEV void wg_mma(float (*acc)[4], const u32* a, const u16* tile, int k0) {
    u64 desc = wg_descriptor(MN ? tile + 64 * k0 : tile + k0);
    if constexpr (NT == 8)
        wgmma_n64<MN ? 1 : 0>(acc, a, desc);
    else
        wgmma_n32<MN ? 1 : 0>(acc, a, desc);
}

// Registers written before `wgmma.fence` are the products' inputs; `wg_wait` returns when every product
// this thread's warpgroup committed has completed (its reads of shared memory included).
DEV void wg_arrive() { asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); }
DEV void wg_commit() { asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); }
DEV void wg_wait() { asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); }
// Keeps the compiler from moving reads or writes of the accumulators across the asynchronous products.
template <int NT>
DEV void wg_hold(float (*acc)[4]) {
#pragma unroll
    for (int j = 0; j < NT; j++)
#pragma unroll
        for (int e = 0; e < 4; e++) asm volatile("" : "+f"(acc[j][e])::"memory");
}
// The f32 values at `src` (shared memory, 16-byte aligned, `bytes` a multiple of 16) added to those at
// `dst` (global memory, 16-byte aligned) by the TMA unit: one instruction for a whole tile, where
// element-wise reductions took one for every four values. `bulk_wait_read` returns once this thread's
// bulk reductions have read their shared memory, `bulk_wait` once they are done.
DEV void bulk_add(float* dst, const float* src, int bytes) {
    asm volatile("cp.reduce.async.bulk.global.shared::cta.bulk_group.add.f32 [%0], [%1], %2;\n"
                 "cp.async.bulk.commit_group;" ::"l"(dst),
                 "r"(shared_address((const u16*)src)), "r"(bytes)
                 : "memory");
}
DEV void bulk_wait_read() { asm volatile("cp.async.bulk.wait_group.read 0;" ::: "memory"); }
DEV void bulk_wait() { asm volatile("cp.async.bulk.wait_group 0;" ::: "memory"); }
// Makes this thread's stores to shared memory visible to the tensor cores' reads (the async proxy).
DEV void to_async_proxy() { asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory"); }
#elif !defined(UMGEN_EMULATED)
#define TILE_ALIGNED ALIGNED
DEV void to_async_proxy() {}
// Element-wise reductions where the bulk one is missing (the one-pass kernel that adds this way runs on
// sm_90a only).
DEV void bulk_add(float* dst, const float* src, int bytes) {
    for (int i = 0; i < bytes / 4; i++) atomicAdd(dst + i, src[i]);
}
DEV void bulk_wait_read() {}
DEV void bulk_wait() {}
#endif

