// Attention for generation: `softmax(q kᵀ · scale) v` per head, head size at most ATT_DH, f32 arithmetic on
// operands in `WT` (keys and values) or f32 (few-query queries).
//
// `umgen_attend_rows`: few queries over many keys (the OAR's decoding step over its cache, the ego module's
// queries over their context). One block per (batch, query row, head); its warps take 32 keys at a time
// (a lane per key for the scores, a lane per head dimension for the values) with an online softmax, and
// the warps' partial results are merged at the end. The key count is `lk`, or the device position + 1.
//
// `umgen_attend_tiles`: many queries (the TAR's attention within a frame and over time). One block of 128
// threads per (instance, head, 32 queries): four threads per query, each holding every fourth head
// dimension, walk tiles of 32 keys and values staged in shared memory; `causal` hides key j from query i
// when j > i + off. An instance index splits into (i / inner, i % inner), each with its own stride, so that
// "every position of every frame" and "every frame of every scene" are both one launch.

#define ATT_DH 128
// 16-byte loads each of `umgen_attend_tiles`'s 128 threads makes for a tile of 32 rows of ATT_DH.
#define ATT_TILE_LOADS (32 * ATT_DH / 8 / 128)
// Splits an `umgen_attend_rows` query takes at most (keys: 32 per warp and split).
#define ROWS_MAX_SPLITS 32

struct AttendRows {
    const float* q;       // q(b, r, h) = q + b·q_sb + r·q_sr + h·dh
    const WT* k;          // k(b, h, j) = k + b·k_sb + h·k_sh + j·k_sj; v alike
    const WT* v;
    float* y;             // y(b, r, h) = y + b·y_sb + r·y_sr + h·dh
    const int* pos;       // keys: *pos + 1 when set, else lk
    float* part;          // [batches·rows·heads][splits][2 + dh]: each split's maximum, sum and output
    unsigned* count;      // [batches·rows·heads]: splits finished (zero between launches)
    long long q_sb, q_sr, k_sb, k_sh, k_sj, y_sb, y_sr;
    int rows, heads, dh, lk, splits;
    float scale;
};

// Merges `n` partial softmax results (maximum, sum, unnormalised output) into `y`, by warp 0.
DEV void merge_parts(const float* part, int stride, int n, int dh, float* y) {
    float mx = NEG_INF;
    for (int w = 0; w < n; w++) mx = fmaxf(mx, part[w * stride]);
    float sum = 0.f;
    for (int w = 0; w < n; w++) {
        const float m = part[w * stride];
        sum += m == NEG_INF ? 0.f : part[w * stride + 1] * expf(m - mx);
    }
    for (int d = lane_id(); d < dh; d += 32) {
        float o = 0.f;
        for (int w = 0; w < n; w++) {
            const float m = part[w * stride];
            if (m != NEG_INF) o += part[w * stride + 2 + d] * expf(m - mx);
        }
        y[d] = o / sum;
    }
}

// One warp's chunk of 32 keys from `c0` (some key of it below `lk`): its scores against `qs`, their running
// maximum and sum, and the values' weighted sum (a lane per head dimension, `acc[i]` for dimension
// lane + 32·i). Any head size, loads guarded.
DEV void rows_chunk_any(const AttendRows& P, const float* qs, const WT* kb, const WT* vb, int c0, int lk,
                        float& mrun, float& srun, float* acc) {
    const int j = c0 + lane_id();
    float sc = NEG_INF;
    if (j < lk) {
        const WT* kr = kb + (long long)j * P.k_sj;
        sc = 0.f;
        if ((P.dh & 7) == 0) {
            // Unrolled to the largest head, so that every load of the key row is in flight at once.
#pragma unroll
            for (int d = 0; d < ATT_DH; d += 8) {
                if (d < P.dh) {
                    float kv[8];
                    load8(kr + d, kv);
                    for (int e = 0; e < 8; e++) sc = fmaf(qs[d + e], kv[e], sc);
                }
            }
        } else {
            for (int d = 0; d < P.dh; d++) sc = fmaf(qs[d], value(kr + d), sc);
        }
    }
    // Lane 0's key is always there, so the chunk's maximum is a number.
    mrun = warp_max(sc);
    const float p = j < lk ? expf(sc - mrun) : 0.f;
    srun = warp_sum(p);
    const int count = lk - c0 < 32 ? lk - c0 : 32;
    // Unrolled over the chunk (loads guarded), so that the value rows' loads overlap.
#pragma unroll
    for (int t = 0; t < 32; t++) {
        const float pt = from_lane(p, t);
        if (t < count) {
            const WT* vr = vb + (long long)(c0 + t) * P.k_sj;
            for (int i = 0; i < ATT_DH / 32; i++) {
                const int d = lane_id() + 32 * i;
                if (d < P.dh) acc[i] = fmaf(pt, value(vr + d), acc[i]);
            }
        }
    }
}

