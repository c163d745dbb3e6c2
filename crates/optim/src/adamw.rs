//! AdamW over all parameter tensors at once.
//!
//! burn's `OptimizerAdaptor<AdamW>` steps one parameter tensor at a time, a chain of about ten tensor
//! operations each: `small` has 331 parameter tensors, and on CUDA the chain's host work took 17–22 ms a
//! step against PyTorch's fused AdamW's 0.7 ms (docs/perf-notes.md). [`FusedAdamW`] gathers every
//! parameter, gradient and moment of a step into [`AdamWSlot`]s and hands them to a backend's
//! multi-tensor [`AdamWKernel`] (umgen's CUDA kernel updates them all in a few launches), and steps
//! tensor by tensor with burn's own `AdamW` where there is none, or where the kernel declines. It keeps
//! burn's record, so checkpoints written by either load into the other, and it takes the gradient
//! clipping's factor as a device tensor so that clipping costs no pass over the gradients of its own.

use burn::module::{AutodiffModule, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::adaptor::{GradAdaptor, OptimizerAdaptor};
use burn::optim::record::AdaptorRecord;
use burn::optim::{
    AdamW, AdamWConfig, AdamWState, AdaptiveMomentumState, GradientsParams, LearningRate,
    MultiGradientsParams, Optimizer, SimpleOptimizer,
};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};
use std::collections::HashMap;
use std::marker::PhantomData;

/// AdamW's hyper-parameters: burn's `AdamWConfig` without AMSGrad, cautious weight decay or per-tensor
/// clipping (umgen clips by the global norm, [`FusedAdamW::step_clipped`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamWSettings {
    /// Decay of the first moment.
    pub beta_1: f32,
    /// Decay of the second moment.
    pub beta_2: f32,
    /// Added to √v̂.
    pub epsilon: f32,
    /// Decoupled weight decay (per unit of learning rate).
    pub weight_decay: f32,
}

impl AdamWSettings {
    /// burn's AdamW with these settings (the per-tensor path, and the reference the kernels match).
    fn burn(&self) -> AdamW {
        AdamWConfig::new()
            .with_beta_1(self.beta_1)
            .with_beta_2(self.beta_2)
            .with_epsilon(self.epsilon)
            .with_weight_decay(self.weight_decay)
            .build()
    }
}

/// One parameter tensor's AdamW step, of any rank (as a backend's primitives).
#[derive(Debug, Clone)]
pub struct AdamWSlot<B: Backend> {
    /// The parameter before the step.
    pub param: FloatTensor<B>,
    /// Its gradient (before the clipping factor).
    pub grad: FloatTensor<B>,
    /// The first and second moments before the step; `None` at the parameter's first step (zero moments).
    pub moments: Option<(FloatTensor<B>, FloatTensor<B>)>,
    /// The step's number for this parameter (1 at its first), which sets the bias corrections.
    pub time: usize,
}

/// What one [`AdamWKernel`] call applies to all its slots.
#[derive(Debug)]
pub struct AdamWStep<B: Backend> {
    /// The hyper-parameters.
    pub settings: AdamWSettings,
    /// The learning rate.
    pub lr: LearningRate,
    /// `[1]`: multiplies every gradient (the global-norm clipping's factor), if any.
    pub grad_scale: Option<FloatTensor<B>>,
}

impl<B: Backend> AdamWStep<B> {
    /// The bias corrections `1 − β₁ᵗ` and `1 − β₂ᵗ` at step `time`, in f32 as burn computes them.
    pub fn corrections(&self, time: usize) -> (f32, f32) {
        let t = i32::try_from(time).unwrap_or(i32::MAX);
        let s = &self.settings;
        (1.0 - s.beta_1.powi(t), 1.0 - s.beta_2.powi(t))
    }

    /// The factor `1 − lr·λ` that decays every weight, or `None` when it is 1 (burn skips the product then).
    pub fn decay(&self) -> Option<f32> {
        let rate = self.lr * self.settings.weight_decay as f64;
        (rate != 0.0).then_some((1.0 - rate) as f32)
    }
}

/// What an [`AdamWKernel`] returns: every slot's new parameter, first and second moment, in the slots'
/// order, each of its parameter's shape; or the slots back with the reason it cannot take them (the
/// optimizer then steps them with burn's AdamW).
pub type AdamWStepped<B> = Result<Vec<[FloatTensor<B>; 3]>, (Vec<AdamWSlot<B>>, String)>;

