//! Errors of the backbone.

/// What can be wrong building or running the backbone.
#[derive(Debug, thiserror::Error)]
pub enum BackboneError {
    /// The frame spec does not fit the config.
    #[error("backbone spec: {0}")]
    Spec(String),
    /// Input tokens of the wrong shape.
    #[error("backbone input: {0}")]
    Input(String),
}

/// Result with [`BackboneError`].
pub type Result<T, E = BackboneError> = std::result::Result<T, E>;
