//! [`FusedNorm`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `norm.cu`'s kernels (compiled with NVRTC) on cubecl's stream with their
//! buffers bound to the launch (so the training thread queues them without waiting), or on a side stream
//! ordered with cubecl's with `train.kernels.stream = "side"` ([`crate::side`]), unless `train.kernels.norm =
//! "burn"`. The input is f32 or a kept bf16 copy; a forward pass asked for a bf16 copy of its f32 input
//! writes it in the same kernel. Rows wider than 1,024, other types, or a failure to compile or launch run
//! the decomposition instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

use super::{FusedNorm, NormKernel, Normed, backward_decomposed, fell_back, forward_decomposed};
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
    (!matches!(x.dtype(), DType::F32 | DType::BF16))
        .then(|| format!("{:?} input (the kernels take f32 or bf16)", x.dtype()))
}

impl FusedNorm for Cuda {
    fn norm_forward(
        x: Tensor<Self, 2>,
        gamma: Tensor<Self, 1>,
        beta: Tensor<Self, 1>,
        eps: f64,
        (out, keep): (FloatDType, Option<FloatDType>),
        kernels: &Kernels,
    ) -> Normed<Self> {
        if kernels.norm == NormKernel::Burn {
            return forward_decomposed(x, gamma, beta, eps, (out, keep));
        }
        if let Some(why) = refused(&x) {
            fell_back(&why);
            return forward_decomposed(x, gamma, beta, eps, (out, keep));
        }
        let [rows, d] = x.dims();
        let pass = Pass::Forward {
            eps: eps as f32,
            out,
            keep,
            kernels: *kernels,
        };
        let inputs = vec![side::fused(x), side::fused(gamma), side::fused(beta)];
        let mut outputs = vec![
            (vec![rows, d], DType::from(out)),
            (vec![rows], DType::F32),
            (vec![rows], DType::F32),
        ];
        outputs.extend(keep.map(|f| (vec![rows, d], DType::from(f))));
        let mut results = side::register_typed("umgen_norm_forward", inputs, outputs, pass).into_iter();
        let mut next = || {
            results
                .next()
                .unwrap_or_else(|| unreachable!("umgen_norm_forward was described with its outputs"))
        };
        let (y, mean, rstd) = (float(next()), float(next()), float(next()));
        let kept = keep.map(|_| float(next()));
        Normed { y, mean, rstd, kept }
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
    /// x, γ, β in; y (in `out`'s format), mean, rstd and, with `keep`, x in that format out.
    Forward {
        eps: f32,
        out: FloatDType,
        keep: Option<FloatDType>,
        kernels: Kernels,
    },
    /// dy, x, mean, rstd, γ in; dx and the warps' column sums of dy · x̂ and dy out.
    Backward { kernels: Kernels },
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        match *self {
            Pass::Forward {
                eps,
                out,
                keep,
                kernels,
            } => {
                // Registered with a fourth output where it keeps a copy.
                let [x, gamma, beta] = match keep {
                    Some(_) => side::contiguous_inputs::<3, 4>(handles, desc),
                    None => side::contiguous_inputs::<3, 3>(handles, desc),
                };
                let formats = Formats { eps, out, keep };
                launch(&x, &gamma, Some(&beta), None, formats, &kernels).unwrap_or_else(|why| {
                    fell_back(&why);
                    let normed = forward_decomposed::<Inner>(
                        float(x),
                        float(gamma),
                        float(beta),
                        f64::from(eps),
                        (out, keep),
                    );
                    let mut results = vec![
                        side::inner(normed.y),
                        side::inner(normed.mean),
                        side::inner(normed.rstd),
                    ];
                    results.extend(normed.kept.map(side::inner));
                    results
                })
            }
            Pass::Backward { kernels } => {
                let [dy, x, mean, rstd, gamma] = side::contiguous_inputs::<5, 3>(handles, desc);
                let grads = Some([&dy, &mean, &rstd]);
                launch(&x, &gamma, None, grads, Formats::BACKWARD, &kernels).unwrap_or_else(|why| {
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

/// A pass's scalars and formats: ε, the output's format and the kept copy's (forward).
#[derive(Debug, Clone, Copy)]
struct Formats {
    eps: f32,
    out: FloatDType,
    keep: Option<FloatDType>,
}

impl Formats {
    /// The backward pass's: f32 results, nothing kept.
    const BACKWARD: Self = Self {
        eps: 0.0,
        out: FloatDType::F32,
        keep: None,
    };
}

/// Runs the forward pass on contiguous `x` `[rows, d]` (f32 or bf16), γ and β (`grads` `None`: y in
/// `out`'s format, mean, rstd, and x in `keep`'s format where asked) or the backward pass (`grads` =
/// `[dy, mean, rstd]`: dx and the warps' column sums), returning the results; an error says why it could
/// not (no result was written that the caller keeps, so it may run the decomposition). On cubecl's stream
/// the kernels are launched from this thread with their buffers bound ([`launch_bound`]); with
/// `train.kernels.stream = "side"` their pointers are fetched and they are launched on cubecl's device
/// thread ([`launch_with_pointers`]), on f32 only (a bf16 input widened and a kept copy cast around them).
fn launch(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    formats: Formats,
    kernels: &Kernels,
) -> Result<Vec<Primitive>, String> {
    let mut operands = vec![gamma];
    operands.extend(beta);
    operands.extend(grads.into_iter().flatten());
    if let Some(t) = operands.iter().find(|t| t.dtype != DType::F32) {
        return Err(format!("{:?} operand (the layer-norm kernels take f32)", t.dtype));
    }
    if !matches!(x.dtype, DType::F32 | DType::BF16) {
        return Err(format!(
            "{:?} input (the layer-norm kernels take f32 or bf16)",
            x.dtype
        ));
    }
    let shape = x.meta.shape();
    let (rows, d) = (shape[0], shape[1]);
    let per = per_lane(d).ok_or_else(|| format!("rows of {d}"))?;
    let sizes = Sizes {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        d: i32::try_from(d).map_err(|_| format!("width {d}"))?,
        eps: formats.eps,
    };
    if kernels.stream == KernelStream::Cubecl {
        return launch_bound(x, gamma, beta, grads, (per, sizes), formats);
    }
    let wide = |t: &Primitive| side::inner(float::<Inner, 2>(t.clone()).cast(FloatDType::F32));
    let x32 = wide(x);
    let mut results = side::on_device_thread(x, kernels.launch_thread, || {
        launch_with_pointers(&x32, gamma, beta, grads, (per, sizes), kernels)
    })?;
    // The side stream's kernels write f32 only.
    if formats.out != FloatDType::F32 {
        results[0] = side::inner(float::<Inner, 2>(results[0].clone()).cast(formats.out));
    }
    if let Some(keep) = formats.keep.filter(|_| grads.is_none()) {
        results.push(side::inner(float::<Inner, 2>(x.clone()).cast(keep)));
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

/// The kernels' name for a format: `32` or `16` (bf16).
fn bits(format: DType) -> Result<&'static str, String> {
    match format {
        DType::F32 => Ok("32"),
        DType::BF16 => Ok("16"),
        other => Err(format!("{other:?} (the layer-norm kernels take f32 or bf16)")),
    }
}

/// [`launch`] on cubecl's stream with the buffers bound to the launch (`NORM_BOUND_KERNELS`): cubecl resolves
/// them as it launches, so this thread neither fetches pointers nor waits for cubecl's device thread.
fn launch_bound(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    (per, sizes): (usize, Sizes),
    Formats { out, keep, .. }: Formats,
) -> Result<Vec<Primitive>, String> {
    let rows = x.meta.shape()[0];
    let bind = |t: &Primitive| t.handle.clone().binding();
    let xs = bits(x.dtype)?;
    let (results, buffers, entry, blocks) = match (beta, grads) {
        (Some(beta), None) => {
            let ys = bits(DType::from(out))?;
            // A kept copy: bf16 of an f32 input, the one the kernels write.
            let kept = match keep.map(DType::from) {
                None => "",
                Some(DType::BF16) if x.dtype == DType::F32 => "_keep",
                Some(other) => return Err(format!("a {other:?} copy of a {:?} input", x.dtype)),
            };
            let mut results = results(x, false, out);
            let [r, d] = [x.meta.shape()[0], x.meta.shape()[1]];
            results.extend(keep.map(|f| empty_packed(x, vec![r, d], DType::from(f))));
            let buffers = [x, gamma, beta].into_iter().chain(&results).map(bind).collect();
            let entry = format!("umgen_norm_forward_bound_x{xs}_y{ys}{kept}_{per}");
            (results, buffers, entry, rows.div_ceil(WARPS))
        }
        (None, Some([dy, mean, rstd])) => {
            let warps = backward_warps(rows);
            let results = results(x, true, FloatDType::F32);
            let inputs = [dy, x, mean, rstd, gamma];
            let buffers = inputs.into_iter().chain(&results).map(bind).collect();
            let entry = format!("umgen_norm_backward_bound_x{xs}_{per}");
            (results, buffers, entry, warps / WARPS)
        }
        _ => return Err("a pass takes β (forward) or the gradients (backward)".into()),
    };
    let blocks = u32::try_from(blocks).map_err(|_| format!("{blocks} blocks"))?;
    // SAFETY: every buffer is bound (cubecl keeps it alive for the launch), contiguous and of the shape and
    // format the kernel reads or writes (`rows × d`, `rows`, `d`, or one row per warp of the grid; the
    // entry point is chosen by the formats).
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
