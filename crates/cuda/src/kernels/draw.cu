// The decoding step's draw: one block per scene picks the token of the device position `p` from the OAR
// logits, under the frame's rules (umgen_generate's `rules.rs` on the host; the same decisions here):
//
// - a known position (boundary, placed or forced token, prefilled in `tok`) draws nothing;
// - token groups (agent slots): a group's first token is a value or pad; after a pad the rest is pad; the
//   middle tokens are values, the last one from `last_lo..last_hi`; positions may carry an id limit;
// - the draw: the top-k ids (most likely first, ties by id) with temperature and top-p, one uniform number
//   from Philox (`uniform`), the distribution walked as `Sampling::draw` walks it; without top-k, Gumbel-max
//   over every allowed id (top-p is then 1, which the engine checks);
// - at a group's first position with a top-k above 1, pad keeps its untruncated probability (its share of
//   the softmax over every allowed id) and the values among the top-k ids share the rest, so that a top-k
//   does not take the rare "an agent enters" (or "leaves") away: it is drawn first, from its own uniform;
// - a kept agent (its group was there in the previous frame) that draws pad redraws from the TAR head's
//   logits, pad allowed again (the TAR, which sees the history, may let it leave);
// - at a group's last position, the new-agent rule: a group that was empty in the previous frame and
//   overlaps a box decoded before it (the ego's first), or exceeds the box budget, becomes pad; with
//   `boxes == 2` (the whole frame), an agent that was there before also empties every new agent decoded
//   before it whose box it overlaps, so that a new agent overlaps no old one wherever their slots lie.
//
// The last block to finish advances the device position, so that the next step needs nothing from the host.

#define DRAW_KMAX 64
// Ids per thread a draw keeps in registers (vocabularies up to this many × the block's threads; larger
// ones are scanned from memory at each round).
#define DRAW_HELD 32
// The id of "nothing found" (exact as a float, which the warp shuffles carry).
#define NO_ID (1 << 30)
// Doubles a box takes in `Draw::boxes`: x, y, heading, length, width; the group's size if it is a new agent
// (its negative once emptied, 0 for the ego and old agents); the group's first position.
#define BOX_WORDS 7

struct Rule {
    int known;        // the token is prefilled: nothing to draw
    int limit;        // drawn ids must be below it (OAR draws only)
    int gstart;       // the group's first position, or −1
    int gj;           // the position's index in its group
    int grun;         // the group's run (GroupRun)
    int gindex;       // the group's index among all groups (newborn flags)
    int finish;       // the group's last position and a run with boxes: apply the new-agent rule
    int keep;         // index of the keep entry, or −1
    int keep_pad;     // the id a kept position redraws
    int keep_off;     // offset of its TAR logits in a scene's keep row
};

struct GroupRun {
    int size, pad, values, last_lo, last_hi;
    int boxes;        // 0: no new-agent rule; 1: against the boxes before; 2: against every old agent
    int max_boxes;
    int field[5];     // x, y, heading, length, width: index in the group
    int bins[5];
    double lo[5], hi[5];
};

struct Draw {
    const float* logits;        // [m][vocab]
    const float* keep_logits;   // [m][state[1]]
    const Rule* rules;          // [n]
    const GroupRun* runs;
    const unsigned char* keep_on;  // [m][keeps]
    const unsigned char* newborn;  // [m][groups]
    int* tok;                   // [m][n]
    int* pos;
    unsigned* done;             // blocks finished at this position
    unsigned* counts;           // new agents tested, dropped
    double* boxes;              // [m][box_cap][BOX_WORDS]
    int* nboxes;                // [m]
    const unsigned* state;      // the frame's counter, the scene stride of `keep_logits`, the first scene
    double temperature, top_p;
    int m, n, vocab, top_k, keeps, groups, box_cap;
    u32 key0, key1;
    int top_p_rest;   // top-p cuts only the ids after the most likely one (Sampling::top_p_rest)
};

// Whether `a` ranks before `b`: larger logit, ties to the smaller id.
DEV bool ranks_before(float va, int ia, float vb, int ib) { return va > vb || (va == vb && ia < ib); }

// Whether id `i` may be drawn at a position with rule `R` (group run `G`) in a scene whose group starts with
// `first`; `limited`: the position's id limit applies (OAR draws; a keep redraw ignores it).
DEV bool allowed(const Rule& R, const GroupRun& G, int first, int i, bool limited) {
    const bool below = !limited || i < R.limit;
    if (R.gstart < 0) return below;
    if (R.gj == 0) return below && (i < G.values || i == G.pad);
    if (first == G.pad) return i == G.pad;
    if (R.gj + 1 == G.size) return i >= G.last_lo && i < G.last_hi;
    return i < G.values && below;
}

