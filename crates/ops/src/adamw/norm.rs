//! [`global_norm`]: the gradients' global L2 norm for `Cuda`, one custom operation in the fusion stream
//! that launches `adamw.cu`'s `umgen_sumsq` once per 128 gradients (each block storing its part's sum of
//! squares) and `umgen_sumsq_final` (one block adding the parts in a fixed order), on cubecl's stream with
//! the gradients bound as buffers.
#![allow(unsafe_code)]

use super::fallbacks::FALLBACKS;
use super::slots::{SPAN, SUMSQ_SLOTS as SLOTS, Slotted, THREADS, fill_slots};
use crate::kernels::LaunchThread;
use crate::side::{self, Handles, Inner, Primitive, SidePass, empty_f32};
use burn::backend::Cuda;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, TensorMetadata};
use burn::tensor::{Tensor, TensorPrimitive};
use burn_cubecl::kernel::into_contiguous;
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;
use umgen_optim::{GradNorm, norm_reference};

/// `SumsqParams` of `adamw.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Params {
    count: u32,
    base: u32,
    first: [u32; SLOTS + 1],
    len: [u32; SLOTS],
}

// SAFETY: plain old data, laid out as the C struct the kernel takes by value.
unsafe impl DeviceRepr for Params {}

/// `SumsqFinalParams` of `adamw.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct FinalParams {
    n: u32,
}

// SAFETY: as `Params`.
unsafe impl DeviceRepr for FinalParams {}

/// The operation: each gradient's element count, in the inputs' order.
#[derive(Debug)]
struct Pass {
    lens: Vec<usize>,
    /// The thread that launches it.
    thread: LaunchThread,
}

/// The global norm of `grads` on `Cuda` ([`umgen_optim::NormKernel`]), launched from `thread`.
pub(super) fn global_norm(
    grads: &[FloatTensor<Cuda>],
    thread: LaunchThread,
) -> Result<GradNorm<Cuda>, String> {
    let lens: Vec<usize> = grads.iter().map(|g| g.shape().num_elements()).collect();
    let refusal = if let Some(g) = grads.iter().find(|g| g.dtype() != DType::F32) {
        Some(format!("a {:?} gradient (the norm kernel takes f32)", g.dtype()))
    } else if lens.iter().sum::<usize>() > u32::MAX as usize / 2 {
        Some(format!("{} gradient elements", lens.iter().sum::<usize>()))
    } else {
        grads.is_empty().then(|| "no gradients".to_string())
    };
    if let Some(why) = refusal {
        FALLBACKS.fell_back(&why);
        return Err(why);
    }
    // Each block of `SPAN` elements is a part; a gradient owns as many as it has spans.
    let spans: Vec<usize> = lens.iter().map(|n| n.div_ceil(SPAN)).collect();
    let outputs = vec![vec![1], vec![spans.iter().sum::<usize>().max(1)]];
    let [norm, parts] =
        side::register_many("umgen_grad_norm", grads.to_vec(), outputs, Pass { lens, thread })
            .try_into()
            .unwrap_or_else(|_| unreachable!("two outputs"));
    let typed = |t| Tensor::<Cuda, 1>::from_primitive(TensorPrimitive::Float(t));
    Ok(GradNorm {
        norm: typed(norm),
        parts: typed(parts),
        spans,
    })
}

impl SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let grads: Vec<Primitive> = desc
            .inputs
            .iter()
            .map(|t| into_contiguous(handles.get_float_tensor::<Inner>(t)))
            .collect();
        let launched = match grads.first() {
            Some(like) => side::on_device_thread(like, self.thread, || self.launch(&grads)),
            None => Err("no gradients".into()),
        };
        match launched {
            Ok((norm, parts)) => vec![norm, parts],
            Err(why) => {
                FALLBACKS.fell_back(&why);
                // The parts by span, as the kernel's, from the reference's sums by gradient.
                let reference = norm_reference::<Inner>(&grads);
                let parts = span_parts(&reference.parts, &self.lens);
                vec![
                    reference.norm.into_primitive().tensor(),
                    parts.into_primitive().tensor(),
                ]
            }
        }
    }
}

