// Matrix-vector products of the decoding step: `y = in(x) · Wᵀ` for up to GEMV_ROWS input rows (scenes),
// one output column per warp, the weight row read once for every scene with 16-byte loads. What feeds the
// product and what happens to its result are chosen per launch, so that a decoding step is one launch per
// product and nothing else:
//
// input (`in_mode`): 0 the rows of `x`; 1 their layer norm (each block computes the rows' statistics);
//   2 the OAR input's embedding of the previous token, `table[row] + pos_emb[p − 1]`, where the table row
//   is `row_base[seg_of[p − 1]] + tok[s][p − 1]` and `p` the device position;
// result (`out_mode`, after the bias and GELU when asked): 0 stored in `out`; 1 added to `out` (the
//   residual stream); 2 the attention's q (to `out`), k and v (to the caches at position `p`); 3 the OAR
//   input: `(p == 0 ? bos : y) + h[s][p]`.

#define GEMV_ROWS 8

struct Gemv {
    const WT* w;              // [n][k]
    const float* x;           // [m][ldx] (in_mode 0, 1)
    const float* g;           // layer norm scale and shift (in_mode 1)
    const float* b;
    const float* table;       // in_mode 2
    const int* row_base;
    const int* seg_of;
    const int* tok;           // [m][ntok]
    const float* pos_emb;     // [N][k]
    const int* pos;           // the device position (in_mode 2, out_mode 2 and 3)
    const float* bias;        // [n] or null
    float* out;               // [m][ldo]
    WT* kc;                   // out_mode 2: key and value caches [m][heads][cap][dh]
    WT* vc;
    const float* bos;         // out_mode 3: [n]
    const float* h;           // out_mode 3: [m][·][n], scene stride h_ss
    long long h_ss;
    int m, n, k, ldx, ldo, ntok;
    int in_mode, gelu, out_mode;
    int heads, dh, cap;
};

// Element `i` of input row `s`.
DEV float gemv_in1(const Gemv& P, const float* st, const float* trow, const float* prow, int s, int i) {
    if (P.in_mode == 2) return trow[i] + prow[i];
    const float x = P.x[(long long)s * P.ldx + i];
    if (P.in_mode == 1) return (x - st[2 * s]) * st[2 * s + 1] * P.g[i] + P.b[i];
    return x;
}

// Elements `c..c + 8` of input row `s`.
DEV void gemv_in8(const Gemv& P, const float* st, const float* trow, const float* prow, int s, int c, float* v) {
    if (P.in_mode == 2) {
        float e[8];
        load8(trow + c, v);
        load8(prow + c, e);
        for (int i = 0; i < 8; i++) v[i] += e[i];
        return;
    }
    load8(P.x + (long long)s * P.ldx + c, v);
    if (P.in_mode == 1) {
        float g[8], b[8];
        load8(P.g + c, g);
        load8(P.b + c, b);
        for (int i = 0; i < 8; i++) v[i] = (v[i] - st[2 * s]) * st[2 * s + 1] * g[i] + b[i];
    }
}

// What happens to result `r` of input row `s`, output column `j`, whose bias is `bias_j` and whose output
// held `prev` (out_mode 1; both loaded ahead, so that no load waits at the end).
DEV void gemv_out(const Gemv& P, int s, long long j, float r, float bias_j, float prev) {
    if (P.bias) r += bias_j;
    if (P.gelu) r = gelu(r);
    float* o = P.out + (long long)s * P.ldo + j;
    if (P.out_mode == 0) {
        *o = r;
    } else if (P.out_mode == 1) {
        *o = prev + r;
    } else if (P.out_mode == 2) {
        const long long d = (long long)P.heads * P.dh;
        if (j < d) {
            *o = r;
            return;
        }
        const long long c = j - d;
        WT* cache = c < d ? P.kc : P.vc;
        const long long col = c < d ? c : c - d;
        const long long head = col / P.dh, e = col % P.dh;
        store(cache + (((long long)s * P.heads + head) * P.cap + *P.pos) * P.dh + e, r);
    } else {
        const int p = *P.pos;
        *o = (p == 0 ? P.bos[j] : r) + P.h[s * P.h_ss + (long long)p * P.n + j];
    }
}

