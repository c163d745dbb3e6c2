//! Skipped steps: a step whose gradient norm or guard values are not finite leaves every parameter and
//! moment as it was, decided on the device through the gradient scale (NaN skips), so that guarding costs
//! the host no wait.

use crate::kernels::{AdamWStep, typed1};
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, Tensor};

/// The gradient that stands out in a step ([`FusedAdamW::largest_gradient`]).
#[derive(Debug, Clone, PartialEq)]
pub struct GradientPeak {
    /// The parameter's module path.
    pub name: String,
    /// Its gradient's L2 norm.
    pub norm: f64,
    /// Parameters whose gradient norm is not finite.
    pub non_finite: usize,
    /// Parameters with a gradient.
    pub params: usize,
}

/// `min(1, max_norm / norm)`, and 1 where the norm is NaN or infinite (as if not clipped).
pub(crate) fn clip_scale<B: Backend>(norm: Tensor<B, 1>, max_norm: f64) -> Tensor<B, 1> {
    let factor = norm.clone().clamp_min(max_norm).recip().mul_scalar(max_norm);
    factor.mask_fill(norm.is_finite().bool_not(), 1.0)
}

/// The gradient scale of a guarded step: the clipping factor (1 when `max_norm <= 0`), or NaN, which
/// skips the step, when the norm or a value of `guard` is not finite.
pub(crate) fn guarded_scale<B: Backend>(
    norm: Tensor<B, 1>,
    max_norm: f64,
    guard: Option<Tensor<B, 1>>,
) -> Tensor<B, 1> {
    let mut bad = norm.clone().is_finite().bool_not();
    if let Some(g) = guard {
        bad = bad.bool_or(g.is_finite().bool_not().any().reshape([1]));
    }
    let scale = if max_norm > 0.0 {
        clip_scale(norm, max_norm)
    } else {
        norm.ones_like()
    };
    scale.mask_fill(bad, f32::NAN)
}

/// `new` where the step went ahead, `old` where it was skipped (`skip`, `[1]`, broadcast).
pub(crate) fn unless_skipped<B: Backend, const D: usize>(
    new: Tensor<B, D>,
    old: Tensor<B, D>,
    skip: &Tensor<B, 1, Bool>,
) -> Tensor<B, D> {
    let mask = skip.clone().reshape([1; D]).expand(new.shape());
    new.mask_where(mask, old)
}

/// Whether a step with this gradient scale is skipped (`[1]`), if it has a scale.
pub(crate) fn skip_mask<B: Backend>(step: &AdamWStep<B>) -> Option<Tensor<B, 1, Bool>> {
    step.grad_scale
        .as_ref()
        .map(|s| typed1::<B>(s.clone()).is_finite().bool_not())
}
