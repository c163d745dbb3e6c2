//! [`FusedGelu`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `gelu.cu`'s kernel on cubecl's stream with its buffers bound to the launch
//! (as AdamW's kernels are), so the training thread queues it without a call to cubecl's device thread
//! and without waiting, unless `train.kernels.gelu = "burn"`. Products in another format than
//! f32 or bf16, empty inputs, or a failure to compile or launch (the first launch of each kernel is checked) run burn's
//! operations instead, counted by [`super::fallbacks`]. The kernels always run on cubecl's stream, whatever
//! `train.kernels.stream` says: a bound launch needs no device pointers and no ordering.
#![allow(unsafe_code)]

use super::{FusedGelu, backward_decomposed, fell_back, forward_decomposed};
use crate::format::float;
use crate::format::float_format;
use crate::side::{self, Handles, Inner, Primitive, empty_f32, empty_packed};
use burn::backend::Cuda;
use burn::tensor::{DType, FloatDType, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;

/// Threads a block (the kernels' `__launch_bounds__(256)`).
const THREADS: u32 = 256;

/// Warps a pass keeps busy at most (64 a multiprocessor of an H100, twice over): each loops over its rows.
/// The passes need that many loads in flight to stream at the memory's speed; with 1,536 warps the bf16
/// backward pass over `[70,368, 1,536]` took 416 µs for 650 MB.
const WARPS: usize = 16_896;

/// Row groups of the backward pass at most: each writes one row of the bias's column sums, which the
/// caller adds (`rows::sum`, two launches over at most 17 MB for `n` = 1,536).
const GROUPS: usize = 4096;

/// `GeluSizes` of `gelu.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Sizes {
    rows: i64,
    n: i32,
    groups: i32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Sizes {}

/// Why the kernels cannot take the product `y` `[rows, n]`, if they cannot.
fn refused(y: &Tensor<Cuda, 2>) -> Option<String> {
    let [rows, n] = y.dims();
    if rows == 0 || n == 0 {
        return Some(format!("an empty product [{rows}, {n}]"));
    }
    (!matches!(y.dtype(), DType::F32 | DType::BF16))
        .then(|| format!("{:?} product (the kernels take f32 or bf16)", y.dtype()))
}

impl FusedGelu for Cuda {
    fn bias_gelu_forward(y: Tensor<Self, 2>, b: Tensor<Self, 1>) -> Tensor<Self, 2> {
        if let Some(why) = refused(&y) {
            fell_back(&why);
            return forward_decomposed(y, b);
        }
        let (shape, dtype) = (y.dims().to_vec(), y.dtype());
        let inputs = vec![side::fused(y), side::fused(b.cast(FloatDType::F32))];
        let [h] = register(Pass::Forward, inputs, vec![(shape, dtype)]);
        float(h)
    }

    fn bias_gelu_backward(
        dh: Tensor<Self, 2>,
        y: Tensor<Self, 2>,
        b: Tensor<Self, 1>,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>) {
        // The forward pass counted a refusal.
        if refused(&y).is_some() {
            return backward_decomposed(dh, y, b);
        }
        let ([rows, n], dtype) = (y.dims(), y.dtype());
        // The kernel reads the gradient in the product's format (the second product writes it so).
        let inputs = vec![
            side::fused(dh.cast(float_format(dtype))),
            side::fused(y),
            side::fused(b.cast(FloatDType::F32)),
        ];
        let outputs = vec![
            (vec![rows, n], dtype),
            (vec![backward_groups(rows, n, dtype), n], DType::F32),
        ];
        let [dy, sums] = register(Pass::Backward, inputs, outputs);
        (float(dy), crate::rows::sum(float::<Cuda, 2>(sums)))
    }
}

/// Row groups of a pass over `rows` rows of `chunks` column chunks (one warp each): as many as keep
/// [`WARPS`] warps busy, and for the backward pass at most [`GROUPS`].
fn groups(rows: usize, chunks: usize, backward: bool) -> usize {
    let most = if backward { GROUPS } else { usize::MAX };
    rows.min(WARPS / chunks.max(1)).min(most).max(1)
}

/// Row groups of the backward pass over `[rows, n]` of `dtype` (the rows of its column sums).
fn backward_groups(rows: usize, n: usize, dtype: DType) -> usize {
    groups(rows, chunks(n, width(n, dtype)), true)
}

/// The column chunks of a row of `n` values taken `width` a lane.
fn chunks(n: usize, width: usize) -> usize {
    n.div_ceil(32 * width)
}

/// The values a lane takes at a time over rows of `n` values of `dtype`: 16 bytes' worth where every row
/// starts on 16 bytes (burn's buffers do), else one.
fn width(n: usize, dtype: DType) -> usize {
    let wide = 16 / dtype.size();
    if n.is_multiple_of(wide) { wide } else { 1 }
}

/// Registers `pass` on the fusion stream.
fn register<const O: usize>(
    pass: Pass,
    inputs: Vec<burn::tensor::ops::FloatTensor<Cuda>>,
    outputs: Vec<(Vec<usize>, DType)>,
) -> [burn::tensor::ops::FloatTensor<Cuda>; O] {
    let id = match pass {
        Pass::Forward => "umgen_gelu_forward",
        Pass::Backward => "umgen_gelu_backward",
    };
    side::register_typed(id, inputs, outputs, pass)
        .try_into()
        .unwrap_or_else(|_| unreachable!("{id} was described with {O} outputs"))
}

/// Which pass (its `[rows, n]` output in the product's format).
#[derive(Debug, Clone, Copy)]
enum Pass {
    /// y, b in; gelu(y + b) out.
    Forward,
    /// dh, y, b in; dh · gelu'(y + b) and the row groups' column sums of it out.
    Backward,
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        match *self {
            Pass::Forward => {
                let [y, b] = side::contiguous_inputs::<2>(handles, desc);
                launch(None, &y, &b).unwrap_or_else(|why| {
                    fell_back(&why);
                    vec![side::inner(forward_decomposed::<Inner>(float(y), float(b)))]
                })
            }
            Pass::Backward => {
                let [dh, y, b] = side::contiguous_inputs::<3>(handles, desc);
                launch(Some(&dh), &y, &b).unwrap_or_else(|why| {
                    fell_back(&why);
                    // The registered shape holds one row per group.
                    let (rows, n) = (y.meta.shape()[0], y.meta.shape()[1]);
                    let groups = backward_groups(rows, n, y.dtype);
                    let (dy, db) = backward_decomposed::<Inner>(float(dh), float(y), float(b));
                    vec![side::inner(dy), side::as_partial_sums(db, groups)]
                })
            }
        }
    }
}

