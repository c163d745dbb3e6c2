//! Each operation's arguments: buffers, sizes and strides in elements, as its kernel takes them
//! (`src/kernels/*.cu` documents each).

use super::Buf;

/// Keys a block of [`AttendRows`] takes (a key per lane of its 8 warps).
pub const ROWS_SPLIT: usize = 256;
/// Blocks an [`AttendRows`] query's keys may be split into (`ROWS_MAX_SPLITS` of `attend.cu`).
pub const ROWS_MAX_SPLITS: usize = 32;
/// Rows a [`Gemv`] takes at most (`GEMV_ROWS` of `gemv.cu`).
pub const GEMV_ROWS: usize = 8;
/// The largest head size the attention kernels take (`ATT_DH` of `attend.cu`).
pub const MAX_HEAD: usize = 128;
/// The largest top-k a draw takes as a list (`DRAW_KMAX` of `draw.cu`); larger ones (and 0) draw by
/// Gumbel-max over every id, which needs top-p 1.
pub const DRAW_KMAX: usize = 64;

/// What a [`Gemv`] multiplies.
#[derive(Debug, Clone)]
pub enum GemvIn {
    /// Rows of `x` (f32), `ld` apart.
    Rows {
        /// The rows.
        x: Buf,
        /// Their stride.
        ld: usize,
    },
    /// The layer norm of rows of `x` with scale `g` and shift `b`.
    Norm {
        /// The rows.
        x: Buf,
        /// Their stride.
        ld: usize,
        /// Scale.
        g: Buf,
        /// Shift.
        b: Buf,
    },
    /// The OAR input's embedding of the previous token: `table[row_base[seg_of[p − 1]] + tok[s][p − 1]] +
    /// pos_emb[p − 1]`, `p` the device position.
    Embed {
        /// Every segment's (projected) table rows.
        table: Buf,
        /// Each segment's first row (i32).
        row_base: Buf,
        /// Each frame position's segment (i32).
        seg_of: Buf,
        /// The frame's tokens `[m][ntok]` (i32).
        tok: Buf,
        /// Tokens per row of `tok`.
        ntok: usize,
        /// Position embeddings `[N][k]`.
        pos_emb: Buf,
        /// The device position (i32).
        pos: Buf,
    },
}

/// Where a [`Gemv`]'s result goes.
#[derive(Debug, Clone)]
pub enum GemvOut {
    /// Stored in rows of `out` (f32), `ld` apart.
    Store {
        /// The rows.
        out: Buf,
        /// Their stride.
        ld: usize,
    },
    /// Added to rows of `out`.
    Add {
        /// The rows.
        out: Buf,
        /// Their stride.
        ld: usize,
    },
    /// Attention projections: columns `0..heads·dh` are the queries (to `q`), the next `heads·dh` the
    /// keys, the last the values, written to the caches `[m][heads][cap][dh]` at the device position.
    Qkv {
        /// The queries' rows.
        q: Buf,
        /// Their stride.
        ld: usize,
        /// Key cache (`W`).
        k: Buf,
        /// Value cache (`W`).
        v: Buf,
        /// Heads.
        heads: usize,
        /// Head size.
        dh: usize,
        /// Positions a cache holds.
        cap: usize,
        /// The device position.
        pos: Buf,
    },
    /// The OAR input: `(p == 0 ? bos : y) + h[s][p]`.
    Prior {
        /// The rows.
        out: Buf,
        /// Their stride.
        ld: usize,
        /// The start vector.
        bos: Buf,
        /// The TAR prior `[m][·][n]`.
        h: Buf,
        /// Its scene stride.
        h_ss: usize,
        /// The device position.
        pos: Buf,
    },
}

/// `y = in(x) · wᵀ` for `m` rows (`m` ≤ [`GEMV_ROWS`]), `w` `[n][k]` (`W`), then bias, GELU, output.
#[derive(Debug, Clone)]
pub struct Gemv {
    /// The weights.
    pub w: Buf,
    /// Rows.
    pub m: usize,
    /// Output columns.
    pub n: usize,
    /// Input columns.
    pub k: usize,
    /// The input.
    pub input: GemvIn,
    /// A bias `[n]`.
    pub bias: Option<Buf>,
    /// GELU after the bias.
    pub gelu: bool,
    /// The output.
    pub output: GemvOut,
}

/// `c (+)= a · wᵀ`: `a` `[rows][lda]` (`W`, `k` columns read), `w` `[n][k]` (`W`), `c` `[rows][ldc]` (f32 or
/// `W`); with `accumulate`, added to `c` (f32 only).
#[derive(Debug, Clone)]
pub struct Gemm {
    /// The rows.
    pub a: Buf,
    /// The weights.
    pub w: Buf,
    /// The result.
    pub c: Buf,
    /// Rows.
    pub rows: usize,
    /// Output columns.
    pub n: usize,
    /// Input columns.
    pub k: usize,
    /// Stride of `a`.
    pub lda: usize,
    /// Stride of `c`.
    pub ldc: usize,
    /// Add to `c`.
    pub accumulate: bool,
}

