//! [`FusedNorm`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `norm.cu`'s kernels (compiled with NVRTC) on cubecl's stream with their
//! buffers bound to the launch (so the training thread queues them without waiting), or on a side stream
//! ordered with cubecl's with `train.kernels.stream = "side"` ([`crate::side`]), unless `train.kernels.norm =
//! "burn"`. Rows wider than 1,024, other types than f32, or a failure to compile or
//! launch run the decomposition instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

use super::{FusedNorm, NormKernel, backward_decomposed, fell_back, forward_decomposed};
use crate::format::float;
use crate::kernels::{KernelStream, Kernels, SideFamily};
use crate::side::{self, Compiled, Handles, Inner, KernelCache, Primitive, empty_f32, empty_packed};
use burn::backend::Cuda;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, FloatDType, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;
use cudarc::nvrtc::CompileOptions;
use std::cell::RefCell;

/// Values a lane keeps of its row, one kernel each: rows up to 32 times as wide.
const PER_LANE: [usize; 6] = [4, 8, 12, 16, 24, 32];

/// Warps a block (the kernels' `__launch_bounds__(256)`).
const WARPS: usize = 8;

/// Blocks of the backward kernel: each warp loops over rows and writes one row of column sums, so this
/// bounds the sums the caller adds (8,192 rows of `d`) while filling an H100 (132 SMs) in one wave.
const BACKWARD_BLOCKS: usize = 1024;

/// `NormSizes` of `norm.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Sizes {
    rows: i64,
    d: i32,
    eps: f32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Sizes {}

/// `NormParams` of `norm.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct Params {
    x: u64,
    gamma: u64,
    beta: u64,
    dy: u64,
    mean: u64,
    rstd: u64,
    y: u64,
    mean_out: u64,
    rstd_out: u64,
    dx: u64,
    dgamma: u64,
    dbeta: u64,
    rows: i64,
    d: i32,
    eps: f32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Params {}

/// The kernels' per-lane capacity for rows of `d`, if one takes them.
fn per_lane(d: usize) -> Option<usize> {
    PER_LANE.into_iter().find(|&p| 32 * p >= d)
}

/// Why the kernels cannot take `x` `[rows, d]`, if they cannot.
fn refused(x: &Tensor<Cuda, 2>) -> Option<String> {
    let [rows, d] = x.dims();
    if rows == 0 || d == 0 {
        return Some(format!("an empty input [{rows}, {d}]"));
    }
    if per_lane(d).is_none() {
        return Some(format!("rows of {d} (the kernels take up to 1,024)"));
    }
    (x.dtype() != DType::F32).then(|| format!("{:?} input (the kernels take f32)", x.dtype()))
}

impl FusedNorm for Cuda {
    fn norm_forward(
        x: Tensor<Self, 2>,
        gamma: Tensor<Self, 1>,
        beta: Tensor<Self, 1>,
        eps: f64,
        out: FloatDType,
        kernels: &Kernels,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>) {
        if kernels.norm == NormKernel::Burn {
            return forward_decomposed(x, gamma, beta, eps, out);
        }
        if let Some(why) = refused(&x) {
            fell_back(&why);
            return forward_decomposed(x, gamma, beta, eps, out);
        }
        let [rows, d] = x.dims();
        let pass = Pass::Forward {
            eps: eps as f32,
            out,
            kernels: *kernels,
        };
        let inputs = vec![side::fused(x), side::fused(gamma), side::fused(beta)];
        let outputs = vec![
            (vec![rows, d], DType::from(out)),
            (vec![rows], DType::F32),
            (vec![rows], DType::F32),
        ];
        let [y, mean, rstd]: [FloatTensor<Cuda>; 3] =
            side::register_typed("umgen_norm_forward", inputs, outputs, pass)
                .try_into()
                .unwrap_or_else(|_| unreachable!("umgen_norm_forward was described with three outputs"));
        (float(y), float(mean), float(rstd))
    }

    fn norm_backward(
        dy: Tensor<Self, 2>,
        x: Tensor<Self, 2>,
        mean: Tensor<Self, 1>,
        rstd: Tensor<Self, 1>,
        gamma: Tensor<Self, 1>,
        kernels: &Kernels,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>) {
        // The forward pass counted a refusal.
        if kernels.norm == NormKernel::Burn || refused(&x).is_some() {
            return backward_decomposed(dy, x, mean, rstd, gamma);
        }
        let [rows, d] = x.dims();
        let warps = backward_warps(rows);
        let inputs = [
            side::fused(dy),
            side::fused(x),
            side::fused(mean),
            side::fused(rstd),
            side::fused(gamma),
        ];
        let [dx, dgamma, dbeta] =
            register_backward(inputs, [vec![rows, d], vec![warps, d], vec![warps, d]], kernels);
        let sum = |t| crate::rows::sum(float::<Cuda, 2>(t));
        (float(dx), sum(dgamma), sum(dbeta))
    }
}