/// The kernels' source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::GELU))
}

/// Launches the forward pass (`dh` `None`: gelu(y + b)) or the backward pass (`dh · gelu'(y + b)` and the
/// row groups' column sums) over contiguous `y` `[rows, n]`, returning the results in `y`'s format (the
/// sums in f32); an error says why it could not (nothing was written that the caller keeps, so it may run
/// burn's operations).
fn launch(dh: Option<&Primitive>, y: &Primitive, b: &Primitive) -> Result<Vec<Primitive>, String> {
    if b.dtype != DType::F32 || dh.is_some_and(|dh| dh.dtype != y.dtype) {
        return Err(format!(
            "operands {:?} (bias), {:?} (product), {:?} (gradient): the kernels take an f32 bias and the \
             gradient in the product's format",
            b.dtype,
            y.dtype,
            dh.map(|t| t.dtype)
        ));
    }
    let shape = y.meta.shape();
    let (rows, n) = (shape[0], shape[1]);
    let width = width(n, y.dtype);
    let chunks = chunks(n, width);
    let g = groups(rows, chunks, dh.is_some());
    // The entry points' name for the product's type, and its C type.
    let (kind, element) = match y.dtype {
        DType::F32 => ("f32", "float"),
        DType::BF16 => ("bf16", "u16"),
        other => return Err(format!("{other:?} product (the kernels take f32 or bf16)")),
    };
    let family = format!("{kind}_{width}");
    let sizes = Sizes {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        n: i32::try_from(n).map_err(|_| format!("width {n}"))?,
        groups: i32::try_from(g).map_err(|_| "row groups".to_string())?,
    };
    let result = empty_packed(y, vec![rows, n], y.dtype);
    let bind = |t: &Primitive| t.handle.clone().binding();
    let (entry, results, buffers) = match dh {
        None => (
            "forward",
            vec![result.clone()],
            vec![bind(y), bind(b), bind(&result)],
        ),
        Some(dh) => {
            let sums = empty_f32(y, vec![g, n]);
            let buffers = vec![bind(dh), bind(y), bind(b), bind(&result), bind(&sums)];
            ("backward", vec![result, sums], buffers)
        }
    };
    // One warp a column chunk of a row group.
    let blocks = (chunks * g).div_ceil(THREADS as usize / 32);
    let name = format!("umgen_gelu_{entry}_{family}");
    let blocks = u32::try_from(blocks).map_err(|_| format!("{name}: {blocks} blocks"))?;
    // SAFETY: every buffer is bound (cubecl keeps it alive for the launch) and packed: `y`, `dh` and the
    // result `rows × n`, `b` `n`, the sums `groups × n`, as the kernel indexes them; a width above 1 only
    // where `n` is a multiple of it, so every 16-byte access (of `y`, `dh` and the result, and of the f32
    // bias where its `V` values fill 16 bytes) is aligned.
    unsafe {
        side::launch_bound_on_cubecl(
            y,
            &name,
            (&format!("GELU_KERNELS({family}, {width}, {element})"), &source),
            ((blocks, 1, 1), THREADS),
            buffers,
            &sizes,
        )
    }?;
    Ok(results)
}
