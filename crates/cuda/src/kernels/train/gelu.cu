// An MLP's bias + GELU over the product `y` `[rows, n]` (f32 or bf16, no bias), forward and backward
// (`gelu/cuda.rs` compiles this with NVRTC and launches it on burn's buffers, bound as the entry points'
// pointer parameters).
//
// burn-fusion runs the bias add and GELU as one element-wise kernel that writes the hidden activation in f32
// and keeps the pre-activation, then a separate cast to bf16 for the next product, and in the backward pass
// GELU's derivative, the cast of the result and the bias's row sums as more passes: on `[70,368, 1,536]`
// (the `small` preset's MLP) about 0.75 ms + 0.23 ms forward against 0.22 ms for reading `y` once and
// writing bf16. Here the forward pass reads `y` and the bias once and writes gelu(y + b) in the product's
// format (`T`: bf16 bits or f32; with the bf16 presets the product is written in bf16, as PyTorch's
// autocast writes it, and the activation is the next product's operand); the backward pass reads the
// output's gradient and `y` (both in `T`), recomputes y + b, writes dh · gelu'(y + b) in `T` and each
// warp's f32 column sums of it (the bias's gradient, summed over the warps by the caller). The arithmetic
// is f32. GELU is the exact one (erf), as burn's forward pass and
// PyTorch's `nn.GELU()`; the derivative is the exact one too, Φ(x) + x·φ(x) (burn's backward pass uses the
// tanh approximation's).
//
// `V` values a lane at a time (16 bytes' worth, 4 f32 or 8 bf16, when `n` is a multiple of that: one 16-byte
// load each; else 1); NVRTC compiles it
// after `warp_device.cuh`'s primitives, and on the host `gelu_emulator.cpp` includes it after
// `warp_emulator.h`'s and runs it thread by thread against a double-precision reference.

// The sizes every entry point takes by value (`Sizes` in `gelu/cuda.rs`, field for field).
struct GeluSizes {
    long long rows;
    int n;       // columns, the bias's length
    int groups;  // row groups; backward: one row of column sums each
};

// What the passes read and write.
template <class T>
struct GeluArgs {
    const T* dh;      // [rows, n] (backward)
    const T* y;       // [rows, n]
    const float* b;   // [n]
    T* out;           // [rows, n]: gelu(y + b) forward, dh · gelu'(y + b) backward
    float* db;        // [groups, n] (backward): each row group's column sums of the gradient
    GeluSizes s;
};

// `V` consecutive values from `p` as floats (one 16-byte load where `V` fills 16 bytes: `p` aligned to it).
template <int V, class T>
DEV void load(const T* p, float (&v)[V]) {
#ifndef UMGEN_EMULATED
    if constexpr (V * sizeof(T) == 16) {
        const uint4 q = *reinterpret_cast<const uint4*>(p);
        const u32 w[4] = {q.x, q.y, q.z, q.w};
        if constexpr (sizeof(T) == 4) {
#pragma unroll
            for (int k = 0; k < 4; k++) v[k] = bits_float(w[k]);
        } else {
#pragma unroll
            for (int k = 0; k < 4; k++) v[2 * k] = bits_float(w[k] << 16), v[2 * k + 1] = bits_float(w[k] & 0xffff0000u);
        }
        return;
    }
#endif
#pragma unroll
    for (int k = 0; k < V; k++) v[k] = value(p + k);
}

