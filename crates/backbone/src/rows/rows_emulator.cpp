// Runs the column-sum kernel (rows.cu) on the host, one std::thread per CUDA thread of a block, in the two
// launches `rows/cuda.rs` makes, and compares the sums with a double-precision reference; they must also be
// bit-identical on blocks of another size:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/rows-emu
//       crates/backbone/src/rows/rows_emulator.cpp && /tmp/rows-emu
//
// (`crates/backbone/tests/backbone/rows.rs` runs it in the test suite.) Exit status 0 when every case agrees.
#include "../warp_emulator.h"
#include "rows.cu"

#include <cstring>

struct Case {
    long long rows;
    int d, groups;
};

// The column sums by `groups` row groups then their rows (one launch when `groups` is 1), blocks of `warps`.
static std::vector<float> sums(const Case& c, const std::vector<float>& x, int warps) {
    const int tiles = (c.d + 31) / 32;
    std::vector<float> part((size_t)c.groups * c.d, NAN), out(c.d, NAN);
    const RowsSizes first{c.rows, c.d, c.groups};
    run_grid([&] { umgen_rows_sum(x.data(), c.groups > 1 ? part.data() : out.data(), first); },
             (long long)tiles * c.groups, warps);
    if (c.groups > 1) {
        const RowsSizes second{c.groups, c.d, 1};
        run_grid([&] { umgen_rows_sum(part.data(), out.data(), second); }, tiles, warps);
    }
    return out;
}

static bool run(const Case& c, std::mt19937& rng) {
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<float> x(c.rows * c.d);
    for (auto& v : x) v = normal(rng);
    std::vector<double> want(c.d, 0.0);
    for (long long r = 0; r < c.rows; r++)
        for (int j = 0; j < c.d; j++) want[j] += x[r * c.d + j];
    const std::vector<float> got = sums(c, x, 8), other = sums(c, x, 2);
    const double errs[] = {relative_error(got, want),
                           std::memcmp(got.data(), other.data(), got.size() * sizeof(float)) == 0 ? 0.0 : 1.0};
    const char* const names[] = {"sums", "differs with 2 warps a block"};
    printf("rows %lld d %d groups %d:", c.rows, c.d, c.groups);
    // f32 sums of up to a few thousand unit terms, against a largest sum of about √rows.
    return report(errs, names, 1e-5);
}

int main() {
    const Case cases[] = {
        {1000, 70, 31},  // a partial last column tile and a partial last group
        {37, 384, 1},    // one launch, fewer rows than phases a warp would take
        {5, 3, 1},       // narrower than a warp
        {3000, 33, 93},  // groups of 33 rows
    };
    return run_cases(cases, run, 5);
}
