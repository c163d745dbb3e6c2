//! Optimisation helpers shared by umgen's trainers.
//!
//! - [`Schedule`]: linear warm-up to the peak learning rate, then cosine decay to a floor at the last step
//!   (and flat after it: unlike burn's cosine scheduler it never restarts).
//! - [`clip_grad_norm`]: scales all gradients so that their global L2 norm is at most a bound (burn's own
//!   clipping works per parameter), without a device-to-host transfer.
//! - [`FusedAdamW`]: AdamW over all parameter tensors at once, through a backend's kernels where it has
//!   them, with the same clipping applied as it reads the gradients ([`FusedAdamW::step_clipped`]).
//! - [`adam_epsilon`]: a configured AdamW ε as the f32 the optimizer takes, or nothing if it is not usable.

mod adamw;
mod kernels;
mod skip;

pub use adamw::{AdamWRecord, AdamWSettings, FusedAdamW, Stepped};
pub use kernels::{
    AdamWKernel, AdamWSlot, AdamWStep, AdamWStepped, GradNorm, MultiTensor, NormKernel, adamw_reference,
    norm_reference,
};
pub use skip::GradientPeak;

use burn::module::{AutodiffModule, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;
use burn::tensor::backend::AutodiffBackend;
use serde::{Deserialize, Serialize};

/// Warm-up + cosine learning rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    /// Peak learning rate.
    pub peak: f64,
    /// Steps of linear warm-up from `peak / warmup` to `peak`.
    pub warmup: u64,
    /// Step at which the cosine reaches the floor.
    pub total: u64,
    /// Final learning rate as a fraction of the peak.
    pub floor: f64,
}

impl Schedule {
    /// The learning rate of step `step` (0-based).
    pub fn lr(&self, step: u64) -> f64 {
        if step < self.warmup {
            return self.peak * (step + 1) as f64 / self.warmup as f64;
        }
        let span = self.total.saturating_sub(self.warmup).max(1) as f64;
        let t = ((step - self.warmup) as f64 / span).min(1.0);
        let low = self.peak * self.floor;
        low + 0.5 * (self.peak - low) * (1.0 + (std::f64::consts::PI * t).cos())
    }
}

struct SquaredNorms<'a, B: AutodiffBackend> {
    grads: &'a GradientsParams,
    parts: Vec<Tensor<B::InnerBackend, 1>>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for SquaredNorms<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if let Some(g) = self.grads.get::<B::InnerBackend, D>(param.id) {
            self.parts.push(g.powf_scalar(2.0).sum());
        }
    }
}

struct Scale<'a, B: AutodiffBackend> {
    grads: &'a mut GradientsParams,
    /// `[1]`, broadcast over every gradient.
    factor: Tensor<B::InnerBackend, 1>,
    _b: std::marker::PhantomData<B>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Scale<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if let Some(g) = self.grads.remove::<B::InnerBackend, D>(param.id) {
            let factor = self.factor.clone().reshape([1; D]);
            self.grads.register(param.id, g * factor);
        }
    }
}

/// The global L2 norm of `grads` over the parameters of `model`, on the device (`[1]`).
pub fn grad_norm<B: AutodiffBackend, M: AutodiffModule<B>>(
    model: &M,
    grads: &GradientsParams,
) -> Tensor<B::InnerBackend, 1> {
    let mut v = SquaredNorms::<B> {
        grads,
        parts: Vec::new(),
    };
    model.visit(&mut v);
    if v.parts.is_empty() {
        return Tensor::zeros([1], &Default::default());
    }
    Tensor::cat(v.parts, 0).sum().sqrt()
}

/// Scales `grads` so that their global norm is at most `max_norm` (no-op when `max_norm <= 0`, or when the
/// norm is not finite) and returns the norm before scaling, still on the device: the factor is computed
/// there, so clipping does not make the host wait for the backward pass (read the norm only when logging).
pub fn clip_grad_norm<B: AutodiffBackend, M: AutodiffModule<B>>(
    model: &M,
    grads: &mut GradientsParams,
    max_norm: f64,
) -> Tensor<B::InnerBackend, 1> {
    let norm = grad_norm::<B, M>(model, grads);
    if max_norm > 0.0 {
        let factor = skip::clip_scale(norm.clone(), max_norm);
        model.visit(&mut Scale::<B> {
            grads,
            factor,
            _b: std::marker::PhantomData,
        });
    }
    norm
}

