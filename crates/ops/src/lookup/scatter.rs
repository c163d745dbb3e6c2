//! The table's gradient by scatters, and the kernels' fallbacks: what both `lookup.rs` and `lookup/cuda.rs` use.

use crate::dispatch::Fallbacks;
use burn::tensor::backend::Backend;
use burn::tensor::{IndexingUpdateOp, Int, Tensor};

pub(super) static FALLBACKS: Fallbacks = Fallbacks::new("embedding gradient");

/// Most bytes the `k` table copies may take together.
pub(super) const COPIES_BYTES: usize = 128 << 20;
/// Most chunks.
pub(super) const MAX_CHUNKS: usize = 256;

/// Chunks for `rows` looked-up rows of a `vocab × d` table: the largest divisor of `rows` whose copies
/// fit [`COPIES_BYTES`], at most [`MAX_CHUNKS`] and at most `rows / 8` (1 if none).
pub(super) fn chunks(rows: usize, vocab: usize, d: usize) -> usize {
    let limit = (COPIES_BYTES / (vocab * d * 4).max(1))
        .min(MAX_CHUNKS)
        .min(rows / 8);
    (1..=limit.max(1))
        .rev()
        .find(|k| rows.is_multiple_of(*k))
        .unwrap_or(1)
}

/// [`table_grad`] by scatters into `k` copies of the table ([`chunks`]), summed.
pub(super) fn scatter_grad<I: Backend>(
    g: Tensor<I, 2>,
    ids: Tensor<I, 1, Int>,
    vocab: usize,
) -> Tensor<I, 2> {
    let [rows, d] = g.dims();
    let k = chunks(rows, vocab, d);
    let r = rows / k;
    let idx = ids.reshape([k, r, 1]).expand([k, r, d]);
    Tensor::<I, 3>::zeros([k, vocab, d], &g.device())
        .scatter(1, idx, g.reshape([k, r, d]), IndexingUpdateOp::Add)
        .sum_dim(0)
        .reshape([vocab, d])
}