/// How many keys an [`AttendRows`] sees.
#[derive(Debug, Clone, Copy)]
pub enum Keys {
    /// This many.
    Fixed(usize),
    /// The device position + 1: a decoding step's, which no operation before the attention in the same
    /// run writes (the kernel reads it, and the keys before it, while the previous kernel finishes).
    Pos(Buf),
}

/// Few queries (f32) over many keys (`W`): block per (batch, row, head).
#[derive(Debug, Clone)]
pub struct AttendRows {
    /// Queries: `q + b·q_sb + r·q_sr + h·dh`.
    pub q: Buf,
    /// Keys: `k + b·k_sb + h·k_sh + j·k_sj`.
    pub k: Buf,
    /// Values, with the keys' strides.
    pub v: Buf,
    /// Results (f32), with `y_sb`, `y_sr`.
    pub y: Buf,
    /// Each split's partial result `[batches·rows·heads][splits][2 + dh]` (f32).
    pub part: Buf,
    /// Splits finished per query `[batches·rows·heads]` (u32, zero between launches).
    pub count: Buf,
    /// Blocks the keys are split into, [`ROWS_SPLIT`] keys each (enough for the keys seen).
    pub splits: usize,
    /// Keys seen.
    pub keys: Keys,
    /// Keys a cache holds (for the bounds of [`Keys::Pos`]).
    pub key_cap: usize,
    /// Strides (elements).
    pub q_sb: usize,
    /// Query row stride.
    pub q_sr: usize,
    /// Key batch stride.
    pub k_sb: usize,
    /// Key head stride.
    pub k_sh: usize,
    /// Key stride.
    pub k_sj: usize,
    /// Result batch stride.
    pub y_sb: usize,
    /// Result row stride.
    pub y_sr: usize,
    /// Batches.
    pub batches: usize,
    /// Query rows per batch.
    pub rows: usize,
    /// Heads.
    pub heads: usize,
    /// Head size.
    pub dh: usize,
    /// Score scale.
    pub scale: f32,
}

/// Strides of an [`AttendTiles`] operand: instance `i` is `(i / inner)·s1 + (i % inner)·s2`, row `r` is
/// `r·row`, head `h` is `h·dh`.
#[derive(Debug, Clone, Copy)]
pub struct Strides {
    /// Outer instance stride.
    pub s1: usize,
    /// Inner instance stride.
    pub s2: usize,
    /// Row stride.
    pub row: usize,
}

/// Many queries over tiles of keys, all `W`: block per (instance, head, 32 queries).
#[derive(Debug, Clone)]
pub struct AttendTiles {
    /// Queries.
    pub q: Buf,
    /// Keys.
    pub k: Buf,
    /// Values (keys' strides).
    pub v: Buf,
    /// Results.
    pub y: Buf,
    /// Query strides.
    pub qs: Strides,
    /// Key and value strides.
    pub ks: Strides,
    /// Result strides.
    pub ys: Strides,
    /// Instances.
    pub instances: usize,
    /// The inner instance count.
    pub inner: usize,
    /// Heads.
    pub heads: usize,
    /// Queries per instance.
    pub lq: usize,
    /// Keys per instance.
    pub lk: usize,
    /// Head size.
    pub dh: usize,
    /// Causal with this offset: key j hidden from query i when j > i + off.
    pub causal: Option<usize>,
    /// Score scale.
    pub scale: f32,
}

/// FlashAttention-2's forward pass (`kernels/flash2/`): `batch` × `heads` heads of `lq` queries over `lk`
/// keys, all `W` (bf16 on the executors that have it, [`super::Exec::flash`]); each operand's strides are
/// (batch, head, row), its last dimension contiguous; `lse` (f32 `[batch·heads·lq]`) takes the rows'
/// log-sum-exp.
#[derive(Debug, Clone)]
pub struct Flash {
    /// Queries.
    pub q: Buf,
    /// Keys.
    pub k: Buf,
    /// Values.
    pub v: Buf,
    /// Results.
    pub y: Buf,
    /// Log-sum-exp of each query row.
    pub lse: Buf,
    /// Query strides.
    pub qs: [usize; 3],
    /// Key strides.
    pub ks: [usize; 3],
    /// Value strides.
    pub vs: [usize; 3],
    /// Result strides.
    pub ys: [usize; 3],
    /// Batches.
    pub batch: usize,
    /// Heads.
    pub heads: usize,
    /// Queries.
    pub lq: usize,
    /// Keys.
    pub lk: usize,
    /// Head size (32 or 64).
    pub dh: usize,
    /// Hide keys after each query (bottom-right aligned).
    pub causal: bool,
}

