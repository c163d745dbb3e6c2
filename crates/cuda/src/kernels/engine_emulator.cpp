// Runs the generation engine's kernels on the host (every CUDA thread a std::thread, warp shuffles emulated)
// and compares them with double-precision references, for `WT` = float or bf16 bits (`-DWT=u16`):
//   c++ -std=c++20 -O2 -pthread -DWT=u16 -o /tmp/engine-emu \
//       crates/cuda/src/kernels/engine_emulator.cpp && /tmp/engine-emu
// (`crates/cuda/tests/emulator.rs` runs it in the test suite.)
#include "warp_emulator.h"
#ifndef WT
#define WT float
#endif
#include "engine_common.cuh"
#include "gemv.cu"
#include "attend.cu"
#include "rows.cu"
#include "draw.cu"
#include <algorithm>

static std::mt19937 g_rng(7);

static float normal() { return std::normal_distribution<float>(0.f, 1.f)(g_rng); }

// Random values, stored as WT (and their rounded values as f32, which references read).
struct Buf {
    std::vector<WT> w;
    std::vector<float> f;
    explicit Buf(size_t n, float scale = 1.f) : w(n), f(n) {
        for (size_t i = 0; i < n; i++) {
            WT x;
            store(&x, normal() * scale);
            w[i] = x;
            f[i] = value(&x);
        }
    }
};

static std::vector<float> randoms(size_t n) {
    std::vector<float> v(n);
    for (auto& x : v) x = normal();
    return v;
}

// The tolerance for results computed from `WT` operands that are themselves rounded to `WT`.
static double tol() { return sizeof(WT) == 2 ? 1e-2 : 1e-5; }

static bool check(const char* name, double err, double limit) {
    const bool ok = err < limit;
    printf("%-28s %.2e%s\n", name, err, ok ? "" : " (FAIL)");
    return ok;
}

static double ref_gelu(double x) { return 0.5 * x * (1.0 + std::erf(x / std::sqrt(2.0))); }

// Every input and output mode of the matrix-vector kernel, against a double reference.
static bool test_gemv(int k, int n = 40) {
    const int m = 3, heads = 2, dh = 4, cap = 6, ntok = 5;
    bool ok = true;
    for (int mode = 0; mode < 4; mode++) {
        const int nn = mode == 2 ? 3 * heads * dh : n;
        Buf w(size_t(nn) * k);
        std::vector<float> x = randoms(size_t(m) * (k + 3)), g = randoms(k), b = randoms(k), bias = randoms(nn);
        std::vector<float> table = randoms(size_t(10) * k), pos_emb = randoms(size_t(ntok) * k);
        std::vector<int> row_base = {0, 4}, seg_of = {0, 0, 1, 1, 1}, tok(size_t(m) * ntok);
        for (auto& t : tok) t = g_rng() % 4;
        std::vector<float> bos = randoms(nn), h = randoms(size_t(m) * ntok * nn);
        const int p = 3;
        std::vector<float> out(size_t(m) * (nn + 1), 0.5f);
        std::vector<WT> kc(size_t(m) * heads * cap * dh), vc(kc.size());
        Gemv P{};
        P.w = w.w.data();
        P.x = x.data();
        P.g = g.data();
        P.b = b.data();
        P.table = table.data();
        P.row_base = row_base.data();
        P.seg_of = seg_of.data();
        P.tok = tok.data();
        P.pos_emb = pos_emb.data();
        P.pos = &p;
        P.bias = mode == 3 ? nullptr : bias.data();
        P.out = out.data();
        P.kc = kc.data();
        P.vc = vc.data();
        P.bos = bos.data();
        P.h = h.data();
        P.h_ss = (long long)ntok * nn;
        P.m = m;
        P.n = nn;
        P.k = k;
        P.ldx = k + 3;
        P.ldo = nn + 1;
        P.ntok = ntok;
        P.in_mode = mode == 3 ? 2 : (mode == 2 ? 1 : mode);
        P.gelu = mode == 0;
        P.out_mode = mode;
        P.heads = heads;
        P.dh = dh;
        P.cap = cap;
        const std::vector<float> before = out;
        // Two blocks: the grid walks the column groups (the launch sizes it to the GPU).
        launch(umgen_gemv, P, 2, 8);
        std::vector<double> want, got;
        for (int s = 0; s < m; s++) {
            std::vector<double> in(k);
            double mean = 0, var = 0;
            for (int i = 0; i < k; i++) mean += x[s * (k + 3) + i] / k;
            for (int i = 0; i < k; i++) var += std::pow(x[s * (k + 3) + i] - mean, 2) / k;
            for (int i = 0; i < k; i++) {
                const double xi = x[s * (k + 3) + i];
                if (P.in_mode == 0) in[i] = xi;
                if (P.in_mode == 1) in[i] = (xi - mean) / std::sqrt(var + 1e-5) * g[i] + b[i];
                if (P.in_mode == 2) {
                    const int row = row_base[seg_of[p - 1]] + tok[s * ntok + p - 1];
                    in[i] = table[row * k + i] + pos_emb[(p - 1) * k + i];
                }
            }
            for (int j = 0; j < nn; j++) {
                double r = 0;
                for (int i = 0; i < k; i++) r += double(w.f[size_t(j) * k + i]) * in[i];
                if (P.bias) r += bias[j];
                if (P.gelu) r = ref_gelu(r);
                const size_t o = size_t(s) * (nn + 1) + j;
                if (mode == 0) want.push_back(r), got.push_back(out[o]);
                if (mode == 1) want.push_back(before[o] + r), got.push_back(out[o]);
                if (mode == 3) want.push_back(r + h[s * ntok * nn + p * nn + j]), got.push_back(out[o]);
                if (mode == 2) {
                    const int d = heads * dh;
                    if (j < d) {
                        want.push_back(r), got.push_back(out[o]);
                    } else {
                        const int c = (j - d) % d, head = c / dh, e = c % dh;
                        const auto& cache = j < 2 * d ? kc : vc;
                        want.push_back(r);
                        got.push_back(value(&cache[((size_t(s) * heads + head) * cap + p) * dh + e]));
                    }
                }
            }
        }
        char name[64];
        snprintf(name, sizeof name, "gemv mode %d k %d", mode, k);
        ok = check(name, relative_error(got, want), tol()) && ok;
    }
    return ok;
}

