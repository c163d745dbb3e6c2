//! How often the AdamW kernels fell back (what steps AdamW is [`crate::Kernels::adamw`]).

use crate::dispatch::Fallbacks;

/// Steps the kernels refused in this process.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
pub(super) static FALLBACKS: Fallbacks = Fallbacks::new("AdamW");

/// How many AdamW steps fell back from the CUDA kernel in this process.
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}
