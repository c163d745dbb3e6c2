//! Errors of generation.

/// What can stop a rollout.
#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    /// Sampling or control settings that cannot be used.
    #[error("{0}")]
    Settings(String),
    /// History frames that do not fit the model.
    #[error("history: {0}")]
    History(String),
    /// The model refused a decoding step.
    #[error(transparent)]
    Model(#[from] umgen_backbone::BackboneError),
    /// The engine's executor refused an operation or the device failed.
    #[error("generation engine: {0}")]
    Engine(#[from] umgen_cuda::ExecError),
}

/// Result with [`GenerateError`].
pub type Result<T, E = GenerateError> = std::result::Result<T, E>;
