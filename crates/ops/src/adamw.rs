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

mod choice;
#[cfg(feature = "cuda")]
mod cuda;
#[cfg(feature = "cuda")]
mod norm;
#[cfg(feature = "cuda")]
mod slots;

pub use choice::{AdamWChoice, fallbacks, select, selected};

use burn::tensor::backend::Backend;
use umgen_optim::MultiTensor;
#[cfg(feature = "cuda")]
use umgen_optim::{AdamWKernel, NormKernel};

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
