// The building blocks of the flash2 kernels (`flash2.cu`, which NVRTC compiles after this file): the
// warp-level primitives (`mma.sync`, `ldmatrix`, quad shuffles), the kernels' parameters, bf16 rounding,
// tiles moved from global to shared memory, and the 16-row fragment products of one warp.
//
// On the host (`UMGEN_EMULATED`), `flash2_emulator.cpp` defines the primitives instead of the block below.

#ifndef UMGEN_EMULATED
typedef unsigned int u32;
typedef unsigned short u16;
#define DEV __device__ __forceinline__
// At most 128 registers a thread, so that two blocks of 8 warps share an SM: the key/value-gradient kernel
// spills about 500 bytes a thread for it and still runs 10 % faster than with 254 registers and one block
// (H100, docs/perf-notes.md).
#define KERNEL extern "C" __global__ void __launch_bounds__(256, 2)
#define SHARED __shared__
#define ALIGNED __align__(16)

// The softmax's base-2 exponent and logarithm as single approximate instructions, what `--use_fast_math`
// makes of exp2f and log2f: the kernels are also compiled by cubecl (`train.kernel_stream = "cubecl"`),
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

DEV int lane_id() { return threadIdx.x & 31; }
DEV int warp_id() { return threadIdx.x >> 5; }
DEV int thread_id() { return threadIdx.x; }
DEV int threads() { return blockDim.x; }
DEV int block_x() { return blockIdx.x; }
// The flattened (batch, head) index: the grid's y and z (y holds at most 65,535).
DEV int block_y() { return blockIdx.y + 65535 * blockIdx.z; }
DEV void sync_block() { __syncthreads(); }
#endif

// Rows of the tiles a block walks through; a block's own rows are 16 per warp (`block_rows`), at most
// MAX_ROWS.
#define ROWS 64
#define MAX_ROWS 128
DEV int block_rows() { return 16 * (threads() >> 5); }
#define NEG_INF (-__int_as_float(0x7f800000))
#define LOG2E 1.4426950408889634f
#define LN2 0.6931471805599453f

// Everything a pass reads and writes. Strides are in elements: (batch, head, row); the head dimension is
// contiguous. Results are contiguous f32: `[b, h, rows, D]`, and `[b, h, lq]` for the log-sum-exp.
struct Params {
    const void* q;
    const void* k;
    const void* v;
    const void* dout;
    const float* lse;
    const float* delta;
    float* out;
    float* lse_out;
    float* dq;
    float* dk;
    float* dv;
    long long qs[3], ks[3], vs[3], os[3], ls[3], es[3];
    int heads, lq, lk, off, causal;
    float scale;
    // Heads in all (batch × heads): the grid may hold more blocks than that.
    int count;
};

DEV u16 bf16_bits(float x) {
    u32 u = __float_as_uint(x);
    u += 0x7fffu + ((u >> 16) & 1u);
    return (u16)(u >> 16);
}

// Two floats rounded to bf16 (to nearest, ties to even) in one word, `lo` in the low half: on the GPU one
// `cvt.rn.bf16x2.f32` (compute capability 8.0) where the bit arithmetic above takes about five
// instructions a value; it packs every probability and score gradient before its product.
#ifdef UMGEN_EMULATED
DEV u32 pack(float lo, float hi) { return (u32)bf16_bits(lo) | ((u32)bf16_bits(hi) << 16); }
#else
DEV u32 pack(float lo, float hi) {
    u32 r;
    asm("cvt.rn.bf16x2.f32 %0, %1, %2;" : "=r"(r) : "f"(hi), "f"(lo));
    return r;
}
#endif

// Two consecutive operand values as bf16 in one word.
DEV u32 pair(const float* p) { return pack(p[0], p[1]); }
DEV u32 pair(const u16* p) { return (u32)p[0] | ((u32)p[1] << 16); }

DEV u16 to_bf16(float x) { return bf16_bits(x); }
DEV u16 to_bf16(u16 x) { return x; }

// Rows [row0, row0 + count) of one head of an operand (`src` at the head's first element, rows `stride`
// elements apart) into `tile` (rows of D + 8), zeros past `rows`.
template <typename T, int D>
DEV void load_tile(u16* tile, const T* src, long long stride, int row0, int rows, int count = ROWS) {
    for (int i = thread_id(); i < count * D; i += threads()) {
        int r = i / D, c = i % D;
        int row = row0 + r;
        tile[r * (D + 8) + c] = row < rows ? to_bf16(src[stride * row + c]) : (u16)0;
    }
}

// The next tile of an operand on its way to shared memory: read from global memory into registers (as bf16
// pairs) before the current tile's products, stored after them, so that the loads' latency overlaps the
// products. Blocks of 8 warps only (8 pairs a thread); other block sizes load the tile when it is stored.
template <typename T, int D>
struct Staged {
    const T* src;
    long long stride;
    int rows, next;
    u32 r[ROWS * D / 2 / 256];
};


template <typename T, int D>
DEV void stage_fetch(Staged<T, D>& s, int row0) {
    s.next = row0;
    if (threads() != 256) return;
#pragma unroll
    for (int k = 0; k < ROWS * D / 2 / 256; k++) {
        int i = thread_id() + 256 * k, r = i / (D / 2), c = 2 * (i % (D / 2)), row = row0 + r;
        const T* p = s.src + s.stride * row + c;
        s.r[k] = row < s.rows ? pair(p) : 0u;
    }
}

