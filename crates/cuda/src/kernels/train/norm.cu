// Layer norm over the last axis of a row-major f32 matrix `[rows, d]`, forward and backward, one warp a
// row (`norm/cuda.rs` compiles this with NVRTC and launches it on burn's buffers).
//
// burn's decomposition of a layer norm runs 8 kernels forward (two reductions, a broadcast scale kept
// out of fusion by its custom operation, casts) and more backward, each a pass over the activation:
// about 0.7 ms forward for a `[70,368, 384]` activation of the `small` preset, where one pass reading
// `x` and writing `y` takes 0.08 ms. Here a warp keeps its row in registers (`PER` values a lane, lane
// `l` holding columns l, l + 32, …, so every load is coalesced), so the forward pass reads `x` once and
// writes `y`, the mean and `1/σ`; the backward pass reads `x`, `dy`, the mean and `1/σ` once, writes `dx`
// and each warp's column sums of `dy · x̂` and `dy` (the scale's and shift's gradients, summed over the
// warps by the caller).
//
// NVRTC compiles it after `warp_device.cuh`'s primitives; on the host `norm_emulator.cpp` includes
// it after `warp_emulator.h`'s and runs it thread by thread against a double-precision reference.

// What both passes take (`NormParams` in `norm/cuda.rs`, field for field).
struct NormParams {
    const float* x;      // [rows, d]
    const float* gamma;  // [d]
    const float* beta;   // [d]
    const float* dy;     // [rows, d] (backward)
    const float* mean;   // [rows] (backward: the forward pass's)
    const float* rstd;   // [rows] (backward)
    float* y;            // [rows, d] (forward)
    float* mean_out;     // [rows] (forward)
    float* rstd_out;     // [rows] (forward)
    float* dx;           // [rows, d] (backward)
    float* dgamma;       // [warps of the grid, d] (backward): each warp's column sums of dy · x̂
    float* dbeta;        // [warps of the grid, d] (backward): each warp's column sums of dy
    long long rows;
    int d;
    float eps;
};

// The forward pass: y = (x − mean) · rstd · γ + β, rstd = 1/√(var + ε) with the centred variance (as
// burn's `LayerNorm`), for d ≤ 32 · PER, written to `out` (`p.y`'s place) as f32 or, where only products
// read it, as their bf16 operand (`T`), so that no f32 copy is written and cast. The input `xs` is f32 or
// the bf16 copy a recomputed layer kept (`TX`). With `keep`, the input is also written there in bf16: the
// copy the backward pass keeps, which a cast kernel would otherwise read the input again to write.
template <int PER, typename TX, typename T>
DEV void norm_forward(const NormParams& p, const TX* xs, T* out, u16* keep) {
    const int lane = lane_id(), d = p.d;
    const long long stride = blocks() * warps_per_block();
    for (long long row = block_x() * warps_per_block() + warp_id(); row < p.rows; row += stride) {
        const TX* x = xs + row * d;
        float v[PER];
        float s = 0.f;
#pragma unroll
        for (int j = 0; j < PER; j++) {
            const int c = lane + 32 * j;
            v[j] = c < d ? value(x + c) : 0.f;
            s += v[j];
        }
        if (keep != nullptr) {
#pragma unroll
            for (int j = 0; j < PER; j++) {
                const int c = lane + 32 * j;
                if (c < d) store(keep + row * d + c, v[j]);
            }
        }
        const float mean = warp_sum(s) / d;
        float q = 0.f;
#pragma unroll
        for (int j = 0; j < PER; j++) {
            const float t = lane + 32 * j < d ? v[j] - mean : 0.f;
            q += t * t;
        }
        const float rstd = rsqrtf(warp_sum(q) / d + p.eps);
        T* y = out + row * d;
#pragma unroll
        for (int j = 0; j < PER; j++) {
            const int c = lane + 32 * j;
            if (c < d) store(y + c, (v[j] - mean) * rstd * p.gamma[c] + p.beta[c]);
        }
        if (lane == 0) {
            p.mean_out[row] = mean;
            p.rstd_out[row] = rstd;
        }
    }
}

