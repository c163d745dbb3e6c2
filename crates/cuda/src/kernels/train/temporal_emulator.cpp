// Runs the attention-over-time kernels (temporal.cu) on the host, one std::thread per CUDA thread of a
// block with the warp shuffles emulated, and compares the output, log-sum-exp and the three gradients with
// a double-precision reference:
//
//   g++ -std=c++20 -O2 -pthread -Wno-unknown-pragmas -o /tmp/temporal-emu
//       crates/cuda/src/kernels/train/temporal_emulator.cpp && /tmp/temporal-emu
//
// (`crates/cuda/tests/training_kernels.rs` runs it in the test suite.) Queries come from a `[b, t, n,
// d]` buffer, keys and values from the two halves of a `[b, t, n, 2d]` one (as the layers' products give
// them), and the key and value gradients go to the two halves of one buffer. Exit status 0 when every case
// agrees within f32 tolerance.
#include "../warp_emulator.h"
#include "temporal.cu"

struct Case {
    int b, t, n, heads, dpl;
    bool causal;
    int warps;
};

static bool run(const Case& c, std::mt19937& rng) {
    const int dh = 32 * c.dpl, d = c.heads * dh;
    const long long rows = (long long)c.b * c.t * c.n;
    std::normal_distribution<float> normal(0.f, 1.f);
    std::vector<float> q(rows * d), kv(rows * 2 * d), dout(rows * d);
    for (auto& x : q) x = normal(rng);
    for (auto& x : kv) x = normal(rng);
    for (auto& x : dout) x = normal(rng);
    std::vector<float> out(rows * d, NAN), lse(rows * c.heads, NAN), dq(rows * d, NAN), dkv(rows * 2 * d, NAN);
    const Axes plain = {(long long)c.t * c.n * d, (long long)c.n * d, d};
    const Axes halves = {(long long)c.t * c.n * 2 * d, (long long)c.n * 2 * d, 2 * d};
    TemporalParams p{q.data(), kv.data(), kv.data() + d, dout.data(), out.data(), lse.data(), dq.data(),
                     dkv.data(), dkv.data() + d, plain, halves, halves, plain, halves, halves,
                     c.b, c.t, c.n, c.heads, c.causal, 1.f / std::sqrt((float)dh)};
    void (*fwd)(TemporalParams) = c.dpl == 1 ? umgen_temporal_forward_1
                                  : c.dpl == 2 ? umgen_temporal_forward_2
                                               : umgen_temporal_forward_4;
    void (*bwd)(TemporalParams) = c.dpl == 1 ? umgen_temporal_backward_1
                                  : c.dpl == 2 ? umgen_temporal_backward_2
                                               : umgen_temporal_backward_4;
    const long long tasks = (long long)c.b * c.n * c.heads, grid = (tasks + c.warps - 1) / c.warps;
    launch(fwd, p, grid, c.warps);
    launch(bwd, p, grid, c.warps);

    // The reference, in double precision, one (sequence, position, head) at a time.
    std::vector<double> rout(rows * d), rlse(rows * c.heads), rdq(rows * d), rdk(rows * d), rdv(rows * d);
    std::vector<float> gdk(rows * d), gdv(rows * d);
    const double scale = 1 / std::sqrt((double)dh);
    for (int bi = 0; bi < c.b; bi++)
        for (int ni = 0; ni < c.n; ni++)
            for (int h = 0; h < c.heads; h++) {
                auto row = [&](int t) { return ((long long)(bi * c.t + t) * c.n + ni); };
                auto Q = [&](int t, int j) { return (double)q[row(t) * d + h * dh + j]; };
                auto K = [&](int t, int j) { return (double)kv[row(t) * 2 * d + h * dh + j]; };
                auto V = [&](int t, int j) { return (double)kv[row(t) * 2 * d + d + h * dh + j]; };
                auto G = [&](int t, int j) { return (double)dout[row(t) * d + h * dh + j]; };
                std::vector<std::vector<double>> P(c.t, std::vector<double>(c.t, 0)), dS = P;
                for (int t = 0; t < c.t; t++) {
                    const int keys = c.causal ? t + 1 : c.t;
                    double m = -1e300, l = 0;
                    std::vector<double> s(keys);
                    for (int u = 0; u < keys; u++) {
                        s[u] = 0;
                        for (int j = 0; j < dh; j++) s[u] += Q(t, j) * K(u, j);
                        s[u] *= scale;
                        m = std::max(m, s[u]);
                    }
                    for (int u = 0; u < keys; u++) l += std::exp(s[u] - m);
                    rlse[row(t) * c.heads + h] = m + std::log(l);
                    for (int u = 0; u < keys; u++) P[t][u] = std::exp(s[u] - m) / l;
                    double delta = 0;
                    for (int j = 0; j < dh; j++) {
                        double o = 0;
                        for (int u = 0; u < keys; u++) o += P[t][u] * V(u, j);
                        rout[row(t) * d + h * dh + j] = o;
                        delta += o * G(t, j);
                    }
                    for (int u = 0; u < keys; u++) {
                        double dp = 0;
                        for (int j = 0; j < dh; j++) dp += G(t, j) * V(u, j);
                        dS[t][u] = P[t][u] * (dp - delta) * scale;
                    }
                }
                for (int t = 0; t < c.t; t++)
                    for (int j = 0; j < dh; j++) {
                        double dqv = 0, dkv_ = 0, dvv = 0;
                        for (int u = 0; u < c.t; u++) {
                            dqv += dS[t][u] * K(u, j);
                            dkv_ += dS[u][t] * Q(u, j);
                            dvv += P[u][t] * G(u, j);
                        }
                        const long long at_ = row(t) * d + h * dh + j;
                        rdq[at_] = dqv, rdk[at_] = dkv_, rdv[at_] = dvv;
                    }
            }
    for (long long r = 0; r < rows; r++)
        for (int j = 0; j < d; j++) gdk[r * d + j] = dkv[r * 2 * d + j], gdv[r * d + j] = dkv[r * 2 * d + d + j];
    const double errs[] = {relative_error(out, rout), relative_error(lse, rlse), relative_error(dq, rdq),
                           relative_error(gdk, rdk), relative_error(gdv, rdv)};
    const char* const names[] = {"out", "lse", "dq", "dk", "dv"};
    printf("b %d t %d n %d heads %d dh %d %s, %d warps:", c.b, c.t, c.n, c.heads, dh,
           c.causal ? "causal" : "bidirectional", c.warps);
    // f32 sums of up to 128 terms.
    return report(errs, names, 2e-5);
}

int main() {
    const Case cases[] = {
        {2, 8, 5, 2, 2, true, 8},    // the `small` preset's T, head size 64
        {1, 20, 3, 3, 1, true, 8},   // the `paper` preset's T, head size 32, idle warps in the last block
        {3, 1, 4, 2, 4, true, 4},    // one frame, head size 128
        {1, 32, 2, 1, 2, false, 2},  // the longest sequence the kernels take, bidirectional
        {1, 5, 7, 6, 1, true, 8},    // more heads than warps a block
        {2, 7, 3, 2, 2, false, 4},   // bidirectional, the last block of queries (or keys) partly past T
        {1, 3, 5, 1, 4, false, 8},   // head size 128, one partial block
        {1, 19, 2, 2, 1, true, 8},   // head size 32, three rows in the last block of four
    };
    return run_cases(cases, run, 11);
}
