//! What steps AdamW on CUDA (`train.adamw`), and how often its kernels fell back.

use crate::dispatch::Choice;
use serde::{Deserialize, Serialize};

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
pub(super) static CHOICE: Choice = Choice::new("AdamW");

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