/// `dst[r] (+)= gelu?(norm?(src[r']) + bias)`: row `r` is `(i1, i2) = (r / inner, r % inner)`, its source
/// `src + (i1 % period)·src_s1 + idx[i2]·src_s2` (period 0: none; no `idx`: `i2`), its destination `dst +
/// i1·dst_s1 + i2·dst_s2` (f32 or `W`; adding into f32 only).
#[derive(Debug, Clone)]
pub struct Rows {
    /// Source rows (f32).
    pub src: Buf,
    /// Source row indices (i32), or none.
    pub idx: Option<Buf>,
    /// Destination rows.
    pub dst: Buf,
    /// Layer norm scale and shift.
    pub norm: Option<(Buf, Buf)>,
    /// Bias.
    pub bias: Option<Buf>,
    /// Source outer stride.
    pub src_s1: usize,
    /// Source inner stride.
    pub src_s2: usize,
    /// Period of the outer index (0: none).
    pub period: usize,
    /// Destination outer stride.
    pub dst_s1: usize,
    /// Destination inner stride.
    pub dst_s2: usize,
    /// Rows.
    pub rows: usize,
    /// Inner count.
    pub inner: usize,
    /// Columns.
    pub d: usize,
    /// Add into the destination.
    pub add: bool,
    /// GELU.
    pub gelu: bool,
}

/// `x = gelu?(x + bias)` on `rows` rows of `cols` (`ld` apart) of a `W` buffer.
#[derive(Debug, Clone)]
pub struct BiasT {
    /// The rows.
    pub x: Buf,
    /// The bias.
    pub bias: Buf,
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Row stride.
    pub ld: usize,
    /// GELU.
    pub gelu: bool,
}

/// `out[r] = table[row_base[seg_of[p]] + tok[r]] + pos_emb[p]` with `p = p0 + r % period`, into `W` rows of `e`.
#[derive(Debug, Clone)]
pub struct Embed {
    /// Table rows of every segment.
    pub table: Buf,
    /// Each segment's first row.
    pub row_base: Buf,
    /// Each position's segment.
    pub seg_of: Buf,
    /// Tokens.
    pub tok: Buf,
    /// Position embeddings.
    pub pos_emb: Buf,
    /// Results.
    pub out: Buf,
    /// Rows.
    pub rows: usize,
    /// Positions cycle with this period…
    pub period: usize,
    /// … from this one.
    pub p0: usize,
    /// Width.
    pub e: usize,
}

/// The action block of each frame of `x` `[m][w][n][d]` replaced by the next frame's (the last by `fresh`
/// `[m][len][d]`).
#[derive(Debug, Clone)]
pub struct Shift {
    /// The window's features.
    pub x: Buf,
    /// The new frame's block.
    pub fresh: Buf,
    /// Scenes.
    pub m: usize,
    /// Frames.
    pub w: usize,
    /// Positions per frame.
    pub n: usize,
    /// Width.
    pub d: usize,
    /// The block's first position.
    pub start: usize,
    /// Its length.
    pub len: usize,
}

/// AMA: each frame's map cells of `x` `[frames][n][d]` (at `offset`) get the bilinear sample of `src`
/// (their copy) at the cell moved by the frame's next action `act` `[frames][3]`.
#[derive(Debug, Clone)]
pub struct Align {
    /// Features.
    pub x: Buf,
    /// The map cells' copy `[frames][rows·cols][d]`.
    pub src: Buf,
    /// Actions (dx, dy, dθ).
    pub act: Buf,
    /// Cell centres in normalised units `[rows·cols][2]`.
    pub base: Buf,
    /// Frames.
    pub frames: usize,
    /// Positions per frame.
    pub n: usize,
    /// Width.
    pub d: usize,
    /// The map's first position.
    pub offset: usize,
    /// Grid rows.
    pub rows: usize,
    /// Grid columns.
    pub cols: usize,
    /// −2 / (cols · cell size).
    pub tx_scale: f32,
    /// −2 / (rows · cell size).
    pub ty_scale: f32,
}

/// One field of a tracked slot: its place in the slot and its bins.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackField {
    /// Position in the slot.
    pub index: usize,
    /// Lower end.
    pub lo: f32,
    /// Upper end.
    pub hi: f32,
    /// Bins.
    pub bins: u32,
    /// Bin width, `(hi − lo) / bins` computed in f64.
    pub width: f32,
}

