// Runs the layer-norm kernels (norm.cu) on the host, one std::thread per CUDA thread of a block with the
// warp shuffle emulated, and compares their results with a double-precision reference:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/norm-emu
//       crates/backbone/src/norm/norm_emulator.cpp && /tmp/norm-emu
//
// (`crates/backbone/tests/backbone/norm.rs` runs it in the test suite.) Exit status 0 when every case
// agrees within f32 tolerance.
#include <barrier>
#include <cmath>
#include <cstdio>
#include <memory>
#include <random>
#include <thread>
#include <vector>

#define UMGEN_EMULATED
#define DEV static inline
#define KERNEL void

static thread_local int g_tid;
static thread_local long long g_bx;
static long long g_blocks;
static int g_warps;
static std::barrier<>* g_warp[8];
static float g_lane[8][32];

DEV int lane_id() { return g_tid & 31; }
DEV int warp_id() { return g_tid >> 5; }
DEV int warps_per_block() { return g_warps; }
DEV long long block_x() { return g_bx; }
DEV long long blocks() { return g_blocks; }
DEV float rsqrtf(float x) { return 1.f / std::sqrt(x); }
// The butterfly of `__shfl_xor_sync`, one exchange at a time through a warp barrier.
DEV float warp_sum(float x) {
    for (int m = 16; m > 0; m >>= 1) {
        g_lane[warp_id()][lane_id()] = x;
        g_warp[warp_id()]->arrive_and_wait();
        x += g_lane[warp_id()][lane_id() ^ m];
        g_warp[warp_id()]->arrive_and_wait();
    }
    return x;
}

#include "norm.cu"

// Runs `kernel` on `grid` blocks of `warps` warps, one block at a time.
static void launch(void (*kernel)(NormParams), NormParams p, long long grid, int warps) {
    g_warps = warps;
    g_blocks = grid;
    std::vector<std::unique_ptr<std::barrier<>>> barriers;
    for (int w = 0; w < warps; w++) {
        barriers.push_back(std::make_unique<std::barrier<>>(32));
        g_warp[w] = barriers.back().get();
    }
    for (long long b = 0; b < grid; b++) {
        std::vector<std::thread> threads;
        for (int t = 0; t < 32 * warps; t++)
            threads.emplace_back([=] {
                g_tid = t;
                g_bx = b;
                kernel(p);
            });
        for (auto& t : threads) t.join();
    }
}

struct Case {
    long long rows;
    int d, per, grid, warps;
};

// The largest |a − b| over the largest |b|.
static double rel(const std::vector<float>& a, const std::vector<double>& b) {
    double err = 0, scale = 1e-12;
    for (size_t i = 0; i < b.size(); i++) {
        err = std::max(err, std::fabs(a[i] - b[i]));
        scale = std::max(scale, std::fabs(b[i]));
    }
    return err / scale;
}

