// Runs the bias + GELU kernels (gelu.cu) on the host, one std::thread per CUDA thread of a block, and
// compares their results with a double-precision reference:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/gelu-emu
//       crates/cuda/src/kernels/train/gelu_emulator.cpp && /tmp/gelu-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Exit status 0 when every case
// agrees: f32 outputs within f32 tolerance, bf16 outputs within half a bf16 step (2⁻⁸) of the largest
// reference value.
#include <cstring>
#include "../warp_emulator.h"
#include "gelu.cu"

struct Case {
    long long rows;
    int n, v, groups, grid, warps;
    bool bf16;
};

// The widths `gelu/cuda.rs` launches: 16 bytes of `T` a lane, or one value.
template <class T>
static void forward(GeluArgs<T> a, int v, long long grid, int warps) {
    constexpr int wide = 16 / sizeof(T);
    if (v == wide) {
        launch(+[](GeluArgs<T> a) { gelu_forward<wide, T>(a); }, a, grid, warps);
    } else {
        launch(+[](GeluArgs<T> a) { gelu_forward<1, T>(a); }, a, grid, warps);
    }
}

template <class T>
static void backward(GeluArgs<T> a, int v, long long grid, int warps) {
    constexpr int wide = 16 / sizeof(T);
    if (v == wide) {
        launch(+[](GeluArgs<T> a) { gelu_backward<wide, T>(a); }, a, grid, warps);
    } else {
        launch(+[](GeluArgs<T> a) { gelu_backward<1, T>(a); }, a, grid, warps);
    }
}

// Both passes in `T` (the inputs converted to it, exactly: bf16 cases draw bf16 values), the outputs
// read back as floats.
template <class T>
static void passes(const Case& c, const std::vector<float>& y, const std::vector<float>& b,
                   const std::vector<float>& dh, std::vector<float>& h, std::vector<float>& dx,
                   std::vector<float>& db) {
    const long long n = c.rows * c.n;
    std::vector<T> out(n), grad(n), ty(n), tdh(n);
    for (long long i = 0; i < n; i++) {
        if constexpr (sizeof(T) == 4) {
            ty[i] = y[i], tdh[i] = dh[i];
        } else {
            ty[i] = to_bf16(y[i]), tdh[i] = to_bf16(dh[i]);
        }
    }
    // Unwritten values stay NaN, which fails the comparison.
    T nan;
    if constexpr (sizeof(T) == 4) {
        nan = NAN;
    } else {
        nan = 0x7fc0;
    }
    std::fill(out.begin(), out.end(), nan);
    std::fill(grad.begin(), grad.end(), nan);
    const GeluSizes s{c.rows, c.n, c.groups};
    forward(GeluArgs<T>{nullptr, ty.data(), b.data(), out.data(), nullptr, s}, c.v, c.grid, c.warps);
    backward(GeluArgs<T>{tdh.data(), ty.data(), b.data(), grad.data(), db.data(), s}, c.v, c.grid, c.warps);
    for (long long i = 0; i < n; i++) {
        if constexpr (sizeof(T) == 4) {
            h[i] = out[i], dx[i] = grad[i];
        } else {
            h[i] = from_bf16(out[i]), dx[i] = from_bf16(grad[i]);
        }
    }
}

static bool run(const Case& c, std::mt19937& rng) {
    const long long n = c.rows * c.n;
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<float> y(n), dh(n), b(c.n);
    // Pre-activations from −6 to 6: both tails of GELU and its derivative.
    for (long long i = 0; i < n; i++) y[i] = 2.f * normal(rng), dh[i] = normal(rng);
    // A bf16 pass reads bf16 operands: draw values bf16 holds, so that the reference reads the same.
    if (c.bf16)
        for (long long i = 0; i < n; i++) y[i] = from_bf16(to_bf16(y[i])), dh[i] = from_bf16(to_bf16(dh[i]));
    for (int i = 0; i < c.n; i++) b[i] = normal(rng);
    std::vector<float> h(n), dx(n), db((long long)c.groups * c.n, NAN);
    if (c.bf16) {
        passes<u16>(c, y, b, dh, h, dx, db);
    } else {
        passes<float>(c, y, b, dh, h, dx, db);
    }

    // The reference, in double precision.
    std::vector<double> rh(n), rdx(n), rdb(c.n, 0);
    for (long long r = 0; r < c.rows; r++)
        for (int i = 0; i < c.n; i++) {
            const long long at = r * c.n + i;
            const double x = (double)y[at] + b[i];
            const double cdf = 0.5 * (1 + std::erf(x / std::sqrt(2.0)));
            rh[at] = x * cdf;
            rdx[at] = dh[at] * (cdf + x * std::exp(-0.5 * x * x) / std::sqrt(2 * M_PI));
            rdb[i] += rdx[at];
        }
    // The row groups' column sums, added as the caller adds them.
    std::vector<float> sdb(c.n, 0);
    for (long long g = 0; g < c.groups; g++)
        for (int i = 0; i < c.n; i++) sdb[i] += db[g * c.n + i];
    const double errs[] = {relative_error(h, rh), relative_error(dx, rdx), relative_error(sdb, rdb)};
    const char* const names[] = {"h", "dx", "db"};
    printf("rows %lld n %d v %d groups %d grid %d × %d warps %s:", c.rows, c.n, c.v, c.groups, c.grid,
           c.warps, c.bf16 ? "bf16" : "f32");
    // bf16 keeps 8 significant bits: rounding to nearest moves a value by at most half a step, 2⁻⁸ of it
    // (truncating would move it up to 2⁻⁷).
    return report(errs, names, c.bf16 ? 0.0039 : 2e-5);
}

int main() {
    const Case cases[] = {
        {37, 48, 4, 8, 2, 4, false},    // rows looped by the grid, groups of 4 or 5 rows (a partial batch)
        {37, 48, 8, 8, 2, 4, true},     // the same in bf16
        {5, 132, 4, 16, 1, 8, false},   // a partial chunk, more row groups than rows
        {64, 384, 8, 32, 3, 8, true},   // several chunks a row, warps looping over the work
        {70, 264, 8, 3, 2, 4, true},    // long row groups: several batches of rows in flight, a partial one
        {21, 7, 1, 4, 1, 2, false},     // a width that is not a multiple of 4
        {30, 45, 1, 6, 2, 3, true},     // the same in bf16, chunks of 32
    };
    return run_cases(cases, run, 11);
}
