// An MLP's bias + GELU over the product `y` `[rows, n]` (f32, no bias), forward and backward
// (`gelu/cuda.rs` compiles this with NVRTC and launches it on burn's buffers, bound as the entry points'
// pointer parameters).
//
// burn-fusion runs the bias add and GELU as one element-wise kernel that writes the hidden activation in f32
// and keeps the pre-activation, then a separate cast to bf16 for the next product, and in the backward pass
// GELU's derivative, the cast of the result and the bias's row sums as more passes: on `[70,368, 1,536]`
// (the `small` preset's MLP) about 0.75 ms + 0.23 ms forward against 0.22 ms for reading `y` once and
// writing bf16. Here the forward pass reads `y` and the bias once and writes gelu(y + b) in the next
// product's format (`T`: bf16 bits or f32); the backward pass reads the output's gradient and `y`,
// recomputes y + b, writes dh · gelu'(y + b) in `T` and each warp's f32 column sums of it (the bias's
// gradient, summed over the warps by the caller). GELU is the exact one (erf), as burn's forward pass and
// PyTorch's `nn.GELU()`; the derivative is the exact one too, Φ(x) + x·φ(x) (burn's backward pass uses the
// tanh approximation's).
//
// `V` values a lane at a time (4 when `n` is a multiple of 4: one 16-byte load each); NVRTC compiles it
// after `warp_device.cuh`'s primitives, and on the host `gelu_emulator.cpp` includes it after
// `warp_emulator.h`'s and runs it thread by thread against a double-precision reference.

// The sizes every entry point takes by value (`Sizes` in `gelu/cuda.rs`, field for field).
struct GeluSizes {
    long long rows;
    int n;       // columns, the bias's length
    int groups;  // backward: row groups, one row of column sums each
};

// What the passes read and write.
template <class T>
struct GeluArgs {
    const float* dh;  // [rows, n] (backward)
    const float* y;   // [rows, n]
    const float* b;   // [n]
    T* out;           // [rows, n]: gelu(y + b) forward, dh · gelu'(y + b) backward
    float* db;        // [groups, n] (backward): each row group's column sums of the gradient
    GeluSizes s;
};

// `V` consecutive floats from `p` (16-byte aligned when V is 4).
template <int V>
DEV void load(const float* p, float (&v)[V]) {
#ifndef UMGEN_EMULATED
    if constexpr (V == 4) {
        const float4 q = *reinterpret_cast<const float4*>(p);
        v[0] = q.x, v[1] = q.y, v[2] = q.z, v[3] = q.w;
        return;
    }
#endif
#pragma unroll
    for (int k = 0; k < V; k++) v[k] = p[k];
}

// `V` values to `p` in `T` (one 16- or 8-byte store when V is 4).
template <int V, class T>
DEV void store_all(T* p, const float (&v)[V]) {
#ifndef UMGEN_EMULATED
    if constexpr (V == 4) {
        if constexpr (sizeof(T) == 4) {
            *reinterpret_cast<float4*>(p) = make_float4(v[0], v[1], v[2], v[3]);
        } else {
            const u32 lo = (u32)to_bf16(v[0]) | ((u32)to_bf16(v[1]) << 16);
            const u32 hi = (u32)to_bf16(v[2]) | ((u32)to_bf16(v[3]) << 16);
            *reinterpret_cast<uint2*>(p) = make_uint2(lo, hi);
        }
        return;
    }
#endif
#pragma unroll
    for (int k = 0; k < V; k++) store(p + k, v[k]);
}

// Φ(x), the standard normal's distribution function.
DEV float normal_cdf(float x) { return 0.5f * (1.0f + erff(x * 0.70710678118654752f)); }

DEV float gelu(float x) { return x * normal_cdf(x); }

// d gelu / dx = Φ(x) + x·φ(x).
DEV float gelu_grad(float x) { return normal_cdf(x) + x * 0.39894228040143268f * expf(-0.5f * x * x); }

// The forward pass: a grid-stride loop over the `V`-wide pieces of `[rows, n]`.
template <int V, class T>
DEV void gelu_forward(const GeluArgs<T>& a) {
    const int per_row = a.s.n / V;
    const long long pieces = a.s.rows * per_row;
    const long long stride = blocks() * warps_per_block() * 32;
    for (long long i = warp_index() * 32 + lane_id(); i < pieces; i += stride) {
        const int c = (int)(i % per_row) * V;
        float v[V], bias[V];
        load<V>(a.y + i * V, v);
        load<V>(a.b + c, bias);
#pragma unroll
        for (int k = 0; k < V; k++) v[k] = gelu(v[k] + bias[k]);
        store_all<V, T>(a.out + i * V, v);
    }
}

// The backward pass: warp w takes column chunk w % chunks (32·V columns, lane l the V from 32·V·chunk +
// V·l) of the rows g, g + groups, g + 2·groups, … of row group g = w / chunks, and writes its column sums
// to db's row g.
template <int V, class T>
DEV void gelu_backward(const GeluArgs<T>& a) {
    const int n = a.s.n, lane = lane_id();
    const int chunks = (n + 32 * V - 1) / (32 * V);
    const long long work = (long long)chunks * a.s.groups, warps = blocks() * warps_per_block();
    for (long long w = warp_index(); w < work; w += warps) {
        const int c = (int)(w % chunks) * 32 * V + lane * V;
        const int g = (int)(w / chunks);
        if (c >= n) continue;
        float bias[V], sum[V];
        load<V>(a.b + c, bias);
#pragma unroll
        for (int k = 0; k < V; k++) sum[k] = 0.0f;
#pragma unroll 2
        for (long long r = g; r < a.s.rows; r += a.s.groups) {
            float dh[V], x[V];
            load<V>(a.dh + r * n + c, dh);
            load<V>(a.y + r * n + c, x);
#pragma unroll
            for (int k = 0; k < V; k++) {
                dh[k] *= gelu_grad(x[k] + bias[k]);
                sum[k] += dh[k];
            }
            store_all<V, T>(a.out + r * n + c, dh);
        }
#pragma unroll
        for (int k = 0; k < V; k++) a.db[(long long)g * n + c + k] = sum[k];
    }
}

#ifndef UMGEN_EMULATED
// The entry points of one output type and width: the buffers bound by the launch, then the sizes.
#define GELU_KERNELS(NAME, V, T)                                                                          \
    KERNEL umgen_gelu_forward_##NAME(const float* y, const float* b, T* out, GeluSizes s) {              \
        gelu_forward<V, T>(GeluArgs<T>{nullptr, y, b, out, nullptr, s});                                  \
    }                                                                                                     \
    KERNEL umgen_gelu_backward_##NAME(const float* dh, const float* y, const float* b, T* out, float* db, \
                                      GeluSizes s) {                                                      \
        gelu_backward<V, T>(GeluArgs<T>{dh, y, b, out, db, s});                                           \
    }
// One family only where `UMGEN_INSTANCE` says which (kernels launched on cubecl's stream, `side/cubecl_stream.rs`).
#ifdef UMGEN_INSTANCE
UMGEN_INSTANCE
#else
GELU_KERNELS(f32_1, 1, float)
GELU_KERNELS(f32_4, 4, float)
GELU_KERNELS(bf16_1, 1, u16)
GELU_KERNELS(bf16_4, 4, u16)
#endif
#endif
