//! Errors of checkpoints.

use std::path::PathBuf;

/// What can go wrong saving or loading a checkpoint.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// A file cannot be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// A checkpoint is damaged or incomplete.
    #[error("checkpoint {path}: {reason}")]
    Corrupt {
        /// The checkpoint directory or file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A checkpoint does not fit the run that wants it (other layout, other model).
    #[error("checkpoint {path} does not match this run: {reason}")]
    Mismatch {
        /// The checkpoint directory.
        path: PathBuf,
        /// What differs.
        reason: String,
    },
    /// A run directory holds checkpoints and none of them verifies.
    #[error(
        "{root} holds {} checkpoint(s) and none is readable (nothing was changed; restore one, or move them away to start afresh): {}",
        reasons.len(),
        reasons.join("; ")
    )]
    NoneReadable {
        /// The checkpoint directory.
        root: PathBuf,
        /// Why each checkpoint, newest first, does not verify.
        reasons: Vec<String>,
    },
    /// Weights cannot be serialised or applied.
    #[error("{what}: {reason}")]
    Weights {
        /// Which weights.
        what: String,
        /// What went wrong.
        reason: String,
    },
}

/// Result with [`CheckpointError`].
pub type Result<T, E = CheckpointError> = std::result::Result<T, E>;

pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> CheckpointError {
    let path = path.into();
    move |error| CheckpointError::Io { path, error }
}