// `rows_chunk_any` for head size DH (32 or 64, rows on 16 bytes) with the query `q` read here (scaled) rather
// than from shared memory: no load is behind a branch, so the query, a lane's key row and the chunk's value
// rows are all in flight at once (a key past `lk` reads the last key's row and is masked; a value row past
// it is weighted 0), one round trip to L2 rather than one per row, and no block barrier before it.
template <int DH>
DEV void rows_chunk(const AttendRows& P, const float* q, const WT* kb, const WT* vb, int c0, int lk,
                    float& mrun, float& srun, float* acc) {
    const int j = c0 + lane_id();
    const int jc = j < lk ? j : lk - 1;
    Packed8 kp[DH / 8];
    const WT* kr = kb + (long long)jc * P.k_sj;
#pragma unroll
    for (int c = 0; c < DH / 8; c++) load_packed8(kr + 8 * c, kp[c]);
    float vv[32][DH / 32];
#pragma unroll
    for (int t = 0; t < 32; t++) {
        const int jt = c0 + t < lk ? c0 + t : lk - 1;
        const WT* vr = vb + (long long)jt * P.k_sj;
#pragma unroll
        for (int i = 0; i < DH / 32; i++) vv[t][i] = value(vr + lane_id() + 32 * i);
    }
    float qv[DH];
#pragma unroll
    for (int d = 0; d < DH; d++) qv[d] = q[d] * P.scale;
    float sc = 0.f;
#pragma unroll
    for (int c = 0; c < DH / 8; c++) {
        float kv[8];
        unpack8(kp[c], kv);
        for (int e = 0; e < 8; e++) sc = fmaf(qv[8 * c + e], kv[e], sc);
    }
    if (j >= lk) sc = NEG_INF;
    // Lane 0's key is always there, so the chunk's maximum is a number.
    mrun = warp_max(sc);
    const float p = j < lk ? expf(sc - mrun) : 0.f;
    srun = warp_sum(p);
#pragma unroll
    for (int t = 0; t < 32; t++) {
        const float pt = from_lane(p, t);
#pragma unroll
        for (int i = 0; i < DH / 32; i++) acc[i] = fmaf(pt, vv[t][i], acc[i]);
    }
}

