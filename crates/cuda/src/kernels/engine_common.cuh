// Shared pieces of the generation engine's kernels (`gemv.cu`, `attend.cu`, `rows.cu`, `draw.cu`), compiled
// after `warp_device.cuh` and `bf16.cuh` (NVRTC) or `warp_emulator.h` (the host emulator).
//
// `WT` is the element type of the weights and of the activations that products read: `u16` (bf16 bits) or
// `float`, defined before this file (`-DWT=...`). Residual streams, norms, softmax statistics and logits
// are f32 whatever `WT` is.

#ifndef WT
#define WT float
#endif

#ifdef UMGEN_EMULATED
DEV float load_global(const float* p) { return *p; }
DEV void fence() {}
DEV unsigned atomic_add_u(unsigned* p, unsigned v) { return std::atomic_ref<unsigned>(*p).fetch_add(v); }
DEV u32 mulhi32(u32 a, u32 b) { return (u32)(((unsigned long long)a * b) >> 32); }
// Products and sums rounded one at a time, as burn's element-wise operations compute them (no FMA).
DEV float mul_rn(float a, float b) { return a * b; }
DEV float add_rn(float a, float b) { return a + b; }
DEV void prefetch_l2(const void*) {}
#else
// A load that skips L1 (another block's write is seen as L2 holds it).
DEV float load_global(const float* p) { return __ldcg(p); }
DEV void fence() { __threadfence(); }
DEV unsigned atomic_add_u(unsigned* p, unsigned v) { return atomicAdd(p, v); }
DEV u32 mulhi32(u32 a, u32 b) { return __umulhi(a, b); }
DEV float mul_rn(float a, float b) { return __fmul_rn(a, b); }
DEV float add_rn(float a, float b) { return __fadd_rn(a, b); }
// Asks L2 for the 128-byte line at `p`: nothing is read into the thread, so it is safe before
// `griddep_wait` whoever writes the line (L2 is where every write lands).
DEV void prefetch_l2(const void* p) { asm volatile("prefetch.global.L2 [%0];" ::"l"(p)); }
#endif

// Programmatic dependent launch (compute capability 9.0): the executor launches each engine kernel so that
// it may start while the kernel before it finishes. `griddep_launch` lets the next one start; everything
// before `griddep_wait` must read nothing an earlier kernel writes (weights only); after it, every earlier
// kernel has finished and its writes are visible. Elsewhere both are no-ops and kernels run in order.
#if defined(UMGEN_EMULATED) || !defined(__CUDA_ARCH__) || __CUDA_ARCH__ < 900
DEV void griddep_launch() {}
DEV void griddep_wait() {}
#else
DEV void griddep_launch() { asm volatile("griddepcontrol.launch_dependents;" ::: "memory"); }
DEV void griddep_wait() { asm volatile("griddepcontrol.wait;" ::: "memory"); }
#endif

// Eight consecutive values at `p` in f32 (`p` 16-byte aligned).
DEV void load8(const float* p, float* v) {
#ifdef UMGEN_EMULATED
    for (int i = 0; i < 8; i++) v[i] = p[i];
#else
    const float4 a = *(const float4*)p;
    const float4 b = *(const float4*)(p + 4);
    v[0] = a.x; v[1] = a.y; v[2] = a.z; v[3] = a.w;
    v[4] = b.x; v[5] = b.y; v[6] = b.z; v[7] = b.w;
#endif
}
DEV void load8(const u16* p, float* v) {
#ifdef UMGEN_EMULATED
    for (int i = 0; i < 8; i++) v[i] = from_bf16(p[i]);
#else
    const uint4 a = *(const uint4*)p;
    const u32 w[4] = {a.x, a.y, a.z, a.w};
#pragma unroll
    for (int i = 0; i < 4; i++) {
        v[2 * i] = bits_float(w[i] << 16);
        v[2 * i + 1] = bits_float(w[i] & 0xffff0000u);
    }
#endif
}

