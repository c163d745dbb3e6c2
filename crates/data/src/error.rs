//! Errors of datasets and importers. Every variant names the file involved.

use std::path::PathBuf;

/// What can go wrong reading, writing or importing a dataset.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file cannot be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// A file is damaged: bad magic, checksum mismatch, truncated, inconsistent header.
    #[error("{path}: corrupt or truncated: {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// An input file (XML) is malformed or inconsistent, at a line.
    #[error("{path}:{line}: {message}")]
    Input {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A request the dataset cannot serve (unknown clip, window past the clip's end, …).
    #[error("{path}: {message}")]
    Request {
        /// The dataset directory.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Result with [`DataError`].
pub type Result<T, E = DataError> = std::result::Result<T, E>;

/// Wraps an I/O error with its path.
pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> DataError {
    let path = path.into();
    move |error| DataError::Io { path, error }
}

/// A corruption error for `path`.
pub(crate) fn corrupt(path: impl Into<PathBuf>, reason: impl Into<String>) -> DataError {
    DataError::Corrupt {
        path: path.into(),
        reason: reason.into(),
    }
}