/// Warps of the backward kernel's grid for `rows` rows (each writes a row of column sums).
fn backward_warps(rows: usize) -> usize {
    rows.div_ceil(WARPS).min(BACKWARD_BLOCKS) * WARPS
}

/// Registers the backward pass on the fusion stream: `inputs` in, f32 outputs of `shapes` out.
fn register_backward<const I: usize, const O: usize>(
    inputs: [FloatTensor<Cuda>; I],
    shapes: [Vec<usize>; O],
    kernels: &Kernels,
) -> [FloatTensor<Cuda>; O] {
    let pass = Pass::Backward { kernels: *kernels };
    side::register("umgen_norm_backward", inputs, shapes, pass)
}

/// Which pass.
#[derive(Debug, Clone, Copy)]
enum Pass {
    /// x, γ, β in; y (in `out`'s format), mean, rstd out.
    Forward {
        eps: f32,
        out: FloatDType,
        kernels: Kernels,
    },
    /// dy, x, mean, rstd, γ in; dx and the warps' column sums of dy · x̂ and dy out.
    Backward { kernels: Kernels },
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        match *self {
            Pass::Forward { eps, out, kernels } => {
                let [x, gamma, beta] = side::contiguous_inputs::<3, 3>(handles, desc);
                launch(&x, &gamma, Some(&beta), None, (eps, out), &kernels).unwrap_or_else(|why| {
                    fell_back(&why);
                    let (y, mean, rstd) =
                        forward_decomposed::<Inner>(float(x), float(gamma), float(beta), f64::from(eps), out);
                    vec![side::inner(y), side::inner(mean), side::inner(rstd)]
                })
            }
            Pass::Backward { kernels } => {
                let [dy, x, mean, rstd, gamma] = side::contiguous_inputs::<5, 3>(handles, desc);
                let grads = Some([&dy, &mean, &rstd]);
                launch(&x, &gamma, None, grads, (0.0, FloatDType::F32), &kernels).unwrap_or_else(|why| {
                    fell_back(&why);
                    let warps = backward_warps(x.meta.shape()[0]);
                    let (dx, dgamma, dbeta) = backward_decomposed::<Inner>(
                        float(dy),
                        float(x),
                        float(mean),
                        float(rstd),
                        float(gamma),
                    );
                    // The registered shapes hold one row per warp.
                    let rows = |t| side::as_partial_sums(t, warps);
                    vec![side::inner(dx), rows(dgamma), rows(dbeta)]
                })
            }
        }
    }
}

thread_local! {
    /// This thread's kernels by device.
    static KERNELS: KernelCache = const { RefCell::new(Vec::new()) };
}

/// Compiles the kernels for `like`'s device.
fn build(like: &Primitive) -> Result<Compiled, String> {
    let names: Vec<String> = PER_LANE
        .iter()
        .flat_map(|p| {
            [
                format!("umgen_norm_forward_{p}"),
                format!("umgen_norm_backward_{p}"),
            ]
        })
        .collect();
    Compiled::compile(like, source()?, |_| CompileOptions::default(), &names, 0)
}

/// The kernels' source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::NORM))
}

/// Runs the forward pass on contiguous `x` `[rows, d]`, γ and β (`grads` `None`: y in `out`'s format,
/// mean, rstd) or the backward pass (`grads` = `[dy, mean, rstd]`: dx and the warps' column sums),
/// returning the results; an error says why it could not (no result was written that the caller keeps, so
/// it may run the decomposition). On cubecl's stream the kernels are launched from this thread with their
/// buffers bound ([`launch_bound`]); with `train.kernels.stream = "side"` their pointers are fetched and they
/// are launched on cubecl's device thread ([`launch_with_pointers`]).
fn launch(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    (eps, out): (f32, FloatDType),
    kernels: &Kernels,
) -> Result<Vec<Primitive>, String> {
    let mut operands = vec![x, gamma];
    operands.extend(beta);
    operands.extend(grads.into_iter().flatten());
    if let Some(t) = operands.iter().find(|t| t.dtype != DType::F32) {
        return Err(format!("{:?} operand (the layer-norm kernels take f32)", t.dtype));
    }
    let shape = x.meta.shape();
    let (rows, d) = (shape[0], shape[1]);
    let per = per_lane(d).ok_or_else(|| format!("rows of {d}"))?;
    let sizes = Sizes {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        d: i32::try_from(d).map_err(|_| format!("width {d}"))?,
        eps,
    };
    if kernels.stream == KernelStream::Cubecl {
        return launch_bound(x, gamma, beta, grads, per, sizes, out);
    }
    let mut results = side::on_device_thread(x, kernels.launch_thread, || {
        launch_with_pointers(x, gamma, beta, grads, (per, sizes), kernels)
    })?;
    // The side stream's kernels write f32 only.
    if out != FloatDType::F32 {
        results[0] = side::inner(float::<Inner, 2>(results[0].clone()).cast(out));
    }
    Ok(results)
}