// Softmax attention of query rows over key rows (double), one head.
static std::vector<double> ref_attend(const std::vector<double>& q, const std::vector<double>& k,
                                      const std::vector<double>& v, int lq, int lk, int dh, bool causal,
                                      int off, double scale) {
    std::vector<double> y(size_t(lq) * dh, 0.0);
    for (int i = 0; i < lq; i++) {
        std::vector<double> s(lk, -INFINITY);
        double mx = -INFINITY;
        for (int j = 0; j < lk; j++) {
            if (causal && j > i + off) continue;
            double d = 0;
            for (int e = 0; e < dh; e++) d += q[i * dh + e] * k[j * dh + e];
            s[j] = d * scale;
            mx = std::max(mx, s[j]);
        }
        double sum = 0;
        for (int j = 0; j < lk; j++) sum += s[j] == -INFINITY ? 0 : std::exp(s[j] - mx);
        for (int j = 0; j < lk; j++) {
            if (s[j] == -INFINITY) continue;
            const double p = std::exp(s[j] - mx) / sum;
            for (int e = 0; e < dh; e++) y[i * dh + e] += p * v[j * dh + e];
        }
    }
    return y;
}

// Few queries over a strided cache whose length is the device position + 1.
static bool test_attend_rows(int dh) {
    const int batches = 2, rows = 3, heads = 2, cap = 70, p = 66;
    Buf k(size_t(batches) * heads * cap * dh), v(k.f.size());
    std::vector<float> q = randoms(size_t(batches) * rows * heads * dh), y(q.size(), NAN);
    // Two warps a block: 64 keys a split, so the 67 keys take 2 splits (and the cache's 70, too).
    const int splits = (cap + 63) / 64;
    std::vector<float> part(size_t(batches) * rows * heads * splits * (2 + dh), NAN);
    std::vector<unsigned> count(size_t(batches) * rows * heads, 0);
    AttendRows P{};
    P.part = part.data();
    P.count = count.data();
    P.splits = splits;
    P.q = q.data();
    P.k = k.w.data();
    P.v = v.w.data();
    P.y = y.data();
    P.pos = &p;
    P.q_sb = (long long)rows * heads * dh;
    P.q_sr = (long long)heads * dh;
    P.k_sb = (long long)heads * cap * dh;
    P.k_sh = (long long)cap * dh;
    P.k_sj = dh;
    P.y_sb = P.q_sb;
    P.y_sr = P.q_sr;
    P.rows = rows;
    P.heads = heads;
    P.dh = dh;
    P.scale = 1.f / std::sqrt(float(dh));
    launch(umgen_attend_rows, P, (long long)batches * rows * heads * splits, 2);
    for (unsigned c : count)
        if (c != 0) return check("attend_rows: a counter left set", 1.0, 0.5);
    std::vector<double> want(y.size()), got(y.begin(), y.end());
    for (int b = 0; b < batches; b++)
        for (int h = 0; h < heads; h++) {
            std::vector<double> qq(size_t(rows) * dh), kk(size_t(p + 1) * dh), vv(kk.size());
            for (int r = 0; r < rows; r++)
                for (int e = 0; e < dh; e++) qq[r * dh + e] = q[P.q_sb * b + P.q_sr * r + h * dh + e];
            for (int j = 0; j <= p; j++)
                for (int e = 0; e < dh; e++) {
                    const size_t at = P.k_sb * b + P.k_sh * h + j * dh + e;
                    kk[j * dh + e] = k.f[at];
                    vv[j * dh + e] = v.f[at];
                }
            const auto r = ref_attend(qq, kk, vv, rows, p + 1, dh, false, 0, P.scale);
            for (int i = 0; i < rows; i++)
                for (int e = 0; e < dh; e++) want[P.q_sb * b + P.q_sr * i + h * dh + e] = r[i * dh + e];
        }
    char name[64];
    snprintf(name, sizeof name, "attend_rows dh %d", dh);
    return check(name, relative_error(got, want), 1e-5);
}