// The warp's best (value, id) of its lanes' `v`, `i` (ties to the smaller id); every lane gets it.
DEV void warp_best(float* v, int* i) {
    for (int off = 16; off > 0; off >>= 1) {
        const float ov = from_xor(*v, off);
        const int oi = (int)from_xor((float)*i, off);
        if (ranks_before(ov, oi, *v, *i)) {
            *v = ov;
            *i = oi;
        }
    }
}

// The block's best (value, id) of the threads' `v`, `i` (ties to the smaller id); every thread gets it.
DEV void block_best(float* v, int* i, float* sv, int* si) {
    warp_best(v, i);
    if (lane_id() == 0) {
        sv[warp_id()] = *v;
        si[warp_id()] = *i;
    }
    sync_block();
    if (thread_id() == 0) {
        for (int w = 1; w < warps_per_block(); w++)
            if (ranks_before(sv[w], si[w], sv[0], si[0])) {
                sv[0] = sv[w];
                si[0] = si[w];
            }
    }
    sync_block();
    *v = sv[0];
    *i = si[0];
    sync_block();
}

// This thread's best allowed, finite id ranking after (bv, bi) (after nothing when bi < 0).
DEV void scan_best(const Draw& P, const float* row, const Rule& R, const GroupRun& G, int first, bool limited,
                   float bv, int bi, float* v, int* i) {
    *v = NEG_INF;
    *i = NO_ID;
    for (int id = thread_id(); id < P.vocab; id += threads()) {
        const float x = row[id];
        if (!finite(x) || !allowed(R, G, first, id, limited)) continue;
        if (bi >= 0 && !ranks_before(bv, bi, x, id)) continue;
        if (ranks_before(x, id, *v, *i)) {
            *v = x;
            *i = id;
        }
    }
}

// A logit and its id as one key whose order is the draw's: larger logit first, ties to the smaller id (the
// float's bits made order-preserving above, the id's complement below). 0 is no entry.
typedef unsigned long long u64;
DEV u64 draw_key(float x, int id) {
    const u32 u = float_bits(x);
    const u32 ord = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    return ((u64)ord << 32) | (u64)(~(u32)id);
}
DEV float key_value(u64 k) {
    const u32 o = (u32)(k >> 32);
    return bits_float((o & 0x80000000u) ? (o & 0x7fffffffu) : ~o);
}
DEV int key_id(u64 k) { return (int)~(u32)k; }

// The warp's largest key; every lane gets it.
DEV u64 warp_max_key(u64 k) {
    for (int off = 16; off > 0; off >>= 1) {
        const u32 hi = float_bits(from_xor(bits_float((u32)(k >> 32)), off));
        const u32 lo = float_bits(from_xor(bits_float((u32)k), off));
        const u64 o = ((u64)hi << 32) | lo;
        k = o > k ? o : k;
    }
    return k;
}

// The ids a position allows as two ranges, [r0, r1) ∪ [r2, r3): what `allowed` tests, once per draw.
DEV void allowed_ranges(const Rule& R, const GroupRun& G, int first, bool limited, int* r) {
    const int lim = limited ? R.limit : (1 << 30);
    r[2] = r[3] = 0;
    if (R.gstart < 0) {
        r[0] = 0;
        r[1] = lim;
    } else if (R.gj == 0) {
        r[0] = 0;
        r[1] = G.values < lim ? G.values : lim;
        if (G.pad < lim) {
            r[2] = G.pad;
            r[3] = G.pad + 1;
        }
    } else if (first == G.pad) {
        r[0] = G.pad;
        r[1] = G.pad + 1;
    } else if (R.gj + 1 == G.size) {
        r[0] = G.last_lo;
        r[1] = G.last_hi;
    } else {
        r[0] = 0;
        r[1] = G.values < lim ? G.values : lim;
    }
}

// The largest of a thread's held keys below `bound` (0: none).
DEV u64 held_below(const u64* held, u64 bound) {
    u64 m = 0;
#pragma unroll
    for (int t = 0; t < DRAW_HELD; t++) m = held[t] < bound && held[t] > m ? held[t] : m;
    return m;
}

