//! The map modality (paper supplementary B.2.2): a C×H×W BEV raster of road elements around the ego
//! (default 6×256×256: lane, stop line, crosswalk, intersection, lane divider, lane connector; 128 m ×
//! 128 m, 0.5 m per pixel, row 0 at the front), encoded by a VQ tokenizer into a `grid` of codebook ids
//! (default 32×32 codes from 8192 entries, 8× downsampling).
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
pub const KIND: &str = "map";

/// Settings of the map modality (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapConfig {
    /// Raster channels.
    pub channels: usize,
    /// Raster rows and columns.
    pub raster: [usize; 2],
    /// Token grid rows and columns; the raster must divide into it evenly.
    pub grid: [usize; 2],
    /// Codebook entries (the vocabulary).
    pub codebook_size: u32,
}

impl Default for MapConfig {
    fn default() -> Self {
        Self {
            channels: 6,
            raster: [256, 256],
            grid: [32, 32],
            codebook_size: 8192,
        }
    }
}

/// The map modality.
#[derive(Debug)]
pub struct MapModality {
    spec: ModalitySpec,
    config: MapConfig,
}

impl MapModality {
    /// A map modality called `name`.
    pub fn new(name: &str, config: MapConfig) -> Result<Self> {
        downsampling(&format!("modality.{name}.grid"), config.raster, config.grid)?;
        if config.channels == 0 {
            return Err(ModalityError::Config {
                key: format!("modality.{name}.channels"),
                message: "must be positive".into(),
            });
        }
        let [rows, cols] = config.grid;
        let spec = ModalitySpec::new(name, KIND, config.codebook_size, rows * cols).with_grid(rows, cols);
        Ok(Self { spec, config })
    }

    /// Builds the modality from its config table; the factory registered under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }

    /// The settings in use.
    pub fn config(&self) -> &MapConfig {
        &self.config
    }

    fn no_tokenizer(&self) -> ModalityError {
        ModalityError::Tokenizer {
            modality: self.spec.name.clone(),
            message: "no VQ tokenizer is attached, so map rasters cannot be encoded or decoded".into(),
        }
    }
}

impl Modality for MapModality {
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
        let m = MapModality::new("map", MapConfig::default()).unwrap();
        assert_eq!((m.spec().tokens_per_frame, m.spec().vocab_size), (1024, 8192));
        let bad = MapConfig {
            grid: [30, 32],
            ..MapConfig::default()
        };
        let err = MapModality::new("map", bad).unwrap_err().to_string();
        assert!(err.contains("modality.map.grid"), "{err}");
        let bad = MapConfig {
            grid: [32, 16],
            ..MapConfig::default()
        };
        assert!(MapModality::new("map", bad).is_err());
    }
}
