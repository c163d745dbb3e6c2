//! [`FusedNorm`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `norm.cu`'s kernels (compiled with NVRTC) on cubecl's stream with their
//! buffers bound to the launch (so the training thread queues them without waiting), or on a side stream
//! ordered with cubecl's with `train.kernels.stream = "side"` ([`crate::side`]), unless `train.kernels.norm =
//! "burn"`. The input is f32 or a kept bf16 copy; a forward pass asked for a bf16 copy of its f32 input
//! writes it in the same kernel. Rows wider than 1,024, other types, or a failure to compile or launch run
//! the decomposition instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

mod geometry;
mod pointers;

use super::{FusedNorm, NormKernel, Normed, backward_decomposed, fell_back, forward_decomposed, plus};
use crate::format::float;
use crate::kernels::{KernelStream, Kernels};
use crate::side::{self, Handles, Inner, Primitive, empty_packed};
use burn::backend::Cuda;
use burn::tensor::{DType, FloatDType, Tensor};
use burn_ir::CustomOpIr;
use geometry::{Sizes, WARPS, backward_warps, per_lane, results, source};

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
        (x, mean, rstd): (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>),
        gamma: Tensor<Self, 1>,
        dres: Option<Tensor<Self, 2>>,
        kernels: &Kernels,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>) {
        // The forward pass counted a refusal.
        if kernels.norm == NormKernel::Burn || refused(&x).is_some() {
            let (dx, dgamma, dbeta) = backward_decomposed(dy, x, mean, rstd, gamma);
            return (plus(dx, dres), dgamma, dbeta);
        }
        let [rows, d] = x.dims();
        let warps = backward_warps(rows);
        let residual = dres.is_some();
        let mut inputs = vec![
            side::fused(dy),
            side::fused(x),
            side::fused(mean),
            side::fused(rstd),
            side::fused(gamma),
        ];
        inputs.extend(dres.map(|r| side::fused(r.cast(FloatDType::F32))));
        let pass = Pass::Backward {
            kernels: *kernels,
            residual,
        };
        let shapes = vec![vec![rows, d], vec![warps, d], vec![warps, d]];
        let mut results = side::register_many("umgen_norm_backward", inputs, shapes, pass).into_iter();
        let mut next = || {
            results
                .next()
                .unwrap_or_else(|| unreachable!("umgen_norm_backward was described with three outputs"))
        };
        let (dx, dgamma, dbeta) = (next(), next(), next());
        let sum = |t| crate::rows::sum(float::<Cuda, 2>(t));
        (float(dx), sum(dgamma), sum(dbeta))
    }
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
    /// dy, x, mean, rstd, γ (and, with `residual`, the residual stream's gradient) in; dx (plus that
    /// gradient) and the warps' column sums of dy · x̂ and dy out.
    Backward { kernels: Kernels, residual: bool },
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
                let [x, gamma, beta] = side::contiguous_inputs(handles, desc);
                let formats = Formats { eps, out, keep };
                launch(&x, &gamma, Some(&beta), None, None, formats, &kernels).unwrap_or_else(|why| {
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
            Pass::Backward { kernels, residual } => {
                let (dy, x, mean, rstd, gamma, dres) = if residual {
                    let [dy, x, mean, rstd, gamma, dres] = side::contiguous_inputs::<6>(handles, desc);
                    (dy, x, mean, rstd, gamma, Some(dres))
                } else {
                    let [dy, x, mean, rstd, gamma] = side::contiguous_inputs::<5>(handles, desc);
                    (dy, x, mean, rstd, gamma, None)
                };
                let grads = Some([&dy, &mean, &rstd]);
                let formats = Formats::BACKWARD;
                launch(&x, &gamma, None, grads, dres.as_ref(), formats, &kernels).unwrap_or_else(|why| {
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
                    let dx = plus(dx, dres.map(float));
                    vec![side::inner(dx), rows(dgamma), rows(dbeta)]
                })
            }
        }
    }
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
/// `[dy, mean, rstd]`: dx, plus `dres` where given, and the warps' column sums), returning the results; an
/// error says why it could not (no result was written that the caller keeps, so it may run the
/// decomposition). On cubecl's stream
/// the kernels are launched from this thread with their buffers bound ([`launch_bound`]); with
/// `train.kernels.stream = "side"` their pointers are fetched and they are launched on cubecl's device
/// thread ([`pointers::launch`]), on f32 only (a bf16 input widened and a kept copy cast around them).
fn launch(
    x: &Primitive,
    gamma: &Primitive,
    beta: Option<&Primitive>,
    grads: Option<[&Primitive; 3]>,
    dres: Option<&Primitive>,
    formats: Formats,
    kernels: &Kernels,
) -> Result<Vec<Primitive>, String> {
    let mut operands = vec![gamma];
    operands.extend(beta);
    operands.extend(grads.into_iter().flatten());
    operands.extend(dres);
    if let Some(t) = operands.iter().find(|t| t.dtype != DType::F32) {
        return Err(format!("{:?} operand (the layer-norm kernels take f32)", t.dtype));
    }
    // Both paths take an f32 or bf16 input (the side stream widens a bf16 one).
    bits(x.dtype)?;
    let shape = x.meta.shape();
    let (rows, d) = (shape[0], shape[1]);
    let per = per_lane(d).ok_or_else(|| format!("rows of {d}"))?;
    let sizes = Sizes {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        d: i32::try_from(d).map_err(|_| format!("width {d}"))?,
        eps: formats.eps,
    };
    if kernels.stream == KernelStream::Cubecl {
        return launch_bound(x, gamma, beta, (grads, dres), (per, sizes), formats);
    }
    let x32 = side::inner(float::<Inner, 2>(x.clone()).cast(FloatDType::F32));
    let mut results = side::on_device_thread(x, kernels.launch_thread, || {
        pointers::launch(&x32, gamma, beta, grads, (per, sizes), kernels)
    })?;
    // The side stream's kernels write f32 only.
    if formats.out != FloatDType::F32 {
        results[0] = side::inner(float::<Inner, 2>(results[0].clone()).cast(formats.out));
    }
    if let Some(keep) = formats.keep.filter(|_| grads.is_none()) {
        results.push(side::inner(float::<Inner, 2>(x.clone()).cast(keep)));
    }
    // The side stream's kernels add no residual gradient.
    if let Some(r) = dres {
        results[0] = side::inner(float::<Inner, 2>(results[0].clone()) + float(r.clone()));
    }
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
    (grads, dres): (Option<[&Primitive; 3]>, Option<&Primitive>),
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
            let inputs = [dy, x, mean, rstd, gamma].into_iter().chain(dres);
            let buffers = inputs.chain(&results).map(bind).collect();
            let res = if dres.is_some() { "_res" } else { "" };
            let entry = format!("umgen_norm_backward_bound_x{xs}{res}_{per}");
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