// The top-k (most likely first, ties to the smaller id) of a row a block holds in registers, into `cv`,
// `ci` (shared); their count. Each warp finds the k largest keys of its ids by rounds of shuffles alone,
// then warp 0 the k largest of those lists: two block barriers in all, and no branch per id.
DEV int held_top_k(const Draw& P, const float* row, const Rule& R, const GroupRun& G, int first, bool limited,
                   float* cv, int* ci) {
    SHARED u64 lists[8][DRAW_KMAX];
    SHARED int total;
    int r[4];
    allowed_ranges(R, G, first, limited, r);
    u64 held[DRAW_HELD];
    // Every load in flight at once; a round then reads registers only.
#pragma unroll
    for (int t = 0; t < DRAW_HELD; t++) {
        const int id = thread_id() + t * threads();
        const float x = id < P.vocab ? row[id] : NEG_INF;
        const bool ok = ((id >= r[0] && id < r[1]) || (id >= r[2] && id < r[3])) && finite(x);
        held[t] = ok ? draw_key(x, id) : 0ull;
    }
    const int w = warp_id(), k = P.top_k;
    u64 mine = held_below(held, ~0ull);
    int n = 0;
    for (; n < k; n++) {
        const u64 best = warp_max_key(mine);
        if (best == 0) break;
        if (lane_id() == 0) lists[w][n] = best;
        if (mine == best) mine = held_below(held, best);
    }
    // A short list ends in zeros (the array holds an earlier draw's entries).
    if (lane_id() == 0)
        for (; n < k; n++) lists[w][n] = 0ull;
    sync_block();
    if (w == 0) {
        // Warp 0's lanes hold the lists' entries c = lane + 32·j, c = list·k + place (a list ends at 0).
        u64 mk[DRAW_KMAX / 4];
#pragma unroll
        for (int j = 0; j < DRAW_KMAX / 4; j++) {
            const int c = lane_id() + 32 * j, list = c / k;
            mk[j] = list < warps_per_block() ? lists[list][c % k] : 0ull;
        }
        u64 bound = ~0ull;
        int count = 0;
        for (; count < k; count++) {
            u64 m = 0;
#pragma unroll
            for (int j = 0; j < DRAW_KMAX / 4; j++) m = mk[j] < bound && mk[j] > m ? mk[j] : m;
            const u64 best = warp_max_key(m);
            if (best == 0) break;
            if (lane_id() == 0) {
                cv[count] = key_value(best);
                ci[count] = key_id(best);
            }
            bound = best;
        }
        if (lane_id() == 0) total = count;
    }
    sync_block();
    return total;
}

// The tempered softmax's probability of id `pad` over every allowed, finite id of `row`, whose largest logit
// is `top` (the head of the top-k list); 0 where `pad` is not among them. Every thread returns it. Partial
// sums in double, added in thread order.
DEV double pad_share(const Draw& P, const float* row, const Rule& R, const GroupRun& G, bool limited,
                     float top) {
    SHARED double part[1024];
    SHARED double pad_e;
    double acc = 0.0, mine = 0.0;
    for (int id = thread_id(); id < P.vocab; id += threads()) {
        const float x = row[id];
        if (!finite(x) || !allowed(R, G, -1, id, limited)) continue;
        const double e = exp(((double)x - (double)top) / P.temperature);
        acc += e;
        if (id == G.pad) mine = e;
    }
    part[thread_id()] = acc;
    // The thread that visited `pad` (ids go to threads round-robin) holds its term.
    if (thread_id() == G.pad % threads()) pad_e = mine;
    sync_block();
    double total = 0.0;
    for (int t = 0; t < threads(); t++) total += part[t];
    const double share = pad_e / total;
    sync_block();
    return share;
}