/// A backend's multi-tensor AdamW step.
pub type AdamWKernel<B> = fn(Vec<AdamWSlot<B>>, &AdamWStep<B>) -> AdamWStepped<B>;

/// A backend's global L2 norm of tensors of any rank (`[1]`), or the reason it cannot take them.
pub type NormKernel<B> = fn(&[FloatTensor<B>]) -> Result<FloatTensor<B>, String>;

/// A backend's multi-tensor kernels for [`FusedAdamW`].
#[derive(Debug)]
pub struct MultiTensor<B: Backend> {
    /// The AdamW step.
    pub adamw: AdamWKernel<B>,
    /// The gradients' global norm, for clipping.
    pub norm: NormKernel<B>,
}

// By hand: derived, they would ask `B` to be `Copy`.
impl<B: Backend> Clone for MultiTensor<B> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<B: Backend> Copy for MultiTensor<B> {}

/// burn's AdamW record for a module `M`, which [`FusedAdamW`] keeps too.
pub type AdamWRecord<M, B> = <OptimizerAdaptor<AdamW, M, B> as Optimizer<M, B>>::Record;

/// AdamW stepping every parameter tensor at once through an [`AdamWKernel`] when there is one.
#[derive(Clone)]
pub struct FusedAdamW<M: AutodiffModule<B>, B: AutodiffBackend> {
    settings: AdamWSettings,
    records: AdamWRecord<M, B>,
    kernels: Option<MultiTensor<B::InnerBackend>>,
    module: PhantomData<M>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> FusedAdamW<M, B> {
    /// An optimizer with `settings` and no state, stepping tensor by tensor until given a kernel.
    pub fn new(settings: AdamWSettings) -> Self {
        Self {
            settings,
            records: Default::default(),
            kernels: None,
            module: PhantomData,
        }
    }

    /// Steps through `kernels` from now on (`None`: tensor by tensor, with burn's AdamW).
    pub fn with_kernels(mut self, kernels: Option<MultiTensor<B::InnerBackend>>) -> Self {
        self.kernels = kernels;
        self
    }

    /// One AdamW step of `module` with `grads` scaled to a global norm of at most `max_norm` (not scaled
    /// when `max_norm <= 0`, or when the norm is not finite), as [`crate::clip_grad_norm`] scales them;
    /// returns the stepped module and the norm before scaling, still on the device. The scaling happens as
    /// the step reads each gradient, so clipping costs no pass over the gradients of its own.
    pub fn step_clipped(
        &mut self,
        lr: LearningRate,
        module: M,
        grads: GradientsParams,
        max_norm: f64,
    ) -> (M, Tensor<B::InnerBackend, 1>) {
        let (module, norm) = self.step_adapted(lr, module, grads.into(), Some(max_norm));
        let norm = norm.unwrap_or_else(|| Tensor::zeros([1], &Default::default()));
        (module, norm)
    }

    /// The global norm of `grads` (`[1]`), through the norm kernel when there is one.
    fn norm(&self, grads: &[FloatTensor<B::InnerBackend>]) -> Option<Tensor<B::InnerBackend, 1>> {
        if grads.is_empty() {
            return None;
        }
        let by_kernel = self.kernels.and_then(|k| (k.norm)(grads).ok());
        Some(match by_kernel {
            Some(norm) => typed1(norm),
            None => norm_reference::<B::InnerBackend>(grads),
        })
    }

    fn step_adapted(
        &mut self,
        lr: LearningRate,
        module: M,
        grads: GradAdaptor,
        max_norm: Option<f64>,
    ) -> (M, Option<Tensor<B::InnerBackend, 1>>) {
        let mut gather = Gather::<M, B> {
            grads,
            records: &mut self.records,
            ids: Vec::new(),
            slots: Vec::new(),
        };
        module.visit(&mut gather);
        let Gather { ids, slots, .. } = gather;
        let norm =
            max_norm.and_then(|_| self.norm(&slots.iter().map(|s| s.grad.clone()).collect::<Vec<_>>()));
        let grad_scale = match (&norm, max_norm) {
            (Some(norm), Some(max)) if max > 0.0 => Some(clip_scale(norm.clone(), max)),
            _ => None,
        };
        let step = AdamWStep {
            settings: self.settings,
            lr,
            grad_scale: grad_scale.map(|s| s.into_primitive().tensor()),
        };
        let stepped = match self.kernels {
            Some(kernels) if !slots.is_empty() => (kernels.adamw)(slots, &step),
            _ => Err((slots, String::new())),
        };
        let outcomes = match stepped {
            Ok(outputs) => {
                let times = ids.iter().map(|(_, t)| *t);
                let done = outputs.into_iter().zip(times).map(|(o, t)| Outcome::Done(o, t));
                ids.iter().map(|(id, _)| *id).zip(done).collect()
            }
            Err((slots, _)) => {
                let pending = slots.into_iter().map(Outcome::Pending);
                ids.iter().map(|(id, _)| *id).zip(pending).collect()
            }
        };
        let module = module.map(&mut Apply::<M, B> {
            outcomes,
            step: &step,
            burn: self.settings.burn(),
            records: &mut self.records,
        });
        (module, norm)
    }
}

/// `min(1, max_norm / norm)`, and 1 where the norm is NaN or infinite (as if not clipped).
pub(crate) fn clip_scale<B: Backend>(norm: Tensor<B, 1>, max_norm: f64) -> Tensor<B, 1> {
    let factor = norm.clone().clamp_min(max_norm).recip().mul_scalar(max_norm);
    factor.mask_fill(norm.is_finite().bool_not(), 1.0)
}

/// The global L2 norm of `grads` in burn's operations, as [`crate::grad_norm`] computes it (each tensor's
/// sum of squares, then their sum): what the norm kernel is checked against, and what runs without one.
pub fn norm_reference<B: Backend>(grads: &[FloatTensor<B>]) -> Tensor<B, 1> {
    let parts = grads
        .iter()
        .map(|g| {
            let n = g.shape().num_elements();
            typed1::<B>(g.clone()).reshape([n]).powf_scalar(2.0).sum()
        })
        .collect();
    Tensor::cat(parts, 0).sum().sqrt()
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> Optimizer<M, B> for FusedAdamW<M, B> {
    type Record = AdamWRecord<M, B>;

    fn step(&mut self, lr: LearningRate, module: M, grads: GradientsParams) -> M {
        self.step_adapted(lr, module, grads.into(), None).0
    }

    fn step_multi(&mut self, lr: LearningRate, module: M, grads: MultiGradientsParams) -> M {
        self.step_adapted(lr, module, grads.into(), None).0
    }

    fn to_record(&self) -> Self::Record {
        self.records.clone()
    }

    fn load_record(mut self, record: Self::Record) -> Self {
        self.records = record;
        self
    }
}

/// Collects the slot of every parameter that has a gradient, taking its state out of the records.
struct Gather<'a, M: AutodiffModule<B>, B: AutodiffBackend> {
    grads: GradAdaptor,
    records: &'a mut AdamWRecord<M, B>,
    /// Each slot's parameter and step number.
    ids: Vec<(ParamId, usize)>,
    slots: Vec<AdamWSlot<B::InnerBackend>>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> ModuleVisitor<B> for Gather<'_, M, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let Some((grad, device)) = self.grads.remove::<B::InnerBackend, D>(param.id) else {
            return;
        };
        let tensor = param.val().inner().to_device(&device);
        let state = self.records.remove(&param.id).map(|r| {
            let s: AdamWState<B::InnerBackend, D> = r.into_state();
            <AdamW as SimpleOptimizer<B::InnerBackend>>::to_device(s, &device).momentum
        });
        let time = state.as_ref().map_or(0, |s| s.time) + 1;
        self.ids.push((param.id, time));
        self.slots.push(AdamWSlot {
            param: tensor.into_primitive().tensor(),
            grad: grad.into_primitive().tensor(),
            moments: state.map(|s| {
                let raw = |t: Tensor<B::InnerBackend, D>| t.into_primitive().tensor();
                (raw(s.moment_1), raw(s.moment_2))
            }),
            time,
        });
    }
}

