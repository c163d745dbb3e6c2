// An embedding table's gradient, `grad[v] = Σ g[i] over the rows i whose id is v`, summed in the rows'
// order whatever the grid (so that same-seed runs agree to the bit), by a counting sort of the ids and a
// walk over the sorted rows. `lookup/cuda.rs` launches the six kernels in order on cubecl's stream:
//
//   count    block c counts the ids of its CHUNK rows into row c of `hist` ([chunks, buckets]);
//   prefix   hist[c][v] becomes the count of id v in the chunks before c, `start[v]` v's total;
//   scan     (one block) `start` becomes the exclusive scan of the totals: v's first sorted position;
//   place    row i of chunk c goes to position start[v] + hist[c][v] + (the rows of its chunk before it
//            with the same id): `order` holds the rows by id, then by row, and `sorted` their ids;
//   sum      block t walks sorted positions [t · TILE, (t + 1) · TILE) column by column: an id whose rows
//            all lie in the tile is written to `grad`, the first and last ids of the tile that run on past
//            it go to the tile's two rows of `partial` ([tiles, 2, d]);
//   finish   block v writes the rows no `sum` wrote: zeros for an id no row has, the partials of tiles
//            in order for an id whose rows span tiles.
//
// Where the scatter into `k` table copies it replaces gave each column of a copy one thread (3,840 threads
// for the `small` map table, 0.7–1.8 ms a table on an H100), every step here has a thread per row or per
// column of a tile, and an id that most rows share (a map's empty code) still spreads over many tiles.
// Ids outside [0, vocab) fall in bucket `vocab`, which nothing writes. NVRTC compiles it after
// `warp_device.cuh`; on the host `lookup_emulator.cpp` includes it after `warp_emulator.h` and compares it
// with a double-precision sum.

#define CHUNK 1024
#define TILE 64

// Sizes of one table gradient (`Sizes` in `lookup/cuda.rs`, field for field).
struct LookupSizes {
    long long rows;  // looked-up rows
    int vocab;       // table rows
    int d;           // table width
    int chunks;      // ⌈rows / CHUNK⌉
};

// The bucket of an id: itself, or `vocab` for one outside the table.
DEV int bucket(int id, int vocab) { return id >= 0 && id < vocab ? id : vocab; }

KERNEL umgen_lookup_count(const int* ids, int* hist, LookupSizes s) {
    const long long c = block_x();
    int* h = hist + c * (s.vocab + 1);
    for (int v = thread_id(); v <= s.vocab; v += threads()) h[v] = 0;
    sync_block();
    const long long r0 = c * CHUNK;
    for (int i = thread_id(); i < CHUNK && r0 + i < s.rows; i += threads())
        atomic_add(&h[bucket(ids[r0 + i], s.vocab)], 1);
}

KERNEL umgen_lookup_prefix(int* hist, int* start, LookupSizes s) {
    const long long v = block_x() * threads() + thread_id();
    const int buckets = s.vocab + 1;
    if (v >= buckets) return;
    int run = 0;
    // Eight chunks' counts read before any is written, so that the reads overlap.
    for (int c0 = 0; c0 < s.chunks; c0 += 8) {
        int n[8];
#pragma unroll
        for (int k = 0; k < 8; k++) n[k] = c0 + k < s.chunks ? hist[(long long)(c0 + k) * buckets + v] : 0;
#pragma unroll
        for (int k = 0; k < 8; k++) {
            if (c0 + k < s.chunks) hist[(long long)(c0 + k) * buckets + v] = run;
            run += n[k];
        }
    }
    start[v] = run;
}

// One block of at most 1,024 threads: each scans a run of consecutive buckets, after thread 0 has scanned
// the runs' totals.
KERNEL umgen_lookup_scan(int* start, LookupSizes s) {
    SHARED int runs[1024];
    const int buckets = s.vocab + 1, per = (buckets + threads() - 1) / threads();
    const int lo = thread_id() * per, hi = lo + per < buckets ? lo + per : buckets;
    int mine = 0;
    for (int v = lo; v < hi; v++) mine += start[v];
    runs[thread_id()] = mine;
    sync_block();
    if (thread_id() == 0) {
        int run = 0;
        for (int t = 0; t < threads(); t++) {
            const int n = runs[t];
            runs[t] = run;
            run += n;
        }
    }
    sync_block();
    int run = runs[thread_id()];
    for (int v = lo; v < hi; v++) {
        const int n = start[v];
        start[v] = run;
        run += n;
    }
}

