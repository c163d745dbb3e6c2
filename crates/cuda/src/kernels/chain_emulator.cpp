// Runs `umgen_chain` (chain.cu) on the host and compares it with its tasks run one by one as their own
// kernels' grids: a layer of the decoding step (norm + q, k, v into the caches, the attention over the
// cache, the output product added to the residual stream, the MLP) on fewer blocks than either the
// products' column groups or the attention's blocks, so that every block takes several in turn. The
// results must be the same bits: a column's and a split's arithmetic does not depend on which block does it.
//   c++ -std=c++20 -O2 -pthread -DWT=u16 -o /tmp/chain-emu \
//       crates/cuda/src/kernels/chain_emulator.cpp && /tmp/chain-emu
// (`crates/cuda/tests/emulator.rs` runs it in the test suite.)
#include "warp_emulator.h"
#ifndef WT
#define WT float
#endif
#define UMGEN_CHAIN
#include "engine_common.cuh"
#include "gemv.cu"
#include "attend.cu"
#include "chain.cu"

static std::mt19937 g_rng(11);

static std::vector<WT> weights(size_t n, float scale) {
    std::vector<WT> w(n);
    for (auto& x : w) store(&x, std::normal_distribution<float>(0.f, scale)(g_rng));
    return w;
}

static std::vector<float> randoms(size_t n) {
    std::vector<float> v(n);
    for (auto& x : v) x = std::normal_distribution<float>(0.f, 1.f)(g_rng);
    return v;
}

// The buffers of one layer of a decoding step for `m` scenes.
struct Layer {
    static constexpr int m = 3, d = 64, heads = 4, dh = 16, hidden = 160, cap = 300, splits = 2;
    int pos = 290;
    std::vector<WT> wqkv = weights(size_t(3) * d * d, 0.2f), wo = weights(size_t(d) * d, 0.2f);
    std::vector<WT> w1 = weights(size_t(hidden) * d, 0.2f), w2 = weights(size_t(d) * hidden, 0.1f);
    std::vector<float> g1 = randoms(d), b1 = randoms(d), g2 = randoms(d), b2 = randoms(d);
    std::vector<float> bias1 = randoms(hidden), bias2 = randoms(d);
    std::vector<float> xs = randoms(size_t(m) * d), q = std::vector<float>(size_t(m) * d);
    std::vector<float> y = std::vector<float>(size_t(m) * d), hb = std::vector<float>(size_t(m) * hidden);
    std::vector<WT> kc = weights(size_t(m) * heads * cap * dh, 1.f), vc = weights(kc.size(), 1.f);
    std::vector<float> part = std::vector<float>(size_t(m) * heads * splits * (2 + dh));
    std::vector<unsigned> count = std::vector<unsigned>(size_t(m) * heads);

    Gemv product(const std::vector<WT>& w, int n, int k, const float* x, int ldx, float* out, int ldo) const {
        Gemv P{};
        P.w = w.data();
        P.x = x;
        P.out = out;
        P.m = m;
        P.n = n;
        P.k = k;
        P.ldx = ldx;
        P.ldo = ldo;
        return P;
    }

    std::vector<ChainTask> tasks() {
        std::vector<ChainTask> t(5);
        t[0].kind = CHAIN_GEMV;
        t[0].g = product(wqkv, 3 * d, d, xs.data(), d, q.data(), d);
        t[0].g.in_mode = 1;
        t[0].g.g = g1.data();
        t[0].g.b = b1.data();
        t[0].g.out_mode = 2;
        t[0].g.kc = kc.data();
        t[0].g.vc = vc.data();
        t[0].g.pos = &pos;
        t[0].g.heads = heads;
        t[0].g.dh = dh;
        t[0].g.cap = cap;
        t[1].kind = CHAIN_ATTEND;
        AttendRows& a = t[1].a;
        a = AttendRows{};
        a.q = q.data();
        a.k = kc.data();
        a.v = vc.data();
        a.y = y.data();
        a.pos = &pos;
        a.part = part.data();
        a.count = count.data();
        a.q_sb = a.q_sr = a.y_sb = a.y_sr = d;
        a.k_sb = (long long)heads * cap * dh;
        a.k_sh = (long long)cap * dh;
        a.k_sj = dh;
        a.rows = 1;
        a.heads = heads;
        a.dh = dh;
        a.splits = splits;
        a.batches = m;
        a.scale = 0.25f;
        t[2].kind = CHAIN_GEMV;
        t[2].g = product(wo, d, d, y.data(), d, xs.data(), d);
        t[2].g.out_mode = 1;
        t[3].kind = CHAIN_GEMV;
        t[3].g = product(w1, hidden, d, xs.data(), d, hb.data(), hidden);
        t[3].g.in_mode = 1;
        t[3].g.g = g2.data();
        t[3].g.b = b2.data();
        t[3].g.bias = bias1.data();
        t[3].g.gelu = 1;
        t[4].kind = CHAIN_GEMV;
        t[4].g = product(w2, d, hidden, hb.data(), hidden, xs.data(), d);
        t[4].g.bias = bias2.data();
        t[4].g.out_mode = 1;
        return t;
    }
};

template <class T>
static bool same(const char* what, const std::vector<T>& a, const std::vector<T>& b) {
    const bool ok = a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0;
    printf("chain: %-24s %s\n", what, ok ? "the same bits" : "DIFFERENT (FAIL)");
    return ok;
}

// The layer as a chain on `grid` blocks against its tasks as separate kernels (a product on two blocks as
// the engine emulator runs them, the attention on one block per (scene, head, split)).
static bool test_chain(long long grid) {
    Layer one, all;
    all = one;
    const std::vector<float> before = one.xs;
    for (const ChainTask& t : one.tasks()) {
        if (t.kind == CHAIN_GEMV) {
            run_grid([t] { gemv_run(t.g, block_x(), blocks(), true); }, 2, 8);
        } else {
            const long long blocks_ = (long long)t.a.batches * t.a.rows * t.a.heads * t.a.splits;
            run_grid([t] { attend_rows_block(t.a, block_x(), true); }, blocks_, 8);
        }
    }
    const std::vector<ChainTask> tasks = all.tasks();
    Chain P{};
    P.tasks = tasks.data();
    P.count = (int)tasks.size();
    P.task_bytes = (int)sizeof(ChainTask);
    chain_emulated(P, grid);
    printf("chain on %lld blocks\n", grid);
    bool ok = same("residual stream", all.xs, one.xs);
    ok = same("keys", all.kc, one.kc) && ok;
    ok = same("values", all.vc, one.vc) && ok;
    ok = same("attention", all.y, one.y) && ok;
    ok = same("counters (zero)", all.count, std::vector<unsigned>(all.count.size())) && ok;
    // And the layer did something: the stream moved.
    bool moved = false;
    for (size_t i = 0; i < before.size(); i++) moved = moved || before[i] != all.xs[i];
    printf("chain: %-24s %s\n", "the stream moved", moved ? "yes" : "no (FAIL)");
    return ok && moved;
}

int main() {
    bool ok = test_chain(5);
    ok = test_chain(1) && ok;
    printf(ok ? "all cases agree\n" : "some cases disagree\n");
    return ok ? 0 : 1;
}
