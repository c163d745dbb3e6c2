// FlashAttention-2 in CUDA C for NVRTC (`train.attention = "flash2"`): forward, key/value gradients and query
// gradients, one kernel each (and, on `wgmma`, the one-pass backward kernel that computes all three
// gradients, `train.kernels.attention_backward = "one-pass"`). Operands f32 or bf16 (`T`), converted to bf16
// as they enter shared memory; products on the tensor cores (`mma.sync` m16n8k16, bf16 in, f32 accumulation);
// scores, probabilities and their gradients stay in registers (the accumulator layout of one product is the
// operand layout of the next). Results (output, gradients) are written in `T`, the log-sum-exp in f32. Each
// block of 4 or 8 warps owns 16 rows per warp (queries, or keys for the key/value gradients) and walks the
// other side in tiles of 64, the next tile read into registers while the current one's products run (8
// warps). Head size `D`: 64 or 32. Where NVRTC targets sm_90a (on an H100), the head size 64 products run on
// `wgmma` (`flash2_warp.cu`): 64 rows a warpgroup, B and the block's own rows read from swizzled tiles in
// shared memory, P and dS from registers.
//
// NVRTC compiles `flash2_warp.cu` (primitives) and `flash2_tiles.cu` (parameters, tiles, fragment products)
// and `flash2_dq.cu` (the one-pass backward pass's queries' gradient) followed by this file
// (`umgen_cuda::source::FLASH2` joins them). The same source compiles on the host (`UMGEN_EMULATED`),
// where `flash2_emulator.cpp` runs every thread of a block and defines the warp-level primitives, so that
// fragment layouts are checked without a GPU.

// Columns (queries, or keys for the query gradients) of a tile that the backward kernels take at a time:
// 32 (half a tile) or 64 (the whole tile). 32 halves their score and score-gradient registers and the
// key/value kernel's spills (336 against 528 bytes a thread in bf16), and was 11-16 % faster on an H100
// (docs/decisions/005-training-attention-flash2.md). Define it before this file to change it (`UMGEN_FLASH2_SOURCE`).
#ifndef SUB
#define SUB 32
#endif

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

