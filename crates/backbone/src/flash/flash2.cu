// FlashAttention-2 in CUDA C for NVRTC (`train.attention = "flash2"`): forward, key/value gradients and
// query gradients, one kernel each. Operands f32 or bf16 (`T`), converted to bf16 as they enter shared
// memory; products on the tensor cores (`mma.sync` m16n8k16, bf16 in, f32 accumulation); scores,
// probabilities and their gradients stay in registers (the accumulator layout of one product is the operand
// layout of the next). Each block of 4 or 8 warps owns 16 rows per warp (queries, or keys for the key/value
// gradients) and walks the other side in tiles of 64, the next tile read into registers while the
// current one's products run (8 warps). Head size `D`: 64 or 32.
//
// The same source compiles on the host (`UMGEN_EMULATED`), where `flash2_emulator.cpp` runs every thread of
// a block and defines the warp-level primitives below, so that fragment layouts are checked without a GPU.

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

DEV u32 pack(float lo, float hi) { return (u32)bf16_bits(lo) | ((u32)bf16_bits(hi) << 16); }

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
DEV Staged<T, D> staged(const T* src, long long stride, int rows) {
    Staged<T, D> s;
    s.src = src, s.stride = stride, s.rows = rows, s.next = 0;
    return s;
}

template <typename T, int D>
DEV void stage_fetch(Staged<T, D>& s, int row0) {
    s.next = row0;
    if (threads() != 256) return;
#pragma unroll
    for (int k = 0; k < ROWS * D / 2 / 256; k++) {
        int i = thread_id() + 256 * k, r = i / (D / 2), c = 2 * (i % (D / 2)), row = row0 + r;
        const T* p = s.src + s.stride * row + c;
        s.r[k] = row < s.rows ? (u32)to_bf16(p[0]) | ((u32)to_bf16(p[1]) << 16) : 0u;
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

// acc[j] (16 × 8 tiles, j < 8) = a · tileᵀ over the head dimension: `tile` holds 64 rows of D.
template <int D>
DEV void times_transposed(float (*acc)[4], const u32 (*a)[4], const u16* tile) {
    int l = lane_id(), m = l >> 3;
#pragma unroll
    for (int j = 0; j < 8; j++)
#pragma unroll
        for (int e = 0; e < 4; e++) acc[j][e] = 0.f;
#pragma unroll
    for (int kk = 0; kk < D / 16; kk++)
#pragma unroll
        for (int j = 0; j < 8; j += 2) {
            u32 b[4];
            ldsm4(b, tile + (8 * (j + (m >> 1)) + (l & 7)) * (D + 8) + 16 * kk + (m & 1) * 8);
            mma(acc[j], a[kk], b);
            mma(acc[j + 1], a[kk], b + 2);
        }
}

// acc (16 × D) += p · tile, p given as accumulator tiles (16 × 64), `tile` 64 rows of D.
template <int D>
DEV void times(float (*acc)[4], const float (*p)[4], const u16* tile) {
    int l = lane_id(), m = l >> 3;
#pragma unroll
    for (int kk = 0; kk < 4; kk++) {
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

// Whether key `key` is hidden from query `query`.
DEV bool hidden(const Params& P, int query, int key) {
    return key >= P.lk || query >= P.lq || (P.causal && key > query + P.off);
}

// One past the last key block a block of queries starting at `q0` sees.
DEV int key_blocks(const Params& P, int q0) {
    int last = P.lk - 1;
    if (P.causal) last = min(last, q0 + block_rows() - 1 + P.off);
    return last / ROWS + 1;
}

template <typename T, int D>
DEV void forward(const Params& P) {
    SHARED ALIGNED u16 qt[MAX_ROWS * (D + 8)];
    SHARED ALIGNED u16 kt[ROWS * (D + 8)];
    SHARED ALIGNED u16 vt[ROWS * (D + 8)];
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    int l = lane_id(), g = l >> 2, t = l & 3;
    const float sl = P.scale * LOG2E;
    load_tile<T, D>(qt, at<T>(P.q, head_base(P.qs, bh, P.heads)), P.qs[2], q0, P.lq, block_rows());
    sync_block();
    u32 qa[D / 16][4];
    load_a<D>(qa, qt);
    float o[D / 8][4], m[2] = {NEG_INF, NEG_INF}, s_sum[2] = {0.f, 0.f};
#pragma unroll
    for (int n = 0; n < D / 8; n++)
#pragma unroll
        for (int e = 0; e < 4; e++) o[n][e] = 0.f;
    int blocks = key_blocks(P, q0);
    Staged<T, D> kn = staged<T, D>(at<T>(P.k, head_base(P.ks, bh, P.heads)), P.ks[2], P.lk);
    Staged<T, D> vn = staged<T, D>(at<T>(P.v, head_base(P.vs, bh, P.heads)), P.vs[2], P.lk);
    stage_fetch(kn, 0);
    stage_fetch(vn, 0);
    for (int kb = 0; kb < blocks; kb++) {
        int k0 = ROWS * kb;
        sync_block();
        stage_store(kn, kt);
        stage_store(vn, vt);
        sync_block();
        if (kb + 1 < blocks) {
            stage_fetch(kn, k0 + ROWS);
            stage_fetch(vn, k0 + ROWS);
        }
        float s[8][4];
        times_transposed<D>(s, qa, kt);
#pragma unroll
        for (int half = 0; half < 2; half++) {
            int query = q0 + 16 * warp_id() + g + 8 * half;
            float mx = NEG_INF;
#pragma unroll
            for (int j = 0; j < 8; j++)
#pragma unroll
                for (int e = 0; e < 2; e++) {
                    int key = k0 + 8 * j + 2 * t + e;
                    float x = (key >= P.lk || (P.causal && key > query + P.off)) ? NEG_INF
                                                                                 : s[j][2 * half + e] * sl;
                    s[j][2 * half + e] = x;
                    mx = fmaxf(mx, x);
                }
            float m_new = fmaxf(m[half], quad_max(mx));
            // A row that has seen no key yet keeps exponents finite.
            float base = m_new == NEG_INF ? 0.f : m_new;
            float alpha = exp2f(m[half] - base);
            float sum = 0.f;
#pragma unroll
            for (int j = 0; j < 8; j++)
#pragma unroll
                for (int e = 0; e < 2; e++) {
                    float p = exp2f(s[j][2 * half + e] - base);
                    s[j][2 * half + e] = p;
                    sum += p;
                }
            s_sum[half] = s_sum[half] * alpha + sum;
            m[half] = m_new;
#pragma unroll
            for (int n = 0; n < D / 8; n++) {
                o[n][2 * half] *= alpha;
                o[n][2 * half + 1] *= alpha;
            }
        }
        times<D>(o, s, vt);
    }
    long long bh_rows = (long long)bh * P.lq;
#pragma unroll
    for (int half = 0; half < 2; half++) {
        float total = quad_sum(s_sum[half]);
        float inv = total > 0.f ? 1.f / total : 0.f;
        int row = q0 + 16 * warp_id() + g + 8 * half;
#pragma unroll
        for (int n = 0; n < D / 8; n++) {
            o[n][2 * half] *= inv;
            o[n][2 * half + 1] *= inv;
        }
        if (t == 0 && row < P.lq) P.lse_out[bh_rows + row] = (m[half] + log2f(total)) * LN2;
    }
    store_rows<D>(P.out + bh_rows * D, o, q0, P.lq, 1.f);
}

// Reads `count` f32 per-query values (log-sum-exp or delta) into `dst`, times `factor`; zeros past `lq`.
DEV void load_row_values(float* dst, const float* src, const long long* s, int bh, int heads, int q0, int lq,
                         float factor, int count = ROWS) {
    long long base = head_base(s, bh, heads);
    for (int i = thread_id(); i < count; i += threads())
        dst[i] = q0 + i < lq ? src[base + s[2] * (q0 + i)] * factor : 0.f;
}

// p = exp2(s · sl − lse2) where the key is visible, else 0; then ds = p ∘ (dp − delta). Rows and columns of
// the tiles are keys and queries (`keys_are_rows`) or queries and keys.
template <bool keys_are_rows>
DEV void probabilities(const Params& P, float (*s)[4], float (*dp)[4], const float* row_lse, const float* row_delta,
                       const float* col_lse, const float* col_delta, int r0, int c0, float sl) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int j = 0; j < 8; j++)
#pragma unroll
        for (int e = 0; e < 4; e++) {
            int r = 16 * warp_id() + g + 8 * (e >> 1), c = 8 * j + 2 * t + (e & 1);
            int query = keys_are_rows ? c0 + c : r0 + r, key = keys_are_rows ? r0 + r : c0 + c;
            float lse2 = keys_are_rows ? col_lse[c] : row_lse[r];
            float delta = keys_are_rows ? col_delta[c] : row_delta[r];
            float p = hidden(P, query, key) ? 0.f : exp2f(s[j][e] * sl - lse2);
            s[j][e] = p;
            dp[j][e] = p * (dp[j][e] - delta);
        }
}

template <typename T, int D>
DEV void backward_kv(const Params& P) {
    SHARED ALIGNED u16 qt[MAX_ROWS * (D + 8)];
    SHARED ALIGNED u16 ot[MAX_ROWS * (D + 8)];
    SHARED float lse2[ROWS], delta[ROWS];
    int bh = block_y(), k0 = block_rows() * block_x();
    if (bh >= P.count) return;
    const float sl = P.scale * LOG2E;
    // K and V enter registers through the query-side tiles.
    load_tile<T, D>(qt, at<T>(P.k, head_base(P.ks, bh, P.heads)), P.ks[2], k0, P.lk, block_rows());
    load_tile<T, D>(ot, at<T>(P.v, head_base(P.vs, bh, P.heads)), P.vs[2], k0, P.lk, block_rows());
    sync_block();
    u32 ka[D / 16][4], va[D / 16][4];
    load_a<D>(ka, qt);
    load_a<D>(va, ot);
    float dk[D / 8][4], dv[D / 8][4];
#pragma unroll
    for (int n = 0; n < D / 8; n++)
#pragma unroll
        for (int e = 0; e < 4; e++) dk[n][e] = dv[n][e] = 0.f;
    int first = 0;
    if (P.causal) first = max(0, k0 - P.off) / ROWS;
    int blocks = (P.lq + ROWS - 1) / ROWS;
    Staged<T, D> qn = staged<T, D>(at<T>(P.q, head_base(P.qs, bh, P.heads)), P.qs[2], P.lq);
    Staged<T, D> on = staged<T, D>(at<T>(P.dout, head_base(P.os, bh, P.heads)), P.os[2], P.lq);
    stage_fetch(qn, ROWS * first);
    stage_fetch(on, ROWS * first);
    for (int qb = first; qb < blocks; qb++) {
        int q0 = ROWS * qb;
        sync_block();
        stage_store(qn, qt);
        stage_store(on, ot);
        load_row_values(lse2, P.lse, P.ls, bh, P.heads, q0, P.lq, LOG2E);
        load_row_values(delta, P.delta, P.es, bh, P.heads, q0, P.lq, 1.f);
        sync_block();
        if (qb + 1 < blocks) {
            stage_fetch(qn, q0 + ROWS);
            stage_fetch(on, q0 + ROWS);
        }
        float s[8][4], dp[8][4];
        times_transposed<D>(s, ka, qt);
        times_transposed<D>(dp, va, ot);
        probabilities<true>(P, s, dp, 0, 0, lse2, delta, k0, q0, sl);
        times<D>(dv, s, ot);
        times<D>(dk, dp, qt);
    }
    long long base = (long long)bh * P.lk * D;
    store_rows<D>(P.dk + base, dk, k0, P.lk, P.scale);
    store_rows<D>(P.dv + base, dv, k0, P.lk, 1.f);
}

template <typename T, int D>
DEV void backward_q(const Params& P) {
    SHARED ALIGNED u16 kt[MAX_ROWS * (D + 8)];
    SHARED ALIGNED u16 vt[MAX_ROWS * (D + 8)];
    SHARED float lse2[MAX_ROWS], delta[MAX_ROWS];
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    const float sl = P.scale * LOG2E;
    load_tile<T, D>(kt, at<T>(P.q, head_base(P.qs, bh, P.heads)), P.qs[2], q0, P.lq, block_rows());
    load_tile<T, D>(vt, at<T>(P.dout, head_base(P.os, bh, P.heads)), P.os[2], q0, P.lq, block_rows());
    load_row_values(lse2, P.lse, P.ls, bh, P.heads, q0, P.lq, LOG2E, block_rows());
    load_row_values(delta, P.delta, P.es, bh, P.heads, q0, P.lq, 1.f, block_rows());
    sync_block();
    u32 qa[D / 16][4], oa[D / 16][4];
    load_a<D>(qa, kt);
    load_a<D>(oa, vt);
    float dq[D / 8][4];
#pragma unroll
    for (int n = 0; n < D / 8; n++)
#pragma unroll
        for (int e = 0; e < 4; e++) dq[n][e] = 0.f;
    int blocks = key_blocks(P, q0);
    Staged<T, D> kn = staged<T, D>(at<T>(P.k, head_base(P.ks, bh, P.heads)), P.ks[2], P.lk);
    Staged<T, D> vn = staged<T, D>(at<T>(P.v, head_base(P.vs, bh, P.heads)), P.vs[2], P.lk);
    stage_fetch(kn, 0);
    stage_fetch(vn, 0);
    for (int kb = 0; kb < blocks; kb++) {
        int k0 = ROWS * kb;
        sync_block();
        stage_store(kn, kt);
        stage_store(vn, vt);
        sync_block();
        if (kb + 1 < blocks) {
            stage_fetch(kn, k0 + ROWS);
            stage_fetch(vn, k0 + ROWS);
        }
        float s[8][4], dp[8][4];
        times_transposed<D>(s, qa, kt);
        times_transposed<D>(dp, oa, vt);
        probabilities<false>(P, s, dp, lse2, delta, 0, 0, q0, k0, sl);
        times<D>(dq, dp, kt);
    }
    store_rows<D>(P.dq + (long long)bh * P.lq * D, dq, q0, P.lq, P.scale);
}

#define INSTANCES(NAME, T, D)                                                                                   \
    KERNEL umgen_flash2_forward_##NAME(Params p) { forward<T, D>(p); }                                         \
    KERNEL umgen_flash2_backward_kv_##NAME(Params p) { backward_kv<T, D>(p); }                                 \
    KERNEL umgen_flash2_backward_q_##NAME(Params p) { backward_q<T, D>(p); }

INSTANCES(f32_64, float, 64)
INSTANCES(bf16_64, u16, 64)
INSTANCES(f32_32, float, 32)
INSTANCES(bf16_32, u16, 32)
