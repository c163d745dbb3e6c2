//! The multi-tensor kernels that [`umgen_optim::FusedAdamW`] steps through on CUDA: AdamW and the
//! gradients' global norm (for clipping).
//!
//! On `Cuda` each is one custom operation in burn-fusion's stream, unless `train.kernels.adamw = "burn"`
//!: the AdamW step launches umgen-cuda's `kernels/train/adamw.cu`'s `umgen_adamw` once per 32 parameter tensors
//! (every tensor's update, the clipping factor applied to each gradient as it is read), the norm
//! `umgen_sumsq` once per 128 gradients and `umgen_sumsq_final` once, all on cubecl's stream with the
//! tensors bound as the launches' buffers, so the host fetches no device address. burn's AdamW took a
//! chain of about ten operations per parameter tensor and the norm two, for 331 tensors in `small`. Other
//! types than f32, or a failure to compile or launch, run [`umgen_optim::adamw_reference`] and
//! [`umgen_optim::norm_reference`] instead, counted by [`fallbacks`]. Other backends have no kernels:
//! the optimizer steps tensor by tensor with burn's AdamW.

#[cfg(feature = "cuda")]
mod cuda;
mod fallbacks;
#[cfg(feature = "cuda")]
mod norm;
#[cfg(feature = "cuda")]
mod slots;

pub use crate::kernels::AdamWChoice;
pub use fallbacks::fallbacks;

use crate::kernels::Kernels;
use burn::tensor::backend::Backend;
use umgen_optim::MultiTensor;

/// The multi-tensor kernels for parameters on `B`, launched as `k` says, if `B` has them and `k` chooses
/// them (`k.adamw`); `None` steps tensor by tensor with burn's AdamW.
pub fn kernels<B: Backend>(k: &Kernels) -> Option<MultiTensor<B>> {
    if k.adamw == AdamWChoice::Burn {
        return None;
    }
    #[cfg(feature = "cuda")]
    {
        use crate::kernels::LaunchThread;
        use burn::backend::Cuda;
        use burn::tensor::ops::FloatTensor;
        use std::sync::Arc;
        use umgen_optim::{AdamWSlot, AdamWStep, AdamWStepped, GradNorm};
        type Step<B> = fn(Vec<AdamWSlot<B>>, &AdamWStep<B>, LaunchThread) -> AdamWStepped<B>;
        type Norm<B> = fn(&[FloatTensor<B>], LaunchThread) -> Result<GradNorm<B>, String>;
        let (step, norm): (Step<Cuda>, Norm<Cuda>) = (cuda::step, norm::global_norm);
        let (step, norm) = (
            crate::dispatch::same::<_, Step<B>>(step)?,
            crate::dispatch::same::<_, Norm<B>>(norm)?,
        );
        let thread = k.launch_thread;
        Some(MultiTensor {
            adamw: Arc::new(move |slots, s| step(slots, s, thread)),
            norm: Arc::new(move |grads| norm(grads, thread)),
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
        let k = Kernels::DEFAULT;
        assert!(kernels::<burn::backend::Flex>(&k).is_none());
        assert!(kernels::<burn::backend::Autodiff<burn::backend::Flex>>(&k).is_none());
    }
}
