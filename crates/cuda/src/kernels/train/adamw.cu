// AdamW over up to UMGEN_ADAMW_SLOTS parameter tensors per launch, and the gradients' global norm over up
// to UMGEN_SUMSQ_SLOTS per launch (umgen_backbone::adamw).
//
// Each slot is one parameter tensor: its parameter, gradient, first and second moment, and where the new
// parameter and moments go (which may be the old moments' buffers). The launch binds them as the
// kernel's buffers, seven per slot in that order, after the gradient scale; `adamw/cuda.rs` writes the
// entry point that takes them (`umgen_adamw`) after this file, since its parameter list has
// 1 + 7 * UMGEN_ADAMW_SLOTS pointers. A block updates UMGEN_ADAMW_SPAN elements of one slot; slot i owns
// blocks first[i] .. first[i + 1].
// NVRTC compiles it after `warp_device.cuh`'s primitives (`side::kernel_source`).
//
// The arithmetic is burn's AdamW's, in its order (burn-optim 0.21, adamw.rs):
//   m = β1 m + (1 − β1) g            (m = (1 − β1) g at a slot's first step)
//   v = β2 v + (1 − β2) g²
//   p = p (1 − lr λ) − lr (m / c1) / (√(v / c2) + ε),   c1 = 1 − β1ᵗ, c2 = 1 − β2ᵗ
// with g the gradient times the clipping factor `scale[0]` when `has_scale`. A scale that is not finite
// skips the step (umgen_optim's guarded step): the parameter and moments are written back as they were,
// zero moments for a slot's first step.

#if !defined(UMGEN_ADAMW_SLOTS) || !defined(UMGEN_SUMSQ_SLOTS)
#error "UMGEN_ADAMW_SLOTS and UMGEN_SUMSQ_SLOTS must be defined"
#endif
#define UMGEN_ADAMW_SPAN 4096
#define UMGEN_ADAMW_THREADS 256

// The slot that owns block `block`: the last i < count with first[i] <= block (slots of no elements own
// no block, so the search passes them).
template <typename P>
__device__ __forceinline__ unsigned int slot_of(const P& p, unsigned int block) {
    unsigned int lo = 0, hi = p.count - 1;
    while (lo < hi) {
        const unsigned int mid = (lo + hi + 1) / 2;
        if (p.first[mid] <= block) {
            lo = mid;
        } else {
            hi = mid - 1;
        }
    }
    return lo;
}

// The sum of `x` over the block's 256 threads, in a fixed order (so that runs agree to the bit); valid in
// thread 0.
__device__ __forceinline__ float block_sum(float x) {
    __shared__ float warps[UMGEN_ADAMW_THREADS / 32];
    x = warp_sum(x);
    if ((threadIdx.x & 31) == 0) {
        warps[threadIdx.x >> 5] = x;
    }
    __syncthreads();
    float t = 0.0f;
    if (threadIdx.x < 32) {
        t = warp_sum(threadIdx.x < UMGEN_ADAMW_THREADS / 32 ? warps[threadIdx.x] : 0.0f);
    }
    return t;
}

// Field for field `Params` of adamw/cuda.rs (u32 and f32 only, so no padding on either side).
struct AdamwParams {
    unsigned int count;      // slots in this launch
    unsigned int has_scale;  // multiply each gradient by scale[0]
    unsigned int decays;     // multiply each weight by `decay` (burn skips it when lr · λ = 0)
    float lr;
    float decay;
    float beta1;
    float beta2;
    float one_minus_beta1;
    float one_minus_beta2;
    float eps;
    unsigned int first[UMGEN_ADAMW_SLOTS + 1];
    unsigned int len[UMGEN_ADAMW_SLOTS];
    unsigned int fresh[UMGEN_ADAMW_SLOTS];  // no moments yet: read neither m nor v
    float c1[UMGEN_ADAMW_SLOTS];
    float c2[UMGEN_ADAMW_SLOTS];
};