static bool run(const Case& c, std::mt19937& rng) {
    const long long n = c.rows * c.d;
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<float> x(n), dy(n), gamma(c.d), beta(c.d);
    for (long long i = 0; i < n; i++) x[i] = 3.f + 2.f * normal(rng), dy[i] = normal(rng);
    for (int i = 0; i < c.d; i++) gamma[i] = 1.f + 0.3f * normal(rng), beta[i] = 0.3f * normal(rng);
    const float eps = 1e-5f;
    const long long warps = (long long)c.grid * c.warps;
    std::vector<float> y(n), mean(c.rows), rstd(c.rows), dx(n), dg(warps * c.d, NAN), db(warps * c.d, NAN);
    NormParams p{x.data(), gamma.data(), beta.data(), dy.data(), mean.data(), rstd.data(), y.data(),
                 mean.data(), rstd.data(), dx.data(), dg.data(), db.data(), c.rows, c.d, eps};
    void (*fwd)(NormParams) = nullptr;
    void (*bwd)(NormParams) = nullptr;
    switch (c.per) {
        case 4: fwd = umgen_norm_forward_4, bwd = umgen_norm_backward_4; break;
        case 8: fwd = umgen_norm_forward_8, bwd = umgen_norm_backward_8; break;
        case 12: fwd = umgen_norm_forward_12, bwd = umgen_norm_backward_12; break;
        case 16: fwd = umgen_norm_forward_16, bwd = umgen_norm_backward_16; break;
        case 24: fwd = umgen_norm_forward_24, bwd = umgen_norm_backward_24; break;
        case 32: fwd = umgen_norm_forward_32, bwd = umgen_norm_backward_32; break;
    }
    launch(fwd, p, c.grid, c.warps);
    launch(bwd, p, c.grid, c.warps);

    // The reference, in double precision.
    std::vector<double> ry(n), rmean(c.rows), rrstd(c.rows), rdx(n), rdg(c.d, 0), rdb(c.d, 0);
    for (long long r = 0; r < c.rows; r++) {
        const float* xr = &x[r * c.d];
        const float* g = &dy[r * c.d];
        double m = 0, v = 0;
        for (int i = 0; i < c.d; i++) m += xr[i];
        m /= c.d;
        for (int i = 0; i < c.d; i++) v += (xr[i] - m) * (xr[i] - m);
        const double s = 1 / std::sqrt(v / c.d + eps);
        rmean[r] = m, rrstd[r] = s;
        double mg = 0, mgx = 0;
        for (int i = 0; i < c.d; i++) {
            const double xh = (xr[i] - m) * s;
            ry[r * c.d + i] = xh * gamma[i] + beta[i];
            mg += g[i] * gamma[i];
            mgx += g[i] * gamma[i] * xh;
            rdg[i] += g[i] * xh;
            rdb[i] += g[i];
        }
        mg /= c.d, mgx /= c.d;
        for (int i = 0; i < c.d; i++) {
            const double xh = (xr[i] - m) * s;
            rdx[r * c.d + i] = s * (g[i] * gamma[i] - mg - xh * mgx);
        }
    }
    // The warps' partial column sums, added as the caller adds them.
    std::vector<float> sdg(c.d, 0), sdb(c.d, 0);
    for (long long w = 0; w < warps; w++)
        for (int i = 0; i < c.d; i++) sdg[i] += dg[w * c.d + i], sdb[i] += db[w * c.d + i];
    const double errs[] = {rel(y, ry), rel(mean, rmean), rel(rstd, rrstd),
                           rel(dx, rdx), rel(sdg, rdg), rel(sdb, rdb)};
    const char* names[] = {"y", "mean", "rstd", "dx", "dgamma", "dbeta"};
    bool ok = true;
    printf("rows %lld d %d per %d grid %d × %d warps:", c.rows, c.d, c.per, c.grid, c.warps);
    for (int i = 0; i < 6; i++) {
        // f32 sums of up to a few hundred terms; NaN (a partial never written) fails too.
        const bool good = errs[i] < 2e-5;
        ok = ok && good;
        printf(" %s %.1e%s", names[i], errs[i], good ? "" : " (FAIL)");
    }
    printf("\n");
    return ok;
}

int main() {
    std::mt19937 rng(7);
    const Case cases[] = {
        {37, 48, 4, 2, 4},     // rows looped by 8 warps, a row narrower than a warp's capacity
        {5, 384, 12, 1, 8},    // more warps than rows: idle warps write zero partial sums
        {300, 100, 4, 3, 8},   // d not a multiple of 32
        {64, 384, 16, 2, 8},   // a larger kernel than needed
        {20, 768, 24, 1, 4},   // the `paper` width
        {9, 1024, 32, 1, 2},   // the widest kernel, full
    };
    bool ok = true;
    for (const Case& c : cases) ok = run(c, rng) && ok;
    printf(ok ? "all cases agree\n" : "some cases disagree\n");
    return ok ? 0 : 1;
}
