//! [`FusedGelu`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `gelu.cu`'s kernel on cubecl's stream with its buffers bound to the launch
//! (as AdamW's kernels are), so the training thread queues it without a call to cubecl's device thread
//! and without waiting, unless `train.gelu = "burn"` ([`super::select`]). Other types than f32, empty
//! inputs, or a failure to compile or launch (the first launch of each kernel is checked) run burn's
//! operations instead, counted by [`super::fallbacks`]. The kernels always run on cubecl's stream, whatever
//! `train.kernel_stream` says: a bound launch needs no device pointers and no ordering.
#![allow(unsafe_code)]

use super::{FusedGelu, GeluKernel, backward_decomposed, fell_back, forward_decomposed, selected};
use crate::attention::float;
use crate::side::{self, Handles, Inner, Primitive, empty_f32, empty_packed};
use burn::backend::Cuda;
use burn::tensor::{DType, FloatDType, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;

/// Threads a block (the kernels' `__launch_bounds__(256)`).
const THREADS: u32 = 256;

/// Blocks of the forward pass at most; the kernel loops over the rest.
const FORWARD_BLOCKS: usize = 8192;

/// Row groups of the backward pass at most: each writes one row of the bias's column sums, which the
/// caller adds (256 rows of `n`), while a `[70,368, 1,536]` pass keeps 3,072 warps busy.
const GROUPS: usize = 256;

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
    (y.dtype() != DType::F32).then(|| format!("{:?} product (the kernels take f32)", y.dtype()))
}

impl FusedGelu for Cuda {
    fn bias_gelu_forward(y: Tensor<Self, 2>, b: Tensor<Self, 1>, out: FloatDType) -> Tensor<Self, 2> {
        if selected() == GeluKernel::Burn {
            return forward_decomposed(y, b, out);
        }
        if let Some(why) = refused(&y) {
            fell_back(&why);
            return forward_decomposed(y, b, out);
        }
        let shape = y.dims().to_vec();
        let inputs = vec![side::fused(y), side::fused(b)];
        let outputs = vec![(shape, DType::from(out))];
        let [h] = register(Pass::Forward { out }, inputs, outputs);
        float(h)
    }

    fn bias_gelu_backward(
        dh: Tensor<Self, 2>,
        y: Tensor<Self, 2>,
        b: Tensor<Self, 1>,
        out: FloatDType,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>) {
        // The forward pass counted a refusal.
        if selected() == GeluKernel::Burn || refused(&y).is_some() {
            return backward_decomposed(dh, y, b, out);
        }
        let [rows, n] = y.dims();
        let inputs = vec![
            side::fused(dh.cast(FloatDType::F32)),
            side::fused(y),
            side::fused(b),
        ];
        let outputs = vec![
            (vec![rows, n], DType::from(out)),
            (vec![groups(rows), n], DType::F32),
        ];
        let [dy, sums] = register(Pass::Backward { out }, inputs, outputs);
        (float(dy), crate::rows::sum(float::<Cuda, 2>(sums)))
    }
}

/// Row groups of the backward pass over `rows` rows.
fn groups(rows: usize) -> usize {
    rows.min(GROUPS)
}

/// Registers `pass` on the fusion stream.
fn register<const O: usize>(
    pass: Pass,
    inputs: Vec<burn::tensor::ops::FloatTensor<Cuda>>,
    outputs: Vec<(Vec<usize>, DType)>,
) -> [burn::tensor::ops::FloatTensor<Cuda>; O] {
    let id = match pass {
        Pass::Forward { .. } => "umgen_gelu_forward",
        Pass::Backward { .. } => "umgen_gelu_backward",
    };
    side::register_typed(id, inputs, outputs, pass)
        .try_into()
        .unwrap_or_else(|_| unreachable!("{id} was described with {O} outputs"))
}