// Many queries: instances split into (i1, i2) with their own strides, causal and not; head sizes 8 and 64
// take the 16-byte loads, 12 the loads of one value.
static bool test_attend_tiles(bool causal, int dh) {
    const int n1 = 2, inner = 3, heads = 2, lq = 37, lk = 41, off = 4, ld = 3 * heads * dh;
    const long long s1 = (long long)inner * lk * ld, s2 = (long long)lk * ld;
    Buf qkv(size_t(n1) * s1);
    std::vector<WT> y(size_t(n1) * inner * lq * heads * dh);
    AttendTiles P{};
    P.q = qkv.w.data();
    P.k = qkv.w.data() + heads * dh;
    P.v = qkv.w.data() + 2 * heads * dh;
    P.y = y.data();
    P.q_s1 = P.k_s1 = s1;
    P.q_s2 = P.k_s2 = s2;
    P.q_sr = P.k_sr = ld;
    P.y_s1 = (long long)inner * lq * heads * dh;
    P.y_s2 = (long long)lq * heads * dh;
    P.y_sr = heads * dh;
    P.inner = inner;
    P.heads = heads;
    P.lq = lq;
    P.lk = lk;
    P.dh = dh;
    P.causal = causal;
    P.off = off;
    P.scale = 0.35f;
    launch(umgen_attend_tiles, P, (long long)n1 * inner * heads * 2, 4);
    std::vector<double> want(y.size()), got(y.size());
    for (size_t i = 0; i < y.size(); i++) got[i] = value(&y[i]);
    for (int a = 0; a < n1; a++)
        for (int c = 0; c < inner; c++)
            for (int h = 0; h < heads; h++) {
                std::vector<double> qq(size_t(lq) * dh), kk(size_t(lk) * dh), vv(kk.size());
                for (int j = 0; j < lk; j++)
                    for (int e = 0; e < dh; e++) {
                        const size_t at = a * s1 + c * s2 + j * ld + h * dh + e;
                        if (j < lq) qq[j * dh + e] = qkv.f[at];
                        kk[j * dh + e] = qkv.f[at + heads * dh];
                        vv[j * dh + e] = qkv.f[at + 2 * heads * dh];
                    }
                const auto r = ref_attend(qq, kk, vv, lq, lk, dh, causal, off, P.scale);
                for (int i = 0; i < lq; i++)
                    for (int e = 0; e < dh; e++)
                        want[a * P.y_s1 + c * P.y_s2 + i * P.y_sr + h * dh + e] = r[i * dh + e];
            }
    char name[64];
    snprintf(name, sizeof name, "attend_tiles%s dh %d", causal ? " causal" : "", dh);
    return check(name, relative_error(got, want), tol());
}

// A bias (and GELU) added in place to `WT` rows of `cols` columns, `cols + 8` apart.
static bool test_bias_t(int cols) {
    const int rows = 7, ld = cols + 8;
    bool ok = true;
    for (int act = 0; act < 2; act++) {
        Buf x(size_t(rows) * ld);
        std::vector<float> bias = randoms(cols);
        BiasT P{};
        P.x = x.w.data();
        P.bias = bias.data();
        P.rows = rows;
        P.cols = cols;
        P.ld = ld;
        P.gelu = act;
        launch(umgen_bias_t, P, 2, 2);
        std::vector<double> want, got;
        for (int r = 0; r < rows; r++)
            for (int c = 0; c < ld; c++) {
                const double v = x.f[size_t(r) * ld + c];
                const double b = c < cols ? v + bias[c] : v;
                want.push_back(c < cols && act ? ref_gelu(b) : b);
                got.push_back(value(&x.w[size_t(r) * ld + c]));
            }
        char name[64];
        snprintf(name, sizeof name, "bias_t %d columns%s", cols, act ? " gelu" : "");
        ok = check(name, relative_error(got, want), tol()) && ok;
    }
    return ok;
}

// The rows kernel: a layer norm of gathered rows (index list, period) into WT, and a scattered f32 add;
// rows of 40 held in registers, of 1,056 read once per pass.
static bool test_rows(int d) {
    const int inner = 3, rows = 12, period = 2;
    std::vector<float> src = randoms(size_t(period) * 7 * d), g = randoms(d), b = randoms(d), bias = randoms(d);
    std::vector<int> idx = {5, 0, 3};
    std::vector<WT> dst(size_t(rows) * d);
    Rows P{};
    P.src = src.data();
    P.idx = idx.data();
    P.dst = dst.data();
    P.g = g.data();
    P.b = b.data();
    P.bias = bias.data();
    P.s_s1 = 7 * d;
    P.s_s2 = d;
    P.d_s1 = (long long)inner * d;
    P.d_s2 = d;
    P.rows = rows;
    P.inner = inner;
    P.period = period;
    P.d = d;
    P.gelu = 1;
    launch(umgen_rows_t, P, 2, 2);
    std::vector<double> want, got;
    for (int r = 0; r < rows; r++) {
        const float* s = src.data() + ((r / inner) % period) * 7 * d + idx[r % inner] * d;
        double mean = 0, var = 0;
        for (int c = 0; c < d; c++) mean += s[c] / double(d);
        for (int c = 0; c < d; c++) var += std::pow(s[c] - mean, 2) / d;
        for (int c = 0; c < d; c++) {
            want.push_back(ref_gelu((s[c] - mean) / std::sqrt(var + 1e-5) * g[c] + b[c] + bias[c]));
            got.push_back(value(&dst[size_t(r) * d + c]));
        }
    }
    char name[64];
    snprintf(name, sizeof name, "rows_t norm gather d %d", d);
    bool ok = check(name, relative_error(got, want), tol());
    // Scatter-add rows of 5 into every other row of a [4][2][d] f32 buffer.
    std::vector<float> acc = randoms(size_t(4) * 2 * d), add = randoms(size_t(4) * d);
    const std::vector<float> before = acc;
    Rows Q{};
    Q.src = add.data();
    Q.dst = acc.data();
    Q.s_s1 = d;
    Q.d_s1 = 2 * d;
    Q.rows = 4;
    Q.inner = 1;
    Q.d = d;
    Q.add = 1;
    launch(umgen_rows_f, Q, 1, 2);
    std::vector<double> w2, g2;
    for (int r = 0; r < 4; r++)
        for (int j = 0; j < 2; j++)
            for (int c = 0; c < d; c++) {
                const size_t at = (size_t(r) * 2 + j) * d + c;
                w2.push_back(before[at] + (j == 0 ? add[size_t(r) * d + c] : 0.f));
                g2.push_back(acc[at]);
            }
    snprintf(name, sizeof name, "rows_f scatter add d %d", d);
    return check(name, relative_error(g2, w2), 1e-6) && ok;
}

