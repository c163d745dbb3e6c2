// Row-wise work of the generation engine's window pass (and of the decoding step's set-up).
//
// `umgen_rows_f` / `umgen_rows_t`: one warp per row, `dst[r] (+)= act(norm(src[r']) + bias)` into f32 or `WT`
// rows. Rows map affinely on both sides: row r is (i1, i2) = (r / inner, r % inner); the source row is
// `src + (i1 % period)·s_s1 + idx[i2]·s_s2` (no modulo without a period, `i2` itself without `idx`), the
// destination `dst + i1·d_s1 + i2·d_s2`. One kernel thus gathers context rows, normalises a frame's
// rows, adds the time embedding to every position of every frame, or scatters projected rows into place.
// `umgen_bias_t`: `x = act(x + bias)` in place on `WT` rows (after a cuBLAS product).
// `umgen_embed`: token embeddings' inputs `table[row_base[seg_of[p]] + tok] + pos_emb[p]` into `WT` rows.
// `umgen_shift_block`: frame t's action block takes frame t + 1's (the newest takes the new frame's).
// `umgen_align`: AMA, the map features moved by each frame's next action, added to them.
// `umgen_track`: the tracked slots' tokens moved one frame ahead (`backbone.track`).

struct Rows {
    const float* src;
    const int* idx;
    void* dst;
    const float* g;          // layer norm (null: none)
    const float* b;
    const float* bias;       // [d] or null
    long long s_s1, s_s2, d_s1, d_s2;
    int rows, inner, period, d, add, gelu;
};

// Column c's result from its source value `v` and the row's statistics.
DEV float rows_value(const Rows& P, float v, float mean, float rstd, int c) {
    if (P.g) v = (v - mean) * rstd * P.g[c] + P.b[c];
    if (P.bias) v += P.bias[c];
    if (P.gelu) v = gelu(v);
    return v;
}

// Values of a row held in registers per lane (rows of up to 32·ROWS_HELD): the row is read in one memory trip
// rather than once per pass and per 32 values.
#define ROWS_HELD 32

// Row r's results for columns lane + 32·i in `v[i]`, with the sums in the order `rows_source` takes them.
DEV void rows_held(const Rows& P, long long r, float* v) {
    long long i1 = r / P.inner;
    const long long i2 = r % P.inner;
    if (P.period) i1 %= P.period;
    const float* s = P.src + i1 * P.s_s1 + (P.idx ? P.idx[i2] : i2) * P.s_s2;
    const int lane = lane_id();
#pragma unroll
    for (int i = 0; i < ROWS_HELD; i++) v[i] = lane + 32 * i < P.d ? s[lane + 32 * i] : 0.f;
    float mean = 0.f, rstd = 0.f;
    if (P.g) {
        float sum = 0.f;
#pragma unroll
        for (int i = 0; i < ROWS_HELD; i++)
            if (lane + 32 * i < P.d) sum += v[i];
        mean = warp_sum(sum) / P.d;
        float sq = 0.f;
#pragma unroll
        for (int i = 0; i < ROWS_HELD; i++)
            if (lane + 32 * i < P.d) {
                const float e = v[i] - mean;
                sq += e * e;
            }
        rstd = rsqrtf(warp_sum(sq) / P.d + 1e-5f);
    }
#pragma unroll
    for (int i = 0; i < ROWS_HELD; i++)
        if (lane + 32 * i < P.d) v[i] = rows_value(P, v[i], mean, rstd, lane + 32 * i);
}

// Row r's source row and its statistics (mean, 1/σ; zeros without a norm).
DEV const float* rows_source(const Rows& P, long long r, float* mean, float* rstd) {
    long long i1 = r / P.inner;
    const long long i2 = r % P.inner;
    if (P.period) i1 %= P.period;
    const float* s = P.src + i1 * P.s_s1 + (P.idx ? P.idx[i2] : i2) * P.s_s2;
    *mean = 0.f;
    *rstd = 0.f;
    if (P.g) {
        float sum = 0.f;
        for (int c = lane_id(); c < P.d; c += 32) sum += s[c];
        const float mu = warp_sum(sum) / P.d;
        float sq = 0.f;
        for (int c = lane_id(); c < P.d; c += 32) {
            const float e = s[c] - mu;
            sq += e * e;
        }
        *mean = mu;
        *rstd = rsqrtf(warp_sum(sq) / P.d + 1e-5f);
    }
    return s;
}

