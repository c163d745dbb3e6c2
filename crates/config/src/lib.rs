//! Layered configuration for umgen.
//!
//! A run's settings come from three layers, later ones winning:
//! 1. a TOML file (`--config configs/tiny.toml`);
//! 2. environment variables `UMGEN__SECTION__KEY=value` (nested keys joined by `__`, lower-cased);
//! 3. command-line overrides `--set section.key=value`, where `value` is read as a TOML value when it
//!    parses as one (`3`, `true`, `[0.0, 10.0]`, `"text"`) and as a plain string otherwise.
//!
//! [`RawConfig::load`] merges the layers with the `config` crate; [`RawConfig::parse`] turns the result
//! into a typed struct. Unknown keys and wrong types are errors that name the full key path and the layer
//! it came from. Each component owns its section's struct and marks it `#[serde(deny_unknown_fields)]`.
//!
//! ```no_run
//! #[derive(serde::Deserialize)]
//! #[serde(deny_unknown_fields)]
//! struct Train { steps: usize }
//! #[derive(serde::Deserialize)]
//! #[serde(deny_unknown_fields)]
//! struct Run { train: Train }
//! let raw = umgen_config::RawConfig::load("configs/tiny.toml".as_ref(), &["train.steps=60".into()])?;
//! let run: Run = raw.parse()?;
//! # Ok::<(), umgen_config::ConfigError>(())
//! ```

mod error;
mod layers;

pub use error::{ConfigError, Result};
pub use layers::{ENV_PREFIX, RawConfig};
