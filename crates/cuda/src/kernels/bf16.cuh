// bf16 loads and stores for the CUDA C kernels that read or write a product's operand (`gelu/gelu.cu`,
// `norm/norm.cu`):
// `side::kernel_source` puts this after `warp_device.cuh` for NVRTC, and `warp_emulator.h` includes it on
// the host; both define `u16`, `u32` and `float_bits` first.

// f32 to bf16 bits, to nearest with ties to even (NaN stays NaN), as burn's cast kernels round.
DEV u16 to_bf16(float x) {
    const u32 u = float_bits(x);
    if ((u & 0x7fffffffu) > 0x7f800000u) return (u16)((u >> 16) | 0x40u);
    return (u16)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

// `x` stored in an f32 or a bf16 result.
DEV void store(float* p, float x) { *p = x; }
DEV void store(u16* p, float x) { *p = to_bf16(x); }

// bf16 bits to f32 (exact).
DEV float from_bf16(u16 h) { return bits_float((u32)h << 16); }

// The value at `p` of an f32 or a bf16 operand, in f32.
DEV float value(const float* p) { return *p; }
DEV float value(const u16* p) { return from_bf16(*p); }