// Column c of row r's destination takes `v`: added to it (`add`) or stored, in f32 (`F32`) or `WT`.
template <bool F32>
DEV void rows_put(const Rows& P, long long r, int c, float v) {
    const long long at = (r / P.inner) * P.d_s1 + (r % P.inner) * P.d_s2 + c;
    if (F32) {
        float* d = (float*)P.dst + at;
        *d = P.add ? *d + v : v;
    } else {
        store((WT*)P.dst + at, v);
    }
}

// A warp per row (grid-strided).
template <bool F32>
DEV void rows_kernel(const Rows& P) {
    griddep_launch();
    griddep_wait();
    const long long stride = blocks() * warps_per_block();
    for (long long r = warp_index(); r < P.rows; r += stride) {
        if (P.d <= 32 * ROWS_HELD) {
            float v[ROWS_HELD];
            rows_held(P, r, v);
#pragma unroll
            for (int i = 0; i < ROWS_HELD; i++)
                if (lane_id() + 32 * i < P.d) rows_put<F32>(P, r, lane_id() + 32 * i, v[i]);
            continue;
        }
        float mean, rstd;
        const float* s = rows_source(P, r, &mean, &rstd);
        for (int c = lane_id(); c < P.d; c += 32) rows_put<F32>(P, r, c, rows_value(P, s[c], mean, rstd, c));
    }
}

KERNEL umgen_rows_f(const Rows P) { rows_kernel<true>(P); }

KERNEL umgen_rows_t(const Rows P) { rows_kernel<false>(P); }

struct BiasT {
    WT* x;
    const float* bias;
    long long rows;
    int cols, ld, gelu;
};

// Groups of 8 columns over every thread of the grid where the rows allow 16-byte accesses (a memory trip
// per 8 values rather than one per value), else a block per row (grid-strided), its threads over the
// columns.
KERNEL umgen_bias_t(const BiasT P) {
    griddep_launch();
    griddep_wait();
    if (P.cols % 8 == 0 && P.ld % 8 == 0 && aligned16(P.x) && aligned16(P.bias)) {
        const long long per = P.cols / 8, total = P.rows * per;
        const long long all = blocks() * threads();
        for (long long i = block_x() * threads() + thread_id(); i < total; i += all) {
            WT* at = P.x + (i / per) * P.ld + 8 * (i % per);
            const float* b = P.bias + 8 * (i % per);
            Packed8 raw;
            load_packed8(at, raw);
            float v[8], bv[8];
            unpack8(raw, v);
            load8(b, bv);
#pragma unroll
            for (int j = 0; j < 8; j++) {
                const float s = v[j] + bv[j];
                v[j] = P.gelu ? gelu(s) : s;
            }
            store8(at, v);
        }
        return;
    }
    for (long long r = block_x(); r < P.rows; r += blocks()) {
        WT* row = P.x + r * P.ld;
        for (int c = thread_id(); c < P.cols; c += threads()) {
            const float v = value(row + c) + P.bias[c];
            store(row + c, P.gelu ? gelu(v) : v);
        }
    }
}

struct Embed {
    const float* table;      // [rows of every segment][e]
    const int* row_base;     // first table row of each segment
    const int* seg_of;       // segment of each frame position
    const int* tok;          // [rows]
    const float* pos_emb;    // [N][e]
    WT* out;                 // [rows][e]
    long long rows;
    int period, p0, e;
};

KERNEL umgen_embed(const Embed P) {
    griddep_launch();
    griddep_wait();
    const long long stride = blocks() * warps_per_block();
    for (long long r = warp_index(); r < P.rows; r += stride) {
        const int p = P.p0 + (int)(r % P.period);
        const float* t = P.table + (long long)(P.row_base[P.seg_of[p]] + P.tok[r]) * P.e;
        const float* q = P.pos_emb + (long long)p * P.e;
        for (int c = lane_id(); c < P.e; c += 32) store(P.out + r * P.e + c, t[c] + q[c]);
    }
}

struct Shift {
    float* x;                // [m][w][n][d]
    const float* fresh;      // [m][len][d]: the new frame's block
    int m, w, n, d, start, len;
};

