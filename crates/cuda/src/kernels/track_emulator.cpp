// Runs the generation engine's `umgen_track` kernel (rows.cu) on the host and compares it with a
// double-precision reference of `backbone::track::moved`: slots moved one frame ahead by constant
// acceleration, with and without the follow rule (braking for a slower slot ahead in the lane), over
// random SUMO-like windows, and hand-worked cases of the rule and of its stop points:
//   c++ -std=c++20 -O2 -pthread -o /tmp/track-emu crates/cuda/src/kernels/track_emulator.cpp && /tmp/track-emu
// (`crates/cuda/tests/emulator.rs` runs it in the test suite.)
#include "warp_emulator.h"
#define WT float
#include "engine_common.cuh"
#include "rows.cu"
#include <algorithm>
#include <random>

static const double PI = 3.14159265358979323846;
static const double LO[5] = {-64, -64, -20, -20, -PI}, HI[5] = {64, 64, 20, 20, PI};
static const float RULE[6] = {1.5f, (float)0.86602540378443865, 7.5f, 0.5f, 1.f, 9.f};

static bool report(const char* name, bool ok) {
    printf("%-28s %s\n", name, ok ? "agrees" : "(FAIL)");
    return ok;
}

static int bin(int q, double v) { return (int)std::floor((v - LO[q]) / ((HI[q] - LO[q]) / 1024)); }
static double centre(int q, int id) { return LO[q] + (id + 0.5) * (HI[q] - LO[q]) / 1024; }

// A vehicle slot at (x, y) driving at `speed` along `heading`.
static void car(std::vector<int>& tok, double x, double y, double speed, double heading) {
    tok.insert(tok.end(), {bin(0, x), bin(1, y), bin(2, speed * std::cos(heading)), bin(3, speed * std::sin(heading)),
                           bin(4, heading), 1024});
}

static Track track(const int* tok, const float* act, int* out, int frames, int w, int slots, int follow) {
    Track P{tok, act, out, frames, w, slots * 6, 0, slots, 6, 1024, 1027, 1,
            {0, 1, 2, 3, 4}, {1024, 1024, 1024, 1024, 1024}, {}, {}, {}, 0.5f, follow,
            {RULE[0], RULE[1], RULE[2], RULE[3], RULE[4], RULE[5]}};
    for (int q = 0; q < 5; q++) {
        P.lo[q] = (float)LO[q];
        P.hi[q] = (float)HI[q];
        P.width[q] = (float)((HI[q] - LO[q]) / 1024);
    }
    return P;
}

