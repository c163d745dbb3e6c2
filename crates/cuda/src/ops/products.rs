//! Arguments of the matrix products: [`Gemv`] (few rows, `gemv.cu`) and [`Gemm`] (cuBLAS).
//! Buffers, sizes and strides are in elements, as the kernel takes them (`src/kernels/*.cu` documents
//! each).

use super::Buf;

/// Rows a [`Gemv`] takes at most (`GEMV_ROWS` of `gemv.cu`).
pub const GEMV_ROWS: usize = 8;

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
