//! Action-aware map alignment (paper §3.2): the map features of frame t, moved by the ego motion to
//! frame t+1, as a prior for the next map.

use burn::tensor::backend::Backend;
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Int, Tensor, TensorData};

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
    let dev = features.device();
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
    if umgen_ops::lookup::has_tracked::<B>() {
        bilinear_rows(features, sx, sy, rows, cols)
    } else {
        grid_sampled(features, sx, sy, rows, cols)
    }
}

/// [`bilinear_rows`] by burn's `grid_sample_2d` (fused on CUDA): the inference backends' path.
fn grid_sampled<B: Backend>(
    features: Tensor<B, 3>,
    sx: Tensor<B, 3>,
    sy: Tensor<B, 3>,
    rows: usize,
    cols: usize,
) -> Tensor<B, 3> {
    let [b, m, d] = features.dims();
    let x = features.reshape([b, rows, cols, d]).permute([0, 3, 1, 2]);
    let grid = Tensor::cat(vec![sx, sy], 2).reshape([b, rows, cols, 2]);
    let opts = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Zeros)
        .with_align_corners(false);
    x.grid_sample_2d(grid, opts)
        .permute([0, 2, 3, 1])
        .reshape([b, m, d])
}

/// `grid_sample_2d`'s bilinear sampling (zeros outside the grid, align_corners = false) of `features` `[b,
/// rows·cols, d]` at the normalised points `sx`, `sy` `[b, rows·cols, 1]`, with burn's reference
/// arithmetic in its order, for the training backends: the four corners are row lookups of the features
/// as one `[b·rows·cols, d]` table ([`umgen_ops::lookup::rows`]). burn 0.21 differentiates its reference
/// sampling, four `gather`s whose backward passes are scatters into zeros (0.66 ms each in a `small` step
/// on an H100); the lookups' backward pass is their table gradient, a counting sort on CUDA.
fn bilinear_rows<B: Backend>(
    features: Tensor<B, 3>,
    sx: Tensor<B, 3>,
    sy: Tensor<B, 3>,
    rows: usize,
    cols: usize,
) -> Tensor<B, 3> {
    let [b, m, d] = features.dims();
    let dev = features.device();
    let px = sx.add_scalar(1.0).mul_scalar(cols as f64 / 2.0).sub_scalar(0.5);
    let py = sy.add_scalar(1.0).mul_scalar(rows as f64 / 2.0).sub_scalar(0.5);
    let (x0, y0) = (px.clone().floor(), py.clone().floor());
    let (fx, fy) = (px - x0.clone(), py - y0.clone());
    let (gx, gy) = (fx.clone().neg().add_scalar(1.0), fy.clone().neg().add_scalar(1.0));
    // Each window's cells start at row b_i · m of the table.
    let first = Tensor::<B, 1, Int>::arange(0..b as i64, &dev)
        .mul_scalar(m as i64)
        .reshape([b, 1, 1]);
    let table = features.reshape([b * m, d]);
    // The corner `dx`, `dy` cells from (x0, y0), weighted by `w` and by 0 outside the grid.
    let corner = |dx: f64, dy: f64, w: Tensor<B, 3>| {
        let (x, y) = (x0.clone().add_scalar(dx), y0.clone().add_scalar(dy));
        let inside = x
            .clone()
            .greater_equal_elem(0.0)
            .bool_and(x.clone().lower_elem(cols as f64))
            .bool_and(y.clone().greater_equal_elem(0.0))
            .bool_and(y.clone().lower_elem(rows as f64));
        let xi = x.clamp(0.0, (cols - 1) as f64).int();
        let yi = y.clamp(0.0, (rows - 1) as f64).int();
        let ids = (yi.mul_scalar(cols as i64) + xi + first.clone()).reshape([1, b * m]);
        let sample = umgen_ops::lookup::rows(table.clone(), ids).reshape([b, m, d]);
        sample * w.mask_fill(inside.bool_not(), 0.0)
    };
    corner(0.0, 0.0, gx.clone() * gy.clone())
        + corner(0.0, 1.0, gx * fy.clone())
        + corner(1.0, 0.0, fx.clone() * gy)
        + corner(1.0, 1.0, fx * fy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::tensor::Distribution;

    type A = Autodiff<Flex>;

    /// The lookups' sampling equals burn's `grid_sample_2d`, output and the features' gradient, on a grid
    /// rotated and shifted so that some points fall between cells and some outside.
    #[test]
    fn lookups_match_grid_sample_and_its_gradient() {
        let dev = Default::default();
        let (b, rows, cols, d) = (3, 5, 6, 4);
        let features = Tensor::<A, 3>::random([b, rows * cols, d], Distribution::Normal(0.0, 1.0), &dev);
        let w = Tensor::<A, 3>::random([b, rows * cols, d], Distribution::Normal(0.0, 1.0), &dev);
        let point = |lo, hi| Tensor::<A, 3>::random([b, rows * cols, 1], Distribution::Uniform(lo, hi), &dev);
        let (sx, sy) = (point(-1.3, 1.3), point(-1.3, 1.3));
        let run = |lookups: bool| {
            let f = Tensor::<A, 3>::from_inner(features.clone().inner()).require_grad();
            let y = if lookups {
                bilinear_rows(f.clone(), sx.clone(), sy.clone(), rows, cols)
            } else {
                grid_sampled(f.clone(), sx.clone(), sy.clone(), rows, cols)
            };
            let g = (y.clone() * w.clone()).sum().backward();
            (y.inner(), f.grad(&g).expect("features' gradient"))
        };
        let ((y, dy), (ry, rdy)) = (run(true), run(false));
        let diff = |a: Tensor<Flex, 3>, b: Tensor<Flex, 3>| (a - b).abs().max().into_scalar();
        assert!(
            ry.clone().abs().max().into_scalar() > 0.1,
            "the points sampled nothing"
        );
        assert!(diff(y, ry) < 1e-6);
        assert!(diff(dy, rdy) < 1e-5);
    }
}
