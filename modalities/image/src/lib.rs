//! The image modality (paper supplementary B.2.4): the front camera view (default 3×256×512 RGB),
//! encoded by a VQ tokenizer into a `grid` of codebook ids (default 16×32 codes from 8192 entries,
//! 16× downsampling).
//!
//! The layout needs only the grid and the codebook size, so a config can be inspected without trained
//! tokenizer weights; tokenizing frames needs the weights.

use serde::{Deserialize, Serialize};
use std::sync::Arc;
use umgen_modality::{
    DecodeReport, Modality, ModalityError, ModalitySpec, Result, downsampling, parse_settings,
};
use umgen_scene::{Frame, SceneClip};

/// The kind name used in configs.
pub const KIND: &str = "image";

/// Settings of the image modality (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImageConfig {
    /// Image rows and columns.
    pub size: [usize; 2],
    /// Token grid rows and columns; the image must divide into it evenly.
    pub grid: [usize; 2],
    /// Codebook entries (the vocabulary).
    pub codebook_size: u32,
}

impl Default for ImageConfig {
    fn default() -> Self {
        Self {
            size: [256, 512],
            grid: [16, 32],
            codebook_size: 8192,
        }
    }
}

/// The image modality.
#[derive(Debug)]
pub struct ImageModality {
    spec: ModalitySpec,
    config: ImageConfig,
}

impl ImageModality {
    /// An image modality called `name`.
    pub fn new(name: &str, config: ImageConfig) -> Result<Self> {
        downsampling(&format!("modality.{name}.grid"), config.size, config.grid)?;
        let [rows, cols] = config.grid;
        let spec = ModalitySpec::new(name, KIND, config.codebook_size, rows * cols).with_grid(rows, cols);
        Ok(Self { spec, config })
    }

    /// Builds the modality from its config table; the factory registered under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }

    /// The settings in use.
    pub fn config(&self) -> &ImageConfig {
        &self.config
    }

    fn no_tokenizer(&self) -> ModalityError {
        ModalityError::Tokenizer {
            modality: self.spec.name.clone(),
            message: "no VQ tokenizer is attached, so camera images cannot be encoded or decoded".into(),
        }
    }
}

impl Modality for ImageModality {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).unwrap_or(serde_json::Value::Null)
    }

    fn tokenize(&self, _clip: &SceneClip, _t: usize) -> Result<Vec<u32>> {
        Err(self.no_tokenizer())
    }

    fn detokenize(&self, _ids: &[u32], _frame: &mut Frame) -> Result<DecodeReport> {
        Err(self.no_tokenizer())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_defaults_and_grid_checks() {
        let m = ImageModality::new("image", ImageConfig::default()).unwrap();
        assert_eq!((m.spec().tokens_per_frame, m.spec().vocab_size), (512, 8192));
        let err = ImageModality::new(
            "image",
            ImageConfig {
                grid: [16, 16],
                ..ImageConfig::default()
            },
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("modality.image.grid"), "{err}");
    }
}
