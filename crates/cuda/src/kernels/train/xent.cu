// Cross-entropy over the rows of a row-major f32 logit matrix `[rows, v]`, one warp a row (`xent/cuda.rs`
// compiles this with NVRTC and launches it on burn's buffers).
//
// burn's decomposition of a row's log-sum-exp is four passes over the logits (max, subtract, exp, sum)
// and its backward pass `g · (exp(x − lse) − q)` three more (exp, scatter, multiply); for the 8,192-way
// map and image heads of `small` each pass is 0.75–1 ms on an H100 (docs/decisions/007-memory-bound-training-kernels.md). Here the
// forward pass reads each logit once, keeping a running maximum and sum per lane (the online
// log-sum-exp), and the backward pass reads each logit once and writes its gradient once, then takes the
// target distribution's few weights off the target ids.
//
// NVRTC compiles it after `warp_device.cuh`'s primitives; on the host `xent_emulator.cpp` includes
// it after `warp_emulator.h`'s and runs it thread by thread against a double-precision reference.

// What both passes take (`XentParams` in `xent/cuda.rs`, field for field).
struct XentParams {
    const float* x;        // [rows, v] logits
    const float* lse;      // [rows] (backward: the forward pass's)
    const float* g;        // [1] (backward): the gradient of the summed loss
    const float* ids;      // [rows, k] (backward): target ids, as f32 (exact below 2^24)
    const float* weights;  // [rows, k] (backward): their weights
    float* lse_out;        // [rows] (forward)
    float* dx;             // [rows, v] (backward)
    long long rows;
    int v;
    int k;
};

// Values a lane takes per step of its loop: loads in flight before the first is used.
#define XENT_UNROLL 8

// The forward pass: each row's log(Σ exp x), shifted by the row's maximum.
KERNEL umgen_xent_forward(XentParams p) {
    const int lane = lane_id(), v = p.v;
    const long long stride = blocks() * warps_per_block();
    for (long long row = block_x() * warps_per_block() + warp_id(); row < p.rows; row += stride) {
        const float* x = p.x + row * v;
        float m = NEG_INF, s = 0.f;
        for (int c0 = 0; c0 < v; c0 += 32 * XENT_UNROLL) {
            float t[XENT_UNROLL];
            float mc = NEG_INF;
#pragma unroll
            for (int j = 0; j < XENT_UNROLL; j++) {
                const int c = c0 + lane + 32 * j;
                t[j] = c < v ? x[c] : NEG_INF;
                mc = fmaxf(mc, t[j]);
            }
            const float mn = fmaxf(m, mc);
            if (mn == NEG_INF) continue;  // nothing but -inf yet
            float add = 0.f;
#pragma unroll
            for (int j = 0; j < XENT_UNROLL; j++) add += expf(t[j] - mn);
            s = s * expf(m - mn) + add;
            m = mn;
        }
        const float mr = warp_max(m);
        const float sr = warp_sum(m == NEG_INF ? 0.f : s * expf(m - mr));
        if (lane == 0) p.lse_out[row] = mr + logf(sr);
    }
}

// The backward pass: dx = g · (exp(x − lse) − q), q the row's target weights at its ids (ids outside the
// row are skipped; repeated ids add up).
KERNEL umgen_xent_backward(XentParams p) {
    const int lane = lane_id(), v = p.v;
    const long long stride = blocks() * warps_per_block();
    const float g = *p.g;
    for (long long row = block_x() * warps_per_block() + warp_id(); row < p.rows; row += stride) {
        const float* x = p.x + row * v;
        float* dx = p.dx + row * v;
        const float lse = p.lse[row];
        for (int c0 = 0; c0 < v; c0 += 32 * XENT_UNROLL) {
            float t[XENT_UNROLL];
#pragma unroll
            for (int j = 0; j < XENT_UNROLL; j++) {
                const int c = c0 + lane + 32 * j;
                t[j] = c < v ? x[c] : 0.f;
            }
#pragma unroll
            for (int j = 0; j < XENT_UNROLL; j++) {
                const int c = c0 + lane + 32 * j;
                if (c < v) dx[c] = g * expf(t[j] - lse);
            }
        }
        // The other lanes' writes of this row are visible to lane 0 after the warp's barrier.
        warp_sync();
        if (lane == 0) {
            for (int j = 0; j < p.k; j++) {
                const int id = (int)p.ids[row * p.k + j];
                if (id >= 0 && id < v) dx[id] -= g * p.weights[row * p.k + j];
            }
        }
        warp_sync();
    }
}
