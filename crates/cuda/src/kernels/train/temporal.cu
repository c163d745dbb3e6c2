// Attention over time: each token position of each sequence attends over its own T ≤ 32 frames, read
// and written where the TAR's layers keep them (`[b, t, n, heads · dh]`, any strides of b, t and n), so
// that no transposition to `[b · n, heads, t, dh]` and back is needed (`temporal/cuda.rs` compiles this
// with NVRTC and launches it on burn's buffers).
//
// One warp per (sequence, position, head); lane `l` holds dimensions l, l + 32, … of a row (`DPL` each, so
// head sizes 32, 64 and 128). A query streams over its keys with an online softmax; the backward pass
// recomputes the probabilities from the log-sum-exp, once for the key and value gradients (keys outer) and
// once for the query gradients (queries outer), with each query's log-sum-exp and `dout · out`
// recomputed first and held by lane t (so the backward pass reads q, k, v and dout only). Rows this short
// leave nothing for tensor cores to do; the work is the reads and the warp's sums. So a warp takes `B` rows
// of the outer side at a time: each row of the inner side it reads then serves B pairs (the kernels were
// bound by these reads from L2, `paper`'s backward pass at about 4.6 TB/s), and the pairs' dot products are
// summed over the warp together (`multi_sum`: 17 shuffles for 8 sums where one at a time took 40).
//
// NVRTC compiles it after `warp_device.cuh`'s primitives; on the host `temporal_emulator.cpp` includes
// it after `warp_emulator.h`'s and runs it thread by thread against a double-precision reference.

// Strides (elements) of the b, t and n axes of one `[b, t, n, heads · dh]` operand.
struct Axes {
    long long b, t, n;
};

// What both passes take (`TemporalParams` in `temporal/cuda.rs`, field for field).
struct TemporalParams {
    const float* q;
    const float* k;
    const float* v;
    const float* dout;  // backward
    float* out_w;       // forward: [b, t, n, heads · dh] (contiguous)
    float* lse_w;       // forward: [b, t, n, heads]
    float* dq;          // backward: [b, t, n, heads · dh] (contiguous)
    float* dk;          // backward: any strides (dk and dv may be halves of one buffer)
    float* dv;
    Axes qa, ka, va, ga, dka, dva;  // strides of q, k, v, dout, dk, dv
    int b, t, n, heads;
    int causal;
    float scale;
};

DEV long long at(const Axes& a, long long bi, long long ti, long long ni) { return bi * a.b + ti * a.t + ni * a.n; }

// Rows of the outer side a warp takes at a time: 4, or 2 for head size 128 (B · DPL values a lane for each
// operand it keeps; 8 rows of head size 32 put the backward kernel's values on the stack).
template <int DPL>
struct Block {
    static constexpr int B = DPL == 4 ? 2 : 4;
};

// Row `t` of an operand (axes `a`, the head's first element at `col`) into this lane's `r`: zeros where
// `t` is past the sequence.
template <int DPL>
DEV void load(float* r, const float* base, const Axes& a, long long bi, int t, long long ni, int col, int frames,
              int lane) {
    const float* row = base + at(a, bi, t, ni) + col;
#pragma unroll
    for (int j = 0; j < DPL; j++) r[j] = t < frames ? row[lane + 32 * j] : 0.f;
}

// This lane's share of a · b.
template <int DPL>
DEV float part(const float* a, const float* b) {
    float s = 0.f;
#pragma unroll
    for (int j = 0; j < DPL; j++) s += a[j] * b[j];
    return s;
}