/// [`launch`] on the side stream: the kernel takes [`Params`], the buffers' device pointers.
fn launch_with_pointers(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    (per, sizes): (usize, Sizes),
    kernels: &Kernels,
) -> Result<Vec<Primitive>, String> {
    let rows = x.meta.shape()[0];
    let mut p = Params {
        rows: sizes.rows,
        d: sizes.d,
        eps: sizes.eps,
        ..Params::default()
    };
    // The pointers, and what keeps the buffers alive until the launch is queued.
    let mut keep = side::Pointers::default();
    let mut ptr = |t: &Primitive| keep.of(t);
    (p.x, p.gamma) = (ptr(x)?, ptr(gamma)?);
    let (results, name, blocks) = match (beta, grads) {
        (Some(beta), None) => {
            p.beta = ptr(beta)?;
            let results = results(x, false, FloatDType::F32);
            (p.y, p.mean_out, p.rstd_out) = (ptr(&results[0])?, ptr(&results[1])?, ptr(&results[2])?);
            (results, format!("umgen_norm_forward_{per}"), rows.div_ceil(WARPS))
        }
        (None, Some([dy, mean, rstd])) => {
            (p.dy, p.mean, p.rstd) = (ptr(dy)?, ptr(mean)?, ptr(rstd)?);
            let warps = backward_warps(rows);
            let results = results(x, true, FloatDType::F32);
            (p.dx, p.dgamma, p.dbeta) = (ptr(&results[0])?, ptr(&results[1])?, ptr(&results[2])?);
            (results, format!("umgen_norm_backward_{per}"), warps / WARPS)
        }
        _ => return Err("a pass takes β (forward) or the gradients (backward)".into()),
    };
    // SAFETY: every pointer in `p` is a live contiguous buffer (kept by `keep`) of the shape the kernel reads or
    // writes (`rows × d`, `rows`, `d`, or one row per warp of the grid).
    unsafe {
        side::launch_kernel(
            (&KERNELS, kernels),
            x,
            (SideFamily::LayerNorm, &|| build(x)),
            &name,
            (&format!("NORM_KERNELS({per})"), &source),
            (blocks, 32 * WARPS as u32),
            &p,
        )
    }?;
    drop(keep);
    Ok(results)
}

/// [`launch`] on cubecl's stream with the buffers bound to the launch (`NORM_BOUND_KERNELS`): cubecl resolves
/// them as it launches, so this thread neither fetches pointers nor waits for cubecl's device thread.
fn launch_bound(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    per: usize,
    sizes: Sizes,
    out: FloatDType,
) -> Result<Vec<Primitive>, String> {
    let rows = x.meta.shape()[0];
    let bind = |t: &Primitive| t.handle.clone().binding();
    let (results, buffers, entry, blocks) = match (beta, grads) {
        (Some(beta), None) => {
            let format = match out {
                FloatDType::F32 => "",
                FloatDType::BF16 => "bf16_",
                other => {
                    return Err(format!(
                        "a {other:?} output (the layer-norm kernels write f32 or bf16)"
                    ));
                }
            };
            let results = results(x, false, out);
            let buffers = [x, gamma, beta].into_iter().chain(&results).map(bind).collect();
            let entry = format!("umgen_norm_forward_bound_{format}{per}");
            (results, buffers, entry, rows.div_ceil(WARPS))
        }
        (None, Some([dy, mean, rstd])) => {
            let warps = backward_warps(rows);
            let results = results(x, true, FloatDType::F32);
            let inputs = [dy, x, mean, rstd, gamma];
            let buffers = inputs.into_iter().chain(&results).map(bind).collect();
            (
                results,
                buffers,
                format!("umgen_norm_backward_bound_{per}"),
                warps / WARPS,
            )
        }
        _ => return Err("a pass takes β (forward) or the gradients (backward)".into()),
    };
    let blocks = u32::try_from(blocks).map_err(|_| format!("{blocks} blocks"))?;
    // SAFETY: every buffer is bound (cubecl keeps it alive for the launch), contiguous and of the shape the
    // kernel reads or writes (`rows × d`, `rows`, `d`, or one row per warp of the grid).
    unsafe {
        side::launch_bound_on_cubecl(
            x,
            &entry,
            (&format!("NORM_BOUND_KERNELS({per})"), &source),
            ((blocks, 1, 1), 32 * WARPS as u32),
            buffers,
            &sizes,
        )
    }?;
    Ok(results)
}

/// The results of a pass over `x` `[rows, d]`, packed: y (in `out`'s format), the rows' means and `1/σ`
/// (forward), or dx (f32) and one row of column sums per warp of the grid for the scale and the shift
/// (`backward`).
fn results(x: &Primitive, backward: bool, out: FloatDType) -> Vec<Primitive> {
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
