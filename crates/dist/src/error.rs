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
    /// Ranks disagree on something they must share (e.g. the step a resumed run starts from).
    #[error("rank {rank}: {what} is {value} here but {rank0} on rank 0")]
    Disagree {
        /// This process's rank.
        rank: usize,
        /// What was compared, and what usually causes a difference.
        what: String,
        /// This rank's value.
        value: u64,
        /// Rank 0's value.
        rank0: u64,
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
