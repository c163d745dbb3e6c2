//! Errors of the process group.

/// What can go wrong between ranks.
#[derive(Debug, thiserror::Error)]
pub enum DistError {
    /// An environment variable is missing or malformed.
    #[error("environment variable {var}={value:?}: {reason}")]
    Env {
        /// The variable.
        var: String,
        /// Its value (empty when unset).
        value: String,
        /// What is wrong.
        reason: String,
    },
    /// The rendezvous did not complete.
    #[error("rank {rank}: rendezvous at {addr}: {reason}")]
    Rendezvous {
        /// This process's rank.
        rank: usize,
        /// `MASTER_ADDR:MASTER_PORT`.
        addr: String,
        /// What went wrong.
        reason: String,
    },
    /// Rank 0 refused this rank (another config, world size or a duplicate rank).
    #[error("rank {rank}: refused by rank 0: {reason}")]
    Refused {
        /// This process's rank.
        rank: usize,
        /// Rank 0's reason.
        reason: String,
    },
    /// A collective failed: a peer died, hung or the connection broke.
    #[error("rank {rank}: {op} failed: {reason}")]
    Collective {
        /// This process's rank.
        rank: usize,
        /// The collective (`all-reduce`, `broadcast`, `barrier`).
        op: &'static str,
        /// Why (names the peer when known).
        reason: String,
    },
    /// NCCL or CUDA reported an error.
    #[error("rank {rank}: NCCL: {reason}")]
    Nccl {
        /// This process's rank.
        rank: usize,
        /// The error.
        reason: String,
    },
}

/// Result with [`DistError`].
pub type Result<T, E = DistError> = std::result::Result<T, E>;
