//! What the layer-norm kernels' two launch paths share: the kernels' row capacities and grid, their
//! sizes block, the results they write and their source.
#![allow(unsafe_code)]

use crate::side::{self, Primitive, empty_f32, empty_packed};
use burn::tensor::{DType, FloatDType};
use cudarc::driver::DeviceRepr;

/// Values a lane keeps of its row, one kernel each: rows up to 32 times as wide.
pub(super) const PER_LANE: [usize; 6] = [4, 8, 12, 16, 24, 32];

/// Warps a block (the kernels' `__launch_bounds__(256)`).
pub(super) const WARPS: usize = 8;

/// Blocks of the backward kernel: each warp loops over rows and writes one row of column sums, so this
/// bounds the sums the caller adds (8,192 rows of `d`) while filling an H100 (132 SMs) in one wave.
const BACKWARD_BLOCKS: usize = 1024;

/// `NormSizes` of `norm.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Sizes {
    pub(super) rows: i64,
    pub(super) d: i32,
    pub(super) eps: f32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Sizes {}

/// The kernels' per-lane capacity for rows of `d`, if one takes them.
pub(super) fn per_lane(d: usize) -> Option<usize> {
    PER_LANE.into_iter().find(|&p| 32 * p >= d)
}

/// Warps of the backward kernel's grid for `rows` rows (each writes a row of column sums).
pub(super) fn backward_warps(rows: usize) -> usize {
    rows.div_ceil(WARPS).min(BACKWARD_BLOCKS) * WARPS
}

/// The kernels' source as NVRTC compiles it.
pub(super) fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::NORM))
}

/// The results of a pass over `x` `[rows, d]`, packed: y (in `out`'s format), the rows' means and `1/σ`
/// (forward), or dx (f32) and one row of column sums per warp of the grid for the scale and the shift
/// (`backward`).
pub(super) fn results(x: &Primitive, backward: bool, out: FloatDType) -> Vec<Primitive> {
    let (rows, d) = (x.meta.shape()[0], x.meta.shape()[1]);
    let stats = if backward {
        vec![backward_warps(rows), d]
    } else {
        vec![rows]
    };
    vec![
        empty_packed(x, vec![rows, d], DType::from(out)),
        empty_f32(x, stats.clone()),
        empty_f32(x, stats),
    ]
}
