//! The multi-tensor kernels that [`umgen_optim::FusedAdamW`] steps through on CUDA: AdamW and the
//! gradients' global norm (for clipping).
//!
//! On `Cuda` each is one custom operation in burn-fusion's stream, unless `train.adamw = "burn"`
//! ([`select`]): the AdamW step launches `adamw/adamw.cu`'s `umgen_adamw` once per 32 parameter tensors
//! (every tensor's update, the clipping factor applied to each gradient as it is read), the norm
//! `umgen_sumsq` once per 128 gradients and `umgen_sumsq_final` once, all on cubecl's stream with the
//! tensors bound as the launches' buffers, so the host fetches no device address. burn's AdamW took a
//! chain of about ten operations per parameter tensor and the norm two, for 331 tensors in `small`. Other
//! types than f32, or a failure to compile or launch, run [`umgen_optim::adamw_reference`] and
//! [`umgen_optim::norm_reference`] instead, counted by [`fallbacks`]. Other backends have no kernels:
//! the optimizer steps tensor by tensor with burn's AdamW.

#[cfg(feature = "cuda")]
mod cuda;
#[cfg(feature = "cuda")]
mod norm;

use crate::dispatch::Choice;
use burn::tensor::backend::Backend;
use serde::{Deserialize, Serialize};
use umgen_optim::MultiTensor;
#[cfg(feature = "cuda")]
use umgen_optim::{AdamWKernel, NormKernel};

/// What steps AdamW when training on CUDA (`train.adamw`); the CPU always steps tensor by tensor.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AdamWChoice {
    /// One CUDA C kernel for all parameter tensors (`adamw/adamw.cu`). The default.
    #[default]
    Fused,
    /// burn's AdamW, one chain of tensor operations per parameter tensor (as before the kernel).
    Burn,
}

/// The process's choice and its fallbacks.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
static CHOICE: Choice = Choice::new("AdamW");

/// Chooses what steps AdamW in every training step this process runs from now on.
pub fn select(choice: AdamWChoice) {
    CHOICE.set_burn(choice == AdamWChoice::Burn);
}

/// What [`select`] chose ([`AdamWChoice::Fused`] unless told otherwise).
pub fn selected() -> AdamWChoice {
    if CHOICE.burn() {
        AdamWChoice::Burn
    } else {
        AdamWChoice::Fused
    }
}

/// How many AdamW steps fell back from the CUDA kernel in this process.
pub fn fallbacks() -> usize {
    CHOICE.fallbacks()
}

/// The multi-tensor kernels for parameters on `B`, if `B` has them. They read [`selected`] at every step
/// (declining with `train.adamw = "burn"`), so that `umgen-kernel-bench train --alternate` can switch them.
pub fn kernels<B: Backend>() -> Option<MultiTensor<B>> {
    #[cfg(feature = "cuda")]
    {
        let adamw: AdamWKernel<burn::backend::Cuda> = cuda::step;
        let norm: NormKernel<burn::backend::Cuda> = norm::global_norm;
        Some(MultiTensor {
            adamw: crate::dispatch::same(adamw)?,
            norm: crate::dispatch::same(norm)?,
        })
    }
    #[cfg(not(feature = "cuda"))]
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cpu_has_no_kernel() {
        assert!(kernels::<burn::backend::Flex>().is_none());
        assert!(kernels::<burn::backend::Autodiff<burn::backend::Flex>>().is_none());
    }
}
