//! The operations on the CPU: the tiled attention against burn's, mixed precision, and the CUDA C kernels
//! run on the host by their emulators.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod attention;
mod emulator;
mod gelu;
mod lookup;
mod norm;
mod precision;
mod rows;
mod temporal;
mod xent;

/// Held while a test seeds burn and draws from it.
static SEEDED: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub type F = burn::backend::Flex;
pub type A = burn::backend::Autodiff<F>;
