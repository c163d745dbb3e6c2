//! [`super::sum`] for `Cuda` (burn-fusion over the cubecl backend): one custom operation in the fusion stream
//! that launches `rows.cu`'s kernel on cubecl's stream with its buffers bound, once over row groups and once
//! over their partial sums. Other types than f32, empty or oversized inputs, or a failure to compile or launch
//! run the staged burn reduction instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

use super::{CHOICE, staged};
use crate::attention::float;
use crate::side::{self, Handles, Inner, Primitive, empty_f32};
use burn::backend::Cuda;
use burn::tensor::{DType, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;

/// Threads a block (the kernel's `__launch_bounds__(256)`).
const THREADS: u32 = 256;
/// Row groups at most: the second launch's rows.
const MAX_GROUPS: usize = 256;
/// Rows a group takes at least (four a phase), so that small matrices are not spread thinner.
const MIN_GROUP_ROWS: usize = 32;

/// `RowsSizes` of `rows.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Sizes {
    rows: i64,
    d: i32,
    groups: i32,
}

// SAFETY: plain old data, laid out as the C struct the kernel takes by value.
unsafe impl DeviceRepr for Sizes {}

/// Row groups of the first launch over `rows` rows (1: a single launch).
fn groups(rows: usize) -> usize {
    (rows / MIN_GROUP_ROWS).clamp(1, MAX_GROUPS)
}

/// The column sums `[d]` of `x` `[rows, d]`.
pub(super) fn sum(x: Tensor<Cuda, 2>) -> Tensor<Cuda, 1> {
    let [rows, d] = x.dims();
    if rows == 0 || d == 0 || x.dtype() != DType::F32 || i32::try_from(d).is_err() {
        CHOICE.fell_back(&format!("{:?} [{rows}, {d}]", x.dtype()));
        return staged(x);
    }
    let [out] = side::register("umgen_rows_sum", [side::fused(x)], [vec![d]], Pass);
    float(out)
}

/// The sums' pass: x in, its column sums out.
#[derive(Debug, Clone, Copy)]
struct Pass;

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let [x] = side::contiguous_inputs::<1, 1>(handles, desc);
        launch(&x).unwrap_or_else(|why| {
            CHOICE.fell_back(&why);
            vec![side::inner(staged(float::<Inner, 2>(x)))]
        })
    }
}

/// The kernel's source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(include_str!("rows.cu")))
}

/// Launches the kernel over contiguous f32 `x` `[rows, d]`: into `groups` partial rows, then over those;
/// returns the sums `[d]`, or why it could not (nothing the caller keeps was written).
fn launch(x: &Primitive) -> Result<Vec<Primitive>, String> {
    if x.dtype != DType::F32 {
        return Err(format!("{:?} rows (the kernel takes f32)", x.dtype));
    }
    let shape = x.meta.shape();
    let (rows, d) = (shape[0], shape[1]);
    let g = groups(rows);
    let tiles = d.div_ceil(32);
    let out = empty_f32(x, vec![d]);
    let sizes = |rows: usize, groups: usize| -> Result<Sizes, String> {
        Ok(Sizes {
            rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
            d: i32::try_from(d).map_err(|_| format!("width {d}"))?,
            groups: i32::try_from(groups).map_err(|_| format!("{groups} groups"))?,
        })
    };
    let blocks = |n: usize| u32::try_from(n).map_err(|_| format!("{n} blocks"));
    let bind = |t: &Primitive| t.handle.clone().binding();
    let partial = (g > 1).then(|| empty_f32(x, vec![g, d]));
    let mut steps = vec![(
        bind(x),
        bind(partial.as_ref().unwrap_or(&out)),
        sizes(rows, g)?,
        blocks(tiles * g)?,
    )];
    if let Some(partial) = &partial {
        steps.push((bind(partial), bind(&out), sizes(g, 1)?, blocks(tiles)?));
    }
    for (input, output, sizes, grid) in steps {
        // SAFETY: both buffers are bound (cubecl keeps them alive for the launch) and packed: the input
        // `rows × d` and the output `groups × d` of `sizes`, as the kernel indexes them.
        unsafe {
            side::launch_bound_on_cubecl(
                x,
                "umgen_rows_sum",
                ("", &source),
                ((grid, 1, 1), THREADS),
                vec![input, output],
                &sizes,
            )
        }?;
    }
    Ok(vec![out])
}

#[cfg(test)]
mod tests {
    use super::groups;

    #[test]
    fn groups_keep_at_least_32_rows_and_at_most_256_groups() {
        assert_eq!(groups(5), 1);
        assert_eq!(groups(1024), 32);
        assert_eq!(groups(70_368), 256);
    }
}