// The bits of eight consecutive `WT` values held in registers until `unpack8` makes them f32: a weight row
// loaded ahead costs 4 registers per 8 values in bf16 rather than 8.
#ifdef UMGEN_EMULATED
struct Packed8 {
    WT v[8];
};
DEV void load_packed8(const WT* p, Packed8& r) {
    for (int i = 0; i < 8; i++) r.v[i] = p[i];
}
DEV void unpack8(const Packed8& r, float* v) {
    for (int i = 0; i < 8; i++) v[i] = value(&r.v[i]);
}
#else
struct Packed8 {
    uint4 a, b;  // `b` only for f32
};
DEV void load_packed8(const u16* p, Packed8& r) { r.a = *(const uint4*)p; }
DEV void load_packed8(const float* p, Packed8& r) {
    r.a = *(const uint4*)p;
    r.b = *(const uint4*)(p + 4);
}
DEV void unpack8(const Packed8& r, float* v) {
    const u32 w[8] = {r.a.x, r.a.y, r.a.z, r.a.w, r.b.x, r.b.y, r.b.z, r.b.w};
    if (sizeof(WT) == 2) {
#pragma unroll
        for (int i = 0; i < 4; i++) {
            v[2 * i] = bits_float(w[i] << 16);
            v[2 * i + 1] = bits_float(w[i] & 0xffff0000u);
        }
    } else {
#pragma unroll
        for (int i = 0; i < 8; i++) v[i] = bits_float(w[i]);
    }
}
#endif

// Whether `p` may be read or written 16 bytes at a time.
DEV bool aligned16(const void* p) { return ((unsigned long long)p & 15) == 0; }

// Eight f32 values stored as `WT` at `p` (16-byte aligned).
#ifdef UMGEN_EMULATED
DEV void store8(WT* p, const float* v) {
    for (int i = 0; i < 8; i++) store(p + i, v[i]);
}
#else
DEV void store8(u16* p, const float* v) {
    u32 w[4];
#pragma unroll
    for (int i = 0; i < 4; i++) w[i] = (u32)to_bf16(v[2 * i]) | ((u32)to_bf16(v[2 * i + 1]) << 16);
    uint4 u;
    u.x = w[0];
    u.y = w[1];
    u.z = w[2];
    u.w = w[3];
    *(uint4*)p = u;
}
DEV void store8(float* p, const float* v) {
    float4 a, b;
    a.x = v[0];
    a.y = v[1];
    a.z = v[2];
    a.w = v[3];
    b.x = v[4];
    b.y = v[5];
    b.z = v[6];
    b.w = v[7];
    *(float4*)p = a;
    *(float4*)(p + 4) = b;
}
#endif

// GELU's exact form (erf), as burn's and PyTorch's `gelu`.
DEV float gelu(float x) { return 0.5f * x * (1.0f + erff(x * 0.70710678118654752f)); }

// Whether `x` is a number other than ±∞.
DEV bool finite(float x) { return x > NEG_INF && x < -NEG_INF; }

// Philox4x32-10 (Salmon et al., 2011) of the counter `c` under the key (k0, k1), in place.
DEV void philox(u32* c, u32 k0, u32 k1) {
    for (int r = 0; r < 10; r++) {
        const u32 hi0 = mulhi32(0xD2511F53u, c[0]), lo0 = 0xD2511F53u * c[0];
        const u32 hi1 = mulhi32(0xCD9E8D57u, c[2]), lo1 = 0xCD9E8D57u * c[2];
        const u32 n0 = hi1 ^ c[1] ^ k0, n2 = hi0 ^ c[3] ^ k1;
        c[0] = n0;
        c[1] = lo1;
        c[2] = n2;
        c[3] = lo0;
        k0 += 0x9E3779B9u;
        k1 += 0xBB67AE85u;
    }
}

// A uniform number in [0, 1) with 53 random bits, for the counter (scene, position, frame, purpose): every
// draw of a run has its own counter, so draws do not depend on how scenes are grouped or ordered.
DEV double uniform(u32 k0, u32 k1, u32 scene, u32 position, u32 frame, u32 purpose) {
    u32 c[4] = {scene, position, frame, purpose};
    philox(c, k0, k1);
    return ((double)(c[0] >> 5) * 67108864.0 + (double)(c[1] >> 6)) * (1.0 / 9007199254740992.0);
}
