// Runs the layer-norm kernels (norm.cu) on the host, one std::thread per CUDA thread of a block with the
// warp shuffle emulated, and compares their results with a double-precision reference:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/norm-emu
//       crates/cuda/src/kernels/train/norm_emulator.cpp && /tmp/norm-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Exit status 0 when every case
// agrees within f32 tolerance.
#include "../warp_emulator.h"
#include "norm.cu"
// The bound entry points (which cubecl's stream launches) of the `small` and `paper` widths.
NORM_BOUND_KERNELS(12)
NORM_BOUND_KERNELS(24)

struct Case {
    long long rows;
    int d, per, grid, warps;
};

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
    // The bound entry points (where cubecl's stream launches them), against the pointer kernels' results:
    // the bf16 output is the f32 output rounded, to the bit, as the cast it replaces rounded it; the kept
    // copy is the input rounded; a bf16 input gives what the f32 kernels give on that input widened (the
    // cast back to f32 it replaces), forward and backward, to the bit.
    double bf16_mismatch = 0, kept_mismatch = 0, x16_mismatch = 0, res_error = 0;
    if (c.per == 12 || c.per == 24) {
        const bool wide = c.per == 24;
        std::vector<u16> yb(n, 0xffff), kept(n, 0xffff);
        std::vector<float> m2(c.rows), r2(c.rows);
        const NormSizes sizes{c.rows, c.d, eps};
        auto keep = wide ? umgen_norm_forward_bound_x32_y16_keep_24 : umgen_norm_forward_bound_x32_y16_keep_12;
        run_grid([&] { keep(x.data(), gamma.data(), beta.data(), yb.data(), m2.data(), r2.data(), kept.data(), sizes); },
                 c.grid, c.warps);
        for (long long i = 0; i < n; i++) bf16_mismatch += yb[i] != to_bf16(y[i]), kept_mismatch += kept[i] != to_bf16(x[i]);
        for (long long r = 0; r < c.rows; r++) bf16_mismatch += m2[r] != mean[r] || r2[r] != rstd[r];

        // The f32 kernels on the kept copy widened, and the bf16-input kernels on the kept copy itself.
        std::vector<float> xw(n), y32(n), m32(c.rows), r32(c.rows), dx32(n), dg32(warps * c.d), db32(warps * c.d);
        for (long long i = 0; i < n; i++) xw[i] = from_bf16(kept[i]);
        NormParams q = p;
        q.x = xw.data(), q.y = y32.data(), q.mean_out = m32.data(), q.rstd_out = r32.data(), q.mean = m32.data(),
        q.rstd = r32.data(), q.dx = dx32.data(), q.dgamma = dg32.data(), q.dbeta = db32.data();
        launch(fwd, q, c.grid, c.warps);
        launch(bwd, q, c.grid, c.warps);
        std::vector<float> y16(n), m16(c.rows), r16(c.rows), dx16(n), dg16(warps * c.d), db16(warps * c.d);
        auto fwd16 = wide ? umgen_norm_forward_bound_x16_y32_24 : umgen_norm_forward_bound_x16_y32_12;
        auto bwd16 = wide ? umgen_norm_backward_bound_x16_24 : umgen_norm_backward_bound_x16_12;
        run_grid([&] { fwd16(kept.data(), gamma.data(), beta.data(), y16.data(), m16.data(), r16.data(), sizes); },
                 c.grid, c.warps);
        run_grid([&] {
            bwd16(dy.data(), kept.data(), m16.data(), r16.data(), gamma.data(), dx16.data(), dg16.data(), db16.data(),
                  sizes);
        }, c.grid, c.warps);
        for (long long i = 0; i < n; i++) x16_mismatch += y16[i] != y32[i] || dx16[i] != dx32[i];
        // With the residual stream's gradient added as dx is written: dx plus it.
        std::vector<float> dres(n), dxr(n), dgr(warps * c.d), dbr(warps * c.d);
        std::vector<double> want(n);
        for (long long i = 0; i < n; i++) dres[i] = 0.5f - (float)((i * 7919) % 1000) / 1000.f;
        for (long long i = 0; i < n; i++) want[i] = dx16[i] + dres[i];
        auto bwd16r = wide ? umgen_norm_backward_bound_x16_res_24 : umgen_norm_backward_bound_x16_res_12;
        run_grid([&] {
            bwd16r(dy.data(), kept.data(), m16.data(), r16.data(), gamma.data(), dres.data(), dxr.data(), dgr.data(),
                   dbr.data(), sizes);
        }, c.grid, c.warps);
        res_error = relative_error(dxr, want);
        for (long long i = 0; i < warps * c.d; i++) res_error += dgr[i] != dg16[i] || dbr[i] != db16[i];
        for (long long r = 0; r < c.rows; r++) x16_mismatch += m16[r] != m32[r] || r16[r] != r32[r];
        for (long long i = 0; i < warps * c.d; i++) x16_mismatch += dg16[i] != dg32[i] || db16[i] != db32[i];
    }
    // The warps' partial column sums, added as the caller adds them.
    std::vector<float> sdg(c.d, 0), sdb(c.d, 0);
    for (long long w = 0; w < warps; w++)
        for (int i = 0; i < c.d; i++) sdg[i] += dg[w * c.d + i], sdb[i] += db[w * c.d + i];
    const double errs[] = {relative_error(y, ry), relative_error(mean, rmean), relative_error(rstd, rrstd),
                           relative_error(dx, rdx), relative_error(sdg, rdg), relative_error(sdb, rdb),
                           bf16_mismatch, kept_mismatch, x16_mismatch, res_error};
    const char* const names[] = {"y", "mean", "rstd", "dx", "dgamma", "dbeta", "bf16 y unlike y rounded",
                                 "kept copy unlike x rounded", "bf16-input passes unlike f32 ones on it",
                                 "dx with the residual's gradient unlike dx plus it"};
    printf("rows %lld d %d per %d grid %d × %d warps:", c.rows, c.d, c.per, c.grid, c.warps);
    // f32 sums of up to a few hundred terms.
    return report(errs, names, 2e-5);
}

int main() {
    const Case cases[] = {
        {37, 48, 4, 2, 4},     // rows looped by 8 warps, a row narrower than a warp's capacity
        {5, 384, 12, 1, 8},    // more warps than rows: idle warps write zero partial sums
        {300, 100, 4, 3, 8},   // d not a multiple of 32
        {64, 384, 16, 2, 8},   // a larger kernel than needed
        {20, 768, 24, 1, 4},   // the `paper` width
        {9, 1024, 32, 1, 2},   // the widest kernel, full
    };
    return run_cases(cases, run, 7);
}