/// The tracked slots of each frame's tokens moved one frame ahead (`backbone::track::moved`).
#[derive(Debug, Clone)]
pub struct Track {
    /// The window's tokens `[frames][n]`.
    pub tok: Buf,
    /// Each frame's next action `[frames][3]`.
    pub act: Buf,
    /// Moved tokens `[frames][slots·k]`.
    pub out: Buf,
    /// Frames (scenes × window).
    pub frames: usize,
    /// Window frames per scene.
    pub w: usize,
    /// Positions per frame.
    pub n: usize,
    /// The segment's first content position.
    pub offset: usize,
    /// Slots.
    pub slots: usize,
    /// Tokens per slot.
    pub k: usize,
    /// Ids below are values.
    pub values: u32,
    /// The pad id that empties slots moved out of range.
    pub pad: Option<u32>,
    /// Constant acceleration.
    pub accel: bool,
    /// x, y, vx, vy, heading.
    pub fields: [TrackField; 5],
    /// Seconds per frame.
    pub step: f32,
}

/// A position's rule for the draw (`Rule` of `draw.cu`, field for field).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rule {
    /// Prefilled: nothing to draw.
    pub known: i32,
    /// Drawn ids must be below it.
    pub limit: i32,
    /// The group's first position, or −1.
    pub gstart: i32,
    /// Index in the group.
    pub gj: i32,
    /// The group's run.
    pub grun: i32,
    /// The group's index among all groups.
    pub gindex: i32,
    /// Apply the new-agent rule here.
    pub finish: i32,
    /// Keep entry, or −1.
    pub keep: i32,
    /// The id a kept position redraws.
    pub keep_pad: i32,
    /// Its TAR logits' offset in a scene's keep row.
    pub keep_off: i32,
}

impl Rule {
    /// A position with nothing but its draw.
    pub const FREE: Self = Self {
        known: 0,
        limit: 1 << 30,
        gstart: -1,
        gj: 0,
        grun: 0,
        gindex: 0,
        finish: 0,
        keep: -1,
        keep_pad: 0,
        keep_off: 0,
    };
}

/// A run of token groups (`GroupRun` of `draw.cu`, field for field).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroupRun {
    /// Tokens per group.
    pub size: i32,
    /// Pad id.
    pub pad: i32,
    /// Values are below.
    pub values: i32,
    /// A group's last token is in `last_lo..last_hi`.
    pub last_lo: i32,
    /// End of that range.
    pub last_hi: i32,
    /// Whether the new-agent rule applies.
    pub boxes: i32,
    /// Boxes a frame may hold.
    pub max_boxes: i32,
    /// x, y, heading, length, width: index in the group.
    pub field: [i32; 5],
    /// Their bins.
    pub bins: [i32; 5],
    /// Their lower ends.
    pub lo: [f64; 5],
    /// Their upper ends.
    pub hi: [f64; 5],
}

impl GroupRun {
    /// A run of no groups (the table's filler where a frame has none).
    pub const EMPTY: Self = Self {
        size: 0,
        pad: 0,
        values: 0,
        last_lo: 0,
        last_hi: 0,
        boxes: 0,
        max_boxes: 0,
        field: [0; 5],
        bins: [0; 5],
        lo: [0.0; 5],
        hi: [0.0; 5],
    };
}

/// The decoding step's draw for `m` scenes at the device position (see `draw.cu`).
#[derive(Debug, Clone)]
pub struct Draw {
    /// OAR logits `[m][vocab]`.
    pub logits: Buf,
    /// TAR logits of kept positions `[m][state[1]]`.
    pub keep_logits: Buf,
    /// Rules `[n]`.
    pub rules: Buf,
    /// Group runs.
    pub runs: Buf,
    /// Keep flags `[m][keeps]`.
    pub keep_on: Buf,
    /// Newborn flags `[m][groups]`.
    pub newborn: Buf,
    /// Tokens `[m][n]`.
    pub tok: Buf,
    /// The device position.
    pub pos: Buf,
    /// Blocks finished (u32).
    pub done: Buf,
    /// New agents tested and dropped (u32 × 2).
    pub counts: Buf,
    /// Boxes `[m][box_cap][5]`.
    pub boxes: Buf,
    /// Boxes held `[m]`.
    pub nboxes: Buf,
    /// The frame's counter, the keep rows' scene stride and the first scene's index in the batch (u32 × 3).
    pub state: Buf,
    /// Temperature.
    pub temperature: f64,
    /// Top-p.
    pub top_p: f64,
    /// Scenes.
    pub m: usize,
    /// Positions.
    pub n: usize,
    /// The segment's vocabulary.
    pub vocab: usize,
    /// Top-k (0: all).
    pub top_k: usize,
    /// Keep entries.
    pub keeps: usize,
    /// Groups.
    pub groups: usize,
    /// Box capacity per scene.
    pub box_cap: usize,
    /// The capacity of `keep_logits` per scene.
    pub keep_cap: usize,
    /// Runs in `runs`.
    pub run_count: usize,
    /// Philox key.
    pub key: [u32; 2],
}