KERNEL umgen_shift_block(const Shift P) {
    griddep_launch();
    griddep_wait();
    const long long total = (long long)P.m * P.len * P.d, stride = blocks() * threads();
    for (long long e = block_x() * threads() + thread_id(); e < total; e += stride) {
        const int c = (int)(e % P.d);
        const long long si = e / P.d;
        const int i = (int)(si % P.len);
        const long long s = si / P.len;
        float* base = P.x + (s * P.w * P.n + P.start + i) * (long long)P.d + c;
        const long long frame = (long long)P.n * P.d;
        for (int t = 0; t + 1 < P.w; t++) base[t * frame] = base[(t + 1) * frame];
        base[(P.w - 1) * frame] = P.fresh[si * P.d + c];
    }
}

struct Align {
    float* x;                // [frames][n][d]: the map's cells at offset..offset + rows·cols
    const float* src;        // [frames][rows·cols][d]: a copy of those cells
    const float* act;        // [frames][3]: dx, dy, dθ of each frame's next action
    const float* base;       // [rows·cols][2]: the cells' normalised centres (x, y)
    int frames, n, d, offset, rows, cols;
    float tx_scale, ty_scale; // −2 / (cols · cell_m), −2 / (rows · cell_m)
};

// One block per (frame, cell): the point the cell samples, as burn's `align` computes it in f32, then
// `grid_sample_2d`'s bilinear weights (zeros outside, align_corners = false) in f64, as burn's CPU backend.
KERNEL umgen_align(const Align P) {
    griddep_launch();
    griddep_wait();
    const long long cells = (long long)P.rows * P.cols;
    for (long long bc = block_x(); bc < P.frames * cells; bc += blocks()) {
        const long long f = bc / cells;
        const int cell = (int)(bc % cells);
        const float dx = P.act[3 * f], dy = P.act[3 * f + 1], th = P.act[3 * f + 2];
        const float co = cosf(th), si = sinf(th);
        const float gx = P.base[2 * cell], gy = P.base[2 * cell + 1];
        const float tx = mul_rn(dy, P.tx_scale), ty = mul_rn(dx, P.ty_scale);
        const float sx = add_rn(add_rn(mul_rn(co, gx), mul_rn(si, gy)), tx);
        const float sy = add_rn(add_rn(mul_rn(-si, gx), mul_rn(co, gy)), ty);
        const double px = ((double)sx + 1.0) * (double)P.cols / 2.0 - 0.5;
        const double py = ((double)sy + 1.0) * (double)P.rows / 2.0 - 0.5;
        const double fx = floor(px), fy = floor(py);
        const long long x0 = (long long)fx, y0 = (long long)fy;
        const double ax = px - fx, ay = py - fy;
        const double wt[4] = {(1.0 - ax) * (1.0 - ay), (1.0 - ax) * ay, ax * (1.0 - ay), ax * ay};
        const long long xs[4] = {x0, x0, x0 + 1, x0 + 1}, ys[4] = {y0, y0 + 1, y0, y0 + 1};
        const float* src = P.src + f * cells * P.d;
        float* out = P.x + (f * P.n + P.offset + cell) * (long long)P.d;
        for (int c = thread_id(); c < P.d; c += threads()) {
            double v = 0.0;
            for (int q = 0; q < 4; q++) {
                const double s = xs[q] >= 0 && xs[q] < P.cols && ys[q] >= 0 && ys[q] < P.rows
                                     ? (double)src[(ys[q] * P.cols + xs[q]) * P.d + c]
                                     : 0.0;
                v += s * wt[q];
            }
            out[c] += (float)v;
        }
    }
}

struct Track {
    const int* tok;          // [frames][n]: the window's tokens
    const float* act;        // [frames][3]: each frame's next action
    int* out;                // [frames][slots·k]
    int frames, w, n, offset, slots, k, values, pad, accel;
    int field[5];            // position in the slot of x, y, vx, vy, heading
    int bins[5];
    float lo[5], hi[5], width[5];
    float step;
    int follow;              // brake for a slower slot ahead (backbone::FollowSpec)
    float rule[6];           // half width, cos heading, min gap, min room, onset, max deceleration
    int stops;               // stop slots braked for as standing leaders (backbone::StopSpec), 0: none
    int s_offset, s_k, s_values, s_state;
    int s_field[3];          // position in the slot of x, y, heading
    int s_stop[4], s_go[4];  // state ids that stop and that release a place (-1: unused)
    float s_lo[3], s_width[3];
    float s_gap;             // metres between a stopped follower's centre and the point
};

