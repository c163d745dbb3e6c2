// The queries' gradient of the flash2 kernels' one-pass backward pass (`train.kernels.attention_backward =
// "one-pass"`, head size 64 on `wgmma`): `flash2.cu`'s `backward_kv` with `ONE_PASS` also adds each column
// step's share of dQ, dSᵀ · K over the block's keys, into an f32 accumulator (`dq_acc`, zeroed by
// `dq_zero`, scaled and written in `T` by `dq_store`), as FlashAttention-2's backward pass does, where
// `backward_q` recomputed the scores and their gradients (two of its three products) to get it. The step's
// dS goes through shared memory (rows keys, columns queries) so that the warps split the product's queries
// and head columns among them; two such tiles take turns, so one barrier a step orders their writes and
// reads. NVRTC compiles this file after `flash2_tiles.cu` and before `flash2.cu`; `STEP` is that file's
// column step `SUB`.

// The one-pass kernel's dynamic shared memory in 16-bit elements: two dS tiles (128 keys × (SUB + 8)
// bf16), then the f32 staging tile of a step's dQ (SUB queries × 64).
#define DS_TILES (2 * MAX_ROWS * (SUB + 8))
#define ONE_PASS_SHARED (DS_TILES + 2 * SUB * 64)

// The dS tile of the step at column `c`: the two take turns.
template <int STEP>
DEV u16* ds_tile(u16* tiles, int c) {
    return tiles + ((c / STEP) & 1) * (MAX_ROWS * (STEP + 8));
}

// This warp's dS (16 keys × STEP queries, accumulator tiles) into `tile` as bf16, rows STEP + 8 apart.
template <int STEP>
DEV void store_ds(u16* tile, const float (*ds)[4]) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int j = 0; j < STEP / 8; j++)
#pragma unroll
        for (int h = 0; h < 2; h++)
            *(u32*)(tile + (16 * warp_id() + g + 8 * h) * (STEP + 8) + 8 * j + 2 * t) =
                pack(ds[j][2 * h], ds[j][2 * h + 1]);
}

// acc (two accumulator tiles: 16 queries × 16 head columns) = queries [16 m, 16 m + 16) of dSᵀ (`ds`, rows
// keys) times head columns [16 n, 16 n + 16) of the block's keys (`keys`, `at_tile` layout), over the
// block's keys: A and B both read transposed by `ldmatrix`.
template <int STEP>
DEV void ds_times_keys(float (*acc)[4], const u16* ds, const u16* keys, int m, int n) {
    zero<2>(acc);
    int l = lane_id(), i = l >> 3, j = l & 7;
#pragma unroll 2
    for (int kk = 0; kk < block_rows() / 16; kk++) {
        u32 a[4], b[4];
        ldsm4t(a, ds + (16 * kk + 8 * (i >> 1) + j) * (STEP + 8) + 16 * m + 8 * (i & 1));
        ldsm4t(b, keys + at_tile<64>(16 * kk + 8 * (i & 1) + j, 8 * (2 * n + (i >> 1))));
        mma(acc[0], a, b);
        mma(acc[1], a, b + 2);
    }
}

// `acc` (`ds_times_keys`' tiles for queries [16 m, 16 m + 16) and head columns [16 n, 16 n + 16)) into
// the step's f32 staging tile (STEP rows of 64).
DEV void stage_dq(float* staging, const float (*acc)[4], int m, int n) {
    int l = lane_id(), g = l >> 2, t = l & 3;
#pragma unroll
    for (int h = 0; h < 2; h++)
#pragma unroll
        for (int j = 0; j < 2; j++)
            *(float2*)(staging + 64 * (16 * m + g + 8 * h) + 16 * n + 8 * j + 2 * t) =
                float2{acc[j][2 * h], acc[j][2 * h + 1]};
}

// The step's share of dQ (the block's dS in `ds`, its keys in `keys`) added to the rows of `head` from query
// `q0` on: (16-query tile, 16-column pair) units of it shared out among the warps, once every warp has
// written its dS, gathered in `staging` and added by one bulk reduction (the TMA unit's, on sm_90a: a
// reduction a value, even four values an instruction, cost more than the products it saves).
template <int STEP>
DEV void add_dq_step(float* head, const u16* ds, const u16* keys, float* staging, int q0, int lq) {
    // The last step's reduction has read the staging tile before any warp writes it again.
    if (thread_id() == 0) bulk_wait_read();
    sync_block();
    for (int u = warp_id(); u < STEP / 16 * 4; u += threads() >> 5) {
        float acc[2][4];
        int m = u % (STEP / 16), n = u / (STEP / 16);
        ds_times_keys<STEP>(acc, ds, keys, m, n);
        stage_dq(staging, acc, m, n);
    }
    to_async_proxy();
    sync_block();
    if (thread_id() == 0 && q0 < lq) bulk_add(head + 64 * q0, staging, min(STEP, lq - q0) * 64 * 4);
}

// Zeroes this block's rows of `dq_acc` (the grid of `backward_q`: `block_rows` queries of head `block_y`).
DEV void dq_zero(const Params& P) {
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    float* head = P.dq_acc + (long long)bh * P.lq * 64;
    int end = min(P.lq, q0 + block_rows()) * 64;
    for (int i = q0 * 64 + 4 * thread_id(); i < end; i += 4 * threads())
        *(float4*)(head + i) = float4{0.f, 0.f, 0.f, 0.f};
}

// This block's rows of `dq` (in `T`, at its strides) = `dq_acc` × scale.
template <typename T>
DEV void dq_store(const Params& P) {
    int bh = block_y(), q0 = block_rows() * block_x();
    if (bh >= P.count) return;
    const float* head = P.dq_acc + (long long)bh * P.lq * 64;
    T* dst = (T*)P.dq + head_base(P.dqs, bh, P.heads);
    int rows = min(P.lq - q0, block_rows());
    for (int i = thread_id(); i < rows * 32; i += threads()) {
        int row = q0 + i / 32, col = 2 * (i % 32);
        float2 x = *(const float2*)(head + 64 * row + col);
        store_pair(dst + row * P.dqs[2] + col, x.x * P.scale, x.y * P.scale);
    }
}
