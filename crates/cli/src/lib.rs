//! The `umgen` command line as a library: [`App`] (the commands with a user's modality kinds added), its
//! argument types ([`cli`]), one module per command
//! ([`commands`]), the device and backend choice ([`device`], [`with_autodiff!`], [`with_inference!`]),
//! the CUDA memory pool's layout ([`memory_pool`]),
//! the data-parallel process setup ([`dist`]), logging and progress bars. The `umgen` binary is its
//! `main`; developer tools (`dev/kernel-bench`) build on the same pieces.

mod app;
pub mod cli;
pub mod commands;
pub mod device;
pub mod dist;
pub mod logging;
pub mod memory_pool;
pub mod progress;

pub use app::{App, Kinds, run_main};