// One key tile's step of the forward pass's online softmax: the raw scores `s` become probabilities, the
// running maximum `m` (log2 units) and sum move on, and the output accumulator `o` is rescaled. Only with
// MASK are keys past the end and (causal) after each query hidden: tiles that hide nothing skip the checks,
// which were most of the per-score instructions (the scores are scaled inside the exponent's FMA).
template <bool MASK, int D>
DEV void softmax_tile(const Params& P, float (*s)[4], float (*o)[4], float* m, float* s_sum, int q0, int k0,
                      float sl) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int half = 0; half < 2; half++) {
        int query = q0 + 16 * warp_id() + g + 8 * half;
        float mx = NEG_INF;
#pragma unroll
        for (int j = 0; j < 8; j++)
#pragma unroll
            for (int e = 0; e < 2; e++) {
                float x = s[j][2 * half + e];
                if (MASK) {
                    int key = k0 + 8 * j + 2 * t + e;
                    if (key >= P.lk || (P.causal && key > query + P.off)) x = NEG_INF;
                    s[j][2 * half + e] = x;
                }
                mx = fmaxf(mx, x);
            }
        float m_new = fmaxf(m[half], quad_max(mx) * sl);
        // A row that has seen no key yet keeps exponents finite.
        float base = m_new == NEG_INF ? 0.f : m_new;
        float alpha = exp2f(m[half] - base);
        float sum = 0.f;
#pragma unroll
        for (int j = 0; j < 8; j++)
#pragma unroll
            for (int e = 0; e < 2; e++) {
                float p = exp2f(fmaf(s[j][2 * half + e], sl, -base));
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
}

template <typename T, int D>
DEV void forward(const Params& P) {
    SHARED TILE_ALIGNED u16 qt[TILE(MAX_ROWS, D)];
    SHARED TILE_ALIGNED u16 kt[TILE(ROWS, D)];
    SHARED TILE_ALIGNED u16 vt[TILE(ROWS, D)];
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    int l = lane_id(), g = l >> 2, t = l & 3;
    const float sl = P.scale * LOG2E;
    load_tile<T, D>(qt, at<T>(P.q, head_base(P.qs, bh, P.heads)), P.qs[2], q0, P.lq, block_rows());
    sync_block();
    // On `wgmma` the queries stay in shared memory (`rows_times_transposed`).
    constexpr bool WG = WGMMA && D == 64;
    u32 qa[WG ? 1 : D / 16][4];
    if constexpr (!WG) load_a<D>(qa, qt);
    float o[D / 8][4], m[2] = {NEG_INF, NEG_INF}, s_sum[2] = {0.f, 0.f};
    zero<D / 8>(o);
    int blocks = key_blocks(P, q0);
    Staged<T, D> kn = staged_from<T, D>(P.k, P.ks, bh, P.heads, P.lk, 0);
    Staged<T, D> vn = staged_from<T, D>(P.v, P.vs, bh, P.heads, P.lk, 0);
    for (int kb = 0; kb < blocks; kb++) {
        int k0 = ROWS * kb;
        store_staged(kn, vn, kt, vt);
        fetch_next(kn, vn, k0, kb + 1 < blocks);
        float s[8][4];
        if constexpr (WG)
            rows_times_transposed<D>(s, qt, kt);
        else
            times_transposed<D>(s, qa, kt);
        // The tile crosses the keys' end, or (causal) some key of it comes after the block's first query.
        if (k0 + ROWS > P.lk || (P.causal && k0 + ROWS - 1 > q0 + P.off))
            softmax_tile<true, D>(P, s, o, m, s_sum, q0, k0, sl);
        else
            softmax_tile<false, D>(P, s, o, m, s_sum, q0, k0, sl);
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
    store_rows<T, D>(P.out, head_base(P.outs, bh, P.heads), P.outs[2], o, q0, P.lq, 1.f);
}

// A head's f32 per-query values (log-sum-exp or delta): the head's first, and the queries' stride.
struct QueryValues {
    const float* head;
    long long stride;
};

// The per-query values `src` (strides `s`) of head `bh`; taken once a kernel, as the head's offset costs
// two integer divisions.
DEV QueryValues query_values(const float* src, const long long* s, int bh, int heads) {
    return {src + head_base(s, bh, heads), s[2]};
}

// Query `q`'s value times `factor`; zero past `lq`.
DEV float query_value(QueryValues v, int q, int lq, float factor) {
    return q < lq ? v.head[v.stride * q] * factor : 0.f;
}

// Reads `count` per-query values from query `q0` on into `dst`, times `factor`; zeros past `lq`.
DEV void load_row_values(float* dst, QueryValues v, int q0, int lq, float factor, int count = ROWS) {
    for (int i = thread_id(); i < count; i += threads()) dst[i] = query_value(v, q0 + i, lq, factor);
}

// p = exp2(s · sl − lse2) where the key is visible, else 0; then ds = p ∘ (dp − delta). Rows and columns of
// the tiles are keys and queries (`keys_are_rows`) or queries and keys. Only with MASK are hidden pairs
// zeroed. Queries past their end meet zero-filled tiles, and in the key/value kernel so do keys past theirs
// (their products are zero or land in rows no one stores), so there only the tiles crossing a causal
// diagonal check. The query kernel also masks the tile crossing the keys' end: there a past-the-end key's
// probability exp2(−lse2) meets a zero key row, and would make inf · 0 = NaN for a row whose log-sum-exp is
// below about −88.
template <bool keys_are_rows, int NT, bool MASK>
DEV void probabilities(const Params& P, float (*s)[4], float (*dp)[4], const float* row_lse, const float* row_delta,
                       const float* col_lse, const float* col_delta, int r0, int c0, float sl) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int j = 0; j < NT; j++)
#pragma unroll
        for (int e = 0; e < 4; e++) {
            int r = 16 * warp_id() + g + 8 * (e >> 1), c = 8 * j + 2 * t + (e & 1);
            int query = keys_are_rows ? c0 + c : r0 + r, key = keys_are_rows ? r0 + r : c0 + c;
            float lse2 = keys_are_rows ? col_lse[c] : row_lse[r];
            float delta = keys_are_rows ? col_delta[c] : row_delta[r];
            bool masked = MASK && hidden(P, query, key);
            float p = masked ? 0.f : exp2f(fmaf(s[j][e], sl, -lse2));
            s[j][e] = p;
            dp[j][e] = p * (dp[j][e] - delta);
        }
}