// Sums each of N values (a power of two, at most 32) over the warp, every lane getting all N sums. A
// transposed butterfly: at each exchange a lane keeps half of its values (those whose index bit matches
// its lane bit) and adds its partner's share of them, so the values halve while the lanes summed double;
// after log2 N exchanges a lane holds one sum, of value `(lane >> (5 − log2 N))`, over the lanes that match
// it, then the remaining exchanges finish it and N reads from one lane each hand it out. 2N − 1 + (5 −
// log2 N) shuffles where N sums one by one take 5N.
template <int N>
DEV void multi_sum(float* x) {
    constexpr int L = N >= 32 ? 5 : N >= 16 ? 4 : N >= 8 ? 3 : N >= 4 ? 2 : N >= 2 ? 1 : 0;
    static_assert(N == 1 << L, "multi_sum takes a power of two up to 32");
    const int lane = lane_id();
#pragma unroll
    for (int k = 0; k < L; k++) {
        const int h = N >> (k + 1), mask = 16 >> k;
        const bool upper = lane & mask;
#pragma unroll
        for (int j = 0; j < h; j++) {
            const float send = upper ? x[j] : x[j + h], keep = upper ? x[j + h] : x[j];
            x[j] = keep + from_xor(send, mask);
        }
    }
#pragma unroll
    for (int mask = 16 >> L; mask > 0; mask >>= 1) x[0] += from_xor(x[0], mask);
    const float mine = x[0];
#pragma unroll
    for (int j = 0; j < N; j++) x[j] = from_lane(mine, j << (5 - L));
}

// One past the last key that queries t0 … t0 + B − 1 see.
template <int B>
DEV int keys_of(const TemporalParams& p, int t0) {
    return p.causal ? (t0 + B < p.t ? t0 + B : p.t) : p.t;
}

// Key u's rows (into `k`, `v`) against the warp's B query rows: x[i] = q_i · k_u and x[B + i] = dout_i ·
// v_u, summed over the warp (the head's columns from `col` on).
template <int DPL, int B>
DEV void pair_sums(float* x, float* k, float* v, const float (*q)[DPL], const float (*g)[DPL],
                   const TemporalParams& p, long long bi, int u, long long ni, int col, int lane) {
    load<DPL>(k, p.k, p.ka, bi, u, ni, col, p.t, lane);
    load<DPL>(v, p.v, p.va, bi, u, ni, col, p.t, lane);
#pragma unroll
    for (int i = 0; i < B; i++) x[i] = part<DPL>(q[i], k), x[B + i] = part<DPL>(g[i], v);
    multi_sum<2 * B>(x);
}

// The warp's (sequence, position, head), or false past the last.
DEV bool task(const TemporalParams& p, long long& bi, long long& ni, int& hi) {
    const long long w = warp_index();
    if (w >= (long long)p.b * p.n * p.heads) return false;
    hi = (int)(w % p.heads);
    ni = (w / p.heads) % p.n;
    bi = w / ((long long)p.heads * p.n);
    return true;
}

// The online softmax's step for one pair: score `x` of a key the query sees (`seen`) joins the running
// maximum `m` and sum `l`; returns the factor the accumulators are rescaled by, and sets `e` to the key's
// weight (0 for a hidden key).
DEV float online(float x, bool seen, float& m, float& l, float& e) {
    const float mn = seen ? fmaxf(m, x) : m, corr = expf(m - mn);
    e = seen ? expf(x - mn) : 0.f;
    l = l * corr + e;
    m = mn;
    return corr;
}