/// A parameter's step: done by the kernel (new parameter and moments, step number), or still to take.
enum Outcome<B: Backend> {
    Done([FloatTensor<B>; 3], usize),
    Pending(AdamWSlot<B>),
}

/// Puts each parameter's new value in the module and its moments in the records.
struct Apply<'a, M: AutodiffModule<B>, B: AutodiffBackend> {
    outcomes: HashMap<ParamId, Outcome<B::InnerBackend>>,
    step: &'a AdamWStep<B::InnerBackend>,
    burn: AdamW,
    records: &'a mut AdamWRecord<M, B>,
}

impl<M: AutodiffModule<B>, B: AutodiffBackend> ModuleMapper<B> for Apply<'_, M, B> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let (id, tensor, mapper) = param.consume();
        let Some(outcome) = self.outcomes.remove(&id) else {
            return Param::from_mapped_value(id, tensor, mapper);
        };
        let typed = |t: FloatTensor<B::InnerBackend>| {
            Tensor::<B::InnerBackend, D>::from_primitive(TensorPrimitive::Float(t))
        };
        let (value, state) = match outcome {
            Outcome::Done([p, m, v], time) => {
                let momentum = AdaptiveMomentumState {
                    time,
                    moment_1: typed(m),
                    moment_2: typed(v),
                    max_moment_2: None,
                };
                (typed(p), AdamWState { momentum })
            }
            Outcome::Pending(slot) => {
                let mut grad = typed(slot.grad);
                if let Some(scale) = &self.step.grad_scale {
                    grad = grad * typed1(scale.clone()).reshape([1; D]);
                }
                let state = slot.moments.map(|(m, v)| AdamWState {
                    momentum: AdaptiveMomentumState {
                        time: slot.time - 1,
                        moment_1: typed(m),
                        moment_2: typed(v),
                        max_moment_2: None,
                    },
                });
                let (p, s) = self.burn.step(self.step.lr, typed(slot.param), grad, state);
                let Some(s) = s else {
                    unreachable!("burn's AdamW always returns its state")
                };
                (p, s)
            }
        };
        self.records.insert(id, AdaptorRecord::from_state(state));
        let mut value = Tensor::from_inner(value);
        if tensor.is_require_grad() {
            value = value.require_grad();
        }
        Param::from_mapped_value(id, value, mapper)
    }
}