// `probabilities` with the per-query values in registers (the `wgmma` kernels have no shared memory left
// for them): this thread's two (`lse2[h]`, `delta[h]` for rows g and g + 8) when the queries are the rows;
// when they are the columns, the tile's columns `lane` and `lane + 32`, each value read from the lane that
// holds it (`c_off` is the columns' offset in the tile).
template <bool keys_are_rows, int NT, bool MASK>
DEV void lane_probabilities(const Params& P, float (*s)[4], float (*dp)[4], const float* lse2, const float* delta,
                            int r0, int c0, int c_off, float sl) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int j = 0; j < NT; j++)
#pragma unroll
        for (int b = 0; b < 2; b++) {
            int c = 8 * j + 2 * t + b;
            float col_lse = 0.f, col_delta = 0.f;
            if (keys_are_rows) {
                col_lse = from_lane(lse2[(c_off + 8 * j) >> 5], (c_off + c) & 31);
                col_delta = from_lane(delta[(c_off + 8 * j) >> 5], (c_off + c) & 31);
            }
#pragma unroll
            for (int h = 0; h < 2; h++) {
                int e = 2 * h + b, r = 16 * warp_id() + g + 8 * h;
                int query = keys_are_rows ? c0 + c : r0 + r, key = keys_are_rows ? r0 + r : c0 + c;
                float l2 = keys_are_rows ? col_lse : lse2[h], dl = keys_are_rows ? col_delta : delta[h];
                bool masked = MASK && hidden(P, query, key);
                float p = masked ? 0.f : exp2f(fmaf(s[j][e], sl, -l2));
                s[j][e] = p;
                dp[j][e] = p * (dp[j][e] - dl);
            }
        }
}

// On `wgmma` (head size 64 on sm_90a) the two operands of the block's own rows stay in shared memory, read
// by the products as A (`rows_times_transposed`), and the other side streams through tiles of ROWS rows;
// elsewhere they enter registers once, through the streamed tiles (which then take MAX_ROWS rows). Either
// way 48 KiB of static shared memory at most.
#define OWN_ROWS(D) (WGMMA && (D) == 64 ? MAX_ROWS : 8)
#define STREAM_ROWS(D) (WGMMA && (D) == 64 ? ROWS : MAX_ROWS)

