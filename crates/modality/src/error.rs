//! Errors of modalities, the registry and the frame layout.

use umgen_scene::SceneError;

/// What can go wrong when building, registering or running a modality.
#[derive(Debug, thiserror::Error)]
pub enum ModalityError {
    /// Two modalities with one name.
    #[error("duplicate modality name `{name}`: each modality in a frame needs its own name")]
    DuplicateName {
        /// The repeated name.
        name: String,
    },
    /// Two factories for one kind.
    #[error("duplicate modality kind `{kind}` in the catalog")]
    DuplicateKind {
        /// The repeated kind.
        kind: String,
    },
    /// A config names a kind no factory builds.
    #[error("modality `{name}`: unknown kind `{kind}` (known kinds: {known})")]
    UnknownKind {
        /// Modality name.
        name: String,
        /// The unknown kind.
        kind: String,
        /// Comma-separated known kinds.
        known: String,
    },
    /// A lookup of a modality that is not registered.
    #[error("no modality named `{name}` is registered")]
    UnknownModality {
        /// The name looked up.
        name: String,
    },
    /// A config problem, with the full key path.
    #[error("config key `{key}`: {message}")]
    Config {
        /// Dotted key path, e.g. `modality.ego.dx`.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// A modality's spec is inconsistent.
    #[error("modality `{modality}`: invalid spec: {reason}")]
    InvalidSpec {
        /// Modality name.
        modality: String,
        /// What is wrong.
        reason: String,
    },
    /// A registry with no modality has no layout.
    #[error("the registry holds no modality; `layout.order` must name at least one")]
    Empty,
    /// A token block of the wrong length.
    #[error("modality `{modality}`: expected {expected} tokens per frame, got {actual}")]
    TokenCount {
        /// Modality name.
        modality: String,
        /// Tokens per frame in the spec.
        expected: usize,
        /// Tokens given.
        actual: usize,
    },
    /// A token id outside the vocabulary allowed at its position.
    #[error("modality `{modality}`: token {id} at frame position {position} is outside {allowed}")]
    TokenOutOfVocab {
        /// Modality name.
        modality: String,
        /// Position in the frame (or within the block for block-level checks).
        position: usize,
        /// The id.
        id: u32,
        /// The allowed ids, in words.
        allowed: String,
    },
    /// A frame lacks the input a modality reads.
    #[error("modality `{modality}`: frame {frame} has no {what}")]
    MissingInput {
        /// Modality name.
        modality: String,
        /// Frame index in its clip.
        frame: usize,
        /// What is missing.
        what: String,
    },
    /// A value that cannot be tokenized (NaN or infinite).
    #[error("modality `{modality}`: field `{field}` has the non-finite value {value}")]
    NonFinite {
        /// Modality name.
        modality: String,
        /// Field name.
        field: String,
        /// The value.
        value: f64,
    },
    /// A modality-specific failure (for example a tokenizer that cannot run).
    #[error("modality `{modality}`: {message}")]
    Tokenizer {
        /// Modality name.
        modality: String,
        /// What failed.
        message: String,
    },
    /// Invalid scene data.
    #[error(transparent)]
    Scene(#[from] SceneError),
}

/// Result with [`ModalityError`].
pub type Result<T, E = ModalityError> = std::result::Result<T, E>;
