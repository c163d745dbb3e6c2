//! Data-parallel training across processes and nodes.
//!
//! One process per GPU, started by `umgen launch`, torchrun or SLURM ([`DistEnv`] reads either
//! contract). The processes meet at rank 0 ([`Session::connect`]: a TCP rendezvous that checks world size
//! and config identity and hands out the NCCL id), keep a [`Watchdog`] that fails every rank, naming the
//! culprit, when one dies or hangs, and run collectives through a [`ProcessGroup`]: [`TcpGroup`] (a ring
//! over TCP through host memory; CPU runs and tests) or, with the `cuda` feature, `NcclGroup` (NCCL on the
//! device memory of burn-cuda tensors). [`Overlap`] averages a training step's gradients in buckets
//! that start while the backward pass goes on; [`all_reduce_grads`] averages given gradients in buckets
//! and [`broadcast_module`] copies rank 0's parameters to every rank. [`Shards`] shares the optimizer's
//! parameters out among the ranks (ZeRO stage 1) and copies each updated one from its owner to all.

mod env;
mod error;
#[cfg(test)]
mod fake;
mod grads;
mod group;
#[cfg(feature = "cuda")]
mod nccl;
mod overlap;
mod ring;
mod session;
mod shard;
mod watchdog;
mod wire;

pub use env::{DEFAULT_PORT, DistEnv, first_host};
pub use error::{DistError, Result};
pub use grads::{all_reduce_grads, broadcast_module, rank0_decides, same_on_all_ranks};
pub use group::{AsyncCollective, Group, ProcessGroup, Single, TcpGroup};
#[cfg(feature = "cuda")]
pub use nccl::{NcclGroup, nccl_id};
pub use overlap::Overlap;
pub use session::{Session, SessionOptions};
pub use shard::Shards;
pub use watchdog::{FailureHook, Watchdog};

/// Default size of a gradient bucket: 25 MiB, as in PyTorch's DDP.
pub const DEFAULT_BUCKET_BYTES: usize = 25 << 20;