// The moved ids of every slot in double precision, and for each whether a result lies within 1e-3 of a
// bin's edge or a rule's threshold within 1e-4 (where f32 may round the other way: not compared).
static void reference(const std::vector<int>& tok, const std::vector<float>& act, int frames, int w, int slots,
                      bool follow, std::vector<int>& out, std::vector<char>& fragile) {
    const int k = 6, n = slots * k;
    out.assign(tok.begin(), tok.end());
    fragile.assign(size_t(frames) * slots, 0);
    for (int f = 0; f < frames; f++) {
        const int t = f % w;
        std::vector<std::array<double, 5>> v(slots);
        std::vector<std::array<double, 2>> dv(slots);
        std::vector<bool> occ(slots);
        for (int s = 0; s < slots; s++) {
            const int* ids = &tok[size_t(f) * n + s * k];
            for (int q = 0; q < 5; q++) v[s][q] = centre(q, ids[q]);
            occ[s] = ids[0] < 1024;
            dv[s] = {0, 0};
            if (t > 0) {
                const int* b = ids - n;
                const double turn = act[3 * (f - 1) + 2];
                const double px = centre(2, b[2]), py = centre(3, b[3]);
                const double ux = std::cos(turn) * px + std::sin(turn) * py;
                const double uy = std::cos(turn) * py - std::sin(turn) * px;
                dv[s] = {v[s][2] - ux, v[s][3] - uy};
                const double ahead = (v[s][2] + dv[s][0]) * v[s][2] + (v[s][3] + dv[s][1]) * v[s][3];
                if (!(b[0] < 1024 && ahead >= 0)) dv[s] = {0, 0};
            }
        }
        for (int s = 0; s < slots; s++) {
            if (!occ[s]) continue;
            bool& weak = (bool&)fragile[size_t(f) * slots + s];
            double dvx = dv[s][0], dvy = dv[s][1];
            if (follow) {
                const double c = std::cos(v[s][4]), sn = std::sin(v[s][4]);
                const double speed = v[s][2] * c + v[s][3] * sn;
                double hardest = 0;
                for (int j = 0; j < slots; j++) {
                    if (!occ[j] || j == s) continue;
                    const auto& u = v[j];
                    const double dx = u[0] - v[s][0], dy = u[1] - v[s][1];
                    const double along = dx * c + dy * sn, across = dy * c - dx * sn;
                    const double same = std::cos(u[4]) * c + std::sin(u[4]) * sn;
                    const double closing = speed - (u[2] * c + u[3] * sn);
                    const double room = std::max(along - RULE[2], (double)RULE[3]);
                    weak = weak || std::fabs(along) < 1e-4 || std::fabs(std::fabs(across) - RULE[0]) < 1e-4 ||
                           std::fabs(same - RULE[1]) < 1e-4 || std::fabs(closing) < 1e-4;
                    if (along > 0 && std::fabs(across) <= RULE[0] && same >= RULE[1] && closing > 0)
                        hardest = std::max(hardest, closing * closing / (2 * room));
                }
                weak = weak || std::fabs(hardest - RULE[4]) < 1e-4;
                if (hardest >= RULE[4]) {
                    const double target = std::max(-std::min(hardest, (double)RULE[5]) * 0.5, -speed);
                    const double delta = std::min(target - (dvx * c + dvy * sn), 0.0);
                    dvx += delta * c;
                    dvy += delta * sn;
                }
            }
            const double dx = act[3 * f], dy = act[3 * f + 1], th = act[3 * f + 2];
            const double px = v[s][0] + (v[s][2] + 0.5 * dvx) * 0.5 - dx;
            const double py = v[s][1] + (v[s][3] + 0.5 * dvy) * 0.5 - dy;
            const double wx = v[s][2] + dvx, wy = v[s][3] + dvy;
            double h = v[s][4] - th;
            h -= std::floor((h + PI) / (2 * PI)) * 2 * PI;
            const double nv[5] = {std::cos(th) * px + std::sin(th) * py, std::cos(th) * py - std::sin(th) * px,
                                  std::cos(th) * wx + std::sin(th) * wy, std::cos(th) * wy - std::sin(th) * wx, h};
            int* o = &out[size_t(f) * n + s * k];
            if (!(nv[0] >= LO[0] && nv[0] < HI[0] && nv[1] >= LO[1] && nv[1] < HI[1])) {
                for (int q = 0; q < k; q++) o[q] = 1027;
                continue;
            }
            for (int q = 0; q < 5; q++) {
                const double x = (nv[q] - LO[q]) / ((HI[q] - LO[q]) / 1024);
                weak = weak || std::fabs(x - std::round(x)) < 1e-3;
                o[q] = std::clamp((int)std::floor(x), 0, 1023);
            }
        }
    }
}

// Two scenes of four-frame windows, 24 slots on four lanes (two each way), a sixth empty, half standing.
static bool test_random() {
    const int scenes = 2, w = 4, frames = scenes * w, slots = 24;
    std::mt19937 rng(11);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    std::vector<int> tok;
    for (int i = 0; i < frames * slots; i++) {
        if (u(rng) < 0.17) {
            tok.insert(tok.end(), 6, 1027);
            continue;
        }
        const double lane = std::floor(u(rng) * 4);
        const double y = (lane - 1.5) * 3.2 + (u(rng) - 0.5) * 0.6;
        const double h = (lane < 2 ? 0.0 : PI - 1e-3) + (u(rng) - 0.5) * 0.2;
        const double sp = u(rng) < 0.5 ? u(rng) * 0.5 : 3 + u(rng) * 12;
        const double x = (u(rng) - 0.5) * 110;
        car(tok, x, y, sp, h);
    }
    std::vector<float> act;
    for (int f = 0; f < frames; f++) act.insert(act.end(), {2.f + 0.3f * f, 0.02f * f - 0.1f, 0.03f - 0.01f * f});
    bool ok = true;
    int braked = 0, compared = 0;
    std::vector<int> kept;
    for (int follow = 0; follow < 2; follow++) {
        std::vector<int> got(tok.size()), want;
        std::vector<char> fragile;
        Track P = track(tok.data(), act.data(), got.data(), frames, w, slots, follow);
        launch(umgen_track, P, 3, 1);
        reference(tok, act, frames, w, slots, follow, want, fragile);
        for (int e = 0; e < frames * slots; e++) {
            if (fragile[e]) continue;
            compared++;
            if (!std::equal(got.begin() + e * 6, got.begin() + e * 6 + 6, want.begin() + e * 6)) {
                printf("follow %d, frame %d, slot %d: kernel and reference differ\n", follow, e / slots, e % slots);
                ok = false;
            }
        }
        if (follow)
            for (int e = 0; e < frames * slots; e++) braked += got[e * 6 + 2] != kept[e * 6 + 2];
        else
            kept = got;
    }
    // Most slots compared, and the rule changed many.
    ok = ok && compared > 2 * frames * slots * 9 / 10 && braked >= 10;
    printf("%d of %d slots compared, %d braked\n", compared, 2 * frames * slots, braked);
    return report("random windows", ok);
}

