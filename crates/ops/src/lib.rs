//! The operations umgen's backbone calls, each with its CPU path, its CUDA kernels and the policy that
//! picks between them.
//!
//! The model (`umgen-backbone`) is generic over `B: Backend` and calls these functions; on the backends
//! it trains on (`Autodiff<Flex>` on the CPU, `Autodiff<Cuda>`), most of them are custom autodiff
//! operations whose passes a trait of the inner backend computes: burn's tensor operations by default,
//! hand-written kernels on CUDA. Rust has no specialisation, so each operation recognises those backends
//! by type (`dispatch.rs`); any other backend takes burn's own operations, which compute the same function.
//!
//! - [`mod@format`]: the products' number format ([`Precision`]: f32, or bf16 operands with f32 master
//!   weights) and the casts around it; [`linear`]: linear layers in it, on the named kernel ([`matmul`]:
//!   cuBLAS or cubek) on CUDA, the bias (and the residual stream a layer joins) added by the product's
//!   epilogue (cuBLASLt on CUDA, `matmul::biased`); [`rows`]: column sums, and the bias add elsewhere.
//! - [`attention`]: the training attention as one operation that keeps only its inputs, output and
//!   log-sum-exp; its passes are [`flash`]'s kernels on CUDA (FlashAttention-2 in CUDA C, or cubecl
//!   kernels) and [`tiled`]'s blocks elsewhere. [`temporal`]: the TAR's attention over time on the rows
//!   as they lie. [`heads`]: the head layout.
//! - [`norm`] (layer norm), [`gelu`] (bias + GELU), [`lookup`] (embedding lookups and their gradient),
//!   [`xent`] (cross-entropy from logits, with [`smoothing`]'s targets): one kernel per pass on CUDA.
//! - [`layer`]: a pre-norm attention layer as one operation with a hand-written backward pass, which
//!   recomputes its activations (activation checkpointing) or reads the ones its forward pass kept.
//! - [`ready`]: points in the forward pass where the backward pass has completed a block's gradients,
//!   for data parallelism's overlapped all-reduce.
//! - [`adamw`]: the optimizer's multi-tensor AdamW step and gradient norm on CUDA.
//! - [`kernels`]: the kernel choices of a run ([`Kernels`]), one value the model passes to every
//!   operation; nothing here is chosen process-wide.

pub mod adamw;
pub mod attention;
mod dispatch;
pub mod flash;
pub mod format;
pub mod gelu;
pub mod heads;
pub mod kernels;
pub mod layer;
pub mod linear;
pub mod lookup;
pub mod matmul;
pub mod mlp;
pub mod norm;
pub mod ready;
pub mod rows;
#[cfg(feature = "cuda")]
mod side;
pub mod smoothing;
pub mod temporal;
pub mod tiled;
pub mod xent;

pub use format::Precision;
pub use kernels::{KeptInputs, Kernels};
#[cfg(feature = "cuda")]
pub use side::external;
#[cfg(feature = "cuda")]
pub use side::{device_thread_calls, foreign_streams};
