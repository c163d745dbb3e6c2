//! [`step`]: the multi-tensor AdamW for `Cuda` (burn-fusion over the cubecl backend), one custom operation
//! in the fusion stream per 32 parameter tensors, each launching `adamw.cu`'s kernel on cubecl's stream
//! with the tensors bound as its buffers; and [`Slotted`], the source of such a kernel's entry point.
#![allow(unsafe_code)]

use super::fallbacks::FALLBACKS;
use super::slots::{ADAMW_SLOTS as SLOTS, SPAN, Slotted, THREADS, fill_slots};
use crate::kernels::LaunchThread;
use crate::side::{self, Handles, Inner, Primitive, SidePass, empty_f32};
use burn::backend::Cuda;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, TensorMetadata};
use burn_cubecl::kernel::into_contiguous;
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;
use umgen_optim::{AdamWSettings, AdamWSlot, AdamWStep, AdamWStepped, adamw_reference};

/// `AdamwParams` of `adamw.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Params {
    count: u32,
    has_scale: u32,
    decays: u32,
    lr: f32,
    decay: f32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    eps: f32,
    first: [u32; SLOTS + 1],
    len: [u32; SLOTS],
    fresh: [u32; SLOTS],
    c1: [f32; SLOTS],
    c2: [f32; SLOTS],
}

// SAFETY: plain old data, laid out as the C struct the kernel takes by value.
unsafe impl DeviceRepr for Params {}

/// One slot as the operation keeps it: whether it has moments, its step number and element count.
#[derive(Debug, Clone, Copy)]
struct Layout {
    moments: bool,
    time: usize,
    len: usize,
}

/// The operation: the step's constants and each slot's layout, in the inputs' order.
#[derive(Debug)]
struct Pass {
    settings: AdamWSettings,
    lr: f64,
    scaled: bool,
    slots: Vec<Layout>,
    /// The thread that launches it.
    thread: LaunchThread,
}

/// Why the kernel cannot take `slot`, if it cannot.
fn refused(slot: &AdamWSlot<Cuda>) -> Option<String> {
    let mut tensors = vec![&slot.param, &slot.grad];
    if let Some((m, v)) = &slot.moments {
        tensors.extend([m, v]);
    }
    let len = slot.param.shape().num_elements();
    if let Some(t) = tensors.iter().find(|t| t.dtype() != DType::F32) {
        return Some(format!(
            "a {:?} parameter tensor or state (it takes f32)",
            t.dtype()
        ));
    }
    if let Some(t) = tensors.iter().find(|t| t.shape().num_elements() != len) {
        return Some(format!(
            "a state of {:?} for a parameter of {:?}",
            t.shape(),
            slot.param.shape()
        ));
    }
    (len > (u32::MAX as usize) - SPAN).then(|| format!("a parameter tensor of {len} elements"))
}

/// The multi-tensor AdamW step on `Cuda` ([`umgen_optim::AdamWKernel`]), launched from `thread`.
pub(super) fn step(
    slots: Vec<AdamWSlot<Cuda>>,
    step: &AdamWStep<Cuda>,
    thread: LaunchThread,
) -> AdamWStepped<Cuda> {
    let refusal = slots.iter().find_map(refused).or_else(|| {
        let scale = step.grad_scale.as_ref()?;
        (scale.dtype() != DType::F32).then(|| format!("a {:?} gradient scale", scale.dtype()))
    });
    if let Some(why) = refusal {
        FALLBACKS.fell_back(&why);
        return Err((slots, why));
    }
    // One operation per launch: burn-fusion looks an operation's inputs up in a list (`OperationStreams`),
    // so registering all of them at once costs the fusion thread time quadratic in their number (`paper`:
    // about 60 ms a step for its 2,400 tensors, the GPU idle meanwhile).
    let mut stepped = Vec::with_capacity(slots.len());
    let mut slots = slots.into_iter().peekable();
    while slots.peek().is_some() {
        let chunk: Vec<_> = slots.by_ref().take(SLOTS).collect();
        stepped.extend(register_chunk(chunk, step, thread));
    }
    Ok(stepped)
}