// Embedding inputs, the action block's shift, and AMA's bilinear move against grid_sample's arithmetic.
static bool test_frame_parts() {
    const int e = 16, n = 6, rows_n = 2 * n;
    std::vector<float> table = randoms(size_t(9) * e), pos_emb = randoms(size_t(n) * e);
    std::vector<int> row_base = {0, 5}, seg_of = {0, 0, 0, 1, 1, 1}, tok(rows_n);
    for (auto& t : tok) t = g_rng() % 4;
    std::vector<WT> out(size_t(rows_n) * e);
    Embed E{table.data(), row_base.data(), seg_of.data(), tok.data(), pos_emb.data(), out.data(), rows_n, n, 0, e};
    launch(umgen_embed, E, 1, 2);
    std::vector<double> want, got;
    for (int r = 0; r < rows_n; r++)
        for (int c = 0; c < e; c++) {
            const int p = r % n;
            want.push_back(table[(row_base[seg_of[p]] + tok[r]) * e + c] + pos_emb[p * e + c]);
            got.push_back(value(&out[size_t(r) * e + c]));
        }
    bool ok = check("embed", relative_error(got, want), tol());
    // Shift: m 2, w 3, n 4, d 5, the block at 1..3.
    const int m = 2, w = 3, nn = 4, d = 5, start = 1, len = 2;
    std::vector<float> x = randoms(size_t(m) * w * nn * d), fresh = randoms(size_t(m) * len * d);
    const std::vector<float> x0 = x;
    Shift S{x.data(), fresh.data(), m, w, nn, d, start, len};
    launch(umgen_shift_block, S, 1, 1);
    std::vector<double> w3, g3;
    for (int s = 0; s < m; s++)
        for (int t = 0; t < w; t++)
            for (int p = 0; p < nn; p++)
                for (int c = 0; c < d; c++) {
                    const size_t at = ((size_t(s) * w + t) * nn + p) * d + c;
                    double want_v = x0[at];
                    if (p >= start && p < start + len)
                        want_v = t + 1 < w ? x0[at + size_t(nn) * d] : fresh[(size_t(s) * len + p - start) * d + c];
                    w3.push_back(want_v);
                    g3.push_back(x[at]);
                }
    ok = check("shift_block", relative_error(g3, w3), 1e-9) && ok;
    // AMA on a 3 × 4 grid in frames of 14 positions (the map at 2..14), two frames.
    const int R = 3, C = 4, frames = 2, pn = 14, off = 2, dd = 3;
    std::vector<float> xa = randoms(size_t(frames) * pn * dd), act = {2.5f, -1.0f, 0.3f, -4.f, 3.f, -1.1f};
    std::vector<float> src(size_t(frames) * R * C * dd), base(size_t(R) * C * 2);
    for (int f = 0; f < frames; f++)
        for (int c = 0; c < R * C * dd; c++) src[size_t(f) * R * C * dd + c] = xa[(size_t(f) * pn + off) * dd + c];
    for (int r = 0; r < R; r++)
        for (int c = 0; c < C; c++) {
            base[2 * (r * C + c)] = (2.f * c + 1.f) / C - 1.f;
            base[2 * (r * C + c) + 1] = (2.f * r + 1.f) / R - 1.f;
        }
    const std::vector<float> xa0 = xa;
    const float cell = 2.f;
    Align A{xa.data(), src.data(), act.data(), base.data(), frames, pn, dd, off, R, C,
            float(-2.0 / (C * cell)), float(-2.0 / (R * cell))};
    launch(umgen_align, A, 5, 1);
    std::vector<double> w4, g4;
    for (int f = 0; f < frames; f++)
        for (int cell_i = 0; cell_i < R * C; cell_i++) {
            const double th = act[3 * f + 2];
            const double gx = base[2 * cell_i], gy = base[2 * cell_i + 1];
            const double sx = std::cos(th) * gx + std::sin(th) * gy + act[3 * f + 1] * (-2.0 / (C * cell));
            const double sy = -std::sin(th) * gx + std::cos(th) * gy + act[3 * f] * (-2.0 / (R * cell));
            const double px = (sx + 1) * C / 2 - 0.5, py = (sy + 1) * R / 2 - 0.5;
            for (int c = 0; c < dd; c++) {
                double v = 0;
                for (int yy = 0; yy < R; yy++)
                    for (int xx = 0; xx < C; xx++) {
                        const double wx = std::max(0.0, 1 - std::fabs(px - xx)), wy = std::max(0.0, 1 - std::fabs(py - yy));
                        v += wx * wy * src[(size_t(f) * R * C + yy * C + xx) * dd + c];
                    }
                const size_t at = (size_t(f) * pn + off + cell_i) * dd + c;
                w4.push_back(xa0[at] + v);
                g4.push_back(xa[at]);
            }
        }
    return check("align", relative_error(g4, w4), 1e-5) && ok;
}

