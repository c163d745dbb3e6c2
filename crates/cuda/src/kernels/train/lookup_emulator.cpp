// Runs the embedding-gradient kernels (lookup.cu) on the host, one std::thread per CUDA thread of a block,
// in the order `lookup/cuda.rs` launches them, and compares the table's gradient with a double-precision
// sum per id; the sums must also be bit-identical across grids of other block sizes (the rows' order
// fixes them):
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/lookup-emu
//       crates/cuda/src/kernels/train/lookup_emulator.cpp && /tmp/lookup-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Exit status 0 when every case
// agrees.
#include "../warp_emulator.h"
#include "lookup.cu"

#include <cstring>

struct Case {
    long long rows;
    int vocab, d;
    // Share of the rows whose id is 0 (a map's empty code), and of ids outside the table.
    double common, outside;
    const char* what;
};

// The gradient from the six kernels, their blocks `warps` warps (the scan's too).
static std::vector<float> grad(const Case& c, const std::vector<int>& ids, const std::vector<float>& g, int warps) {
    const int buckets = c.vocab + 1;
    LookupSizes s{c.rows, c.vocab, c.d, (int)((c.rows + CHUNK - 1) / CHUNK)};
    const long long tiles = (c.rows + TILE - 1) / TILE;
    std::vector<int> hist((size_t)s.chunks * buckets, -1), start(buckets, -1), order(c.rows, -1), sorted(c.rows, -1);
    std::vector<float> out((size_t)c.vocab * c.d, NAN), partial((size_t)2 * tiles * c.d, NAN);
    const int threads = 32 * warps;
    run_grid([&] { umgen_lookup_count(ids.data(), hist.data(), s); }, s.chunks, warps);
    run_grid([&] { umgen_lookup_prefix(hist.data(), start.data(), s); }, (buckets + threads - 1) / threads, warps);
    run_grid([&] { umgen_lookup_scan(start.data(), s); }, 1, warps);
    run_grid([&] { umgen_lookup_place(ids.data(), hist.data(), start.data(), order.data(), sorted.data(), s); },
             s.chunks, warps);
    run_grid([&] { umgen_lookup_sum(g.data(), order.data(), sorted.data(), out.data(), partial.data(), s); },
             tiles, warps);
    run_grid([&] { umgen_lookup_finish(start.data(), partial.data(), out.data(), s); }, c.vocab, warps);
    return out;
}

static bool run(const Case& c, std::mt19937& rng) {
    std::uniform_real_distribution<double> share(0, 1);
    std::uniform_int_distribution<int> any(0, c.vocab - 1);
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<int> ids(c.rows);
    for (auto& id : ids) {
        const double u = share(rng);
        id = u < c.outside ? (u < c.outside / 2 ? -1 : c.vocab + 3) : u < c.outside + c.common ? 0 : any(rng);
    }
    std::vector<float> g(c.rows * c.d);
    for (auto& x : g) x = normal(rng);
    std::vector<double> want((size_t)c.vocab * c.d, 0.0);
    for (long long i = 0; i < c.rows; i++)
        if (ids[i] >= 0 && ids[i] < c.vocab)
            for (int j = 0; j < c.d; j++) want[(size_t)ids[i] * c.d + j] += g[i * c.d + j];
    const std::vector<float> got = grad(c, ids, g, 8), other = grad(c, ids, g, 2);
    const double errs[] = {relative_error(got, want),
                           std::memcmp(got.data(), other.data(), got.size() * sizeof(float)) == 0 ? 0.0 : 1.0};
    const char* const names[] = {"grad", "differs with 2 warps a block"};
    printf("%s (rows %lld, vocab %d, d %d):", c.what, c.rows, c.vocab, c.d);
    // f32 sums of up to a few thousand terms of unit size, against a largest sum of about √rows.
    return report(errs, names, 1e-5);
}

int main() {
    const Case cases[] = {
        {3000, 50, 20, 0.0, 0.0, "uniform ids over three chunks, a partial last tile"},
        {2500, 40, 33, 0.9, 0.0, "one id in nine rows of ten (spans most tiles)"},
        {200, 300, 8, 0.1, 0.05, "more ids than rows, ids outside the table ignored"},
        {64, 3, 5, 0.0, 0.0, "one tile"},
        {1, 4, 300, 0.0, 0.0, "one row, wider than a block"},
    };
    return run_cases(cases, run, 7);
}
