// The building blocks of the flash2 kernels (`flash2.cu`, which NVRTC compiles after this file): the
// kernels' parameters, bf16 rounding, tiles moved from global to shared memory, and the fragment products of
// one warp (`mma.sync`) or warpgroup (`wgmma`). `flash2_warp.cu`, before this file, defines the GPU's
// warp-level primitives; on the host (`UMGEN_EMULATED`), `flash2_emulator.cpp` defines them instead.

// Hopper's warpgroup products (`wgmma.mma_async`) take the head size 64 products where the compiler targets
// `sm_90a` (both streams' builds do on a compute capability 9.0 device, `flash2.rs`): one instruction
// multiplies 64 rows (the four warps of a warpgroup, 16 each, with the A fragments of `mma.sync`) by a B
// operand read from shared memory by the tensor cores, where `mma.sync` needs one `ldmatrix` a warp for
// every two 16×8 products. Elsewhere, and for head size 32, the kernels run on `mma.sync`. The emulator
// takes this path with `UMGEN_WGMMA_EMULATED`.
#if defined(__CUDA_ARCH_FEAT_SM90_ALL) || defined(UMGEN_WGMMA_EMULATED)
#define WGMMA 1
#else
#define WGMMA 0
#endif

// Rows of the tiles a block walks through; a block's own rows are 16 per warp (`block_rows`), at most
// MAX_ROWS.
#define ROWS 64
#define MAX_ROWS 128
DEV int block_rows() { return 16 * (threads() >> 5); }

// Where element (row, col) of a tile lies. On `wgmma`, rows of 64 are 128 bytes with their 16-byte chunks
// swizzled (chunk c of row r at c ^ (r % 8)): the layout it reads with the 128-byte swizzle, also free of
// bank conflicts for `ldmatrix` and a warp's row of stores. Otherwise rows are padded by 8 elements (as
// conflict-free, and cheaper to address: the `mma.sync` kernels spill less).
template <int D>
DEV int at_tile(int row, int col) {
    if (WGMMA && D == 64) return row * 64 + ((((col >> 3) ^ row) & 7) << 3) + (col & 7);
    return row * (D + 8) + col;
}
// Elements of a tile of `rows` rows.
#define TILE(rows, D) ((rows) * (WGMMA && (D) == 64 ? 64 : (D) + 8))
#define NEG_INF (-__int_as_float(0x7f800000))
#define LOG2E 1.4426950408889634f
#define LN2 0.6931471805599453f