// A group run of `size` tokens (values 0..8, pad 9, last ids `last_lo..last_hi`) whose boxes read x, y
// and heading at 0, 1, 2 of the group and length and width from the y token again; `boxes` the rule.
static GroupRun box_run(int size, int last_lo, int last_hi, int boxes) {
    GroupRun run{};
    run.size = size;
    run.pad = 9;
    run.values = 9;
    run.last_lo = last_lo;
    run.last_hi = last_hi;
    run.boxes = boxes;
    run.max_boxes = 5;
    const int fields[5] = {0, 1, 2, 1, 1};
    for (int f = 0; f < 5; f++) {
        run.field[f] = fields[f];
        run.bins[f] = 9;
        run.lo[f] = f == 2 ? -0.9 : 0.0;
        run.hi[f] = f == 2 ? 0.9 : 9.0;
    }
    return run;
}

// The arguments of a draw over a test's buffers: greedy (top-k 1, temperature 1), one keep entry.
struct RuleDraw {
    const std::vector<float>* logits;
    const std::vector<Rule>* rules;
    const GroupRun* run;
    const unsigned char *keep_on, *newborn;
    int *tok, *pos, *nboxes;
    unsigned *done, *counts;
    double* boxes;
    const unsigned* state;
    int m, n, vocab, groups, box_cap;
    Draw args() const {
        Draw P{};
        P.logits = logits->data();
        P.keep_logits = logits->data();
        P.rules = rules->data();
        P.runs = run;
        P.keep_on = keep_on;
        P.newborn = newborn;
        P.tok = tok;
        P.pos = pos;
        P.done = done;
        P.counts = counts;
        P.boxes = boxes;
        P.nboxes = nboxes;
        P.state = state;
        P.temperature = 1.0;
        P.top_p = 1.0;
        P.m = m;
        P.n = n;
        P.vocab = vocab;
        P.top_k = 1;
        P.keeps = 1;
        P.groups = groups;
        P.box_cap = box_cap;
        return P;
    }
};