template <typename T, int D>
DEV void stage_store(const Staged<T, D>& s, u16* tile) {
    if (threads() != 256) {
        load_tile<T, D>(tile, s.src, s.stride, s.next, s.rows);
        return;
    }
#pragma unroll
    for (int k = 0; k < ROWS * D / 2 / 256; k++) {
        int i = thread_id() + 256 * k, r = i / (D / 2), c = 2 * (i % (D / 2));
        *(u32*)(tile + r * (D + 8) + c) = s.r[k];
    }
}

// An operand (strides `s`) of head `bh` staged from its row `row0` on.
template <typename T, int D>
DEV Staged<T, D> staged_from(const void* src, const long long* s, int bh, int heads, int rows, int row0) {
    Staged<T, D> st;
    st.src = (const T*)src + s[0] * (bh / heads) + s[1] * (bh % heads);
    st.stride = s[2], st.rows = rows, st.next = 0;
    stage_fetch(st, row0);
    return st;
}

// Waits for every warp to finish with the current tiles, then stores the staged ones in their place.
template <typename T, int D>
DEV void store_staged(const Staged<T, D>& a, const Staged<T, D>& b, u16* ta, u16* tb) {
    sync_block();
    stage_store(a, ta);
    stage_store(b, tb);
}

// Waits for the stored tiles to be complete, then starts fetching the tiles after them (if `more`).
template <typename T, int D>
DEV void fetch_next(Staged<T, D>& a, Staged<T, D>& b, int row0, bool more) {
    sync_block();
    if (!more) return;
    stage_fetch(a, row0 + ROWS);
    stage_fetch(b, row0 + ROWS);
}

// Zeroes `n` accumulator tiles.
template <int N>
DEV void zero(float (*acc)[4]) {
#pragma unroll
    for (int n = 0; n < N; n++)
#pragma unroll
        for (int e = 0; e < 4; e++) acc[n][e] = 0.f;
}

// The head's base offset of an operand with strides `s` for the flattened (batch, head) index `bh`.
DEV long long head_base(const long long* s, int bh, int heads) {
    return s[0] * (bh / heads) + s[1] * (bh % heads);
}

template <typename T>
DEV const T* at(const void* p, long long offset) {
    return (const T*)p + offset;
}

// Loads the A fragments (16 rows × D) of this warp's rows of `tile`.
template <int D>
DEV void load_a(u32 (*a)[4], const u16* tile) {
    int l = lane_id(), m = l >> 3;
    int row = 16 * warp_id() + (l & 7) + (m & 1) * 8;
#pragma unroll
    for (int kk = 0; kk < D / 16; kk++) ldsm4(a[kk], tile + row * (D + 8) + 16 * kk + (m >> 1) * 8);
}

// This block's rows of two operands (one head of each, rows `stride_a` and `stride_b` apart) as the A
// fragments of each warp's 16 rows, through the tiles `ta` and `tb`.
template <typename T, int D>
DEV void block_fragments(u32 (*a)[4], u32 (*b)[4], u16* ta, u16* tb, const T* src_a, long long stride_a,
                         const T* src_b, long long stride_b, int row0, int rows) {
    load_tile<T, D>(ta, src_a, stride_a, row0, rows, block_rows());
    load_tile<T, D>(tb, src_b, stride_b, row0, rows, block_rows());
    sync_block();
    load_a<D>(a, ta);
    load_a<D>(b, tb);
}

// acc[j] (16 × 8 tiles, j < NT) = a · tileᵀ over the head dimension: `tile` holds 8 · NT rows of D.
template <int D, int NT = 8>
DEV void times_transposed(float (*acc)[4], const u32 (*a)[4], const u16* tile) {
    int l = lane_id(), m = l >> 3;
    zero<NT>(acc);
#pragma unroll
    for (int kk = 0; kk < D / 16; kk++)
#pragma unroll
        for (int j = 0; j < NT; j += 2) {
            u32 b[4];
            ldsm4(b, tile + (8 * (j + (m >> 1)) + (l & 7)) * (D + 8) + 16 * kk + (m & 1) * 8);
            mma(acc[j], a[kk], b);
            mma(acc[j + 1], a[kk], b + 2);
        }
}

// acc (16 × D) += p · tile, p given as NT accumulator tiles (16 × 8 · NT), `tile` 8 · NT rows of D.
template <int D, int NT = 8>
DEV void times(float (*acc)[4], const float (*p)[4], const u16* tile) {
    int l = lane_id(), m = l >> 3;
#pragma unroll
    for (int kk = 0; kk < NT / 2; kk++) {
        u32 a[4] = {pack(p[2 * kk][0], p[2 * kk][1]), pack(p[2 * kk][2], p[2 * kk][3]),
                    pack(p[2 * kk + 1][0], p[2 * kk + 1][1]), pack(p[2 * kk + 1][2], p[2 * kk + 1][3])};
#pragma unroll
        for (int n = 0; n < D / 8; n += 2) {
            u32 b[4];
            ldsm4t(b, tile + (16 * kk + (m & 1) * 8 + (l & 7)) * (D + 8) + 8 * (n + (m >> 1)));
            mma(acc[n], a, b);
            mma(acc[n + 1], a, b + 2);
        }
    }
}

// Rows (this warp's 16) of an accumulator (16 × D) into a contiguous f32 result, times `scale`.
template <int D>
DEV void store_rows(float* dst, const float (*acc)[4], int row0, int rows, float scale) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int half = 0; half < 2; half++) {
        int row = row0 + 16 * warp_id() + g + 8 * half;
        if (row >= rows) continue;
#pragma unroll
        for (int n = 0; n < D / 8; n++) {
            float* p = dst + (long long)row * D + 8 * n + 2 * t;
            p[0] = acc[n][2 * half] * scale;
            p[1] = acc[n][2 * half + 1] * scale;
        }
    }
}