// Everything a pass reads and writes. Strides are in elements: (batch, head, row); the head dimension is
// contiguous. out, dq, dk and dv are in the operands' type, at their strides (`outs`, `dqs`, `dks`, `dvs`;
// the caller lays them out merged, `[b, rows, h·D]`, as the next product reads them): bf16 operands give
// the bf16 results the products around the attention read, as PyTorch's autocast does. The log-sum-exp is
// f32, contiguous `[b, h, lq]`.
struct Params {
    const void* q;
    const void* k;
    const void* v;
    const void* dout;
    const float* lse;
    const float* delta;
    void* out;
    float* lse_out;
    void* dq;
    void* dk;
    void* dv;
    long long qs[3], ks[3], vs[3], os[3], ls[3], es[3];
    long long outs[3], dqs[3], dks[3], dvs[3];
    int heads, lq, lk, off, causal;
    float scale;
    // Heads in all (batch × heads): the grid may hold more blocks than that.
    int count;
    // The one-pass backward pass's f32 accumulator of the queries' gradient, `[count, lq, 64]` contiguous.
    float* dq_acc;
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


DEV u16 to_bf16(float x) { return bf16_bits(x); }
DEV u16 to_bf16(u16 x) { return x; }

// Eight consecutive elements at `p` (16-byte aligned) as bf16 pairs.
DEV void chunk8(u32* r, const u16* p) {
    uint4 v = *(const uint4*)p;
    r[0] = v.x, r[1] = v.y, r[2] = v.z, r[3] = v.w;
}
DEV void chunk8(u32* r, const float* p) {
    float4 a = *(const float4*)p, b = *(const float4*)(p + 4);
    r[0] = pack(a.x, a.y), r[1] = pack(a.z, a.w), r[2] = pack(b.x, b.y), r[3] = pack(b.z, b.w);
}

// Whether rows `stride` elements apart from `src` on start on 16 bytes, so that they move in 8-element chunks.
template <typename T>
DEV bool in_chunks(const T* src, long long stride) {
    return (unsigned long long)src % 16 == 0 && (stride * (long long)sizeof(T)) % 16 == 0;
}

// Rows [row0, row0 + count) of one head of an operand (`src` at the head's first element, rows `stride`
// elements apart) into `tile` (laid out by `at_tile`), zeros past `rows`: in 8-element chunks where the rows
// allow, else element by element.
template <typename T, int D>
DEV void load_tile(u16* tile, const T* src, long long stride, int row0, int rows, int count = ROWS) {
    if (in_chunks(src, stride)) {
#pragma unroll 1
        for (int i = thread_id(); i < count * D / 8; i += threads()) {
            int r = i / (D / 8), c = 8 * (i % (D / 8)), row = row0 + r;
            u32 v[4] = {0u, 0u, 0u, 0u};
            if (row < rows) chunk8(v, src + stride * row + c);
            *(uint4*)(tile + at_tile<D>(r, c)) = make_uint4(v[0], v[1], v[2], v[3]);
        }
    } else {
#pragma unroll 1
        for (int i = thread_id(); i < count * D; i += threads()) {
            int r = i / D, c = i % D;
            int row = row0 + r;
            tile[at_tile<D>(r, c)] = row < rows ? to_bf16(src[stride * row + c]) : (u16)0;
        }
    }
    to_async_proxy();
}

// The next tile of an operand on its way to shared memory: read from global memory into registers (as bf16)
// before the current tile's products, stored after them, so that the loads' latency overlaps the products.
// Each thread moves whole 8-element chunks (one 16-byte load and store; two loads for f32), where pairs of
// elements took four times the loads, stores and address arithmetic (integer work was the busiest pipe of
// the `wgmma` forward kernel, Nsight Compute, docs/decisions/005-training-attention-flash2.md). Only blocks of 8 warps whose head's rows
// start on 16 bytes (`chunks`: burn's buffers as the backbone lays them out) stage; others load the tile
// when it is stored.
template <typename T, int D>
struct Staged {
    const T* src;
    long long stride;
    int rows, next;
    bool chunks;
    u32 r[ROWS * D / 2 / 256];
};

template <typename T, int D>
DEV void stage_fetch(Staged<T, D>& s, int row0) {
    s.next = row0;
    if (!s.chunks) return;
#pragma unroll
    for (int k = 0; k < ROWS * D / 2048; k++) {
        int i = thread_id() + 256 * k, r = i / (D / 8), c = 8 * (i % (D / 8)), row = row0 + r;
        if (row < s.rows)
            chunk8(s.r + 4 * k, s.src + s.stride * row + c);
        else
            s.r[4 * k] = s.r[4 * k + 1] = s.r[4 * k + 2] = s.r[4 * k + 3] = 0u;
    }
}

template <typename T, int D>
DEV void stage_store(const Staged<T, D>& s, u16* tile) {
    if (!s.chunks) {
        load_tile<T, D>(tile, s.src, s.stride, s.next, s.rows);
        return;
    }
#pragma unroll
    for (int k = 0; k < ROWS * D / 2048; k++) {
        int i = thread_id() + 256 * k, r = i / (D / 8), c = 8 * (i % (D / 8));
        *(uint4*)(tile + at_tile<D>(r, c)) = make_uint4(s.r[4 * k], s.r[4 * k + 1], s.r[4 * k + 2], s.r[4 * k + 3]);
    }
    to_async_proxy();
}

// An operand (strides `s`) of head `bh` staged from its row `row0` on.
template <typename T, int D>
DEV Staged<T, D> staged_from(const void* src, const long long* s, int bh, int heads, int rows, int row0) {
    Staged<T, D> st;
    st.src = (const T*)src + s[0] * (bh / heads) + s[1] * (bh % heads);
    st.stride = s[2], st.rows = rows, st.next = 0;
    st.chunks = threads() == 256 && in_chunks(st.src, st.stride);
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
    for (int kk = 0; kk < D / 16; kk++) ldsm4(a[kk], tile + at_tile<D>(row, 16 * kk + (m >> 1) * 8));
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

// Step kk (16 columns) of p (accumulator tiles, 16 × 8 · NT) as an A fragment of bf16 pairs: the accumulator
// layout of one product is, pairwise, the operand layout of the next.
DEV void pack_step(u32* a, const float (*p)[4], int kk) {
    a[0] = pack(p[2 * kk][0], p[2 * kk][1]), a[1] = pack(p[2 * kk][2], p[2 * kk][3]);
    a[2] = pack(p[2 * kk + 1][0], p[2 * kk + 1][1]), a[3] = pack(p[2 * kk + 1][2], p[2 * kk + 1][3]);
}

#if WGMMA
// The D / 16 steps of acc += rows · tileᵀ (`wg_mma_ss`: A from the block's rows in shared memory), issued
// into the open group.
template <int D, int NT>
DEV void ss_steps(float (*acc)[4], const u16* rows, const u16* tile) {
#pragma unroll
    for (int kk = 0; kk < D / 16; kk++) wg_mma_ss<NT, false>(acc, rows, tile, 16 * kk);
}

// The NT / 2 steps of acc (16 × D) += p · tile (`wg_mma`, N-major B: the tile's rows are k), p packed by
// `pack_step` into `a`, issued into the open group.
template <int D, int NT>
DEV void rs_steps(float (*acc)[4], const u32 (*a)[4], const u16* tile) {
#pragma unroll
    for (int kk = 0; kk < NT / 2; kk++) wg_mma<D / 8, true>(acc, a[kk], tile, 16 * kk);
}
#endif

// The block's rows of the two operands a backward kernel keeps for its whole loop: on `wgmma` (WG) into
// their own tiles `ra` and `rb`, which the products read as A; otherwise into the A fragments `a` and `b`,
// through the streamed tiles `ta` and `tb` (`block_fragments`).
template <bool WG, typename T, int D>
DEV void own_rows(u16* ra, u16* rb, u32 (*a)[4], u32 (*b)[4], u16* ta, u16* tb, const T* src_a, long long stride_a,
                  const T* src_b, long long stride_b, int row0, int rows) {
    if constexpr (WG) {
        load_tile<T, D>(ra, src_a, stride_a, row0, rows, block_rows());
        load_tile<T, D>(rb, src_b, stride_b, row0, rows, block_rows());
    } else {
        block_fragments<T, D>(a, b, ta, tb, src_a, stride_a, src_b, stride_b, row0, rows);
    }
}

// acc[j] (16 × 8 tiles, j < NT) = a · tileᵀ over the head dimension: `tile` holds 8 · NT rows of D.
template <int D, int NT = 8>
DEV void times_transposed(float (*acc)[4], const u32 (*a)[4], const u16* tile) {
    zero<NT>(acc);
#if WGMMA
    if constexpr (D == 64) {
        wg_hold<NT>(acc);
        wg_arrive();
#pragma unroll
        for (int kk = 0; kk < D / 16; kk++) wg_mma<NT, false>(acc, a[kk], tile, 16 * kk);
        wg_commit();
        wg_wait();
        wg_hold<NT>(acc);
        return;
    }
#endif
    int l = lane_id(), m = l >> 3;
#pragma unroll
    for (int kk = 0; kk < D / 16; kk++)
#pragma unroll
        for (int j = 0; j < NT; j += 2) {
            u32 b[4];
            ldsm4(b, tile + at_tile<D>(8 * (j + (m >> 1)) + (l & 7), 16 * kk + (m & 1) * 8));
            mma(acc[j], a[kk], b);
            mma(acc[j + 1], a[kk], b + 2);
        }
}

// acc[j] (16 × 8 tiles, j < NT) = this warp's rows of `rows` (the block's rows, `at_tile` layout) · tileᵀ:
// `times_transposed` with the A operand read from shared memory by `wgmma` (head size 64 on sm_90a only).
template <int D, int NT = 8>
DEV void rows_times_transposed(float (*acc)[4], const u16* rows, const u16* tile) {
#if WGMMA
    zero<NT>(acc);
    wg_hold<NT>(acc);
    wg_arrive();
    ss_steps<D, NT>(acc, rows, tile);
    wg_commit();
    wg_wait();
    wg_hold<NT>(acc);
#endif
}

// Two `rows_times_transposed` products in one `wgmma` group (one wait for both, the tensor cores never idle
// between them); without `wgmma`, one after the other on `mma.sync` from the A fragments `a` and `b`.
template <int D, int NT>
DEV void both_times_transposed(float (*acc)[4], const u16* rows, const u32 (*a)[4], const u16* tile,
                               float (*acc2)[4], const u16* rows2, const u32 (*b)[4], const u16* tile2) {
#if WGMMA
    if constexpr (D == 64) {
        zero<NT>(acc);
        zero<NT>(acc2);
        wg_hold<NT>(acc);
        wg_hold<NT>(acc2);
        wg_arrive();
        ss_steps<D, NT>(acc, rows, tile);
        ss_steps<D, NT>(acc2, rows2, tile2);
        wg_commit();
        wg_wait();
        wg_hold<NT>(acc);
        wg_hold<NT>(acc2);
        return;
    }
#endif
    times_transposed<D, NT>(acc, a, tile);
    times_transposed<D, NT>(acc2, b, tile2);
}

// acc (16 × D) += p · tile, p given as NT accumulator tiles (16 × 8 · NT), `tile` 8 · NT rows of D.
template <int D, int NT = 8>
DEV void times(float (*acc)[4], const float (*p)[4], const u16* tile) {
#if WGMMA
    if constexpr (D == 64) {
        u32 a[NT / 2][4];
#pragma unroll
        for (int kk = 0; kk < NT / 2; kk++) pack_step(a[kk], p, kk);
        wg_hold<D / 8>(acc);
        wg_arrive();
        rs_steps<D, NT>(acc, a, tile);
        wg_commit();
        wg_wait();
        wg_hold<D / 8>(acc);
        return;
    }
#endif
    int l = lane_id(), m = l >> 3;
#pragma unroll
    for (int kk = 0; kk < NT / 2; kk++) {
        u32 a[4];
        pack_step(a, p, kk);
#pragma unroll
        for (int n = 0; n < D / 8; n += 2) {
            u32 b[4];
            ldsm4t(b, tile + at_tile<D>(16 * kk + (m & 1) * 8 + (l & 7), 8 * (n + (m >> 1))));
            mma(acc[n], a, b);
            mma(acc[n + 1], a, b + 2);
        }
    }
}

// Two `times` products (acc += p · tile, acc2 += p2 · tile2) in one `wgmma` group; without it, one after the
// other.
template <int D, int NT>
DEV void both_times(float (*acc)[4], const float (*p)[4], const u16* tile, float (*acc2)[4], const float (*p2)[4],
                    const u16* tile2) {
#if WGMMA
    if constexpr (D == 64) {
        u32 a[NT / 2][4], b[NT / 2][4];
#pragma unroll
        for (int kk = 0; kk < NT / 2; kk++) {
            pack_step(a[kk], p, kk);
            pack_step(b[kk], p2, kk);
        }
        wg_hold<D / 8>(acc);
        wg_hold<D / 8>(acc2);
        wg_arrive();
        rs_steps<D, NT>(acc, a, tile);
        rs_steps<D, NT>(acc2, b, tile2);
        wg_commit();
        wg_wait();
        wg_hold<D / 8>(acc);
        wg_hold<D / 8>(acc2);
        return;
    }
#endif
    times<D, NT>(acc, p, tile);
    times<D, NT>(acc2, p2, tile2);
}

// A pair of adjacent results: two floats, or two bf16 values in one word.
DEV void store_pair(float* p, float lo, float hi) { p[0] = lo, p[1] = hi; }
DEV void store_pair(u16* p, float lo, float hi) { *(u32*)p = pack(lo, hi); }

// Rows (this warp's 16) of an accumulator (16 × D) into a result of type `T` (the operands') at `dst` +
// `base`, whose rows are `stride` apart, times `scale`.
template <typename T, int D>
DEV void store_rows(void* dst, long long base, long long stride, const float (*acc)[4], int row0, int rows,
                    float scale) {
    T* head = (T*)dst + base;
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int half = 0; half < 2; half++) {
        int row = row0 + 16 * warp_id() + g + 8 * half;
        if (row >= rows) continue;
#pragma unroll
        for (int n = 0; n < D / 8; n++)
            store_pair(head + row * stride + 8 * n + 2 * t, acc[n][2 * half] * scale, acc[n][2 * half + 1] * scale);
    }
}