impl Pass {
    /// The partial sums of squares, 128 gradients a launch, then their sum's square root.
    fn launch(&self, grads: &[Primitive]) -> Result<(Primitive, Primitive), String> {
        let Some(like) = grads.first() else {
            return Err("no gradients".into());
        };
        let blocks: usize = self.lens.iter().map(|n| n.div_ceil(SPAN)).sum();
        let partials = empty_f32(like, vec![blocks.max(1)]);
        let norm = empty_f32(like, vec![1]);
        let mut base = 0u32;
        for (chunk, (gs, lens)) in grads.chunks(SLOTS).zip(self.lens.chunks(SLOTS)).enumerate() {
            let mut p = Params {
                count: gs.len() as u32,
                base,
                first: [0; SLOTS + 1],
                len: [0; SLOTS],
            };
            let mut buffers = vec![partials.handle.clone().binding()];
            for (i, (g, &len)) in gs.iter().zip(lens).enumerate() {
                p.len[i] = len as u32;
                p.first[i + 1] = p.first[i] + len.div_ceil(SPAN) as u32;
                buffers.push(g.handle.clone().binding());
            }
            fill_slots(&mut buffers, 1, 1, SLOTS);
            let launched = p.first[gs.len()];
            base += launched;
            if launched == 0 {
                continue;
            }
            // SAFETY: the buffers are bound (cubecl keeps them alive for the launch); the kernel reads a
            // gradient below its `len` (its element count, the tensor made contiguous) and writes partial
            // sums below `base + launched` ≤ `blocks`, the partials' length.
            unsafe {
                side::launch_bound_on_cubecl(
                    like,
                    "umgen_sumsq",
                    ("", &source),
                    ((launched, 1, 1), THREADS),
                    buffers,
                    &p,
                )
            }
            .map_err(|e| format!("{e} (launch {chunk})"))?;
        }
        let buffers = vec![partials.handle.clone().binding(), norm.handle.clone().binding()];
        // SAFETY: one block reads the `n` partial sums and writes the one-element norm.
        unsafe {
            side::launch_bound_on_cubecl(
                like,
                "umgen_sumsq_final",
                ("", &source),
                ((1, 1, 1), THREADS),
                buffers,
                &FinalParams { n: base },
            )
        }?;
        Ok((norm, partials))
    }
}

/// Sums by gradient laid out as the kernel's parts by span: each gradient's sum in its first span, zeros
/// in its others (what a fallback reports, so that each gradient keeps its number of parts).
fn span_parts(by_gradient: &Tensor<Inner, 1>, lens: &[usize]) -> Tensor<Inner, 1> {
    let device = by_gradient.device();
    let mut pieces = Vec::with_capacity(2 * lens.len());
    for (i, n) in lens.iter().enumerate() {
        let spans = n.div_ceil(SPAN);
        if spans == 0 {
            continue;
        }
        pieces.push(by_gradient.clone().slice(i..i + 1));
        if spans > 1 {
            pieces.push(Tensor::zeros([spans - 1], &device));
        }
    }
    if pieces.is_empty() {
        return Tensor::zeros([1], &device);
    }
    Tensor::cat(pieces, 0)
}

/// `adamw.cu` and the entry point `umgen_sumsq`, which takes the partial sums and 128 gradients
/// (`umgen_sumsq_final` is in the file itself).
fn source() -> Result<String, String> {
    let slotted = Slotted {
        entry: "umgen_sumsq",
        fixed: "float* partials",
        per_slot: &[("g", true)],
        slots: SLOTS,
        params: "SumsqParams",
        slot_type: "SumsqSlot",
        call: "sumsq_update(p, i, s.g, partials)",
    };
    Ok(slotted.source())
}