/// AdamW's ε as the f32 burn's optimizer takes, when it is positive and stays positive and finite in f32
/// (1e-50 would round to 0, 1e300 to infinity); `None` otherwise, for the caller to refuse by its key.
pub fn adam_epsilon(eps: f64) -> Option<f32> {
    let e = eps as f32;
    (eps > 0.0 && e > 0.0 && e.is_finite()).then_some(e)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Module;
    use burn::nn::{Initializer, Linear, LinearConfig};
    use burn::tensor::ElementConversion;

    type B = burn::backend::Autodiff<burn::backend::Flex>;

    #[test]
    fn schedule_warms_up_then_decays_without_restart() {
        let s = Schedule {
            peak: 1e-3,
            warmup: 10,
            total: 110,
            floor: 0.1,
        };
        assert!((s.lr(0) - 1e-4).abs() < 1e-12);
        assert!((s.lr(9) - 1e-3).abs() < 1e-12);
        assert!((s.lr(10) - 1e-3).abs() < 1e-12);
        assert!((s.lr(60) - (1e-4 + 0.5 * 9e-4)).abs() < 1e-12);
        assert!((s.lr(110) - 1e-4).abs() < 1e-12);
        assert!((s.lr(500) - 1e-4).abs() < 1e-12);
    }

    #[derive(Module, Debug)]
    struct Net<B: burn::tensor::backend::Backend> {
        a: Linear<B>,
        b: Linear<B>,
    }

    #[test]
    fn clipping_matches_the_global_norm() {
        let dev = Default::default();
        // Fixed weights: a random draw can put the output sum near 0 and the gradient norm under the
        // bound, which made this test fail about once in a few hundred runs.
        let constant = |value| Initializer::Constant { value };
        let m = Net::<B> {
            a: LinearConfig::new(3, 4).with_initializer(constant(0.5)).init(&dev),
            b: LinearConfig::new(4, 2)
                .with_initializer(constant(-0.25))
                .init(&dev),
        };
        let x = Tensor::<B, 2>::ones([2, 3], &dev).mul_scalar(3.0);
        let loss = m.b.forward(m.a.forward(x)).sum().powf_scalar(2.0);
        let mut g = GradientsParams::from_grads(loss.backward(), &m);
        // Independent computation: the sum of squares of every gradient tensor.
        let mut want = 0.0f64;
        for id in [m.a.weight.id, m.b.weight.id] {
            let t = g.get::<burn::backend::Flex, 2>(id).unwrap();
            want += t.powf_scalar(2.0).sum().into_scalar().elem::<f64>();
        }
        for id in [m.a.bias.as_ref().unwrap().id, m.b.bias.as_ref().unwrap().id] {
            let t = g.get::<burn::backend::Flex, 1>(id).unwrap();
            want += t.powf_scalar(2.0).sum().into_scalar().elem::<f64>();
        }
        let norm: f64 = clip_grad_norm::<B, _>(&m, &mut g, 0.5).into_scalar().elem();
        assert!(
            (norm - want.sqrt()).abs() / norm < 1e-5,
            "{norm} vs {}",
            want.sqrt()
        );
        assert!(norm > 0.5);
        let after: f64 = grad_norm::<B, _>(&m, &g).into_scalar().elem();
        assert!((after - 0.5).abs() < 1e-4);
        // A bound above the norm, or none, leaves the gradients as they are.
        for bound in [1.0, 0.0] {
            let before: f64 = clip_grad_norm::<B, _>(&m, &mut g, bound).into_scalar().elem();
            let now: f64 = grad_norm::<B, _>(&m, &g).into_scalar().elem();
            assert!((before - now).abs() < 1e-7, "bound {bound}: {before} -> {now}");
        }
    }

    #[test]
    fn adam_epsilon_keeps_what_f32_holds() {
        assert_eq!(adam_epsilon(1e-8), Some(1e-8));
        assert_eq!(adam_epsilon(1.0), Some(1.0));
        for bad in [0.0, -1e-8, 1e-50, 1e300, f64::NAN, f64::INFINITY] {
            assert_eq!(adam_epsilon(bad), None, "{bad}");
        }
    }
}
