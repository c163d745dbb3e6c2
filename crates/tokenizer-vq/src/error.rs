//! Errors of VQ tokenizers.

use std::path::PathBuf;

/// What can go wrong building, training or running a VQ tokenizer.
#[derive(Debug, thiserror::Error)]
pub enum VqError {
    /// A bad setting, with its config key.
    #[error("config key `{key}`: {message}")]
    Config {
        /// Dotted key.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// Input rasters of the wrong size or values.
    #[error("{0}")]
    Input(String),
    /// Training data could not be produced.
    #[error("training data: {0}")]
    Data(String),
    /// A tokenizer file is missing, damaged or of another shape.
    #[error("tokenizer {path}: {message}")]
    Files {
        /// The tokenizer directory or file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Checkpoint I/O.
    #[error(transparent)]
    Checkpoint(#[from] umgen_checkpoint::CheckpointError),
    /// A collective of a data-parallel run failed.
    #[error(transparent)]
    Dist(#[from] umgen_dist::DistError),
    /// Metric file I/O.
    #[error("metrics in {path}: {error}")]
    Metrics {
        /// The run directory.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
}

/// Result with [`VqError`].
pub type Result<T, E = VqError> = std::result::Result<T, E>;