// Warps that share an output column: enough that each takes at most GEMV_SLICE inputs (a power of two, at
// most the block's 8). The launch gives blocks of 8 warps: `ceil(n / (8 / gemv_split(k)))`, at most as many
// as are resident on the GPU at once.
#define GEMV_SLICE 1024
DEV int gemv_split(int k) {
    int split = 1;
    while (split < 8 && split * GEMV_SLICE < k) split *= 2;
    return split;
}

// Loads slice `k0..k1` of weight row `j` (8-wide, the first 4 × 256 inputs of it) into `wv`, packed.
DEV void gemv_prefetch(const Gemv& P, long long j, int k0, int k1, Packed8* wv) {
    const WT* wr = P.w + j * P.k;
#pragma unroll
    for (int c = 0; c < 4; c++) {
        const int at = k0 + lane_id() * 8 + 256 * c;
        if (at < k1) load_packed8(wr + at, wv[c]);
    }
}

// The grid (SMs × resident blocks, or fewer) walks groups of output columns: each warp takes `slice`
// inputs of one column of the group. A warp's weights for its first group are loaded before the wait for
// the kernel before (weights are never written), those of its next group while the current one is summed;
// the rows' norm statistics are computed once per block. With several warps a column, their sums meet in
// shared memory.
// Three blocks an SM (registers capped at 85): the grid of SMs × resident blocks then covers a `paper` layer's
// column groups (288 to 384 of them) in one turn, where two blocks an SM left a second group to a third of
// the blocks (`paper` 1.05 → 0.97 ms a token on an H200; `small`, whose groups fit either way, 0.161 → 0.167).
KERNEL_RESIDENT(3) umgen_gemv(const Gemv P) {
    SHARED float st[2 * GEMV_ROWS];
    SHARED float partial[8][GEMV_ROWS];
    griddep_launch();
    const long long bx = block_x(), nb = blocks();
    const int m = P.m;
    const int split = gemv_split(P.k), per_block = warps_per_block() / split;
    const int local = warp_id() / split, part = warp_id() % split;
    const int slice = (P.k + split - 1) / split;
    const int k0 = part * slice, k1 = k0 + slice < P.k ? k0 + slice : P.k;
    const bool vec = (P.k & 7) == 0 && (slice & 7) == 0;
    const long long groups = (P.n + per_block - 1) / per_block;
    Packed8 wv[4];
    // The bias is a weight too: the column's is loaded with its row.
    float bias_j = 0.f;
    {
        const long long j = bx * per_block + local;
        if (vec && j < P.n) gemv_prefetch(P, j, k0, k1, wv);
        if (P.bias && j < P.n) bias_j = P.bias[j];
    }
    // Nothing above read what an earlier kernel writes: the weights' loads are in flight across the wait.
    griddep_wait();
    if (P.in_mode == 1) {
        // Warp s: row s's mean and 1/σ (biased variance, ε 1e-5, as burn's LayerNorm), its first 1,024
        // values read once into registers.
        const int s = warp_id();
        if (s < m) {
            const float* xr = P.x + (long long)s * P.ldx;
            float v[32], sum = 0.f;
#pragma unroll
            for (int t = 0; t < 32; t++) {
                const int i = lane_id() + 32 * t;
                v[t] = i < P.k ? xr[i] : 0.f;
                sum += v[t];
            }
            for (int i = lane_id() + 1024; i < P.k; i += 32) sum += xr[i];
            const float mean = warp_sum(sum) / P.k;
            float sq = 0.f;
#pragma unroll
            for (int t = 0; t < 32; t++) {
                const float d = v[t] - mean;
                sq += lane_id() + 32 * t < P.k ? d * d : 0.f;
            }
            for (int i = lane_id() + 1024; i < P.k; i += 32) {
                const float d = xr[i] - mean;
                sq += d * d;
            }
            const float var = warp_sum(sq) / P.k;
            if (lane_id() == 0) {
                st[2 * s] = mean;
                st[2 * s + 1] = rsqrtf(var + 1e-5f);
            }
        }
        sync_block();
    }
    // The previous token's table and position rows (in_mode 2); position 0 reads row 0 and discards it.
    const float* trow[GEMV_ROWS];
    for (int s = 0; s < GEMV_ROWS; s++) trow[s] = P.table;
    const float* prow = P.pos_emb;
    if (P.in_mode == 2) {
        const int p = *P.pos;
        const int q = p > 0 ? p - 1 : 0;
        prow = P.pos_emb + (long long)q * P.k;
        for (int s = 0; s < GEMV_ROWS; s++)
            if (s < m) trow[s] = P.table + (long long)(P.row_base[P.seg_of[q]] + P.tok[s * P.ntok + q]) * P.k;
    }
    for (long long g = bx; g < groups; g += nb) {
        const long long j = g * per_block + local, jn = (g + nb) * per_block + local;
        const bool here = j < P.n;
        const bool writer = here && part == 0 && lane_id() == 0;
        // The residual stream's values this column adds to, asked for before the products.
        float prev[GEMV_ROWS];
        for (int s = 0; s < GEMV_ROWS; s++)
            prev[s] = writer && P.out_mode == 1 && s < m ? P.out[(long long)s * P.ldo + j] : 0.f;
        Packed8 wn[4];
        if (vec && jn < P.n) gemv_prefetch(P, jn, k0, k1, wn);
        const float bias_next = P.bias && jn < P.n ? P.bias[jn] : 0.f;
        float acc[GEMV_ROWS];
        for (int s = 0; s < GEMV_ROWS; s++) acc[s] = 0.f;
        if (here && vec) {
#pragma unroll
            for (int c = 0; c < 4; c++) {
                const int at = k0 + lane_id() * 8 + 256 * c;
                if (at < k1) {
                    float w8[8];
                    unpack8(wv[c], w8);
                    for (int s = 0; s < GEMV_ROWS; s++) {
                        if (s < m) {
                            float xv[8];
                            gemv_in8(P, st, trow[s], prow, s, at, xv);
                            for (int e = 0; e < 8; e++) acc[s] = fmaf(w8[e], xv[e], acc[s]);
                        }
                    }
                }
            }
            // Slices past 4 × 256 inputs (k over 8 warps × 1,024) go on without prefetched weights.
            const WT* wr = P.w + j * P.k;
            for (int at = k0 + lane_id() * 8 + 1024; at < k1; at += 256) {
                float w8[8];
                load8(wr + at, w8);
                for (int s = 0; s < GEMV_ROWS; s++) {
                    if (s < m) {
                        float xv[8];
                        gemv_in8(P, st, trow[s], prow, s, at, xv);
                        for (int e = 0; e < 8; e++) acc[s] = fmaf(w8[e], xv[e], acc[s]);
                    }
                }
            }
        } else if (here) {
            const WT* wr = P.w + j * P.k;
            for (int i = k0 + lane_id(); i < k1; i += 32) {
                const float wv1 = value(wr + i);
                for (int s = 0; s < GEMV_ROWS; s++)
                    if (s < m) acc[s] = fmaf(wv1, gemv_in1(P, st, trow[s], prow, s, i), acc[s]);
            }
        }
        for (int s = 0; s < GEMV_ROWS; s++)
            if (s < m) acc[s] = warp_sum(acc[s]);
        if (split > 1) {
            if (lane_id() == 0)
                for (int s = 0; s < GEMV_ROWS; s++) partial[warp_id()][s] = acc[s];
            sync_block();
            if (part == 0 && lane_id() == 0)
                for (int s = 0; s < GEMV_ROWS; s++)
                    for (int q = 1; q < split; q++) acc[s] += partial[warp_id() + q][s];
            sync_block();
        }
        if (writer)
            for (int s = 0; s < GEMV_ROWS; s++)
                if (s < m) gemv_out(P, s, j, acc[s], bias_j, prev[s]);
#pragma unroll
        for (int c = 0; c < 4; c++) wv[c] = wn[c];
        bias_j = bias_next;
    }
}