// The tracked slots with the follow rule: of six slots (one empty), only the one closing on a standing
// slot 20 m ahead in its lane brakes, to the bins the rule gives in double precision (about 4 m/s²); the
// others move as without the rule.
static bool test_hand() {
    std::vector<int> tok;
    car(tok, 0.06, 0.06, 10, 0);
    car(tok, 20, 0.3, 0, 0);
    car(tok, -45, 0, 10, 0);
    car(tok, 0, 10, 10, 0);
    tok.insert(tok.end(), 6, 1027);
    car(tok, 10, -0.2, 10, PI - 0.01);
    const std::vector<float> act = {0.f, 0.f, 0.f};
    std::vector<int> on(36), off(36);
    for (int follow = 0; follow < 2; follow++)
        launch(umgen_track, track(tok.data(), act.data(), follow ? on.data() : off.data(), 1, 1, 6, follow), 1, 1);
    bool ok = std::equal(on.begin() + 6, on.end(), off.begin() + 6);
    const double u0 = centre(2, tok[2]), u1 = centre(2, tok[8]);
    const double need = (u0 - u1) * (u0 - u1) / (2 * (centre(0, tok[6]) - centre(0, tok[0]) - 7.5));
    const double v = u0 - 0.5 * need;
    ok = ok && on[2] == bin(2, v) && on[0] == bin(0, centre(0, tok[0]) + 0.5 * (u0 + v) / 2) && off[2] - on[2] >= 50;
    return report("follow, by hand", ok);
}

// Stop points (backbone::StopSpec): one car at 10 m/s and three head slots after it in the frame (1 m
// bins over ±64 m, 128 heading bins, state 128 + code: 129 red, 130 yellow, 131 green, pad 132). A red
// head 20 m ahead in its lane brakes it to the bins the rule gives in double precision (v²/(2(d − 3 m)));
// a green head at the same place releases it; a red head behind or in the next lane does nothing.
static bool test_stops() {
    const double W = 1.0, HW = 2 * PI / 128;
    auto head = [&](std::vector<int>& tok, double x, double y, double h, int state) {
        tok.insert(tok.end(), {(int)std::floor((x + 64) / W), (int)std::floor((y + 64) / W),
                               (int)std::floor((h + PI) / HW), state});
    };
    auto run = [&](std::vector<int> heads, bool stops) {
        std::vector<int> tok;
        car(tok, 0.06, 0.06, 10, 0);
        while (heads.size() < 12) heads.push_back(132);
        tok.insert(tok.end(), heads.begin(), heads.end());
        const std::vector<float> act = {0.f, 0.f, 0.f};
        std::vector<int> out(6);
        Track P = track(tok.data(), act.data(), out.data(), 1, 1, 1, 1);
        P.n = 18;
        if (stops) {
            P.stops = 3, P.s_offset = 6, P.s_k = 4, P.s_values = 128, P.s_state = 3;
            for (int q = 0; q < 3; q++) P.s_field[q] = q;
            for (int i = 0; i < 4; i++) P.s_stop[i] = P.s_go[i] = -1;
            P.s_stop[0] = 129, P.s_go[0] = 130, P.s_go[1] = 131;
            P.s_lo[0] = P.s_lo[1] = -64.f, P.s_lo[2] = (float)-PI;
            P.s_width[0] = P.s_width[1] = (float)W, P.s_width[2] = (float)HW;
            P.s_gap = 3.f;
        }
        launch(umgen_track, P, 1, 1);
        return out;
    };
    std::vector<int> red, green, behind, beside;
    head(red, 20, 0.3, 0, 129);
    green = red;
    head(green, 20.2, 0.4, 0, 131);
    head(behind, -15, 0.3, 0, 129);
    head(beside, 20, 3.5, 0, 129);
    const std::vector<int> free = run(red, false), braked = run(red, true);
    const double x0 = centre(0, bin(0, 0.06)), v = centre(2, bin(2, 10)), line = -64 + (std::floor(20 + 64) + 0.5) * W;
    const double need = v * v / (2 * (line - x0 - 3)), slower = v - 0.5 * need;
    bool ok = braked[2] == bin(2, slower) && braked[0] == bin(0, x0 + 0.5 * (v + slower) / 2) && free[2] - braked[2] >= 30;
    ok = ok && run(green, true) == free && run(behind, true) == free && run(beside, true) == free;
    return report("stop points, by hand", ok);
}

int main() {
    bool ok = test_random();
    ok = test_hand() && ok;
    ok = test_stops() && ok;
    printf(ok ? "all cases agree\n" : "some cases disagree\n");
    return ok ? 0 : 1;
}
