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

// What happens to result `r` of input row `s`, output column `j`.
DEV void gemv_out(const Gemv& P, int s, long long j, float r) {
    if (P.bias) r += P.bias[j];
    if (P.gelu) r = gelu(r);
    float* o = P.out + (long long)s * P.ldo + j;
    if (P.out_mode == 0) {
        *o = r;
    } else if (P.out_mode == 1) {
        *o += r;
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

KERNEL umgen_gemv(const Gemv P) {
    SHARED float st[2 * GEMV_ROWS];
    const int m = P.m;
    if (P.in_mode == 1) {
        // Warp s: row s's mean and 1/σ (biased variance, ε 1e-5, as burn's LayerNorm).
        const int s = warp_id();
        if (s < m) {
            const float* xr = P.x + (long long)s * P.ldx;
            float sum = 0.f;
            for (int i = lane_id(); i < P.k; i += 32) sum += xr[i];
            const float mean = warp_sum(sum) / P.k;
            float sq = 0.f;
            for (int i = lane_id(); i < P.k; i += 32) {
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
    const long long stride = blocks() * warps_per_block();
    for (long long j = warp_index(); j < P.n; j += stride) {
        float acc[GEMV_ROWS];
        for (int s = 0; s < GEMV_ROWS; s++) acc[s] = 0.f;
        const WT* wr = P.w + j * P.k;
        if ((P.k & 7) == 0) {
#pragma unroll 4
            for (int c = lane_id() * 8; c < P.k; c += 256) {
                float wv[8];
                load8(wr + c, wv);
                for (int s = 0; s < GEMV_ROWS; s++) {
                    if (s < m) {
                        float xv[8];
                        gemv_in8(P, st, trow[s], prow, s, c, xv);
                        for (int e = 0; e < 8; e++) acc[s] = fmaf(wv[e], xv[e], acc[s]);
                    }
                }
            }
        } else {
            for (int i = lane_id(); i < P.k; i += 32) {
                const float wv = value(wr + i);
                for (int s = 0; s < GEMV_ROWS; s++)
                    if (s < m) acc[s] = fmaf(wv, gemv_in1(P, st, trow[s], prow, s, i), acc[s]);
            }
        }
        for (int s = 0; s < GEMV_ROWS; s++) {
            if (s < m) {
                const float r = warp_sum(acc[s]);
                if (lane_id() == 0) gemv_out(P, s, j, r);
            }
        }
    }
}