// Blocks (batch, row, head, split): split s takes keys [s·K, (s + 1)·K), K = 32 per warp; splits past the
// last key return at once. A block's warps merge in shared memory; with several splits, each writes its
// part and the last to finish merges them (a counter per query, reset by that block).
KERNEL umgen_attend_rows(const AttendRows P) {
    griddep_launch();
    SHARED float qs[ATT_DH];
    // The warps' parts, then (for the merging block) every split's: up to ROWS_MAX_SPLITS of them.
    SHARED float bpart[ROWS_MAX_SPLITS][2 + ATT_DH];
    SHARED int last;
    const long long blk = block_x();
    const int split = (int)(blk % P.splits);
    const long long bhr = blk / P.splits;
    const int h = (int)(bhr % P.heads);
    const long long br = bhr / P.heads;
    const long long r = br % P.rows, b = br / P.rows;
    const int wpb = warps_per_block(), per = 32 * wpb;
    const WT* kb = P.k + b * P.k_sb + (long long)h * P.k_sh;
    const WT* vb = P.v + b * P.k_sb + (long long)h * P.k_sh;
    // The keys: in a decoding step, the device position + 1, read before the wait (the position moves only
    // between steps, and the keys and values before it were written by earlier steps, so their lines are
    // asked of L2 while the kernel before finishes). Splits past the last key have nothing to do.
    const int lk = P.pos ? *P.pos + 1 : P.lk;
    const int active = (lk + per - 1) / per;
    if (split >= active) return;
    if (P.pos) {
        const int j = split * per + warp_id() * 32 + lane_id();
        if (j < lk - 1) {
            for (int e = 0; e < P.dh; e += 128 / (int)sizeof(WT)) {
                prefetch_l2(kb + (long long)j * P.k_sj + e);
                prefetch_l2(vb + (long long)j * P.k_sj + e);
            }
        }
    }
    griddep_wait();
    const float* q = P.q + b * P.q_sb + r * P.q_sr + (long long)h * P.dh;
    float mrun = NEG_INF, srun = 0.f, acc[ATT_DH / 32];
    for (int i = 0; i < ATT_DH / 32; i++) acc[i] = 0.f;
    const int c0 = split * per + warp_id() * 32;
    if ((P.dh == 64 || P.dh == 32) && ((P.k_sj | P.k_sh | P.k_sb) & 7) == 0) {
        if (c0 < lk) {
            if (P.dh == 64) rows_chunk<64>(P, q, kb, vb, c0, lk, mrun, srun, acc);
            else rows_chunk<32>(P, q, kb, vb, c0, lk, mrun, srun, acc);
        }
    } else {
        for (int d = thread_id(); d < P.dh; d += threads()) qs[d] = q[d] * P.scale;
        sync_block();
        if (c0 < lk) rows_chunk_any(P, qs, kb, vb, c0, lk, mrun, srun, acc);
    }
    if (lane_id() == 0) {
        bpart[warp_id()][0] = mrun;
        bpart[warp_id()][1] = srun;
    }
    for (int i = 0; i < ATT_DH / 32; i++) {
        const int d = lane_id() + 32 * i;
        if (d < P.dh) bpart[warp_id()][2 + d] = acc[i];
    }
    sync_block();
    float* y = P.y + b * P.y_sb + r * P.y_sr + (long long)h * P.dh;
    if (active == 1) {
        if (warp_id() == 0) merge_parts(&bpart[0][0], 2 + ATT_DH, wpb, P.dh, y);
        return;
    }
    // This split's merged part, then the counter: the last split to arrive merges every part.
    const int stride = 2 + P.dh;
    float* mine = P.part + (bhr * P.splits + split) * stride;
    if (warp_id() == 0) merge_parts(&bpart[0][0], 2 + ATT_DH, wpb, P.dh, mine + 2);
    if (thread_id() == 0) {
        float mx = NEG_INF, sum = 0.f;
        for (int w = 0; w < wpb; w++) mx = fmaxf(mx, bpart[w][0]);
        for (int w = 0; w < wpb; w++)
            sum += bpart[w][0] == NEG_INF ? 0.f : bpart[w][1] * expf(bpart[w][0] - mx);
        // The merged output above is normalised: store it with sum 1 at maximum 0, scaled by log(sum)+mx.
        mine[0] = mx + logf(sum);
        mine[1] = 1.f;
    }
    sync_block();
    if (thread_id() == 0) {
        fence();
        last = atomic_add_u(P.count + bhr, 1u) + 1 == (unsigned)active;
    }
    sync_block();
    if (last) {
        fence();
        // Every split's part into shared memory at once (the block's own parts are no longer needed),
        // read past L1, which may hold nothing of other blocks' writes but must not.
        float* staged = &bpart[0][0];
        const float* parts = P.part + bhr * P.splits * stride;
        for (int e = thread_id(); e < active * stride; e += threads()) staged[e] = load_global(parts + e);
        sync_block();
        if (warp_id() == 0) merge_parts(staged, stride, active, P.dh, y);
        if (thread_id() == 0) P.count[bhr] = 0;
    }
}

struct AttendTiles {
    const WT* q;          // q(i, h, r) = q + (i / inner)·q_s1 + (i % inner)·q_s2 + r·q_sr + h·dh
    const WT* k;          // k and v alike with k's strides
    const WT* v;
    WT* y;                // y alike with y's strides
    long long q_s1, q_s2, q_sr, k_s1, k_s2, k_sr, y_s1, y_s2, y_sr;
    int inner, heads, lq, lk, dh, causal, off;
    float scale;
};

