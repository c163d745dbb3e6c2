// Runs the cross-entropy kernels (xent.cu) on the host, one std::thread per CUDA thread of a block with the
// warp shuffle emulated, and compares their results with a double-precision reference:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/xent-emu
//       crates/cuda/src/kernels/train/xent_emulator.cpp && /tmp/xent-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Exit status 0 when every case
// agrees within f32 tolerance.
#include "../warp_emulator.h"
#include "xent.cu"

struct Case {
    long long rows;
    int v, k, grid, warps;
    float spread;  // of the logits
};

static bool run(const Case& c, std::mt19937& rng) {
    const long long n = c.rows * c.v;
    std::normal_distribution<float> normal(0.f, 1.f);
    std::uniform_int_distribution<int> id(0, c.v - 1);
    std::vector<float> x(n), lse(c.rows, NAN), dx(n, NAN), w(c.rows * c.k);
    std::vector<float> ids(c.rows * c.k);
    for (long long i = 0; i < n; i++) x[i] = c.spread * normal(rng);
    for (long long r = 0; r < c.rows; r++) {
        double total = 0;
        for (int j = 0; j < c.k; j++) {
            // A repeated id (as a clamped, zero-weight window entry) and one outside the row: skipped.
            ids[r * c.k + j] = j == 1 && c.k > 2 ? ids[r * c.k] : (j == 2 && c.k > 3 ? c.v + 5 : id(rng));
            w[r * c.k + j] = ids[r * c.k + j] >= c.v ? 0.f : std::fabs(normal(rng));
            total += w[r * c.k + j];
        }
        for (int j = 0; j < c.k; j++) w[r * c.k + j] /= total;
    }
    const float g = 0.75f;
    XentParams p{x.data(), lse.data(), &g, ids.data(), w.data(), lse.data(), dx.data(), c.rows, c.v, c.k};
    launch(umgen_xent_forward, p, c.grid, c.warps);
    launch(umgen_xent_backward, p, c.grid, c.warps);

    // The reference, in double precision.
    std::vector<double> rlse(c.rows), rdx(n);
    for (long long r = 0; r < c.rows; r++) {
        const float* xr = &x[r * c.v];
        double m = -INFINITY, s = 0;
        for (int i = 0; i < c.v; i++) m = std::max(m, (double)xr[i]);
        for (int i = 0; i < c.v; i++) s += std::exp(xr[i] - m);
        rlse[r] = m + std::log(s);
        for (int i = 0; i < c.v; i++) rdx[r * c.v + i] = g * std::exp(xr[i] - rlse[r]);
        for (int j = 0; j < c.k; j++) {
            const int t = (int)ids[r * c.k + j];
            if (t < c.v) rdx[r * c.v + t] -= g * w[r * c.k + j];
        }
    }
    const double errs[] = {relative_error(lse, rlse), relative_error(dx, rdx)};
    const char* const names[] = {"lse", "dx"};
    printf("rows %lld v %d k %d grid %d × %d warps:", c.rows, c.v, c.k, c.grid, c.warps);
    return report(errs, names, 2e-5);
}

int main() {
    const Case cases[] = {
        {37, 1028, 1, 2, 4, 3.f},   // agent vocabulary, hard targets, rows looped by 8 warps
        {5, 8192, 7, 1, 8, 1.f},    // map / image vocabulary, a smoothed window; idle warps
        {20, 100, 4, 3, 2, 30.f},   // v not a multiple of 256; logits far apart (exp underflows)
        {9, 3, 2, 1, 1, 2.f},       // narrower than a warp
    };
    return run_cases(cases, run, 11);
}
