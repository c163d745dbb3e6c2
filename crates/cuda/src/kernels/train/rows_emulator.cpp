// Runs the column-sum kernel (rows.cu) on the host, one std::thread per CUDA thread of a block, in the two
// launches `rows/cuda.rs` makes, and compares the sums with a double-precision reference; they must also be
// bit-identical on blocks of another size:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/rows-emu
//       crates/cuda/src/kernels/train/rows_emulator.cpp && /tmp/rows-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Exit status 0 when every case agrees.
#include "../warp_emulator.h"
#include "rows.cu"

#include <cstring>

struct Case {
    long long rows;
    int d, groups;
    bool bf16;
    bool cast = false;  // f32 rows, their bf16 copy written by the first launch
};

// The column sums by `groups` row groups then their rows (one launch when `groups` is 1), blocks of `warps`;
// the first launch reads `x` as bf16 where the case says so (its values are bf16's already), or writes its
// bf16 copy to `copy` (bf16 bits, as u32 to keep the NaN check simple) where the case casts.
static std::vector<float> sums(const Case& c, const std::vector<float>& x, int warps, std::vector<u16>* copy = nullptr) {
    const int tiles = (c.d + 31) / 32;
    std::vector<float> part((size_t)c.groups * c.d, NAN), out(c.d, NAN);
    std::vector<u16> half(x.size());
    for (size_t i = 0; i < x.size(); i++) half[i] = to_bf16(x[i]);
    const RowsSizes first{c.rows, c.d, c.groups};
    float* to = c.groups > 1 ? part.data() : out.data();
    if (c.bf16) {
        run_grid([&] { umgen_rows_sum_bf16(half.data(), to, first); }, (long long)tiles * c.groups, warps);
    } else if (copy) {
        run_grid([&] { umgen_rows_sum_cast(x.data(), to, copy->data(), first); }, (long long)tiles * c.groups, warps);
    } else {
        run_grid([&] { umgen_rows_sum(x.data(), to, first); }, (long long)tiles * c.groups, warps);
    }
    if (c.groups > 1) {
        const RowsSizes second{c.groups, c.d, 1};
        run_grid([&] { umgen_rows_sum(part.data(), out.data(), second); }, tiles, warps);
    }
    return out;
}

static bool run(const Case& c, std::mt19937& rng) {
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<float> x(c.rows * c.d);
    for (auto& v : x) v = c.bf16 ? from_bf16(to_bf16(normal(rng))) : normal(rng);
    std::vector<double> want(c.d, 0.0);
    for (long long r = 0; r < c.rows; r++)
        for (int j = 0; j < c.d; j++) want[j] += x[r * c.d + j];
    // Unwritten bf16 values stay a NaN pattern no rounding gives.
    std::vector<u16> copy(x.size(), 0xffff);
    const std::vector<float> got = sums(c, x, 8, c.cast ? &copy : nullptr), other = sums(c, x, 2);
    size_t wrong = 0;
    if (c.cast)
        for (size_t i = 0; i < x.size(); i++) wrong += copy[i] != to_bf16(x[i]);
    const double errs[] = {relative_error(got, want),
                           std::memcmp(got.data(), other.data(), got.size() * sizeof(float)) == 0 ? 0.0 : 1.0,
                           (double)wrong};
    const char* const names[] = {"sums", "differs with 2 warps a block", "bf16 copy wrong"};
    printf("rows %lld d %d groups %d %s:", c.rows, c.d, c.groups, c.bf16 ? "bf16" : c.cast ? "f32 cast" : "f32");
    // f32 sums of up to a few thousand unit terms, against a largest sum of about √rows.
    return report(errs, names, 1e-5);
}

int main() {
    const Case cases[] = {
        {1000, 70, 31, false},  // a partial last column tile and a partial last group
        {37, 384, 1, false},    // one launch, fewer rows than phases a warp would take
        {5, 3, 1, false},       // narrower than a warp
        {3000, 33, 93, false},  // groups of 33 rows
        {1000, 70, 31, true},   // bf16 rows, summed in f32
        {37, 384, 1, true},     // bf16 in one launch
        {1000, 70, 31, false, true},  // f32 rows and their bf16 copy, in two launches
        {37, 384, 1, false, true},    // the same in one
    };
    return run_cases(cases, run, 5);
}