/// `t` as a rank-1 tensor (the gradient scale).
fn typed1<B: Backend>(t: FloatTensor<B>) -> Tensor<B, 1> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

/// [`AdamWKernel`]'s arithmetic in burn's operations on flattened tensors, in the order burn's AdamW
/// computes it: the reference a kernel is checked against, and what a kernel can run when it cannot
/// launch after taking the slots.
pub fn adamw_reference<B: Backend>(
    slots: Vec<AdamWSlot<B>>,
    step: &AdamWStep<B>,
) -> Vec<[FloatTensor<B>; 3]> {
    let s = step.settings;
    slots
        .into_iter()
        .map(|slot| {
            let shape = slot.param.shape();
            let flat = |t: FloatTensor<B>| {
                let n = t.shape().num_elements();
                Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(t)).reshape([n])
            };
            let mut g = flat(slot.grad);
            if let Some(scale) = &step.grad_scale {
                g = g * typed1::<B>(scale.clone());
            }
            let (m, v) = match slot.moments {
                Some((m, v)) => (
                    flat(m).mul_scalar(s.beta_1) + g.clone().mul_scalar(1.0 - s.beta_1),
                    flat(v).mul_scalar(s.beta_2) + g.square().mul_scalar(1.0 - s.beta_2),
                ),
                None => (
                    g.clone().mul_scalar(1.0 - s.beta_1),
                    g.square().mul_scalar(1.0 - s.beta_2),
                ),
            };
            let (c1, c2) = step.corrections(slot.time);
            let delta = m.clone().div_scalar(c1) / (v.clone().div_scalar(c2).sqrt().add_scalar(s.epsilon));
            let mut p = flat(slot.param);
            if let Some(decay) = step.decay() {
                p = p.mul_scalar(decay);
            }
            let p = p - delta.mul_scalar(step.lr);
            [p, m, v].map(|t| B::float_reshape(t.into_primitive().tensor(), shape.clone()))
        })
        .collect()
}

#[cfg(test)]
#[path = "adamw_tests.rs"]
mod tests;