// One block of `umgen_attend_tiles` for head sizes up to DHMAX (the loops over a thread's dimensions are
// unrolled to DHMAX / 4: a head of 64 compiled as such runs half the instructions of one compiled for
// ATT_DH and masked).
template <int DHMAX>
DEV void attend_tiles(const AttendTiles& P, float (*ks)[ATT_DH], float (*vs)[ATT_DH]) {
    const long long blk = block_x();
    const int qblocks = (P.lq + 31) / 32;
    const int qb = (int)(blk % qblocks);
    const long long ih = blk / qblocks;
    const int h = (int)(ih % P.heads);
    const long long inst = ih / P.heads;
    const long long i1 = inst / P.inner, i2 = inst % P.inner;
    const int t = thread_id(), part = t & 3, row = qb * 32 + (t >> 2);
    const int per = DHMAX == ATT_DH ? P.dh / 4 : DHMAX / 4;
    const WT* kb = P.k + i1 * P.k_s1 + i2 * P.k_s2 + (long long)h * P.dh;
    const WT* vb = P.v + i1 * P.k_s1 + i2 * P.k_s2 + (long long)h * P.dh;
    // Dimensions part, part + 4, ... of this thread's query, scaled.
    float qv[DHMAX / 4], acc[DHMAX / 4];
    const WT* qr = P.q + i1 * P.q_s1 + i2 * P.q_s2 + (long long)(row < P.lq ? row : 0) * P.q_sr + (long long)h * P.dh;
#pragma unroll
    for (int i = 0; i < DHMAX / 4; i++) {
        qv[i] = i < per ? value(qr + part + 4 * i) * P.scale : 0.f;
        acc[i] = 0.f;
    }
    float mrun = NEG_INF, srun = 0.f;
    int kend = P.lk;
    if (P.causal) {
        const int last = qb * 32 + 31 + P.off + 1;
        if (last < kend) kend = last;
    }
    // Whole 16-byte groups of 8 values where the head, the rows and the bases allow: every load of a tile
    // is then in flight at once (the TAR's attention over time reads 20 rows a frame apart, and one memory
    // trip per value made it a millisecond a layer).
    const bool vec = P.dh % 8 == 0 && P.k_sr % 8 == 0 && aligned16(kb) && aligned16(vb);
    for (int k0 = 0; k0 < kend; k0 += 32) {
        const int rows = kend - k0 < 32 ? kend - k0 : 32;
        if (vec) {
            const int groups = P.dh / 8, total = rows * groups;
            Packed8 kp[ATT_TILE_LOADS], vp[ATT_TILE_LOADS];
#pragma unroll
            for (int u = 0; u < ATT_TILE_LOADS; u++) {
                const int idx = t + u * 128;
                if (idx < total) {
                    const long long at = (long long)(k0 + idx / groups) * P.k_sr + 8 * (idx % groups);
                    load_packed8(kb + at, kp[u]);
                    load_packed8(vb + at, vp[u]);
                }
            }
#pragma unroll
            for (int u = 0; u < ATT_TILE_LOADS; u++) {
                const int idx = t + u * 128;
                if (idx < total) {
                    const int kk = idx / groups, d = 8 * (idx % groups);
                    unpack8(kp[u], &ks[kk][d]);
                    unpack8(vp[u], &vs[kk][d]);
                }
            }
        } else {
            for (int idx = t; idx < rows * P.dh; idx += threads()) {
                const int kk = idx / P.dh, d = idx % P.dh;
                ks[kk][d] = value(kb + (long long)(k0 + kk) * P.k_sr + d);
                vs[kk][d] = value(vb + (long long)(k0 + kk) * P.k_sr + d);
            }
        }
        sync_block();
        // The keys this warp's rows see (the same for its 32 lanes, whose shuffles take them all): none for a
        // warp past the last query, those up to its last row's under `causal`.
        const int wfirst = qb * 32 + 8 * warp_id();
        int kn = wfirst < P.lq ? rows : 0;
        if (P.causal && wfirst + 8 + P.off - k0 < kn) kn = wfirst + 8 + P.off - k0 > 0 ? wfirst + 8 + P.off - k0 : 0;
        // One key at a time with its own rescaling: a loop the compiler need not unroll (unrolled over 32
        // keys and 128 dimensions it made NVRTC's slowest kernel), at two exponentials a key.
        for (int kk = 0; kk < kn; kk++) {
            float s = 0.f;
#pragma unroll
            for (int i = 0; i < DHMAX / 4; i++)
                if (i < per) s = fmaf(qv[i], ks[kk][part + 4 * i], s);
            s += from_xor(s, 1);
            s += from_xor(s, 2);
            const int j = k0 + kk;
            if (P.causal && j > row + P.off) continue;
            const float mnew = fmaxf(mrun, s);
            const float alpha = expf(mrun - mnew), p = expf(s - mnew);
            srun = fmaf(srun, alpha, p);
#pragma unroll
            for (int i = 0; i < DHMAX / 4; i++)
                if (i < per) acc[i] = fmaf(p, vs[kk][part + 4 * i], acc[i] * alpha);
            mrun = mnew;
        }
        sync_block();
    }
    if (row < P.lq) {
        WT* y = P.y + i1 * P.y_s1 + i2 * P.y_s2 + (long long)row * P.y_sr + (long long)h * P.dh;
#pragma unroll
        for (int i = 0; i < DHMAX / 4; i++)
            if (i < per) store(y + part + 4 * i, acc[i] / srun);
    }
}

KERNEL umgen_attend_tiles(const AttendTiles P) {
    griddep_launch();
    griddep_wait();
    SHARED float ks[32][ATT_DH];
    SHARED float vs[32][ATT_DH];
    if (P.dh == 64)
        attend_tiles<64>(P, ks, vs);
    else
        attend_tiles<ATT_DH>(P, ks, vs);
}