template <int DPL>
DEV void temporal_forward(const TemporalParams& p) {
    constexpr int B = Block<DPL>::B;
    long long bi, ni;
    int hi;
    if (!task(p, bi, ni, hi)) return;
    const int lane = lane_id(), dh = 32 * DPL, d = p.heads * dh, col = hi * dh;
    const Axes oa = {(long long)p.t * p.n * d, (long long)p.n * d, d};
    for (int t0 = 0; t0 < p.t; t0 += B) {
        float q[B][DPL], acc[B][DPL], m[B], l[B];
#pragma unroll
        for (int i = 0; i < B; i++) {
            load<DPL>(q[i], p.q, p.qa, bi, t0 + i, ni, col, p.t, lane);
#pragma unroll
            for (int j = 0; j < DPL; j++) acc[i][j] = 0.f;
            m[i] = -3.0e38f, l[i] = 0.f;  // below any score, and exp(m − s) is then 0
        }
        const int keys = keys_of<B>(p, t0);
        for (int u = 0; u < keys; u++) {
            float k[DPL], v[DPL], s[B];
            load<DPL>(k, p.k, p.ka, bi, u, ni, col, p.t, lane);
            load<DPL>(v, p.v, p.va, bi, u, ni, col, p.t, lane);
#pragma unroll
            for (int i = 0; i < B; i++) s[i] = part<DPL>(q[i], k);
            multi_sum<B>(s);
#pragma unroll
            for (int i = 0; i < B; i++) {
                float e;
                const float corr = online(s[i] * p.scale, !p.causal || u <= t0 + i, m[i], l[i], e);
#pragma unroll
                for (int j = 0; j < DPL; j++) acc[i][j] = acc[i][j] * corr + e * v[j];
            }
        }
#pragma unroll
        for (int i = 0; i < B; i++) {
            const int t = t0 + i;
            if (t >= p.t) break;
            float* o = p.out_w + at(oa, bi, t, ni) + col;
#pragma unroll
            for (int j = 0; j < DPL; j++) o[lane + 32 * j] = acc[i][j] / l[i];
            if (lane == 0) p.lse_w[((bi * p.t + t) * p.n + ni) * p.heads + hi] = m[i] + logf(l[i]);
        }
    }
}

