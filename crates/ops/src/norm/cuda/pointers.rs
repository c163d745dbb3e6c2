//! The layer-norm kernels on a side stream (`train.kernels.stream = "side"`): launched on cubecl's device
//! thread with the buffers' device pointers in one parameter block (`NormParams`, `NORM_KERNELS`), f32
//! only. The default path binds the buffers instead (`super::launch_bound`).
#![allow(unsafe_code)]

use super::geometry::{PER_LANE, Sizes, WARPS, backward_warps, results, source};
use crate::kernels::{Kernels, SideFamily};
use crate::side::{self, Compiled, KernelCache, Primitive};
use burn::tensor::FloatDType;
use cudarc::driver::DeviceRepr;
use cudarc::nvrtc::CompileOptions;
use std::cell::RefCell;

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

/// [`super::launch`] on the side stream: the kernel takes [`Params`], the buffers' device pointers.
pub(super) fn launch(
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
