//! The operations on the CPU: the tiled attention against burn's, and mixed precision. (The CUDA C
//! kernels' host emulators run in umgen-cuda's tests.)
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod attention;
mod precision;

/// Held while a test seeds burn and draws from it.
static SEEDED: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub type F = burn::backend::Flex;
pub type A = burn::backend::Autodiff<F>;