DEV bool track_has(const int* ids, int id) {
    for (int i = 0; i < 4; i++)
        if (ids[i] >= 0 && ids[i] == id) return true;
    return false;
}

// Whether stop slot j of frame f asks to stop: a value x, a stop state, and no slot at the same x and y
// ids in a go state.
DEV bool track_stop(const Track& P, long long f, int j) {
    const int* frame = P.tok + f * P.n + P.s_offset;
    const int* o = frame + j * P.s_k;
    if (o[P.s_field[0]] >= P.s_values || !track_has(P.s_stop, o[P.s_state])) return false;
    for (int g = 0; g < P.stops; g++) {
        const int* p = frame + g * P.s_k;
        if (p[P.s_field[0]] == o[P.s_field[0]] && p[P.s_field[1]] == o[P.s_field[1]] && track_has(P.s_go, p[P.s_state]))
            return false;
    }
    return true;
}

// What a leader at (x, y) heading h, closing at `closing` m/s with `gap` m between centres, asks of the
// slot at v (x, y, ·, ·, ·; cos c, sin s of its heading): w²/(2r), or 0 where it does not lead.
DEV float track_need(const Track& P, const float* v, float c, float s, float x, float y, float h, float closing,
                     float gap) {
    const float dx = add_rn(x, -v[0]), dy = add_rn(y, -v[1]);
    const float along = add_rn(mul_rn(dx, c), mul_rn(dy, s));
    const float across = add_rn(mul_rn(dy, c), -mul_rn(dx, s));
    const float same_way = add_rn(mul_rn(cosf(h), c), mul_rn(sinf(h), s));
    const float room = fmaxf(add_rn(along, -gap), P.rule[3]);
    const float need = mul_rn(closing, closing) / mul_rn(room, 2.f);
    return along > 0.f && fabsf(across) <= P.rule[0] && same_way >= P.rule[1] && closing > 0.f ? need : 0.f;
}

// The centre of bin `id` of `width` from `lo`, in burn's f32 order: (id + 0.5)·width + lo.
DEV float bin_centre(int id, float width, float lo) { return add_rn(mul_rn((float)id + 0.5f, width), lo); }

// The centre of bin `id` of tracked field f.
DEV float track_centre(const Track& P, int f, int id) { return bin_centre(id, P.width[f], P.lo[f]); }

// Braking for the slowest-to-meet slot ahead in the lane (`backbone::track`'s `follow`, op for op in f32):
// the hardest w²/(2r) over the leaders, once at the onset, replaces a weaker change along the heading.
DEV void track_follow(const Track& P, long long f, const float* v, float* dvx, float* dvy) {
    const float c = cosf(v[4]), s = sinf(v[4]);
    const float speed = add_rn(mul_rn(v[2], c), mul_rn(v[3], s));
    float hardest = 0.f;
    for (int j = 0; j < P.slots; j++) {
        const int* o = P.tok + f * P.n + P.offset + j * P.k;
        if (o[P.field[0]] >= P.values) continue;
        float u[5];
        for (int q = 0; q < 5; q++) u[q] = track_centre(P, q, o[P.field[q]]);
        const float closing = add_rn(speed, -add_rn(mul_rn(u[2], c), mul_rn(u[3], s)));
        hardest = fmaxf(hardest, track_need(P, v, c, s, u[0], u[1], u[4], closing, P.rule[2]));
    }
    for (int j = 0; j < P.stops; j++) {
        if (!track_stop(P, f, j)) continue;
        const int* o = P.tok + f * P.n + P.s_offset + j * P.s_k;
        float u[3];
        for (int q = 0; q < 3; q++) u[q] = bin_centre(o[P.s_field[q]], P.s_width[q], P.s_lo[q]);
        hardest = fmaxf(hardest, track_need(P, v, c, s, u[0], u[1], u[2], speed, P.s_gap));
    }
    if (hardest < P.rule[4]) return;
    const float target = fmaxf(mul_rn(fminf(hardest, P.rule[5]), -P.step), -speed);
    const float change = add_rn(mul_rn(*dvx, c), mul_rn(*dvy, s));
    const float delta = fminf(add_rn(target, -change), 0.f);
    *dvx = add_rn(*dvx, mul_rn(delta, c));
    *dvy = add_rn(*dvy, mul_rn(delta, s));
}