template <int DPL>
DEV void temporal_backward(const TemporalParams& p) {
    constexpr int B = Block<DPL>::B;
    long long bi, ni;
    int hi;
    if (!task(p, bi, ni, hi)) return;
    const int lane = lane_id(), dh = 32 * DPL, d = p.heads * dh, col = hi * dh;
    const Axes oa = {(long long)p.t * p.n * d, (long long)p.n * d, d};
    // Lane t keeps query t's log-sum-exp and δ_t = dout_t · out_t = Σ_u p_tu (dout_t · v_u), both
    // recomputed here from q, k, v and dout alone (an online softmax, as the forward pass).
    float lse_mine = 0.f, delta_mine = 0.f;
    for (int t0 = 0; t0 < p.t; t0 += B) {
        float q[B][DPL], g[B][DPL], m[B], l[B], dpe[B];
#pragma unroll
        for (int i = 0; i < B; i++) {
            load<DPL>(q[i], p.q, p.qa, bi, t0 + i, ni, col, p.t, lane);
            load<DPL>(g[i], p.dout, p.ga, bi, t0 + i, ni, col, p.t, lane);
            m[i] = -3.0e38f, l[i] = 0.f, dpe[i] = 0.f;
        }
        const int keys = keys_of<B>(p, t0);
        for (int u = 0; u < keys; u++) {
            float k[DPL], v[DPL], x[2 * B];
            pair_sums<DPL, B>(x, k, v, q, g, p, bi, u, ni, col, lane);
#pragma unroll
            for (int i = 0; i < B; i++) {
                float e;
                const float corr = online(x[i] * p.scale, !p.causal || u <= t0 + i, m[i], l[i], e);
                dpe[i] = dpe[i] * corr + e * x[B + i];
            }
        }
#pragma unroll
        for (int i = 0; i < B; i++)
            if (lane == t0 + i) {
                lse_mine = m[i] + logf(l[i]);
                delta_mine = dpe[i] / l[i];
            }
    }
    // Key and value gradients: keys u0 … u0 + B − 1 gather every query that sees them.
    for (int u0 = 0; u0 < p.t; u0 += B) {
        float k[B][DPL], v[B][DPL], dk[B][DPL], dv[B][DPL];
#pragma unroll
        for (int i = 0; i < B; i++) {
            load<DPL>(k[i], p.k, p.ka, bi, u0 + i, ni, col, p.t, lane);
            load<DPL>(v[i], p.v, p.va, bi, u0 + i, ni, col, p.t, lane);
#pragma unroll
            for (int j = 0; j < DPL; j++) dk[i][j] = dv[i][j] = 0.f;
        }
        for (int t = p.causal ? u0 : 0; t < p.t; t++) {
            float q[DPL], g[DPL], x[2 * B];
            load<DPL>(q, p.q, p.qa, bi, t, ni, col, p.t, lane);
            load<DPL>(g, p.dout, p.ga, bi, t, ni, col, p.t, lane);
            const float lse = from_lane(lse_mine, t), delta = from_lane(delta_mine, t);
#pragma unroll
            for (int i = 0; i < B; i++) x[i] = part<DPL>(q, k[i]), x[B + i] = part<DPL>(g, v[i]);
            multi_sum<2 * B>(x);
#pragma unroll
            for (int i = 0; i < B; i++) {
                const bool seen = u0 + i < p.t && (!p.causal || t >= u0 + i);
                const float pr = seen ? expf(x[i] * p.scale - lse) : 0.f;
                const float ds = pr * (x[B + i] - delta) * p.scale;
#pragma unroll
                for (int j = 0; j < DPL; j++) {
                    dv[i][j] += pr * g[j];
                    dk[i][j] += ds * q[j];
                }
            }
        }
#pragma unroll
        for (int i = 0; i < B; i++) {
            const int u = u0 + i;
            if (u >= p.t) break;
            float* dkr = p.dk + at(p.dka, bi, u, ni) + col;
            float* dvr = p.dv + at(p.dva, bi, u, ni) + col;
#pragma unroll
            for (int j = 0; j < DPL; j++) {
                dkr[lane + 32 * j] = dk[i][j];
                dvr[lane + 32 * j] = dv[i][j];
            }
        }
    }
    // Query gradients: queries t0 … t0 + B − 1 over the keys they see.
    for (int t0 = 0; t0 < p.t; t0 += B) {
        float q[B][DPL], g[B][DPL], dq[B][DPL], lse[B], delta[B];
#pragma unroll
        for (int i = 0; i < B; i++) {
            load<DPL>(q[i], p.q, p.qa, bi, t0 + i, ni, col, p.t, lane);
            load<DPL>(g[i], p.dout, p.ga, bi, t0 + i, ni, col, p.t, lane);
            lse[i] = from_lane(lse_mine, (t0 + i) & 31), delta[i] = from_lane(delta_mine, (t0 + i) & 31);
#pragma unroll
            for (int j = 0; j < DPL; j++) dq[i][j] = 0.f;
        }
        const int keys = keys_of<B>(p, t0);
        for (int u = 0; u < keys; u++) {
            float k[DPL], v[DPL], x[2 * B];
            pair_sums<DPL, B>(x, k, v, q, g, p, bi, u, ni, col, lane);
#pragma unroll
            for (int i = 0; i < B; i++) {
                const bool seen = t0 + i < p.t && (!p.causal || u <= t0 + i);
                const float pr = seen ? expf(x[i] * p.scale - lse[i]) : 0.f;
                const float ds = pr * (x[B + i] - delta[i]) * p.scale;
#pragma unroll
                for (int j = 0; j < DPL; j++) dq[i][j] += ds * k[j];
            }
        }
#pragma unroll
        for (int i = 0; i < B; i++) {
            const int t = t0 + i;
            if (t >= p.t) break;
            float* dqr = p.dq + at(oa, bi, t, ni) + col;
#pragma unroll
            for (int j = 0; j < DPL; j++) dqr[lane + 32 * j] = dq[i][j];
        }
    }
}

// One kernel per pass and head size (32 · DPL).
#define TEMPORAL_KERNELS(DPL)                                                            \
    KERNEL umgen_temporal_forward_##DPL(TemporalParams p) { temporal_forward<DPL>(p); }  \
    KERNEL umgen_temporal_backward_##DPL(TemporalParams p) { temporal_backward<DPL>(p); }
// One family only where `UMGEN_INSTANCE` says which (kernels launched on cubecl's stream, `side/cubecl_stream.rs`).
#ifdef UMGEN_INSTANCE
UMGEN_INSTANCE
#else
TEMPORAL_KERNELS(1)
TEMPORAL_KERNELS(2)
TEMPORAL_KERNELS(4)
#endif
