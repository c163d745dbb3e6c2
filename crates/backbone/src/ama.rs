//! Action-aware map alignment (paper §3.2): the map features of frame t, moved by the ego motion to
//! frame t+1, as a prior for the next map.

use burn::tensor::backend::Backend;
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Tensor, TensorData};

/// Moves grid features `[b, rows·cols, d]` (row 0 at the front, column 0 at the left, `cell_m` metres per
/// cell) into the frame reached by the ego motion `[b, 3]` = (dx, dy, dθ): the output at a cell shows the
/// input at `R(dθ)·p + (dx, dy)`, sampled bilinearly, zero outside the grid.
pub fn align<B: Backend>(
    features: Tensor<B, 3>,
    action: Tensor<B, 2>,
    rows: usize,
    cols: usize,
    cell_m: f64,
) -> Tensor<B, 3> {
    let [b, m, d] = features.dims();
    let dev = features.device();
    let x = features.reshape([b, rows, cols, d]).permute([0, 3, 1, 2]);
    // Normalised coordinates of output cell centres (align_corners = false): x across columns, y down rows.
    let mut base = Vec::with_capacity(rows * cols * 2);
    for r in 0..rows {
        for c in 0..cols {
            base.push((2.0 * c as f32 + 1.0) / cols as f32 - 1.0);
            base.push((2.0 * r as f32 + 1.0) / rows as f32 - 1.0);
        }
    }
    let base = Tensor::<B, 1>::from_data(TensorData::new(base, [rows * cols * 2]), &dev).reshape([
        1,
        rows * cols,
        2,
    ]);
    let (gx, gy) = (base.clone().narrow(2, 0, 1), base.narrow(2, 1, 1));
    let col = |k: usize| action.clone().narrow(1, k, 1).unsqueeze_dim::<3>(2);
    let (dx, dy, th) = (col(0), col(1), col(2));
    let (c, s) = (th.clone().cos(), th.sin());
    // Columns run along -y and rows along -x, so in normalised units p_in = R(θ)·p_out + d becomes
    // [[c, s, -2dy/W], [-s, c, -2dx/H]] applied to (x, y).
    let (ext_y, ext_x) = (cols as f64 * cell_m, rows as f64 * cell_m);
    let tx = dy.mul_scalar(-2.0 / ext_y);
    let ty = dx.mul_scalar(-2.0 / ext_x);
    let sx = c.clone() * gx.clone() + s.clone() * gy.clone() + tx;
    let sy = s.neg() * gx + c * gy + ty;
    let grid = Tensor::cat(vec![sx, sy], 2).reshape([b, rows, cols, 2]);
    let opts = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    x.grid_sample_2d(grid, opts)
        .permute([0, 2, 3, 1])
        .reshape([b, m, d])
}
