// The warp-level primitives of the CUDA C kernels in this crate for the host (`warp_device.cuh` defines
// them on the GPU): every CUDA thread of a block is a std::thread, shuffles go through a warp barrier, and
// a grid runs one block at a time. Included by the `*_emulator.cpp` files before the kernel source.
#pragma once
#include <atomic>
#include <barrier>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <memory>
#include <thread>
#include <vector>

#define UMGEN_EMULATED
#define DEV static inline
#define KERNEL void
#define KERNEL_RESIDENT(n) void
#define NEG_INF (-INFINITY)
// Blocks run one at a time, so a function's static arrays serve as the block's shared memory.
#define SHARED static

typedef unsigned short u16;
typedef unsigned int u32;
DEV float bits_float(u32 u) {
    float f;
    std::memcpy(&f, &u, 4);
    return f;
}
DEV u32 float_bits(float f) {
    u32 u;
    std::memcpy(&u, &f, 4);
    return u;
}
#include "bf16.cuh"

static thread_local int g_tid;
static thread_local long long g_bx;
static long long g_blocks;
static int g_warps;
static std::barrier<>* g_warp[8];
static std::barrier<>* g_block;
static float g_lane[8][32];

DEV int lane_id() { return g_tid & 31; }
DEV int warp_id() { return g_tid >> 5; }
DEV int warps_per_block() { return g_warps; }
DEV long long block_x() { return g_bx; }
DEV long long blocks() { return g_blocks; }
DEV long long warp_index() { return g_bx * g_warps + warp_id(); }
DEV int thread_id() { return g_tid; }
DEV int threads() { return 32 * g_warps; }
// `__syncthreads()`.
DEV void sync_block() { g_block->arrive_and_wait(); }
// `atomicAdd` on an int.
DEV int atomic_add(int* p, int v) { return std::atomic_ref<int>(*p).fetch_add(v); }
DEV float rsqrtf(float x) { return 1.f / std::sqrt(x); }

// Every lane's `x`, read by the calling lane from `lane(i)` through the warp's barrier.
template <class F>
static float exchange(float x, F lane) {
    g_lane[warp_id()][lane_id()] = x;
    g_warp[warp_id()]->arrive_and_wait();
    const float y = g_lane[warp_id()][lane(lane_id())];
    g_warp[warp_id()]->arrive_and_wait();
    return y;
}

// The butterfly of `__shfl_xor_sync`.
DEV float warp_sum(float x) {
    for (int m = 16; m > 0; m >>= 1) x += exchange(x, [m](int l) { return l ^ m; });
    return x;
}

// The butterfly of `__shfl_xor_sync` taking the maximum.
DEV float warp_max(float x) {
    for (int m = 16; m > 0; m >>= 1) x = std::fmax(x, exchange(x, [m](int l) { return l ^ m; }));
    return x;
}

// `__syncwarp()`: every lane of the warp arrives before any goes on.
DEV void warp_sync() { g_warp[warp_id()]->arrive_and_wait(); }

// `__shfl_sync(x, lane)`.
DEV float from_lane(float x, int lane) {
    return exchange(x, [lane](int) { return lane; });
}

// `__shfl_xor_sync(x, mask)`.
DEV float from_xor(float x, int mask) {
    return exchange(x, [mask](int l) { return l ^ mask; });
}

// Runs `body` as each thread of `grid` blocks of `warps` warps (at most 8), one block at a time.
template <class F>
static void run_grid(F body, long long grid, int warps) {
    g_warps = warps;
    g_blocks = grid;
    std::vector<std::unique_ptr<std::barrier<>>> barriers;
    for (int w = 0; w < warps; w++) {
        barriers.push_back(std::make_unique<std::barrier<>>(32));
        g_warp[w] = barriers.back().get();
    }
    std::barrier<> block(32 * warps);
    g_block = &block;
    for (long long b = 0; b < grid; b++) {
        std::vector<std::thread> threads;
        for (int t = 0; t < 32 * warps; t++)
            threads.emplace_back([=] {
                g_tid = t;
                g_bx = b;
                body();
            });
        for (auto& t : threads) t.join();
    }
}

// Runs `kernel(p)` on `grid` blocks of `warps` warps (at most 8), one block at a time.
template <class P>
static void launch(void (*kernel)(P), P p, long long grid, int warps) {
    run_grid([=] { kernel(p); }, grid, warps);
}

// The largest |a − b| over the largest |b|.
template <class A, class B>
static double relative_error(const A& a, const B& b) {
    double err = 0, scale = 1e-12;
    for (size_t i = 0; i < b.size(); i++) {
        const double e = std::fabs(a[i] - b[i]);
        // std::max would pass over a NaN (a result never written).
        if (std::isnan(e)) return NAN;
        err = std::max(err, e);
        scale = std::max(scale, std::fabs((double)b[i]));
    }
    return err / scale;
}

// Prints each named error after the case's title (already printed), with " (FAIL)" beside any not under
// `tolerance` (NaN, a result never written, fails too), and ends the line; true when every one passes.
template <size_t N>
static bool report(const double (&errs)[N], const char* const (&names)[N], double tolerance) {
    bool ok = true;
    for (size_t i = 0; i < N; i++) {
        const bool good = errs[i] < tolerance;
        ok = ok && good;
        printf(" %s %.1e%s", names[i], errs[i], good ? "" : " (FAIL)");
    }
    printf("\n");
    return ok;
}

// Runs every case (all of them, also after a failure) with one generator seeded `seed`; the process's exit
// status: 0 when every case agrees.
template <class Case, size_t N>
static int run_cases(const Case (&cases)[N], bool (*run)(const Case&, std::mt19937&), unsigned seed) {
    std::mt19937 rng(seed);
    bool ok = true;
    for (const Case& c : cases) ok = run(c, rng) && ok;
    printf(ok ? "all cases agree\n" : "some cases disagree\n");
    return ok ? 0 : 1;
}
