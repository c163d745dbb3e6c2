//! Errors of training.

use std::path::PathBuf;

/// What can stop a training run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A setting or the data do not allow training.
    #[error("{0}")]
    Setup(String),
    /// The run directory holds checkpoints of another run, or a run that was not asked to resume.
    #[error("{path}: {message}")]
    RunDir {
        /// The run directory.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The model could not be built or run.
    #[error(transparent)]
    Backbone(#[from] umgen_backbone::BackboneError),
    /// Tokens could not be read.
    #[error(transparent)]
    Data(#[from] umgen_data::DataError),
    /// Checkpoint I/O.
    #[error(transparent)]
    Checkpoint(#[from] umgen_checkpoint::CheckpointError),
    /// A collective between ranks failed.
    #[error(transparent)]
    Dist(#[from] umgen_dist::DistError),
    /// A step's loss or gradient norm is not finite and `train.nonfinite` (or `max_skipped_steps`) stops
    /// the run; the newest checkpoint holds weights from before it.
    #[error(
        "step {step}: the loss or the gradient norm is not finite: {message}; the run stopped without writing a checkpoint from a skipped step"
    )]
    NonFinite {
        /// The first such step (counted from 1).
        step: u64,
        /// The loss terms, gradient norm and largest gradient, and why the run stops.
        message: String,
    },
    /// Metric files.
    #[error("metrics in {path}: {error}")]
    Metrics {
        /// The run directory.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
}

/// Result with [`TrainError`].
pub type Result<T, E = TrainError> = std::result::Result<T, E>;