// With ONE_PASS (head size 64 on `wgmma` only) it also adds the queries' gradient into `dq_acc`
// (`flash2_dq.cu`), and masks the keys past their end: their zero rows give a dS of exp2(−lse2) · −delta
// (NaN for a row whose log-sum-exp is below about −88), which would meet K there.
template <typename T, int D, bool ONE_PASS = false>
DEV void backward_kv(const Params& P) {
    constexpr bool WG = WGMMA && D == 64;
    static_assert(!ONE_PASS || WG, "the one-pass backward pass runs on wgmma, head size 64");
    SHARED TILE_ALIGNED u16 qt[TILE(STREAM_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 ot[TILE(STREAM_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 kr[TILE(OWN_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 vr[TILE(OWN_ROWS(D), D)];
    // Without `wgmma`, the tile's log-sum-exps and deltas (with it, registers: no room).
    SHARED float lse_s[WG ? 1 : ROWS], delta_s[WG ? 1 : ROWS];
    DYNAMIC_SHARED(u16, ds_tiles, ONE_PASS ? ONE_PASS_SHARED : 8);
    int bh = block_y(), k0 = block_rows() * block_x();
    if (bh >= P.count) return;
    float* dq_head = ONE_PASS ? P.dq_acc + (long long)bh * P.lq * D : nullptr;
    bool past_end = ONE_PASS && k0 + block_rows() > P.lk;
    const float sl = P.scale * LOG2E;
    const QueryValues lses = query_values(P.lse, P.ls, bh, P.heads);
    const QueryValues deltas = query_values(P.delta, P.es, bh, P.heads);
    const T* k_src = at<T>(P.k, head_base(P.ks, bh, P.heads));
    const T* v_src = at<T>(P.v, head_base(P.vs, bh, P.heads));
    u32 ka[WG ? 1 : D / 16][4], va[WG ? 1 : D / 16][4];
    own_rows<WG, T, D>(kr, vr, ka, va, qt, ot, k_src, P.ks[2], v_src, P.vs[2], k0, P.lk);
    float dk[D / 8][4], dv[D / 8][4];
    zero<D / 8>(dk);
    zero<D / 8>(dv);
    int first = 0;
    if (P.causal) first = max(0, k0 - P.off) / ROWS;
    int blocks = (P.lq + ROWS - 1) / ROWS;
    Staged<T, D> qn = staged_from<T, D>(P.q, P.qs, bh, P.heads, P.lq, ROWS * first);
    Staged<T, D> on = staged_from<T, D>(P.dout, P.os, bh, P.heads, P.lq, ROWS * first);
    for (int qb = first; qb < blocks; qb++) {
        int q0 = ROWS * qb;
        store_staged(qn, on, qt, ot);
        // With `wgmma`, this thread's queries' log-sum-exps and deltas: lane and lane + 32 of the tile.
        float lse2[2], delta[2];
        if constexpr (WG) {
#pragma unroll
            for (int h = 0; h < 2; h++) {
                int q = q0 + lane_id() + 32 * h;
                lse2[h] = query_value(lses, q, P.lq, LOG2E);
                delta[h] = query_value(deltas, q, P.lq, 1.f);
            }
        } else {
            load_row_values(lse_s, lses, q0, P.lq, LOG2E);
            load_row_values(delta_s, deltas, q0, P.lq, 1.f);
        }
        fetch_next(qn, on, q0, qb + 1 < blocks);
#pragma unroll
        for (int c = 0; c < ROWS; c += SUB) {
            float s[SUB / 8][4], dp[SUB / 8][4];
            const u16 *qc = qt + at_tile<D>(c, 0), *oc = ot + at_tile<D>(c, 0);
            both_times_transposed<D, SUB / 8>(s, kr, ka, qc, dp, vr, va, oc);
            // Some key of the block comes after some query of these columns.
            bool mask = past_end || (P.causal && k0 + block_rows() - 1 > q0 + c + P.off);
            if constexpr (WG) {
                if (mask)
                    lane_probabilities<true, SUB / 8, true>(P, s, dp, lse2, delta, k0, q0 + c, c, sl);
                else
                    lane_probabilities<true, SUB / 8, false>(P, s, dp, lse2, delta, k0, q0 + c, c, sl);
            } else if (mask) {
                probabilities<true, SUB / 8, true>(P, s, dp, 0, 0, lse_s + c, delta_s + c, k0, q0 + c, sl);
            } else {
                probabilities<true, SUB / 8, false>(P, s, dp, 0, 0, lse_s + c, delta_s + c, k0, q0 + c, sl);
            }
            if constexpr (ONE_PASS) store_ds<SUB>(ds_tile<SUB>(ds_tiles, c), dp);
            both_times<D, SUB / 8>(dv, s, oc, dk, dp, qc);
            if constexpr (ONE_PASS)
                add_dq_step<SUB>(dq_head, ds_tile<SUB>(ds_tiles, c), kr, (float*)(ds_tiles + DS_TILES), q0 + c, P.lq);
        }
    }
    if (ONE_PASS && thread_id() == 0) bulk_wait();
    store_rows<T, D>(P.dk, head_base(P.dks, bh, P.heads), P.dks[2], dk, k0, P.lk, P.scale);
    store_rows<T, D>(P.dv, head_base(P.dvs, bh, P.heads), P.dvs[2], dv, k0, P.lk, 1.f);
}

template <typename T, int D>
DEV void backward_q(const Params& P) {
    constexpr bool WG = WGMMA && D == 64;
    SHARED TILE_ALIGNED u16 kt[TILE(STREAM_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 vt[TILE(STREAM_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 qr[TILE(OWN_ROWS(D), D)];
    SHARED TILE_ALIGNED u16 orows[TILE(OWN_ROWS(D), D)];
    SHARED float lse_s[WG ? 1 : MAX_ROWS], delta_s[WG ? 1 : MAX_ROWS];
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    const float sl = P.scale * LOG2E;
    const QueryValues lses = query_values(P.lse, P.ls, bh, P.heads);
    const QueryValues deltas = query_values(P.delta, P.es, bh, P.heads);
    // The rows' log-sum-exps and deltas: with `wgmma` this thread's (rows g and g + 8 of its warp).
    float lse2[2], delta[2];
    if constexpr (WG) {
#pragma unroll
        for (int h = 0; h < 2; h++) {
            int q = q0 + 16 * warp_id() + (lane_id() >> 2) + 8 * h;
            lse2[h] = query_value(lses, q, P.lq, LOG2E);
            delta[h] = query_value(deltas, q, P.lq, 1.f);
        }
    } else {
        load_row_values(lse_s, lses, q0, P.lq, LOG2E, block_rows());
        load_row_values(delta_s, deltas, q0, P.lq, 1.f, block_rows());
    }
    const T* q_src = at<T>(P.q, head_base(P.qs, bh, P.heads));
    const T* o_src = at<T>(P.dout, head_base(P.os, bh, P.heads));
    u32 qa[WG ? 1 : D / 16][4], oa[WG ? 1 : D / 16][4];
    own_rows<WG, T, D>(qr, orows, qa, oa, kt, vt, q_src, P.qs[2], o_src, P.os[2], q0, P.lq);
    float dq[D / 8][4];
    zero<D / 8>(dq);
    int blocks = key_blocks(P, q0);
    Staged<T, D> kn = staged_from<T, D>(P.k, P.ks, bh, P.heads, P.lk, 0);
    Staged<T, D> vn = staged_from<T, D>(P.v, P.vs, bh, P.heads, P.lk, 0);
    for (int kb = 0; kb < blocks; kb++) {
        int k0 = ROWS * kb;
        store_staged(kn, vn, kt, vt);
        fetch_next(kn, vn, k0, kb + 1 < blocks);
#pragma unroll
        for (int c = 0; c < ROWS; c += SUB) {
            float s[SUB / 8][4], dp[SUB / 8][4];
            const u16 *kc = kt + at_tile<D>(c, 0), *vc = vt + at_tile<D>(c, 0);
            both_times_transposed<D, SUB / 8>(s, qr, qa, kc, dp, orows, oa, vc);
            // Some key of these columns comes after the keys' end or (causal) the block's first query.
            bool mask = k0 + c + SUB > P.lk || (P.causal && k0 + c + SUB - 1 > q0 + P.off);
            if constexpr (WG) {
                if (mask)
                    lane_probabilities<false, SUB / 8, true>(P, s, dp, lse2, delta, q0, k0 + c, c, sl);
                else
                    lane_probabilities<false, SUB / 8, false>(P, s, dp, lse2, delta, q0, k0 + c, c, sl);
            } else if (mask) {
                probabilities<false, SUB / 8, true>(P, s, dp, lse_s, delta_s, 0, 0, q0, k0 + c, sl);
            } else {
                probabilities<false, SUB / 8, false>(P, s, dp, lse_s, delta_s, 0, 0, q0, k0 + c, sl);
            }
            times<D, SUB / 8>(dq, dp, kc);
        }
    }
    store_rows<T, D>(P.dq, head_base(P.dqs, bh, P.heads), P.dqs[2], dq, q0, P.lq, P.scale);
}

// The one-pass backward pass's kernels for operands `T` (head size 64 on `wgmma`).
#define ONE_PASS_64(NAME, T)                                                                                   \
    KERNEL umgen_flash2_dq_zero_##NAME(Params p) { dq_zero(p); }                                               \
    KERNEL umgen_flash2_backward_one_pass_##NAME(Params p) { backward_kv<T, 64, true>(p); }                    \
    KERNEL umgen_flash2_dq_store_##NAME(Params p) { dq_store<T>(p); }

#define INSTANCES(NAME, T, D)                                                                                   \
    KERNEL umgen_flash2_forward_##NAME(Params p) { forward<T, D>(p); }                                         \
    KERNEL umgen_flash2_backward_kv_##NAME(Params p) { backward_kv<T, D>(p); }                                 \
    KERNEL umgen_flash2_backward_q_##NAME(Params p) { backward_q<T, D>(p); }

// One type and head size only where `UMGEN_INSTANCE` says which (kernels launched on cubecl's stream,
// `side/cubecl_stream.rs`).
#ifdef UMGEN_INSTANCE
UMGEN_INSTANCE
#else
INSTANCES(f32_64, float, 64)
INSTANCES(bf16_64, u16, 64)
INSTANCES(f32_32, float, 32)
INSTANCES(bf16_32, u16, 32)
#if WGMMA
ONE_PASS_64(f32_64, float)
ONE_PASS_64(bf16_64, u16)
#endif
#endif