// One slot's buffers.
struct AdamwSlot {
    const float* param;
    const float* grad;
    const float* m;
    const float* v;
    float* param_out;
    float* m_out;
    float* v_out;
};

// This block's part of slot `i`.
__device__ __forceinline__ void adamw_update(const AdamwParams& p, unsigned int i, AdamwSlot s,
                                             const float* scale) {
    const unsigned int len = p.len[i];
    const unsigned int start = (blockIdx.x - p.first[i]) * UMGEN_ADAMW_SPAN;
    const unsigned int end = min(start + UMGEN_ADAMW_SPAN, len);
    const float factor = p.has_scale ? scale[0] : 1.0f;
    const bool fresh = p.fresh[i] != 0;
    const float c1 = p.c1[i];
    const float c2 = p.c2[i];
    if (p.has_scale && !isfinite(factor)) {
        for (unsigned int j = start + threadIdx.x; j < end; j += UMGEN_ADAMW_THREADS) {
            s.param_out[j] = s.param[j];
            s.m_out[j] = fresh ? 0.0f : s.m[j];
            s.v_out[j] = fresh ? 0.0f : s.v[j];
        }
        return;
    }
    for (unsigned int j = start + threadIdx.x; j < end; j += UMGEN_ADAMW_THREADS) {
        float g = s.grad[j];
        if (p.has_scale) {
            g = g * factor;
        }
        const float g2 = g * g;
        float m = g * p.one_minus_beta1;
        float v = g2 * p.one_minus_beta2;
        if (!fresh) {
            m = __fadd_rn(__fmul_rn(s.m[j], p.beta1), m);
            v = __fadd_rn(__fmul_rn(s.v[j], p.beta2), v);
        }
        const float delta = __fdiv_rn(__fdiv_rn(m, c1), __fadd_rn(__fsqrt_rn(__fdiv_rn(v, c2)), p.eps));
        float w = s.param[j];
        if (p.decays) {
            w = __fmul_rn(w, p.decay);
        }
        s.param_out[j] = __fsub_rn(w, __fmul_rn(delta, p.lr));
        s.m_out[j] = m;
        s.v_out[j] = v;
    }
}

// Field for field `Params` of adamw/norm.rs.
struct SumsqParams {
    unsigned int count;  // slots in this launch
    unsigned int base;   // this launch's first block among all launches (its first partial sum)
    unsigned int first[UMGEN_SUMSQ_SLOTS + 1];
    unsigned int len[UMGEN_SUMSQ_SLOTS];
};

// One slot's buffer.
struct SumsqSlot {
    const float* g;
};

// The sum of squares of this block's part of slot `i`, stored as partial sum base + blockIdx.x.
__device__ __forceinline__ void sumsq_update(const SumsqParams& p, unsigned int i, const float* g,
                                             float* partials) {
    const unsigned int start = (blockIdx.x - p.first[i]) * UMGEN_ADAMW_SPAN;
    const unsigned int end = min(start + UMGEN_ADAMW_SPAN, p.len[i]);
    float acc = 0.0f;
    for (unsigned int j = start + threadIdx.x; j < end; j += UMGEN_ADAMW_THREADS) {
        acc = fmaf(g[j], g[j], acc);
    }
    const float total = block_sum(acc);
    if (threadIdx.x == 0) {
        partials[p.base + blockIdx.x] = total;
    }
}

// Field for field `FinalParams` of adamw/norm.rs.
struct SumsqFinalParams {
    unsigned int n;  // partial sums
};

// One block: the square root of the sum of the partial sums.
extern "C" __global__ void __launch_bounds__(UMGEN_ADAMW_THREADS)
    umgen_sumsq_final(const float* partials, float* norm, SumsqFinalParams p) {
    float acc = 0.0f;
    for (unsigned int j = threadIdx.x; j < p.n; j += UMGEN_ADAMW_THREADS) {
        acc += partials[j];
    }
    const float total = block_sum(acc);
    if (threadIdx.x == 0) {
        norm[0] = sqrtf(total);
    }
}
