//! Errors of configuration loading.

use std::path::PathBuf;

/// What can be wrong with a configuration.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file cannot be read.
    #[error("cannot read config file {path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// The file is not valid TOML.
    #[error("config file {path} is not valid TOML: {message}")]
    Syntax {
        /// The file.
        path: PathBuf,
        /// The parser's message, with line and column.
        message: String,
    },
    /// A `--set` argument is malformed.
    #[error("override `{arg}`: {message}")]
    Override {
        /// The argument as given.
        arg: String,
        /// What is wrong.
        message: String,
    },
    /// A key has the wrong type, is unknown, or is missing.
    #[error("config key `{key}` ({origin}): {message}")]
    Key {
        /// Dotted key path.
        key: String,
        /// Which layer set it: the file, an environment variable, or a `--set` override.
        origin: String,
        /// What is wrong.
        message: String,
    },
    /// The layers could not be merged.
    #[error("cannot merge config layers for {path}: {message}")]
    Merge {
        /// The file.
        path: PathBuf,
        /// The merge error.
        message: String,
    },
}

/// Result with [`ConfigError`].
pub type Result<T, E = ConfigError> = std::result::Result<T, E>;