// The backward pass: with x̂ = (x − mean) · rstd and g = dy · γ,
// dx = rstd · (g − mean(g) − x̂ · mean(g · x̂)); each warp adds its rows' dy · x̂ and dy per column. The
// input `xs` is f32 or the bf16 copy the forward pass kept (`TX`). With `dres`, the gradient the residual
// stream brings to the norm's input (`[rows, d]`, f32) is added to dx as it is written, which a pass of its
// own would read and write again.
template <int PER, typename TX>
DEV void norm_backward(const NormParams& p, const TX* xs, const float* dres) {
    const int lane = lane_id(), d = p.d;
    const long long warp = block_x() * warps_per_block() + warp_id();
    const long long stride = blocks() * warps_per_block();
    float dg[PER], db[PER];
#pragma unroll
    for (int j = 0; j < PER; j++) dg[j] = db[j] = 0.f;
    for (long long row = warp; row < p.rows; row += stride) {
        const TX* x = xs + row * d;
        const float* dy = p.dy + row * d;
        const float mean = p.mean[row], rstd = p.rstd[row];
        float xh[PER], g[PER];
        float sg = 0.f, sgx = 0.f;
#pragma unroll
        for (int j = 0; j < PER; j++) {
            const int c = lane + 32 * j;
            const bool in = c < d;
            const float dyc = in ? dy[c] : 0.f;
            xh[j] = in ? (value(x + c) - mean) * rstd : 0.f;
            g[j] = in ? dyc * p.gamma[c] : 0.f;
            dg[j] += dyc * xh[j];
            db[j] += dyc;
            sg += g[j];
            sgx += g[j] * xh[j];
        }
        const float mg = warp_sum(sg) / d, mgx = warp_sum(sgx) / d;
        float* dx = p.dx + row * d;
#pragma unroll
        for (int j = 0; j < PER; j++) {
            const int c = lane + 32 * j;
            if (c < d) {
                const float v = rstd * (g[j] - mg - xh[j] * mgx);
                dx[c] = dres != nullptr ? v + dres[row * d + c] : v;
            }
        }
    }
#pragma unroll
    for (int j = 0; j < PER; j++) {
        const int c = lane + 32 * j;
        if (c < d) {
            p.dgamma[warp * d + c] = dg[j];
            p.dbeta[warp * d + c] = db[j];
        }
    }
}

// One kernel per pass and row capacity: d ≤ 128, 256, 384, 512, 768, 1024.
#define NORM_KERNELS(PER)                                                          \
    KERNEL umgen_norm_forward_##PER(NormParams p) { norm_forward<PER>(p, p.x, p.y, nullptr); } \
    KERNEL umgen_norm_backward_##PER(NormParams p) { norm_backward<PER>(p, p.x, nullptr); }

// The sizes the bound entry points take after their buffers (`Sizes` in `norm/cuda.rs`, field for field).
struct NormSizes {
    long long rows;
    int d;
    float eps;
};

// The same passes with their buffers as parameters, which cubecl binds as it launches (`norm/cuda.rs`): the
// host then needs no device pointers, so it makes no call to cubecl's device thread and does not wait.
// Named by the formats of the input and the output (`x32`/`x16`, `y32`/`y16`; bf16 as `u16` bits) and,
// for a forward pass that also writes the kept bf16 copy of its f32 input, `keep`.
#define NORM_FORWARD_BOUND(PER, NAME, TX, TY, KEEP_PARAM, KEEP)                                               \
    KERNEL umgen_norm_forward_bound_##NAME##_##PER(const TX* x, const float* gamma, const float* beta, TY* y,  \
                                                   float* mean, float* rstd KEEP_PARAM, NormSizes s) {        \
        norm_forward<PER>(NormParams{nullptr, gamma, beta, nullptr, nullptr, nullptr, nullptr, mean, rstd,   \
                                     nullptr, nullptr, nullptr, s.rows, s.d, s.eps},                          \
                          x, y, KEEP);                                                                        \
    }
#define NORM_BACKWARD_BOUND(PER, NAME, TX, RES_PARAM, RES)                                                    \
    KERNEL umgen_norm_backward_bound_##NAME##_##PER(const float* dy, const TX* x, const float* mean,          \
                                                    const float* rstd, const float* gamma RES_PARAM, float* dx, \
                                                    float* dgamma, float* dbeta, NormSizes s) {               \
        norm_backward<PER>(NormParams{nullptr, gamma, nullptr, dy, mean, rstd, nullptr, nullptr, nullptr, dx, \
                                      dgamma, dbeta, s.rows, s.d, s.eps},                                     \
                           x, RES);                                                                           \
    }
#define NORM_COMMA ,
#define NORM_BOUND_KERNELS(PER)                                                   \
    NORM_FORWARD_BOUND(PER, x32_y32, float, float, , nullptr)                     \
    NORM_FORWARD_BOUND(PER, x32_y16, float, u16, , nullptr)                       \
    NORM_FORWARD_BOUND(PER, x16_y32, u16, float, , nullptr)                       \
    NORM_FORWARD_BOUND(PER, x16_y16, u16, u16, , nullptr)                         \
    NORM_FORWARD_BOUND(PER, x32_y16_keep, float, u16, NORM_COMMA u16* keep, keep) \
    NORM_BACKWARD_BOUND(PER, x32, float, , nullptr)                               \
    NORM_BACKWARD_BOUND(PER, x16, u16, , nullptr)                                 \
    NORM_BACKWARD_BOUND(PER, x32_res, float, NORM_COMMA const float* dres, dres)  \
    NORM_BACKWARD_BOUND(PER, x16_res, u16, NORM_COMMA const float* dres, dres)
// One family only where `UMGEN_INSTANCE` says which (kernels launched on cubecl's stream, `side/cubecl_stream.rs`).
#ifdef UMGEN_INSTANCE
UMGEN_INSTANCE
#else
NORM_KERNELS(4)
NORM_KERNELS(8)
NORM_KERNELS(12)
NORM_KERNELS(16)
NORM_KERNELS(24)
NORM_KERNELS(32)
#endif
