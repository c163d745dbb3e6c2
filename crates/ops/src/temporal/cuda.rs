//! [`TemporalAttention`] for `Cuda` (burn-fusion over the cubecl backend): each pass is a custom operation
//! in the fusion stream that launches `temporal.cu`'s kernels (compiled with NVRTC) on cubecl's stream, or
//! on a side stream ordered with cubecl's with `train.kernels.stream = "side"` ([`crate::side`]). More than
//! 32 frames, head sizes other than 32, 64 and 128, other types than f32, or a failure to compile or launch
//! run the decomposition instead, counted by [`crate::flash::fallbacks`] with the attention's other
//! fallbacks.
#![allow(unsafe_code)]

use super::{Saved, TemporalAttention, backward_decomposed, forward_decomposed};
use crate::format::Precision;
use crate::format::float;
use crate::kernels::{Kernels, SideFamily};
use crate::side::{self, Compiled, Handles, Inner, KernelCache, Primitive, empty_f32};
use burn::backend::Cuda;
use burn::tensor::{DType, Tensor};
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;
use cudarc::nvrtc::CompileOptions;
use std::cell::RefCell;

/// The longest sequence the kernels take (lane t keeps query t's statistics).
const MAX_FRAMES: usize = 32;

/// Warps a block (the kernels' `__launch_bounds__(256)`).
const WARPS: usize = 8;

/// `Axes` of `temporal.cu`: strides of the b, t and n axes.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct Axes {
    b: i64,
    t: i64,
    n: i64,
}

/// `TemporalParams` of `temporal.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
struct Params {
    q: u64,
    k: u64,
    v: u64,
    dout: u64,
    out_w: u64,
    lse_w: u64,
    dq: u64,
    dk: u64,
    dv: u64,
    qa: Axes,
    ka: Axes,
    va: Axes,
    ga: Axes,
    dka: Axes,
    dva: Axes,
    b: i32,
    t: i32,
    n: i32,
    heads: i32,
    causal: i32,
    scale: f32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Params {}

/// Values a lane holds of a head of `dh`, if a kernel takes that head size.
fn per_lane(dh: usize) -> Option<usize> {
    [1, 2, 4].into_iter().find(|&p| 32 * p == dh)
}

/// Why the kernels cannot take `q` `[b, t, n, d]` with `heads` heads, if they cannot.
fn refused(q: &Tensor<Cuda, 4>, heads: usize) -> Option<String> {
    let [b, t, n, d] = q.dims();
    if b * t * n * d == 0 || heads == 0 || !d.is_multiple_of(heads) {
        return Some(format!(
            "attention over time of [{b}, {t}, {n}, {d}] in {heads} heads"
        ));
    }
    if t > MAX_FRAMES {
        return Some(format!(
            "{t} frames (the temporal kernels take up to {MAX_FRAMES})"
        ));
    }
    if per_lane(d / heads).is_none() {
        return Some(format!(
            "head size {} (the temporal kernels take 32, 64 and 128)",
            d / heads
        ));
    }
    if i32::try_from(b.max(n).max(heads)).is_err() {
        return Some(format!("[{b}, {t}, {n}] in {heads} heads: over 32-bit sizes"));
    }
    (q.dtype() != DType::F32).then(|| format!("{:?} operands (the temporal kernels take f32)", q.dtype()))
}

impl TemporalAttention for Cuda {
    /// The backward kernel recomputes each query's log-sum-exp and `dout · out` from q, kv and dout.
    const KEEPS_FORWARD: bool = false;

    fn temporal_forward(
        q: Tensor<Self, 4>,
        kv: Tensor<Self, 4>,
        heads: usize,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        if let Some(why) = refused(&q, heads) {
            crate::flash::fell_back("temporal", &why, "decomposed");
            return forward_decomposed(q, kv, heads, causal, precision);
        }
        let [b, t, n, d] = q.dims();
        let pass = Pass {
            heads,
            causal,
            backward: false,
            precision,
            kernels: *kernels,
        };
        let [out, lse] = side::register(
            "umgen_temporal_forward",
            [side::fused(q), side::fused(kv)],
            [vec![b, t, n, d], vec![b, t, n, heads]],
            pass,
        );
        (float(out), float(lse))
    }

    #[allow(clippy::too_many_arguments)]
    fn temporal_backward(
        q: Tensor<Self, 4>,
        kv: Tensor<Self, 4>,
        saved: Option<Saved<Self>>,
        dout: Tensor<Self, 4>,
        heads: usize,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        // The forward pass counted a refusal; the decomposition recomputes the forward pass it needs.
        if refused(&q, heads).is_some() {
            return backward_decomposed(q, kv, saved, dout, heads, causal, precision);
        }
        let [b, t, n, d] = q.dims();
        let pass = Pass {
            heads,
            causal,
            backward: true,
            precision,
            kernels: *kernels,
        };
        let [dq, dkv] = side::register(
            "umgen_temporal_backward",
            [side::fused(q), side::fused(kv), side::fused(dout)],
            [vec![b, t, n, d], vec![b, t, n, 2 * d]],
            pass,
        );
        (float(dq), float(dkv))
    }
}

/// What a pass computes.
#[derive(Debug, Clone, Copy)]
struct Pass {
    heads: usize,
    causal: bool,
    /// q, kv, dout in; dq, dkv out (otherwise q, kv in; out, lse out).
    backward: bool,
    /// For the decomposition, should the kernels fail.
    precision: Precision,
    /// The stream and the launching thread.
    kernels: Kernels,
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let Pass {
            heads,
            causal,
            backward,
            precision,
            kernels,
        } = *self;
        let thread = kernels.launch_thread;
        if backward {
            let [q, kv, dout] = side::contiguous_inputs::<3>(handles, desc);
            side::on_device_thread(&q, thread, || {
                launch(&q, &kv, Some(&dout), (heads, causal), kernels)
            })
            .unwrap_or_else(|why| {
                crate::flash::fell_back("temporal", &why, "decomposed");
                let (dq, dkv) = backward_decomposed::<Inner>(
                    float(q),
                    float(kv),
                    None,
                    float(dout),
                    heads,
                    causal,
                    precision,
                );
                vec![side::inner(dq), side::inner(dkv)]
            })
        } else {
            let [q, kv] = side::contiguous_inputs::<2>(handles, desc);
            side::on_device_thread(&q, thread, || launch(&q, &kv, None, (heads, causal), kernels))
                .unwrap_or_else(|why| {
                    crate::flash::fell_back("temporal", &why, "decomposed");
                    let (out, lse) =
                        forward_decomposed::<Inner>(float(q), float(kv), heads, causal, precision);
                    vec![side::inner(out), side::inner(lse)]
                })
        }
    }
}