// The draw: greedy picks the best allowed id (ties to the smaller id) under the group rules, a known
// position is left alone, a group after a pad is pad, the new-agent rule drops an overlapping newborn, and
// the last block advances the position.
static bool test_draw() {
    const int m = 2, n = 8, vocab = 12;
    // Positions 2..5: one group of 4 (values 0..8, pad 9, last ids 10..11), with boxes at fields 0..3 of
    // the group; position 6 is limited to ids below 5.
    std::vector<Rule> rules(n);
    for (auto& r : rules) r = Rule{0, 1 << 30, -1, 0, 0, 0, 0, -1, 0, 0};
    rules[0].known = 1;
    for (int j = 0; j < 4; j++) {
        rules[2 + j].gstart = 2;
        rules[2 + j].gj = j;
    }
    rules[5].finish = 1;
    rules[6].limit = 5;
    const GroupRun run = box_run(4, 10, 12, 1);
    std::vector<int> tok(size_t(m) * n, -1);
    tok[0] = 7;
    tok[n] = 7;
    std::vector<float> logits(size_t(m) * vocab);
    std::vector<unsigned char> keep_on(1, 0), newborn = {1, 1};
    unsigned done = 0, counts[2] = {0, 0};
    std::vector<double> boxes(size_t(m) * 2 * BOX_WORDS, 0.0);
    std::vector<int> nboxes = {1, 1};
    // Scene 0's ego box at the origin, 4.5 × 2 m; scene 1's far away, so that its agent stays.
    const double ego0[5] = {0, 0, 0, 4.5, 2.0}, ego1[5] = {50, 50, 0, 1, 1};
    for (int f = 0; f < 5; f++) boxes[f] = ego0[f], boxes[2 * BOX_WORDS + f] = ego1[f];
    int pos = 0;
    const unsigned state[3] = {0, 0, 0};
    Draw P = RuleDraw{&logits, &rules, &run, keep_on.data(), newborn.data(), tok.data(), &pos, nboxes.data(),
                      &done, counts, boxes.data(), state, m, n, vocab, 1, 2}
                 .args();
    // Per position, each scene's logits: the best id is given first (ties at equal values go to the
    // smaller id), then what the rules should make of it.
    const int best[8][2] = {{3, 3}, {6, 11}, {9, 0}, {4, 1}, {2, 2}, {11, 11}, {8, 8}, {5, 5}};
    const int want[8][2] = {{7, 7}, {6, 11}, {9, 0}, {9, 1}, {9, 2}, {9, 11}, {3, 3}, {5, 5}};
    bool ok = true;
    for (int p = 0; p < n; p++) {
        for (int s = 0; s < m; s++) {
            for (int i = 0; i < vocab; i++) logits[size_t(s) * vocab + i] = float(i % 4) * 0.1f;
            logits[size_t(s) * vocab + best[p][s]] = 2.f;
            if (p == 6) logits[size_t(s) * vocab + 3] = 1.f;  // the best id below the limit of 5
            if (p == 7) logits[size_t(s) * vocab + 1] = 2.f;  // a tie with 5: 1 wins
        }
        launch(umgen_draw, P, m, 8);
        ok = ok && pos == p + 1 && done == 0;
    }
    // Position 7's tie goes to id 1; scene 0's group was pad from its first token.
    const int tie = 1;
    for (int s = 0; s < m; s++)
        for (int p = 0; p < n; p++) {
            const int expect = p == 7 ? tie : want[p][s];
            if (tok[size_t(s) * n + p] != expect) {
                printf("draw: scene %d position %d drew %d, want %d\n", s, p, tok[size_t(s) * n + p], expect);
                ok = false;
            }
        }
    // Scene 1's newborn group (x 0.5, y 1.5 m, 1.5 × 1.5 m) is far from its ego box and stays: tested 1,
    // dropped 0, two boxes.
    ok = ok && counts[0] == 1 && counts[1] == 0 && nboxes[1] == 2;
    // Run the group again in scene 1 with its ego box on top of the agent: it is dropped.
    for (int f = 0; f < 5; f++) boxes[2 * BOX_WORDS + f] = ego0[f];
    nboxes[1] = 1;
    pos = 2;
    for (int p = 2; p < 6; p++) {
        for (int s = 0; s < m; s++) {
            for (int i = 0; i < vocab; i++) logits[size_t(s) * vocab + i] = 0.f;
            logits[size_t(s) * vocab + best[p][1]] = 2.f;
        }
        launch(umgen_draw, P, m, 8);
    }
    for (int p = 2; p < 6; p++) ok = ok && tok[size_t(n) + p] == 9;
    ok = ok && counts[1] >= 1;
    // A vocabulary larger than a block holds in registers (one warp, 2,000 ids) is scanned from memory
    // (position 7 has no rule).
    const int big = 2000;
    std::vector<float> wide(size_t(m) * big);
    for (auto& v : wide) v = normal();
    wide[1234] = 9.f;
    wide[big + 77] = 9.f;
    P.logits = wide.data();
    P.vocab = big;
    pos = 7;
    launch(umgen_draw, P, m, 1);
    ok = ok && tok[7] == 1234 && tok[n + 7] == 77;
    return check("draw (rules, greedy)", ok ? 0.0 : 1.0, 0.5);
}

// The whole-frame new-agent rule (`boxes == 2`): a new agent in the first group and an old agent in the
// second, both drawn greedily onto the same spot. Checking only the boxes before it, the new agent stays;
// with the whole frame, the old agent's finish empties it (and the old agent stays).
static bool test_draw_whole_frame() {
    const int n = 6, vocab = 12;
    bool ok = true;
    for (int mode = 1; mode <= 2; mode++) {
        // Positions 0..2 and 3..5: two groups of 3 (x, y, heading; length and width read y again).
        std::vector<Rule> rules(n);
        for (int p = 0; p < n; p++) {
            const int g = p / 3;
            rules[p] = Rule{0, 1 << 30, 3 * g, p % 3, 0, g, p % 3 == 2, -1, 0, 0};
        }
        const GroupRun run = box_run(3, 0, 9, mode);
        std::vector<int> tok(n, -1);
        std::vector<float> logits(vocab);
        std::vector<unsigned char> keep_on(1, 0), newborn = {1, 0};
        unsigned done = 0, counts[2] = {0, 0};
        std::vector<double> boxes(3 * BOX_WORDS, 0.0);
        // The ego box far away.
        boxes[0] = boxes[1] = 50.0, boxes[3] = boxes[4] = 1.0;
        int nboxes = 1, pos = 0;
        const unsigned state[3] = {0, 0, 0};
        const Draw P = RuleDraw{&logits, &rules, &run, keep_on.data(), newborn.data(), tok.data(), &pos, &nboxes,
                                &done, counts, boxes.data(), state, 1, n, vocab, 2, 3}
                           .args();
        // Both agents at x 2.5, y 3.5 m (3.5 × 3.5 m), heading 0: they overlap.
        const int best[n] = {2, 3, 4, 2, 3, 4};
        for (int p = 0; p < n; p++) {
            for (int i = 0; i < vocab; i++) logits[i] = 0.f;
            logits[best[p]] = 2.f;
            launch(umgen_draw, P, 1, 8);
        }
        const bool emptied = tok[0] == 9 && tok[1] == 9 && tok[2] == 9;
        const bool old_kept = tok[3] == 2 && tok[4] == 3 && tok[5] == 4;
        if (mode == 1) ok = ok && !emptied && old_kept && counts[0] == 1 && counts[1] == 0 && nboxes == 3;
        if (mode == 2) ok = ok && emptied && old_kept && counts[0] == 1 && counts[1] == 1 && nboxes == 3 &&
                             boxes[BOX_WORDS + 5] == -3.0 && boxes[2 * BOX_WORDS + 5] == 0.0;
        if (!ok) printf("draw (whole frame): mode %d tokens %d %d %d %d %d %d counts %u %u\n", mode, tok[0],
                        tok[1], tok[2], tok[3], tok[4], tok[5], counts[0], counts[1]);
    }
    return check("draw (new agents against the whole frame)", ok ? 0.0 : 1.0, 0.5);
}