/// Registers the step of up to [`SLOTS`] slots as one custom operation (one launch); their new parameters
/// and moments.
fn register_chunk(
    slots: Vec<AdamWSlot<Cuda>>,
    step: &AdamWStep<Cuda>,
    thread: LaunchThread,
) -> Vec<[FloatTensor<Cuda>; 3]> {
    let mut inputs = Vec::with_capacity(4 * slots.len() + 1);
    inputs.extend(step.grad_scale.clone());
    let mut shapes = Vec::with_capacity(3 * slots.len());
    let mut layout = Vec::with_capacity(slots.len());
    for slot in slots {
        let shape = slot.param.shape().to_vec();
        layout.push(Layout {
            moments: slot.moments.is_some(),
            time: slot.time,
            len: shape.iter().product(),
        });
        inputs.extend([slot.param, slot.grad]);
        if let Some((m, v)) = slot.moments {
            inputs.extend([m, v]);
        }
        shapes.extend([shape.clone(), shape.clone(), shape]);
    }
    let pass = Pass {
        settings: step.settings,
        lr: step.lr,
        scaled: step.grad_scale.is_some(),
        slots: layout,
        thread,
    };
    let mut outputs = side::register_many("umgen_adamw", inputs, shapes, pass).into_iter();
    let mut stepped = Vec::new();
    while let (Some(p), Some(m), Some(v)) = (outputs.next(), outputs.next(), outputs.next()) {
        stepped.push([p, m, v]);
    }
    stepped
}

impl Pass {
    /// The step as [`umgen_optim`] describes it, with `scale` on `Inner`.
    fn step(&self, scale: Option<Primitive>) -> AdamWStep<Inner> {
        AdamWStep {
            settings: self.settings,
            lr: self.lr,
            grad_scale: scale,
        }
    }
}

impl SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let mut inputs = desc
            .inputs
            .iter()
            .map(|t| into_contiguous(handles.get_float_tensor::<Inner>(t)));
        let scale = if self.scaled { inputs.next() } else { None };
        let mut slots = Vec::with_capacity(self.slots.len());
        for l in &self.slots {
            let (Some(param), Some(grad)) = (inputs.next(), inputs.next()) else {
                unreachable!("two inputs a slot")
            };
            let moments = if l.moments {
                let (Some(m), Some(v)) = (inputs.next(), inputs.next()) else {
                    unreachable!("two more with moments")
                };
                Some((m, v))
            } else {
                None
            };
            slots.push(AdamWSlot {
                param,
                grad,
                moments,
                time: l.time,
            });
        }
        let step = self.step(scale);
        let launched = match slots.first() {
            Some(like) => side::on_device_thread(&like.param, self.thread, || self.launch(&slots, &step)),
            None => Ok(Vec::new()),
        };
        match launched {
            Ok(outputs) => outputs,
            Err(why) => {
                FALLBACKS.fell_back(&why);
                adamw_reference(slots, &step).into_iter().flatten().collect()
            }
        }
    }
}