// A draw from `row` under the rule; every thread returns it. `purpose` keeps the draws' numbers apart.
DEV int draw_from(const Draw& P, const float* row, const Rule& R, const GroupRun& G, int first, bool limited,
                  int scene, int p, u32 purpose) {
    SHARED float sv[8];
    SHARED int si[8];
    SHARED float cv[DRAW_KMAX];
    SHARED int ci[DRAW_KMAX];
    SHARED int picked;
    const u32 sc = P.state[2] + scene, frame = P.state[0];
    if (P.top_k < 1 || P.top_k > DRAW_KMAX) {
        // Gumbel-max: the argmax of logit / T + Gumbel noise is a draw from the tempered softmax.
        float v = NEG_INF;
        int i = NO_ID;
        for (int id = thread_id(); id < P.vocab; id += threads()) {
            const float x = row[id];
            if (!finite(x) || !allowed(R, G, first, id, limited)) continue;
            const double u = uniform(P.key0, P.key1, sc, p, frame, purpose | (u32)id) + 0x1p-54;
            const float key = (float)((double)x / P.temperature - log(-log(u)));
            if (ranks_before(key, id, v, i)) {
                v = key;
                i = id;
            }
        }
        block_best(&v, &i, sv, si);
        return v == NEG_INF ? 0 : i;
    }
    int count = 0;
    if (P.vocab <= DRAW_HELD * threads()) {
        count = held_top_k(P, row, R, G, first, limited, cv, ci);
    } else {
        // A vocabulary too large to hold: block-wide rounds, the winner's thread rescanning memory.
        float v, bv = 0.f;
        int i, bi = -1;
        scan_best(P, row, R, G, first, limited, bv, bi, &v, &i);
        for (; count < P.top_k; count++) {
            float wv = v;
            int wi = i;
            block_best(&wv, &wi, sv, si);
            if (wv == NEG_INF) break;
            if (thread_id() == 0) {
                cv[count] = wv;
                ci[count] = wi;
            }
            bv = wv;
            bi = wi;
            if (i == wi) scan_best(P, row, R, G, first, limited, bv, bi, &v, &i);
        }
    }
    // A group's first position: pad at its untruncated share, drawn first; the values of the list share the
    // rest (the list without pad).
    const bool present = R.gstart >= 0 && R.gj == 0 && P.top_k > 1;
    // The list's head (every thread sees it: the selection ended on a block-wide exchange) is the row's
    // largest allowed logit.
    const double pad_p = present && count > 0 ? pad_share(P, row, R, G, limited, cv[0]) : 0.0;
    if (present && thread_id() == 0) {
        int kept = 0;
        for (int j = 0; j < count; j++) {
            if (ci[j] == G.pad) continue;
            cv[kept] = cv[j];
            ci[kept] = ci[j];
            kept++;
        }
        if (count > 0 && (kept == 0 || uniform(P.key0, P.key1, sc, p, frame, purpose | 0xfffffeu) < pad_p)) {
            ci[0] = G.pad;
            cv[0] = 0.f;
            kept = 1;
        }
        count = kept;
    }
    if (present) {
        sync_block();
    }
    if (thread_id() == 0) {
        int id = 0;
        if (count > 0) {
            double pr[DRAW_KMAX], total = 0.0;
            const double top = (double)cv[0];
            for (int j = 0; j < count; j++) {
                pr[j] = exp(((double)cv[j] - top) / P.temperature);
                total += pr[j];
            }
            for (int j = 0; j < count; j++) pr[j] /= total;
            int keep = count;
            if (P.top_p < 1.0) {
                // `umgen_generate::sampling::nucleus`: with top_p_rest the first id keeps its probability and
                // the cut is made among the others, against top_p of their mass, which they then share.
                const int skip = P.top_p_rest ? 1 : 0;
                const double share = skip ? 1.0 - pr[0] : 1.0;
                double mass = 0.0;
                for (int j = skip; j < count; j++) {
                    mass += pr[j];
                    if (mass >= P.top_p * share) {
                        keep = j + 1;
                        break;
                    }
                }
                double kept = 0.0;
                for (int j = skip; j < keep; j++) kept += pr[j];
                if (kept > 0.0)
                    for (int j = skip; j < keep; j++) pr[j] = pr[j] / kept * share;
            }
            double u = uniform(P.key0, P.key1, sc, p, frame, purpose | 0xffffffu);
            id = ci[keep - 1];
            for (int j = 0; j < keep; j++) {
                if (u < pr[j]) {
                    id = ci[j];
                    break;
                }
                u -= pr[j];
            }
        }
        picked = id;
    }
    sync_block();
    const int id = picked;
    sync_block();
    return id;
}

// The four corners of a box (x, y, heading, length, width), as `umgen_eval::collision::corners`.
DEV void box_corners(const double* b, double (*c)[2]) {
    const double co = cos(b[2]), si = sin(b[2]), hl = b[3] / 2.0, hw = b[4] / 2.0;
    const double u[4] = {hl, -hl, -hl, hl}, v[4] = {hw, hw, -hw, -hw};
    for (int q = 0; q < 4; q++) {
        c[q][0] = b[0] + u[q] * co - v[q] * si;
        c[q][1] = b[1] + u[q] * si + v[q] * co;
    }
}