// `V` values to `p` in `T` (one 16-byte store where `V` fills 16 bytes).
template <int V, class T>
DEV void store_all(T* p, const float (&v)[V]) {
#ifndef UMGEN_EMULATED
    if constexpr (V * sizeof(T) == 16) {
        u32 w[4];
        if constexpr (sizeof(T) == 4) {
#pragma unroll
            for (int k = 0; k < 4; k++) w[k] = float_bits(v[k]);
        } else {
#pragma unroll
            for (int k = 0; k < 4; k++) w[k] = (u32)to_bf16(v[2 * k]) | ((u32)to_bf16(v[2 * k + 1]) << 16);
        }
        *reinterpret_cast<uint4*>(p) = make_uint4(w[0], w[1], w[2], w[3]);
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

// Both passes split the work alike: warp w takes column chunk w % chunks (32·V columns, lane l the V from
// 32·V·chunk + V·l) of the rows g, g + groups, g + 2·groups, … of row group g = w / chunks, so that a lane
// keeps its bias values (and, backward, its column sums) in registers and indexes rows without a division.
// `IN_FLIGHT` rows are loaded before any is stored: the passes stream at the memory's speed only with
// enough loads outstanding, and a store the compiler cannot prove apart from the next row's loads keeps
// them behind it (one row at a time, the bf16 backward pass moved about 1.7 TB/s on an H100).
#define IN_FLIGHT 4

// The forward pass. (Its loop and the backward pass's were one lambda-taking helper for a while: the
// forward kernel took 200 µs instead of 178 a `[70,368, 1,536]` launch, so both stay written out.)
template <int V, class T>
DEV void gelu_forward(const GeluArgs<T>& a) {
    const int n = a.s.n, lane = lane_id();
    const int chunks = (n + 32 * V - 1) / (32 * V);
    const long long work = (long long)chunks * a.s.groups, warps = blocks() * warps_per_block();
    for (long long w = warp_index(); w < work; w += warps) {
        const int c = (int)(w % chunks) * 32 * V + lane * V;
        const int g = (int)(w / chunks);
        if (c >= n) continue;
        float bias[V];
        load<V>(a.b + c, bias);
        for (long long r0 = g; r0 < a.s.rows; r0 += IN_FLIGHT * (long long)a.s.groups) {
            float v[IN_FLIGHT][V];
#pragma unroll
            for (int j = 0; j < IN_FLIGHT; j++) {
                const long long r = r0 + j * (long long)a.s.groups;
                if (r < a.s.rows) load<V>(a.y + r * n + c, v[j]);
            }
#pragma unroll
            for (int j = 0; j < IN_FLIGHT; j++) {
                const long long r = r0 + j * (long long)a.s.groups;
                if (r >= a.s.rows) break;
#pragma unroll
                for (int k = 0; k < V; k++) v[j][k] = gelu(v[j][k] + bias[k]);
                store_all<V, T>(a.out + r * n + c, v[j]);
            }
        }
    }
}

// The backward pass; row group g's column sums go to db's row g.
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
        for (long long r0 = g; r0 < a.s.rows; r0 += IN_FLIGHT * (long long)a.s.groups) {
            float dh[IN_FLIGHT][V], x[IN_FLIGHT][V];
#pragma unroll
            for (int j = 0; j < IN_FLIGHT; j++) {
                const long long r = r0 + j * (long long)a.s.groups;
                if (r < a.s.rows) load<V>(a.dh + r * n + c, dh[j]), load<V>(a.y + r * n + c, x[j]);
            }
#pragma unroll
            for (int j = 0; j < IN_FLIGHT; j++) {
                const long long r = r0 + j * (long long)a.s.groups;
                if (r >= a.s.rows) break;
#pragma unroll
                for (int k = 0; k < V; k++) {
                    dh[j][k] *= gelu_grad(x[j][k] + bias[k]);
                    sum[k] += dh[j][k];
                }
                store_all<V, T>(a.out + r * n + c, dh[j]);
            }
        }
#pragma unroll
        for (int k = 0; k < V; k++) a.db[(long long)g * n + c + k] = sum[k];
    }
}

#ifndef UMGEN_EMULATED
// The entry points of one operand type and width: the buffers bound by the launch, then the sizes.
#define GELU_KERNELS(NAME, V, T)                                                                          \
    KERNEL umgen_gelu_forward_##NAME(const T* y, const float* b, T* out, GeluSizes s) {                  \
        gelu_forward<V, T>(GeluArgs<T>{nullptr, y, b, out, nullptr, s});                                  \
    }                                                                                                     \
    KERNEL umgen_gelu_backward_##NAME(const T* dh, const T* y, const float* b, T* out, float* db,         \
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
GELU_KERNELS(bf16_8, 8, u16)
#endif
#endif