KERNEL umgen_lookup_place(const int* ids, const int* hist, const int* start, int* order, int* sorted,
                          LookupSizes s) {
    SHARED int chunk[CHUNK];
    const long long c = block_x(), r0 = c * CHUNK;
    const int n = s.rows - r0 < CHUNK ? (int)(s.rows - r0) : CHUNK;
    for (int i = thread_id(); i < n; i += threads()) chunk[i] = bucket(ids[r0 + i], s.vocab);
    sync_block();
    const int* h = hist + c * (s.vocab + 1);
    for (int i = thread_id(); i < n; i += threads()) {
        const int b = chunk[i];
        int rank = 0;
        for (int j = 0; j < i; j++) rank += chunk[j] == b;
        const int pos = start[b] + h[b] + rank;
        order[pos] = (int)(r0 + i);
        sorted[pos] = b;
    }
}

// Positions a thread reads ahead in `sum` before adding them in order.
#define AHEAD 16

KERNEL umgen_lookup_sum(const float* g, const int* order, const int* sorted, float* grad, float* partial,
                        LookupSizes s) {
    SHARED int rows[TILE], ids[TILE + 1];
    const long long t = block_x(), p0 = t * TILE;
    const int n = s.rows - p0 < TILE ? (int)(s.rows - p0) : TILE;
    for (int i = thread_id(); i <= n; i += threads()) {
        if (i < n) rows[i] = order[p0 + i];
        // The id after the tile (-1 past the last row) tells whether the tile's last id runs on.
        ids[i] = p0 + i < s.rows ? sorted[p0 + i] : -1;
    }
    // Whether the tile's first id started before it.
    const bool runs_in = p0 > 0 && sorted[p0 - 1] == sorted[p0];
    sync_block();
    for (int j = thread_id(); j < s.d; j += threads()) {
        float acc = 0.f;
        int a = 0;  // where the current id's rows start in the tile
        for (int i0 = 0; i0 < n; i0 += AHEAD) {
            float x[AHEAD];
#pragma unroll
            for (int k = 0; k < AHEAD; k++) x[k] = i0 + k < n ? g[(long long)rows[i0 + k] * s.d + j] : 0.f;
#pragma unroll
            for (int k = 0; k < AHEAD; k++) {
                const int i = i0 + k;
                if (i >= n) break;
                acc += x[k];
                const int b = ids[i];
                const bool last_here = ids[i + 1] != b;
                if (i + 1 < n && !last_here) continue;
                if (b < s.vocab) {
                    const bool first_here = a > 0 || !runs_in;
                    if (first_here && last_here)
                        grad[(long long)b * s.d + j] = acc;
                    else
                        partial[(2 * t + (a == 0 ? 0 : 1)) * s.d + j] = acc;
                }
                acc = 0.f;
                a = i + 1;
            }
        }
    }
}

// Tile phases of `finish`: the partials of an id's tiles t, t + PHASES, … are summed apart, then the
// phases in order (a fixed order whatever the block's size).
#define PHASES 8

KERNEL umgen_lookup_finish(const int* start, const float* partial, float* grad, LookupSizes s) {
    SHARED float sums[PHASES][32];
    const long long v = block_x();
    const int first = start[v], end = start[v + 1];
    float* row = grad + v * s.d;
    if (first == end) {
        for (int j = thread_id(); j < s.d; j += threads()) row[j] = 0.f;
        return;
    }
    const int a = first / TILE, z = (end - 1) / TILE;
    if (a == z) return;  // all in one tile: `sum` wrote it
    const int lane = lane_id(), warps = threads() / 32;
    for (int c0 = 0; c0 < s.d; c0 += 32) {
        const int j = c0 + lane;
        for (int ph = warp_id(); ph < PHASES; ph += warps) {
            float acc = 0.f;
            if (j < s.d) {
#pragma unroll 4
                for (int t = a + ph; t <= z; t += PHASES)
                    acc += partial[(2LL * t + ((long long)t * TILE >= first ? 0 : 1)) * s.d + j];
            }
            sums[ph][lane] = acc;
        }
        sync_block();
        if (warp_id() == 0 && j < s.d) {
            float total = 0.f;
#pragma unroll
            for (int ph = 0; ph < PHASES; ph++) total += sums[ph][lane];
            row[j] = total;
        }
        sync_block();
    }
}