// Whether two boxes overlap (separating axes; touching edges do not), as `umgen_eval::collision::overlap`.
DEV bool boxes_overlap(const double* a, const double* b) {
    double pa[4][2], pb[4][2];
    box_corners(a, pa);
    box_corners(b, pb);
    for (int poly = 0; poly < 2; poly++) {
        double (*pp)[2] = poly == 0 ? pa : pb;
        for (int e = 0; e < 2; e++) {
            const double ax = -(pp[e + 1][1] - pp[e][1]), ay = pp[e + 1][0] - pp[e][0];
            double a0 = 1e308, a1 = -1e308, b0 = 1e308, b1 = -1e308;
            for (int q = 0; q < 4; q++) {
                const double x = pa[q][0] * ax + pa[q][1] * ay, y = pb[q][0] * ax + pb[q][1] * ay;
                a0 = fmin(a0, x);
                a1 = fmax(a1, x);
                b0 = fmin(b0, y);
                b1 = fmax(b1, y);
            }
            if (a1 <= b0 || b1 <= a0) return false;
        }
    }
    return true;
}

// The new-agent rule at the last position `p` of a finished group of scene `b` (one thread).
DEV void new_agent(const Draw& P, const Rule& R, const GroupRun& G, int b, int p) {
    int* row = P.tok + (long long)b * P.n;
    if (row[R.gstart] == G.pad) return;
    const bool newborn = P.newborn[(long long)b * P.groups + R.gindex] != 0;
    if (newborn) atomic_add_u(P.counts, 1u);
    double box[5];
    for (int f = 0; f < 5; f++) {
        const int id = row[R.gstart + G.field[f]];
        if (id < 0 || id >= G.bins[f]) return;
        box[f] = G.lo[f] + ((double)id + 0.5) * (G.hi[f] - G.lo[f]) / (double)G.bins[f];
    }
    double* mine = P.boxes + (long long)b * P.box_cap * BOX_WORDS;
    const int nb = P.nboxes[b];
    bool drop = false;
    if (newborn) {
        // The budget counts the boxes left (an emptied new agent's size is negative).
        int held = 0;
        for (int q = 0; q < nb; q++) held += mine[BOX_WORDS * q + 5] >= 0.0;
        drop = held >= G.max_boxes;
        for (int q = 0; q < nb && !drop; q++)
            drop = mine[BOX_WORDS * q + 5] >= 0.0 && boxes_overlap(mine + BOX_WORDS * q, box);
    } else if (G.boxes == 2) {
        for (int q = 0; q < nb; q++) {
            double* o = mine + BOX_WORDS * q;
            if (o[5] <= 0.0 || !boxes_overlap(o, box)) continue;
            const int s = (int)o[6], size = (int)o[5];
            for (int i = s; i < s + size; i++) row[i] = G.pad;
            o[5] = -o[5];
            atomic_add_u(P.counts + 1, 1u);
        }
    }
    if (drop) {
        for (int q = R.gstart; q <= p; q++) row[q] = G.pad;
        atomic_add_u(P.counts + 1, 1u);
    } else if (nb < P.box_cap) {
        double* o = mine + BOX_WORDS * nb;
        for (int f = 0; f < 5; f++) o[f] = box[f];
        o[5] = newborn ? (double)(p + 1 - R.gstart) : 0.0;
        o[6] = (double)R.gstart;
        P.nboxes[b] = nb + 1;
    }
}

KERNEL umgen_draw(const Draw P) {
    griddep_launch();
    griddep_wait();
    const int b = (int)block_x();
    const int p = *P.pos;
    const Rule R = P.rules[p];
    GroupRun G = {};
    if (R.gstart >= 0) G = P.runs[R.grun];
    int* row = P.tok + (long long)b * P.n;
    if (!R.known) {
        const int first = R.gstart >= 0 && R.gj > 0 ? row[R.gstart] : -1;
        int id = draw_from(P, P.logits + (long long)b * P.vocab, R, G, first, true, b, p, 0u);
        if (R.keep >= 0 && P.keep_on[(long long)b * P.keeps + R.keep] && id == R.keep_pad &&
            !(R.gstart >= 0 && R.gj > 0 && first == G.pad)) {
            const float* tar = P.keep_logits + (long long)b * P.state[1] + R.keep_off;
            id = draw_from(P, tar, R, G, first, false, b, p, 1u << 24);
        }
        if (thread_id() == 0) row[p] = id;
    }
    sync_block();
    if (thread_id() == 0) {
        if (R.finish) new_agent(P, R, G, b, p);
        fence();
        if (atomic_add_u(P.done, 1u) + 1 == (unsigned)P.m) {
            *P.done = 0;
            *P.pos = p + 1;
        }
    }
}