/// Which pass, and the format of its `[rows, n]` output.
#[derive(Debug, Clone, Copy)]
enum Pass {
    /// y, b in; gelu(y + b) out.
    Forward { out: FloatDType },
    /// dh, y, b in; dh · gelu'(y + b) and the row groups' column sums of it out.
    Backward { out: FloatDType },
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        match *self {
            Pass::Forward { out } => {
                let [y, b] = side::contiguous_inputs::<2, 1>(handles, desc);
                launch(None, &y, &b, out).unwrap_or_else(|why| {
                    fell_back(&why);
                    vec![side::inner(forward_decomposed::<Inner>(float(y), float(b), out))]
                })
            }
            Pass::Backward { out } => {
                let [dh, y, b] = side::contiguous_inputs::<3, 2>(handles, desc);
                launch(Some(&dh), &y, &b, out).unwrap_or_else(|why| {
                    fell_back(&why);
                    let rows = y.meta.shape()[0];
                    let (dy, db) = backward_decomposed::<Inner>(float(dh), float(y), float(b), out);
                    // The registered shape holds one row per group.
                    vec![side::inner(dy), side::as_partial_sums(db, groups(rows))]
                })
            }
        }
    }
}

/// The kernels' source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(include_str!("gelu.cu")))
}

/// Launches the forward pass (`dh` `None`: gelu(y + b)) or the backward pass (`dh · gelu'(y + b)` and the
/// row groups' column sums) over contiguous `y` `[rows, n]`, returning the results in `out` (the sums in
/// f32); an error says why it could not (nothing was written that the caller keeps, so it may run burn's
/// operations).
fn launch(
    dh: Option<&Primitive>,
    y: &Primitive,
    b: &Primitive,
    out: FloatDType,
) -> Result<Vec<Primitive>, String> {
    let operands = [Some(y), Some(b), dh];
    if let Some(t) = operands.into_iter().flatten().find(|t| t.dtype != DType::F32) {
        return Err(format!(
            "{:?} operand (the bias + GELU kernels take f32)",
            t.dtype
        ));
    }
    let shape = y.meta.shape();
    let (rows, n) = (shape[0], shape[1]);
    let width = if n % 4 == 0 { 4 } else { 1 };
    // The entry points' name for the output type, and its C type.
    let (kind, element) = match out {
        FloatDType::F32 => ("f32", "float"),
        FloatDType::BF16 => ("bf16", "u16"),
        other => return Err(format!("{other:?} output (the kernels write f32 or bf16)")),
    };
    let family = format!("{kind}_{width}");
    let sizes = Sizes {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        n: i32::try_from(n).map_err(|_| format!("width {n}"))?,
        groups: i32::try_from(groups(rows)).map_err(|_| "row groups".to_string())?,
    };
    let result = empty_packed(y, vec![rows, n], DType::from(out));
    let bind = |t: &Primitive| t.handle.clone().binding();
    let (entry, results, buffers, blocks) = match dh {
        None => {
            let pieces = (rows * n / width).div_ceil(THREADS as usize);
            let buffers = vec![bind(y), bind(b), bind(&result)];
            ("forward", vec![result], buffers, pieces.clamp(1, FORWARD_BLOCKS))
        }
        Some(dh) => {
            let sums = empty_f32(y, vec![groups(rows), n]);
            let warps = n.div_ceil(32 * width) * groups(rows);
            let buffers = vec![bind(dh), bind(y), bind(b), bind(&result), bind(&sums)];
            (
                "backward",
                vec![result, sums],
                buffers,
                warps.div_ceil(THREADS as usize / 32),
            )
        }
    };
    let name = format!("umgen_gelu_{entry}_{family}");
    let blocks = u32::try_from(blocks).map_err(|_| format!("{name}: {blocks} blocks"))?;
    // SAFETY: every buffer is bound (cubecl keeps it alive for the launch) and packed: `y`, `dh` and the
    // result `rows × n`, `b` `n`, the sums `groups × n`, as the kernel indexes them; a width of 4 only
    // where `n` is a multiple of 4, so every 16-byte access is aligned.
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