// A draw at position 1 of `m` scenes with no keeps and no boxes in use: its buffers, and its arguments over
// them (built in place: `P` points into the members).
struct PlainDraw {
    std::vector<int> tok, nboxes;
    std::vector<unsigned char> flags;
    std::vector<double> boxes;
    unsigned done = 0, counts[2] = {0, 0};
    unsigned state[3] = {5, 0, 11};
    int pos = 1;
    Draw P{};
    PlainDraw(const std::vector<float>& logits, const std::vector<Rule>& rules, const GroupRun* run, int m, int n,
              int vocab, int top_k, double temperature, double top_p, u32 key0, u32 key1)
        : tok(size_t(m) * n, 0), nboxes(m, 1), flags(m, 0), boxes(size_t(m) * BOX_WORDS, 0.0) {
        P = RuleDraw{&logits, &rules, run, flags.data(), flags.data(), tok.data(), &pos, nboxes.data(), &done, counts,
                     boxes.data(), state, m, n, vocab, 1, 1}
                .args();
        P.temperature = temperature;
        P.top_p = top_p;
        P.top_k = top_k;
        P.key0 = key0;
        P.key1 = key1;
    }
    PlainDraw(const PlainDraw&) = delete;
};

// A group's first position with a top-k: pad comes out at its untruncated share of the softmax (0.9 here,
// 0.998 if the top-5 list alone counted), the values only from the list.
static bool test_group_first_draws() {
    const int vocab = 300, m = 1000, n = 4, pad = 290;
    std::vector<Rule> rules(n, Rule{0, 1 << 30, -1, 0, 0, 0, 0, -1, 0, 0});
    rules[1] = Rule{0, 1 << 30, 1, 0, 0, 0, 0, -1, 0, 0};
    GroupRun run{};
    run.size = 11;
    run.pad = pad;
    run.values = 256;
    run.last_lo = 256;
    run.last_hi = 260;
    // 200 equal values and pad at 9 × their mass: pad's share is 0.9.
    std::vector<float> logits(size_t(m) * vocab, -INFINITY);
    for (int s = 0; s < m; s++) {
        for (int i = 0; i < 200; i++) logits[size_t(s) * vocab + i] = 0.f;
        logits[size_t(s) * vocab + pad] = float(std::log(9.0 * 200.0));
    }
    PlainDraw d(logits, rules, &run, m, n, vocab, 5, 1.0, 1.0, 7, 9);
    launch(umgen_draw, d.P, m, 1);
    const std::vector<int>& tok = d.tok;
    int pads = 0, outside = 0;
    for (int s = 0; s < m; s++) {
        const int id = tok[size_t(s) * n + 1];
        if (id == pad) pads++;
        else if (id < 0 || id > 3) outside++;  // the list: pad, then the ties' smallest ids 0..3
    }
    const double share = double(pads) / m;
    if (outside > 0) printf("group-first draws: %d values outside the top-k list\n", outside);
    // 1,000 draws: a standard deviation of 0.0095 around 0.9, and 0.098 from what the list alone gives.
    return check("draw (group first: pad share)", outside > 0 ? 1.0 : std::fabs(share - 0.9), 0.04);
}

// The nucleus of the rest: a top-20 list of id 0 at 0.9 and 19 tied values at 1/190 each. A plain top-p of
// 0.8 keeps id 0 alone; with top_p_rest id 0 keeps its 0.9 and top-p 0.8 of the rest's 0.1 (0.08) takes 16
// values (ids 1..16, the ties' smallest), which share 0.1.
static bool test_rest_nucleus_draws() {
    const int vocab = 300, m = 2000, n = 4;
    std::vector<Rule> rules(n, Rule{0, 1 << 30, -1, 0, 0, 0, 0, -1, 0, 0});
    GroupRun run{};
    std::vector<float> logits(size_t(m) * vocab, -INFINITY);
    for (int s = 0; s < m; s++) {
        for (int i = 1; i < 200; i++) logits[size_t(s) * vocab + i] = 0.f;
        logits[size_t(s) * vocab] = float(std::log(171.0));
    }
    double err = 0.0;
    for (const int rest : {0, 1}) {
        PlainDraw d(logits, rules, &run, m, n, vocab, 20, 1.0, 0.8, 7, 9);
        d.P.top_p_rest = rest;
        launch(umgen_draw, d.P, m, 1);
        int lead = 0, outside = 0;
        for (int s = 0; s < m; s++) {
            const int id = d.tok[size_t(s) * n + 1];
            if (id == 0) lead++;
            else if (id > 16) outside++;
        }
        if (outside > 0) printf("rest nucleus (%d): %d ids outside it\n", rest, outside);
        // 2,000 draws: a standard deviation of 0.0067 around 0.9.
        const double want = rest ? 0.9 : 1.0;
        err = std::max(err, outside > 0 ? 1.0 : std::fabs(double(lead) / m - want));
    }
    return check("draw (top-p of the rest)", err, 0.03);
}

