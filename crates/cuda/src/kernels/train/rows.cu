// Column sums of a row-major f32 or bf16 matrix `[rows, d]` (`rows.rs`'s `sum` on CUDA), summed in f32 (bf16
// where a product's bf16 gradient gives a bias its gradient, as PyTorch's autocast does), in two launches: the rows in
// `groups` groups (one row of partial sums each), then those rows. Block (c, g) sums columns [32c, 32c + 32)
// of group g: phase p takes the group's rows p, p + PHASES, … (a warp's 32 lanes read one 128-byte row
// segment at a time), then the phases are added in order, so the sums are the same whatever the block's
// size. burn's reduction gave each column one unit walking its rows: 15–20 µs for a `[256, 384]` matrix
// that one wave of these blocks reads in a few.
//
// NVRTC compiles it after `warp_device.cuh` and `bf16.cuh`; on the host `rows_emulator.cpp` includes it after
// `warp_emulator.h` and compares it with a double-precision sum. The second launch always reads f32.

#define PHASES 8

// Sizes of one launch (`Sizes` in `rows/cuda.rs`, field for field).
struct RowsSizes {
    long long rows;  // rows of the input
    int d;           // columns
    int groups;      // row groups, one output row each
};

// `cast` (where not null): the first launch also writes `x` rounded to bf16, packed, as it reads it: a
// gradient whose bias sum and bf16 copy for a product come from one pass (`rows::sum_cast`).
template <class T>
DEV void rows_sum(const T* x, float* out, u16* cast, RowsSizes s) {
    SHARED float part[PHASES][32];
    const int tiles = (s.d + 31) / 32;
    const long long g = block_x() / tiles;
    const int c = 32 * (int)(block_x() % tiles) + lane_id();
    const long long per = (s.rows + s.groups - 1) / s.groups, r0 = g * per;
    const long long r1 = r0 + per < s.rows ? r0 + per : s.rows;
    const int warps = threads() / 32;
    for (int ph = warp_id(); ph < PHASES; ph += warps) {
        float acc = 0.f;
        if (c < s.d) {
#pragma unroll 4
            for (long long r = r0 + ph; r < r1; r += PHASES) {
                const float v = value(x + r * s.d + c);
                if (cast) cast[r * s.d + c] = to_bf16(v);
                acc += v;
            }
        }
        part[ph][lane_id()] = acc;
    }
    sync_block();
    if (warp_id() == 0 && c < s.d) {
        float total = 0.f;
#pragma unroll
        for (int ph = 0; ph < PHASES; ph++) total += part[ph][lane_id()];
        out[g * s.d + c] = total;
    }
}

KERNEL umgen_rows_sum(const float* x, float* out, RowsSizes s) { rows_sum(x, out, (u16*)0, s); }
KERNEL umgen_rows_sum_bf16(const u16* x, float* out, RowsSizes s) { rows_sum(x, out, (u16*)0, s); }
KERNEL umgen_rows_sum_cast(const float* x, float* out, u16* cast, RowsSizes s) { rows_sum(x, out, cast, s); }
