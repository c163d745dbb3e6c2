//! [`FusedXent`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation in the
//! fusion stream that launches `xent.cu`'s kernels (compiled with NVRTC) on cubecl's
//! stream, or on a side stream ordered with cubecl's with `train.kernels.stream = "side"`
//! ([`crate::side`]), unless `train.kernels.xent = "burn"`.
//! Other types than f32, or a failure to compile or launch, run burn's operations instead, counted by
//! [`super::fallbacks`].
#![allow(unsafe_code)]

use super::{FALLBACKS, FusedXent, XentKernel, grad_decomposed, lse_decomposed};
use crate::format::float;
use crate::kernels::{Kernels, SideFamily};
use crate::side::{self, Compiled, Handles, Inner, KernelCache, Primitive, empty_f32};
use burn::backend::Cuda;
use burn::tensor::{DType, Int, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;
use cudarc::nvrtc::CompileOptions;
use std::cell::RefCell;

/// Warps a block (the kernels' `__launch_bounds__(256)`).
const WARPS: usize = 8;

/// Blocks at most: each warp loops over rows, so a few waves of an H100 (132 SMs) cover any height.
const MAX_BLOCKS: usize = 4096;

/// `XentParams` of `xent.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct Params {
    x: u64,
    lse: u64,
    g: u64,
    ids: u64,
    weights: u64,
    lse_out: u64,
    dx: u64,
    rows: i64,
    v: i32,
    k: i32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Params {}

/// Why the kernels cannot take logits `x` `[rows, v]`, if they cannot.
fn refused(x: &Tensor<Cuda, 2>) -> Option<String> {
    let [rows, v] = x.dims();
    if rows == 0 || v == 0 {
        return Some(format!("empty logits [{rows}, {v}]"));
    }
    // The target ids travel as f32, exact below 2^24.
    if v > 1 << 24 {
        return Some(format!("rows of {v} logits (the kernels take up to 2^24)"));
    }
    (x.dtype() != DType::F32).then(|| format!("{:?} logits (the kernels take f32)", x.dtype()))
}

impl FusedXent for Cuda {
    fn xent_lse(x: Tensor<Self, 2>, kernels: &Kernels) -> Tensor<Self, 2> {
        if kernels.xent == XentKernel::Burn {
            return lse_decomposed(x);
        }
        if let Some(why) = refused(&x) {
            FALLBACKS.fell_back(&why);
            return lse_decomposed(x);
        }
        let rows = x.dims()[0];
        let [lse] = side::register(
            "umgen_xent_forward",
            [side::fused(x)],
            [vec![rows]],
            Pass::Forward { kernels: *kernels },
        );
        float::<Cuda, 1>(lse).reshape([rows, 1])
    }

    fn xent_grad(
        x: Tensor<Self, 2>,
        lse: Tensor<Self, 2>,
        ids: Tensor<Self, 2, Int>,
        weights: Tensor<Self, 2>,
        g: Tensor<Self, 1>,
        kernels: &Kernels,
    ) -> Tensor<Self, 2> {
        // The forward pass counted a refusal.
        if kernels.xent == XentKernel::Burn || refused(&x).is_some() {
            return grad_decomposed(x, lse, ids, weights, g);
        }
        let [rows, v] = x.dims();
        // The kernel reads the ids as f32 (exact below 2^24; the Int tensors' type is the backend's).
        let inputs = [
            side::fused(x),
            side::fused(lse),
            side::fused(g),
            side::fused(ids.float()),
            side::fused(weights),
        ];
        let pass = Pass::Backward { kernels: *kernels };
        let [dx] = side::register("umgen_xent_backward", inputs, [vec![rows, v]], pass);
        float(dx)
    }
}

/// Which pass.
#[derive(Debug, Clone, Copy)]
enum Pass {
    /// x in; lse out.
    Forward { kernels: Kernels },
    /// x, lse, g, ids (as f32), weights in; dx out.
    Backward { kernels: Kernels },
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        match self {
            Pass::Forward { kernels } => {
                let [x] = side::contiguous_inputs::<1>(handles, desc);
                side::on_device_thread(&x, kernels.launch_thread, || launch(&x, None, *kernels))
                    .unwrap_or_else(|why| {
                        FALLBACKS.fell_back(&why);
                        let lse = lse_decomposed::<Inner>(float(x));
                        let rows = lse.dims()[0];
                        vec![side::inner(lse.reshape([rows]))]
                    })
            }
            Pass::Backward { kernels } => {
                let [x, lse, g, ids, weights] = side::contiguous_inputs::<5>(handles, desc);
                let grads = Some([&lse, &g, &ids, &weights]);
                side::on_device_thread(&x, kernels.launch_thread, || launch(&x, grads, *kernels))
                    .unwrap_or_else(|why| {
                        FALLBACKS.fell_back(&why);
                        let ids = float::<Inner, 2>(ids).int();
                        let dx =
                            grad_decomposed::<Inner>(float(x), float(lse), ids, float(weights), float(g));
                        vec![side::inner(dx)]
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
    let names = [
        "umgen_xent_forward".to_string(),
        "umgen_xent_backward".to_string(),
    ];
    Compiled::compile(like, source()?, |_| CompileOptions::default(), &names, 0)
}

/// The kernels' source as NVRTC compiles it (two kernels: every entry compiles all of it).
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::XENT))
}

/// Runs the forward pass on contiguous logits `x` `[rows, v]` (`grads` `None`: the rows' log-sum-exp) or
/// the backward pass (`grads` = `[lse, g, ids, weights]`: dx), returning the result; an error says why
/// it could not (no result was written that the caller keeps, so it may run burn's operations).
fn launch(x: &Primitive, grads: Option<[&Primitive; 4]>, kernels: Kernels) -> Result<Vec<Primitive>, String> {
    let mut operands = vec![x];
    operands.extend(grads.into_iter().flatten());
    if let Some(t) = operands.iter().find(|t| t.dtype != DType::F32) {
        return Err(format!(
            "{:?} operand (the cross-entropy kernels take f32)",
            t.dtype
        ));
    }
    let shape = x.meta.shape();
    let (rows, v) = (shape[0], shape[1]);
    let mut p = Params {
        rows: i64::try_from(rows).map_err(|_| format!("{rows} rows"))?,
        v: i32::try_from(v).map_err(|_| format!("rows of {v}"))?,
        ..Params::default()
    };
    // The pointers, and what keeps the buffers alive until the launch is queued.
    let mut keep = side::Pointers::default();
    let mut ptr = |t: &Primitive| keep.of(t);
    p.x = ptr(x)?;
    let (result, name) = match grads {
        None => {
            let lse = empty_f32(x, vec![rows]);
            p.lse_out = ptr(&lse)?;
            (lse, "umgen_xent_forward")
        }
        Some([lse, g, ids, weights]) => {
            let k = ids.meta.shape()[1];
            p.k = i32::try_from(k).map_err(|_| format!("{k} targets a row"))?;
            (p.lse, p.g, p.ids, p.weights) = (ptr(lse)?, ptr(g)?, ptr(ids)?, ptr(weights)?);
            let dx = empty_f32(x, vec![rows, v]);
            p.dx = ptr(&dx)?;
            (dx, "umgen_xent_backward")
        }
    };
    let blocks = rows.div_ceil(WARPS).min(MAX_BLOCKS);
    // SAFETY: every pointer in `p` is a live contiguous buffer (kept by `keep`) of the shape the kernel reads
    // or writes (`rows × v`, `rows`, `rows × k`, or one value for g).
    unsafe {
        side::launch_kernel(
            (&KERNELS, &kernels),
            x,
            (SideFamily::CrossEntropy, &|| build(x)),
            name,
            ("", &source),
            (blocks, 32 * WARPS as u32),
            &p,
        )
    }?;
    drop(keep);
    Ok(vec![result])
}