impl Pass {
    /// Launches the kernel once over `slots` (at most [`SLOTS`]: [`step`] registers one operation per launch);
    /// the new parameters and moments, three a slot.
    fn launch(&self, slots: &[AdamWSlot<Inner>], step: &AdamWStep<Inner>) -> Result<Vec<Primitive>, String> {
        let Some(like) = slots.first().map(|s| &s.param) else {
            return Ok(Vec::new());
        };
        if slots.len() > SLOTS {
            return Err(format!(
                "{} parameter tensors in one launch (at most {SLOTS})",
                slots.len()
            ));
        }
        // The moments are updated where they lie when nothing else holds them (burn's own AdamW writes new
        // tensors, so the optimizer's records are the only holders); the parameters, which the module and
        // the autodiff graph may still hold, always go to new memory.
        let fresh_or = |t: Option<&Primitive>, shape: &[usize]| match t {
            Some(t) if t.handle.can_mut() && t.is_contiguous() => t.clone(),
            _ => empty_f32(like, shape.to_vec()),
        };
        let outputs: Vec<[Primitive; 3]> = slots
            .iter()
            .map(|s| {
                let shape = s.param.meta.shape().to_vec();
                let (m, v) = s.moments.as_ref().map(|(m, v)| (m, v)).unzip();
                [
                    empty_f32(like, shape.clone()),
                    fresh_or(m, &shape),
                    fresh_or(v, &shape),
                ]
            })
            .collect();
        let (c, s) = (&step.settings, step);
        let dummy = slots[0].grad.handle.clone().binding();
        let mut p = Params {
            count: slots.len() as u32,
            has_scale: s.grad_scale.is_some() as u32,
            decays: s.decay().is_some() as u32,
            lr: s.lr as f32,
            decay: s.decay().unwrap_or(1.0),
            beta1: c.beta_1,
            beta2: c.beta_2,
            one_minus_beta1: 1.0 - c.beta_1,
            one_minus_beta2: 1.0 - c.beta_2,
            eps: c.epsilon,
            first: [0; SLOTS + 1],
            len: [0; SLOTS],
            fresh: [0; SLOTS],
            c1: [1.0; SLOTS],
            c2: [1.0; SLOTS],
        };
        let scale = s
            .grad_scale
            .as_ref()
            .map_or(dummy.clone(), |t| t.handle.clone().binding());
        let mut buffers = vec![scale];
        for (i, (slot, out)) in slots.iter().zip(&outputs).enumerate() {
            let len = self.slots[i].len;
            p.len[i] = len as u32;
            p.first[i + 1] = p.first[i] + len.div_ceil(SPAN) as u32;
            p.fresh[i] = slot.moments.is_none() as u32;
            (p.c1[i], p.c2[i]) = step.corrections(slot.time);
            let (m, v) = match &slot.moments {
                Some((m, v)) => (m.handle.clone().binding(), v.handle.clone().binding()),
                None => (dummy.clone(), dummy.clone()),
            };
            buffers.extend([
                slot.param.handle.clone().binding(),
                slot.grad.handle.clone().binding(),
                m,
                v,
            ]);
            buffers.extend(out.iter().map(|t| t.handle.clone().binding()));
        }
        fill_slots(&mut buffers, 1, 7, SLOTS);
        let blocks = p.first[slots.len()];
        if blocks > 0 {
            // SAFETY: every buffer is bound (cubecl keeps it alive for the launch), of `len` f32 for its slot
            // (checked by `refused`, and made contiguous when read), and the kernel reads and writes a slot's
            // buffers only below its `len`.
            unsafe {
                side::launch_bound_on_cubecl(
                    like,
                    "umgen_adamw",
                    ("", &source),
                    ((blocks, 1, 1), THREADS),
                    buffers,
                    &p,
                )
            }?;
        }
        Ok(outputs.into_iter().flatten().collect())
    }
}

/// `adamw.cu` and the entry point `umgen_adamw`, which takes the gradient scale and 32 slots of seven
/// buffers.
fn source() -> Result<String, String> {
    const NAMES: [&str; 7] = ["p", "g", "m", "v", "po", "mo", "vo"];
    let kinds = NAMES.map(|n| (n, !n.ends_with('o')));
    let slotted = Slotted {
        entry: "umgen_adamw",
        fixed: "const float* scale",
        per_slot: &kinds,
        slots: SLOTS,
        params: "AdamwParams",
        slot_type: "AdamwSlot",
        call: "adamw_update(p, i, s, scale)",
    };
    Ok(slotted.source())
}
