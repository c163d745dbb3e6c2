//! Errors of the facade.

/// Anything that can fail while setting up a run.
#[derive(Debug, thiserror::Error)]
pub enum UmgenError {
    /// Loading or typing the configuration.
    #[error(transparent)]
    Config(#[from] umgen_config::ConfigError),
    /// Building modalities or the layout.
    #[error(transparent)]
    Modality(#[from] umgen_modality::ModalityError),
    /// Datasets and token caches.
    #[error(transparent)]
    Data(#[from] umgen_data::DataError),
    /// VQ tokenizers.
    #[error(transparent)]
    Vq(#[from] umgen_tokenizer_vq::VqError),
    /// The backbone.
    #[error(transparent)]
    Backbone(#[from] umgen_backbone::BackboneError),
    /// Training.
    #[error(transparent)]
    Train(#[from] umgen_train::TrainError),
    /// Checkpoints.
    #[error(transparent)]
    Checkpoint(#[from] umgen_checkpoint::CheckpointError),
    /// An export bundle that is missing, damaged or does not match.
    #[error("bundle {path}: {message}")]
    Bundle {
        /// The bundle directory or file.
        path: std::path::PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A configuration given as text is not valid.
    #[error("invalid configuration text: {0}")]
    Text(String),
}

/// Result with [`UmgenError`].
pub type Result<T, E = UmgenError> = std::result::Result<T, E>;
