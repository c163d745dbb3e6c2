//! [`super::sum`] and [`super::sum_cast`] for `Cuda` (burn-fusion over the cubecl backend): one custom
//! operation in the fusion stream that launches `rows.cu`'s kernel on cubecl's stream with its buffers bound,
//! once over row groups (writing the rows' bf16 copy too, for `sum_cast`) and once over their partial sums.
//! Other types than f32 and bf16, empty or oversized inputs, or a failure to compile or launch run the staged
//! burn reduction (and burn's cast) instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

use super::staged::{FALLBACKS, staged};
use crate::format::float;
use crate::side::{self, Handles, Inner, Primitive, empty_f32, empty_packed};
use burn::backend::Cuda;
use burn::tensor::{DType, FloatDType, Tensor};
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
    if let Some(why) = refused(&x) {
        FALLBACKS.fell_back(&why);
        return staged(x);
    }
    let d = x.dims()[1];
    let [out] = side::register("umgen_rows_sum", [side::fused(x)], [vec![d]], Pass::Sum);
    float(out)
}

/// `x` `[rows, d]` (f32) rounded to bf16, and its column sums `[d]` (of the f32 values), in one pass.
pub(super) fn sum_cast(x: Tensor<Cuda, 2>) -> (Tensor<Cuda, 2>, Tensor<Cuda, 1>) {
    // `rows::sum_cast` sends f32 rows only (`launch` refuses others too).
    if let Some(why) = refused(&x) {
        FALLBACKS.fell_back(&why);
        return (x.clone().cast(FloatDType::BF16), staged(x));
    }
    let [rows, d] = x.dims();
    let outputs = vec![(vec![rows, d], DType::BF16), (vec![d], DType::F32)];
    let [cast, out] = side::register_typed(
        "umgen_rows_sum_cast",
        vec![side::fused(x)],
        outputs,
        Pass::SumCast,
    )
    .try_into()
    .unwrap_or_else(|_| unreachable!("umgen_rows_sum_cast was described with 2 outputs"));
    (float(cast), float(out))
}

/// Why the kernel cannot take `x`, if it cannot.
fn refused(x: &Tensor<Cuda, 2>) -> Option<String> {
    let [rows, d] = x.dims();
    (rows == 0 || d == 0 || !matches!(x.dtype(), DType::F32 | DType::BF16) || i32::try_from(d).is_err())
        .then(|| format!("{:?} [{rows}, {d}]", x.dtype()))
}

/// The sums' pass: x in, its column sums out (and before them its bf16 copy, for [`Pass::SumCast`]).
#[derive(Debug, Clone, Copy)]
enum Pass {
    Sum,
    SumCast,
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let [x] = side::contiguous_inputs(handles, desc);
        let cast = matches!(self, Pass::SumCast);
        launch(&x, cast).unwrap_or_else(|why| {
            FALLBACKS.fell_back(&why);
            let x = float::<Inner, 2>(x);
            let sums = side::inner(staged(x.clone()));
            match cast {
                true => vec![side::inner(x.cast(FloatDType::BF16)), sums],
                false => vec![sums],
            }
        })
    }
}

/// The kernel's source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::ROWS))
}

/// Launches the kernel over contiguous f32 or bf16 `x` `[rows, d]`: into `groups` partial rows (f32), then
/// over those; returns the f32 sums `[d]` (after `x`'s bf16 copy, packed, where `cast`: f32 `x` only), or
/// why it could not (nothing the caller keeps was written).
fn launch(x: &Primitive, cast: bool) -> Result<Vec<Primitive>, String> {
    let first = match (x.dtype, cast) {
        (DType::F32, false) => "umgen_rows_sum",
        (DType::F32, true) => "umgen_rows_sum_cast",
        (DType::BF16, false) => "umgen_rows_sum_bf16",
        (other, _) => {
            return Err(format!(
                "{other:?} rows (the kernel takes f32, or bf16 without a cast)"
            ));
        }
    };
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
    let copy = cast.then(|| empty_packed(x, vec![rows, d], DType::BF16));
    let mut buffers = vec![bind(x), bind(partial.as_ref().unwrap_or(&out))];
    buffers.extend(copy.as_ref().map(bind));
    let mut steps = vec![(first, buffers, sizes(rows, g)?, blocks(tiles * g)?)];
    if let Some(partial) = &partial {
        let buffers = vec![bind(partial), bind(&out)];
        steps.push(("umgen_rows_sum", buffers, sizes(g, 1)?, blocks(tiles)?));
    }
    for (entry, buffers, sizes, grid) in steps {
        // SAFETY: every buffer is bound (cubecl keeps it alive for the launch) and packed: the input and
        // the bf16 copy `rows × d`, the output `groups × d` of `sizes`, as the kernel indexes them.
        unsafe {
            side::launch_bound_on_cubecl(x, entry, ("", &source), ((grid, 1, 1), THREADS), buffers, &sizes)
        }?;
    }
    Ok(copy.into_iter().chain([out]).collect())
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