// One thread per (frame, slot), the arithmetic of `backbone::track::moved` op for op in f32.
KERNEL umgen_track(const Track P) {
    griddep_launch();
    griddep_wait();
    const long long total = (long long)P.frames * P.slots, stride = blocks() * threads();
    for (long long e = block_x() * threads() + thread_id(); e < total; e += stride) {
        const long long f = e / P.slots;
        const int slot = (int)(e % P.slots), t = (int)(f % P.w);
        const int* ids = P.tok + f * P.n + P.offset + slot * P.k;
        int* out = P.out + f * (long long)P.slots * P.k + slot * P.k;
        for (int j = 0; j < P.k; j++) out[j] = ids[j];
        float v[5];
        for (int q = 0; q < 5; q++) v[q] = track_centre(P, q, ids[P.field[q]]);
        const float dx = P.act[3 * f], dy = P.act[3 * f + 1], dth = P.act[3 * f + 2];
        const float co = cosf(dth), si = sinf(dth);
        float dvx = 0.f, dvy = 0.f;
        if (P.accel && P.w > 1) {
            // The velocity's change since the window's previous frame (none for its first), seen in this
            // frame's axes; kept only for an object there before that would not turn around.
            const int* before = t > 0 ? ids - P.n : ids;
            const float turn = t > 0 ? P.act[3 * (f - 1) + 2] : 0.f;
            const float pvx = track_centre(P, 2, before[P.field[2]]);
            const float pvy = track_centre(P, 3, before[P.field[3]]);
            const float tc = cosf(turn), ts = sinf(turn);
            const float ux = add_rn(mul_rn(tc, pvx), mul_rn(ts, pvy));
            const float uy = add_rn(mul_rn(tc, pvy), -mul_rn(ts, pvx));
            dvx = add_rn(v[2], -ux);
            dvy = add_rn(v[3], -uy);
            const bool was_there = before[P.field[0]] < P.values;
            const float ahead = add_rn(mul_rn(add_rn(v[2], dvx), v[2]), mul_rn(add_rn(v[3], dvy), v[3]));
            if (!(was_there && ahead >= 0.f)) {
                dvx = 0.f;
                dvy = 0.f;
            }
        }
        if (ids[P.field[0]] >= P.values) continue;  // an empty slot (pad, or a category) stays as it is
        if (P.follow) track_follow(P, f, v, &dvx, &dvy);
        const float px = add_rn(add_rn(v[0], mul_rn(add_rn(v[2], mul_rn(dvx, 0.5f)), P.step)), -dx);
        const float py = add_rn(add_rn(v[1], mul_rn(add_rn(v[3], mul_rn(dvy, 0.5f)), P.step)), -dy);
        float nv[5];
        nv[0] = add_rn(mul_rn(co, px), mul_rn(si, py));
        nv[1] = add_rn(mul_rn(co, py), -mul_rn(si, px));
        const float wx = add_rn(v[2], dvx), wy = add_rn(v[3], dvy);
        nv[2] = add_rn(mul_rn(co, wx), mul_rn(si, wy));
        nv[3] = add_rn(mul_rn(co, wy), -mul_rn(si, wx));
        const float hd = add_rn(v[4], -dth);
        const float pi = 3.14159265358979323846f, tau = 6.28318530717958647692f;
        nv[4] = add_rn(hd, -mul_rn(floorf(add_rn(hd, pi) / tau), tau));
        const bool stays = nv[0] >= P.lo[0] && nv[0] < P.hi[0] && nv[1] >= P.lo[1] && nv[1] < P.hi[1];
        if (P.pad >= 0 && !stays) {
            for (int j = 0; j < P.k; j++) out[j] = P.pad;
            continue;
        }
        for (int q = 0; q < 5; q++) {
            float b = floorf(add_rn(nv[q], -P.lo[q]) / P.width[q]);
            b = b < 0.f ? 0.f : (b > (float)(P.bins[q] - 1) ? (float)(P.bins[q] - 1) : b);
            out[P.field[q]] = (int)b;
        }
    }
}
