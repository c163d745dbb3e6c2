//! Arguments of the attention kernels: [`AttendRows`] and [`AttendTiles`] (`attend.cu`) and [`Flash`]
//! (`kernels/flash2/`).
//! Buffers, sizes and strides are in elements, as the kernel takes them (`src/kernels/*.cu` documents
//! each).

use super::Buf;

/// Keys a block of [`AttendRows`] takes (a key per lane of its 8 warps).
pub const ROWS_SPLIT: usize = 256;
/// Blocks an [`AttendRows`] query's keys may be split into (`ROWS_MAX_SPLITS` of `attend.cu`).
pub const ROWS_MAX_SPLITS: usize = 32;
/// The largest head size the attention kernels take (`ATT_DH` of `attend.cu`).
pub const MAX_HEAD: usize = 128;

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