thread_local! {
    /// This thread's kernels by device.
    static KERNELS: KernelCache = const { RefCell::new(Vec::new()) };
}

/// Compiles the kernels for `like`'s device.
fn build(like: &Primitive) -> Result<Compiled, String> {
    let names: Vec<String> = [1, 2, 4]
        .iter()
        .flat_map(|p| {
            [
                format!("umgen_temporal_forward_{p}"),
                format!("umgen_temporal_backward_{p}"),
            ]
        })
        .collect();
    Compiled::compile(like, source()?, |_| CompileOptions::default(), &names, 0)
}

/// The kernels' source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::TEMPORAL))
}

/// Strides of a contiguous `[b, t, n, width]` tensor's first three axes.
fn axes(t: usize, n: usize, width: usize) -> Axes {
    let i = |x: usize| x as i64;
    Axes {
        b: i(t * n * width),
        t: i(n * width),
        n: i(width),
    }
}

/// Runs the forward pass on contiguous `q` `[b, t, n, d]` and `kv` `[b, t, n, 2d]` (`dout` `None`: the
/// output and log-sum-exp) or the backward pass (`dout`, contiguous: dq and dkv),
/// returning its results; an error says why it could not (no result was written that the caller keeps, so
/// it may run the decomposition).
fn launch(
    q: &Primitive,
    kv: &Primitive,
    dout: Option<&Primitive>,
    (heads, causal): (usize, bool),
    kernels: Kernels,
) -> Result<Vec<Primitive>, String> {
    let mut operands = vec![q, kv];
    operands.extend(dout);
    if let Some(t) = operands.iter().find(|t| t.dtype != DType::F32) {
        return Err(format!("{:?} operand (the temporal kernels take f32)", t.dtype));
    }
    let s = q.meta.shape();
    let (b, t, n, d) = (s[0], s[1], s[2], s[3]);
    let dpl = per_lane(d / heads).ok_or_else(|| format!("head size {}", d / heads))?;
    let int = |x: usize| i32::try_from(x).map_err(|_| format!("size {x} over 32 bits"));
    let (plain, halves) = (axes(t, n, d), axes(t, n, 2 * d));
    let mut p = Params {
        qa: plain,
        ka: halves,
        va: halves,
        ga: plain,
        dka: halves,
        dva: halves,
        b: int(b)?,
        t: int(t)?,
        n: int(n)?,
        heads: int(heads)?,
        causal: i32::from(causal),
        scale: 1.0 / ((d / heads) as f32).sqrt(),
        ..Params::default()
    };
    // The pointers, and what keeps the buffers alive until the launch is queued.
    let mut keep = side::Pointers::default();
    let mut ptr = |t: &Primitive| keep.of(t);
    let f32_bytes = 4;
    (p.q, p.k) = (ptr(q)?, ptr(kv)?);
    p.v = p.k + (d * f32_bytes) as u64;
    let (results, name) = match dout {
        None => {
            let results = vec![empty_f32(q, vec![b, t, n, d]), empty_f32(q, vec![b, t, n, heads])];
            (p.out_w, p.lse_w) = (ptr(&results[0])?, ptr(&results[1])?);
            (results, format!("umgen_temporal_forward_{dpl}"))
        }
        Some(dout) => {
            p.dout = ptr(dout)?;
            let results = vec![empty_f32(q, vec![b, t, n, d]), empty_f32(q, vec![b, t, n, 2 * d])];
            (p.dq, p.dk) = (ptr(&results[0])?, ptr(&results[1])?);
            p.dv = p.dk + (d * f32_bytes) as u64;
            (results, format!("umgen_temporal_backward_{dpl}"))
        }
    };
    let blocks = (b * n * heads).div_ceil(WARPS);
    // SAFETY: every pointer in `p` is a live contiguous buffer (kept by `keep`) of the shape its strides in `p`
    // describe (`v` and `dv` the second halves of `kv` and `dkv`).
    unsafe {
        side::launch_kernel(
            (&KERNELS, &kernels),
            q,
            (SideFamily::AttentionOverTime, &|| build(q)),
            &name,
            (&format!("TEMPORAL_KERNELS({dpl})"), &source),
            (blocks, 32 * WARPS as u32),
            &p,
        )
    }?;
    drop(keep);
    Ok(results)
}