// Sampled draws against a direct reference with the same Philox numbers: the top-k list (ties among the
// logits, a vocabulary held in registers and one scanned from memory) with temperature and top-p, and
// Gumbel-max over every id without top-k.
static bool test_sampled_draws() {
    bool ok = true;
    for (const int vocab : {300, 2000}) {
        for (const int top_k : {20, 0}) {
            const int m = 3, n = 4;
            const double temperature = 0.8, top_p = top_k ? 0.7 : 1.0;
            std::vector<Rule> rules(n, Rule{0, 1 << 30, -1, 0, 0, 0, 0, -1, 0, 0});
            GroupRun run{};
            std::vector<float> logits(size_t(m) * vocab);
            for (auto& v : logits) v = float(int(normal() * 4)) * 0.25f;  // many ties
            PlainDraw d(logits, rules, &run, m, n, vocab, top_k, temperature, top_p, 123, 456);
            launch(umgen_draw, d.P, m, vocab > 1000 ? 1 : 8);
            const std::vector<int>& tok = d.tok;
            for (int s = 0; s < m; s++) {
                const float* row = logits.data() + size_t(s) * vocab;
                int want = 0;
                if (top_k > 0) {
                    std::vector<int> order(vocab);
                    for (int i = 0; i < vocab; i++) order[i] = i;
                    std::sort(order.begin(), order.end(), [&](int a, int b) {
                        return row[a] > row[b] || (row[a] == row[b] && a < b);
                    });
                    order.resize(top_k);
                    std::vector<double> pr;
                    double total = 0;
                    for (int i : order) total += pr.emplace_back(std::exp((double(row[i]) - row[order[0]]) / temperature));
                    for (auto& x : pr) x /= total;
                    size_t keep = pr.size();
                    double mass = 0;
                    for (size_t j = 0; j < pr.size(); j++) {
                        mass += pr[j];
                        if (mass >= top_p) {
                            keep = j + 1;
                            break;
                        }
                    }
                    double kept = 0;
                    for (size_t j = 0; j < keep; j++) kept += pr[j];
                    double u = uniform(123, 456, 11 + s, 1, 5, 0xffffffu);
                    want = order[keep - 1];
                    for (size_t j = 0; j < keep; j++) {
                        if (u < pr[j] / kept) {
                            want = order[j];
                            break;
                        }
                        u -= pr[j] / kept;
                    }
                } else {
                    float best = -INFINITY;
                    for (int i = 0; i < vocab; i++) {
                        const double u = uniform(123, 456, 11 + s, 1, 5, (u32)i) + 0x1p-54;
                        const float key = (float)(double(row[i]) / temperature - std::log(-std::log(u)));
                        if (key > best) best = key, want = i;
                    }
                }
                if (tok[size_t(s) * n + 1] != want) {
                    printf("sampled draw (vocab %d, top-k %d), scene %d: %d, want %d\n", vocab, top_k, s,
                           tok[size_t(s) * n + 1], want);
                    ok = false;
                }
            }
        }
    }
    return check("draw (sampled)", ok ? 0.0 : 1.0, 0.5);
}

int main() {
    bool ok = true;
    ok = test_gemv(64) && ok;
    ok = test_gemv(20) && ok;
    // Few columns where each takes several warps: the emulator runs every thread of a block.
    ok = test_gemv(3072, 12) && ok;  // 4 warps a column (the MLP's second product)
    ok = test_gemv(8256, 6) && ok;   // 8 warps a column, slices past the prefetched 1,024
    ok = test_gemv(2600, 6) && ok;   // 4 warps a column, slices of 650: the scalar loop
    ok = test_attend_rows(8) && ok;
    ok = test_attend_rows(40) && ok;
    ok = test_attend_rows(64) && ok;  // the head sizes whose loads are all in flight at once
    ok = test_attend_rows(32) && ok;
    ok = test_attend_tiles(false, 8) && ok;
    ok = test_attend_tiles(true, 8) && ok;
    ok = test_attend_tiles(true, 12) && ok;
    ok = test_attend_tiles(true, 64) && ok;  // compiled for its head size
    ok = test_bias_t(24) && ok;  // 16-byte groups
    ok = test_bias_t(20) && ok;  // a block per row
    ok = test_rows(40) && ok;
    ok = test_rows(1056) && ok;
    ok = test_frame_parts() && ok;
    ok = test_draw() && ok;
    ok = test_draw_whole_frame() && ok;
    ok = test_sampled_draws() && ok;
    ok = test_group_first_draws() && ok;
    ok = test_rest_nucleus_draws() && ok;
    printf(ok ? "all cases agree\n" : "some cases disagree\n");
    return ok ? 0 : 1;
}
