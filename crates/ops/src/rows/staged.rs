//! The row sums by burn's reductions, and the kernels' fallbacks: what both `rows.rs` and `rows/cuda.rs` use.

use crate::dispatch::Fallbacks;
use burn::tensor::backend::Backend;
use burn::tensor::{FloatDType, Tensor};

/// Row groups of [`sum`]'s first stage.
pub(super) const GROUPS: usize = 256;

pub(super) static FALLBACKS: Fallbacks = Fallbacks::new("row-sum");

/// [`sum`] by burn's reductions: the rows in [`GROUPS`] groups, then the groups (in f32).
pub(super) fn staged<I: Backend>(x: Tensor<I, 2>) -> Tensor<I, 1> {
    let x = x.cast(FloatDType::F32);
    let d = x.dims()[1];
    let m = x.dims()[0];
    let per = m / GROUPS;
    if per < 2 {
        return x.sum_dim(0).reshape([d]);
    }
    let grouped = x.clone().narrow(0, 0, GROUPS * per).reshape([GROUPS, per, d]);
    let total = grouped.sum_dim(1).reshape([GROUPS, d]).sum_dim(0);
    let rest = m - GROUPS * per;
    let total = if rest > 0 {
        total + x.narrow(0, GROUPS * per, rest).sum_dim(0)
    } else {
        total
    };
    total.reshape([d])
}
