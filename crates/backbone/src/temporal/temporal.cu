// Attention over time: each token position of each sequence attends over its own T ≤ 32 frames, read
// and written where the TAR's layers keep them (`[b, t, n, heads · dh]`, any strides of b, t and n), so
// that no transposition to `[b · n, heads, t, dh]` and back is needed (`temporal/cuda.rs` compiles this
// with NVRTC and launches it on burn's buffers).
//
// One warp per (sequence, position, head); lane `l` holds dimensions l, l + 32, … of a row (`DPL` each, so
// head sizes 32, 64 and 128). A query streams over its keys with an online softmax; the backward pass
// recomputes the probabilities from the log-sum-exp, once for the key and value gradients (keys outer) and
// once for the query gradients (queries outer), with each query's log-sum-exp and `dout · out`
// recomputed first and held by lane t (so the backward pass reads q, k, v and dout only). Rows this short leave nothing for tensor cores to do; the work is the reads and writes.
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

template <int DPL>
DEV void load(float* r, const float* row, int lane) {
#pragma unroll
    for (int j = 0; j < DPL; j++) r[j] = row[lane + 32 * j];
}

template <int DPL>
DEV float dot(const float* a, const float* b) {
    float s = 0.f;
#pragma unroll
    for (int j = 0; j < DPL; j++) s += a[j] * b[j];
    return warp_sum(s);
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

template <int DPL>
DEV void temporal_forward(const TemporalParams& p) {
    long long bi, ni;
    int hi;
    if (!task(p, bi, ni, hi)) return;
    const int lane = lane_id(), dh = 32 * DPL, d = p.heads * dh;
    const Axes oa = {(long long)p.t * p.n * d, (long long)p.n * d, d};
    for (int t = 0; t < p.t; t++) {
        float q[DPL], acc[DPL], kv[DPL];
        load<DPL>(q, p.q + at(p.qa, bi, t, ni) + hi * dh, lane);
#pragma unroll
        for (int j = 0; j < DPL; j++) acc[j] = 0.f;
        float m = -3.0e38f, l = 0.f;  // below any score, and exp(m − s) is then 0
        const int keys = p.causal ? t + 1 : p.t;
        for (int u = 0; u < keys; u++) {
            load<DPL>(kv, p.k + at(p.ka, bi, u, ni) + hi * dh, lane);
            const float s = dot<DPL>(q, kv) * p.scale;
            const float mn = fmaxf(m, s), corr = expf(m - mn), e = expf(s - mn);
            load<DPL>(kv, p.v + at(p.va, bi, u, ni) + hi * dh, lane);
#pragma unroll
            for (int j = 0; j < DPL; j++) acc[j] = acc[j] * corr + e * kv[j];
            l = l * corr + e;
            m = mn;
        }
        float* o = p.out_w + at(oa, bi, t, ni) + hi * dh;
#pragma unroll
        for (int j = 0; j < DPL; j++) o[lane + 32 * j] = acc[j] / l;
        if (lane == 0) p.lse_w[((bi * p.t + t) * p.n + ni) * p.heads + hi] = m + logf(l);
    }
}

template <int DPL>
DEV void temporal_backward(const TemporalParams& p) {
    long long bi, ni;
    int hi;
    if (!task(p, bi, ni, hi)) return;
    const int lane = lane_id(), dh = 32 * DPL, d = p.heads * dh;
    const Axes oa = {(long long)p.t * p.n * d, (long long)p.n * d, d};
    // Lane t keeps query t's log-sum-exp and δ_t = dout_t · out_t = Σ_u p_tu (dout_t · v_u), both
    // recomputed here from q, k, v and dout alone (an online softmax, as the forward pass).
    float lse_mine = 0.f, delta_mine = 0.f;
    for (int t = 0; t < p.t; t++) {
        float q[DPL], g[DPL], kv[DPL];
        load<DPL>(q, p.q + at(p.qa, bi, t, ni) + hi * dh, lane);
        load<DPL>(g, p.dout + at(p.ga, bi, t, ni) + hi * dh, lane);
        float m = -3.0e38f, l = 0.f, dpe = 0.f;
        const int keys = p.causal ? t + 1 : p.t;
        for (int u = 0; u < keys; u++) {
            load<DPL>(kv, p.k + at(p.ka, bi, u, ni) + hi * dh, lane);
            const float s = dot<DPL>(q, kv) * p.scale;
            load<DPL>(kv, p.v + at(p.va, bi, u, ni) + hi * dh, lane);
            const float dp = dot<DPL>(g, kv);
            const float mn = fmaxf(m, s), corr = expf(m - mn), e = expf(s - mn);
            l = l * corr + e;
            dpe = dpe * corr + e * dp;
            m = mn;
        }
        if (lane == t) {
            lse_mine = m + logf(l);
            delta_mine = dpe / l;
        }
    }
    // Key and value gradients: key u gathers every query that sees it.
    for (int u = 0; u < p.t; u++) {
        float k[DPL], v[DPL], dk[DPL], dv[DPL];
        load<DPL>(k, p.k + at(p.ka, bi, u, ni) + hi * dh, lane);
        load<DPL>(v, p.v + at(p.va, bi, u, ni) + hi * dh, lane);
#pragma unroll
        for (int j = 0; j < DPL; j++) dk[j] = dv[j] = 0.f;
        for (int t = p.causal ? u : 0; t < p.t; t++) {
            float q[DPL], g[DPL];
            load<DPL>(q, p.q + at(p.qa, bi, t, ni) + hi * dh, lane);
            load<DPL>(g, p.dout + at(p.ga, bi, t, ni) + hi * dh, lane);
            const float lse = from_lane(lse_mine, t), delta = from_lane(delta_mine, t);
            const float pr = expf(dot<DPL>(q, k) * p.scale - lse);
            const float ds = pr * (dot<DPL>(g, v) - delta) * p.scale;
#pragma unroll
            for (int j = 0; j < DPL; j++) {
                dv[j] += pr * g[j];
                dk[j] += ds * q[j];
            }
        }
        float* dkr = p.dk + at(p.dka, bi, u, ni) + hi * dh;
        float* dvr = p.dv + at(p.dva, bi, u, ni) + hi * dh;
#pragma unroll
        for (int j = 0; j < DPL; j++) {
            dkr[lane + 32 * j] = dk[j];
            dvr[lane + 32 * j] = dv[j];
        }
    }
    // Query gradients.
    for (int t = 0; t < p.t; t++) {
        float q[DPL], g[DPL], dq[DPL];
        load<DPL>(q, p.q + at(p.qa, bi, t, ni) + hi * dh, lane);
        load<DPL>(g, p.dout + at(p.ga, bi, t, ni) + hi * dh, lane);
        const float lse = from_lane(lse_mine, t), delta = from_lane(delta_mine, t);
#pragma unroll
        for (int j = 0; j < DPL; j++) dq[j] = 0.f;
        const int keys = p.causal ? t + 1 : p.t;
        for (int u = 0; u < keys; u++) {
            float k[DPL], v[DPL];
            load<DPL>(k, p.k + at(p.ka, bi, u, ni) + hi * dh, lane);
            load<DPL>(v, p.v + at(p.va, bi, u, ni) + hi * dh, lane);
            const float pr = expf(dot<DPL>(q, k) * p.scale - lse);
            const float ds = pr * (dot<DPL>(g, v) - delta) * p.scale;
#pragma unroll
            for (int j = 0; j < DPL; j++) dq[j] += ds * k[j];
        }
        float* dqr = p.dq + at(oa, bi, t, ni) + hi * dh;
#pragma unroll
        for (int j = 0; j < DPL; j++) dqr[lane + 32 * j] = dq[j];
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
