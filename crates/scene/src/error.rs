//! Errors of the scene model.

/// What can be wrong with scene data.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// A raster's buffer does not match its declared shape.
    #[error("{what}: buffer holds {actual} values, shape {shape:?} needs {expected}")]
    BufferSize {
        /// Which raster (for example "map raster").
        what: &'static str,
        /// Declared shape.
        shape: Vec<usize>,
        /// Values the shape needs.
        expected: usize,
        /// Values present.
        actual: usize,
    },
    /// A clip is not usable (empty, bad interval, non-finite values).
    #[error("clip `{clip}`: {reason}")]
    InvalidClip {
        /// Clip id.
        clip: String,
        /// What is wrong.
        reason: String,
    },
    /// A frame index past the end of a clip.
    #[error("clip `{clip}` has {len} frames; frame {index} does not exist")]
    FrameOutOfRange {
        /// Clip id.
        clip: String,
        /// Number of frames.
        len: usize,
        /// Requested index.
        index: usize,
    },
}

/// Result with [`SceneError`].
pub type Result<T, E = SceneError> = std::result::Result<T, E>;
