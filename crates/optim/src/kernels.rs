//! What a backend's multi-tensor kernels take and return ([`MultiTensor`]), and the same arithmetic in
//! burn's operations ([`adamw_reference`], [`norm_reference`]): what the kernels are checked against and
//! what runs where a backend has none.

use crate::adamw::AdamWSettings;
use crate::skip::{skip_mask, unless_skipped};
use burn::optim::LearningRate;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};
use std::sync::Arc;

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

/// A backend's multi-tensor AdamW step (a closure: the backend's launch settings travel with it).
pub type AdamWKernel<B> = Arc<dyn Fn(Vec<AdamWSlot<B>>, &AdamWStep<B>) -> AdamWStepped<B> + Send + Sync>;

/// The gradients' global L2 norm and the sums of squares it adds up, on the device.
#[derive(Debug, Clone)]
pub struct GradNorm<B: Backend> {
    /// `[1]`: the norm.
    pub norm: Tensor<B, 1>,
    /// `[K]`: sums of squares of parts of the gradients, each part within one gradient.
    pub parts: Tensor<B, 1>,
    /// How many consecutive parts each gradient (in the order given) has: the parts are the gradients'
    /// in order, so the first `spans[0]` belong to the first gradient, and so on.
    pub spans: Vec<usize>,
}

/// A backend's global L2 norm of tensors of any rank, or the reason it cannot take them.
pub type NormKernel<B> = Arc<dyn Fn(&[FloatTensor<B>]) -> Result<GradNorm<B>, String> + Send + Sync>;

/// A backend's multi-tensor kernels for [`FusedAdamW`].
pub struct MultiTensor<B: Backend> {
    /// The AdamW step.
    pub adamw: AdamWKernel<B>,
    /// The gradients' global norm, for clipping.
    pub norm: NormKernel<B>,
}

// By hand: derived, they would ask `B` to be `Clone` and the closures to be `Debug`.
impl<B: Backend> Clone for MultiTensor<B> {
    fn clone(&self) -> Self {
        Self {
            adamw: Arc::clone(&self.adamw),
            norm: Arc::clone(&self.norm),
        }
    }
}

impl<B: Backend> std::fmt::Debug for MultiTensor<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("MultiTensor { adamw, norm }")
    }
}

/// The global L2 norm of `grads` in burn's operations, as [`crate::grad_norm`] computes it (each tensor's
/// sum of squares, then their sum): what the norm kernel is checked against, and what runs without one.
pub fn norm_reference<B: Backend>(grads: &[FloatTensor<B>]) -> GradNorm<B> {
    let parts: Vec<Tensor<B, 1>> = grads
        .iter()
        .map(|g| {
            let n = g.shape().num_elements();
            typed1::<B>(g.clone()).reshape([n]).powf_scalar(2.0).sum()
        })
        .collect();
    let parts = Tensor::cat(parts, 0);
    GradNorm {
        norm: parts.clone().sum().sqrt(),
        parts,
        spans: vec![1; grads.len()],
    }
}
/// `t` as a rank-1 tensor (the gradient scale).
pub(crate) fn typed1<B: Backend>(t: FloatTensor<B>) -> Tensor<B, 1> {
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
            let (old_m, old_v) = match &slot.moments {
                Some((m, v)) => (Some(flat(m.clone())), Some(flat(v.clone()))),
                None => (None, None),
            };
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
            let before = flat(slot.param);
            let mut p = before.clone();
            if let Some(decay) = step.decay() {
                p = p.mul_scalar(decay);
            }
            let mut out = [p - delta.mul_scalar(step.lr), m, v];
            if let Some(skip) = skip_mask(step) {
                let (p, zeros) = (before.clone(), before.zeros_like());
                let [np, nm, nv] = out;
                out = [
                    unless_skipped(np, p, &skip),
                    unless_skipped(nm, old_m.unwrap_or_else(|| zeros.clone()), &skip),
                    unless_skipped(nv, old_v.unwrap_or(zeros), &skip),
                ];
            }
            out.map(|t| B::float_reshape(t.into_primitive().tensor(), shape.clone()))
        })
        .collect()
}
