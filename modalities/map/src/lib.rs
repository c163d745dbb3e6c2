//! The map modality (paper supplementary B.2.2): a C×H×W BEV raster of road layers around the ego (default
//! 6×256×256 — lane, stop line, crosswalk, intersection, lane divider, lane connector — over 128 m × 128 m,
//! 0.5 m per pixel, row 0 at the front), encoded by a VQ tokenizer into a `grid` of codebook ids (default
//! 32×32 codes from 8192 entries, 8× downsampling).
//!
//! The raster is the frame's own `map` when it has one of the right size, else it is rendered from the
//! clip's road network around the ego pose. Decoding writes `frame.map` (cells with probability > 0.5).
//! The layout needs only the grid and the codebook size, so a config can be inspected without trained
//! weights; tokenizing needs `tokenizer = "<dir>"` (made by `umgen tokenizer train --modality map`).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use umgen_modality::{Modality, ModalityError, ModalitySpec, Result, downsampling};
use umgen_render::MapView;
use umgen_scene::{Frame, MapLayer, MapRaster, SceneClip};
use umgen_tokenizer_vq::{
    CodecLoader, Output, RasterView, VqArch, VqModality, VqModalityConfig, VqTrainConfig, cpu_loader,
    vq_factory,
};

/// The kind name used in configs.
pub const KIND: &str = "map";

/// Settings of the map modality (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct MapConfig {
    /// Layers, one channel each, in channel order (`lane`, `stop_line`, `crosswalk`, `intersection`,
    /// `lane_divider`, `lane_connector`).
    pub layers: Vec<String>,
    /// Raster rows and columns.
    pub raster: [usize; 2],
    /// Side of the square view around the ego (m).
    pub extent_m: f64,
    /// Token grid rows and columns.
    pub grid: [usize; 2],
    /// Codebook entries (the vocabulary).
    pub codebook_size: u32,
    /// Directory of a trained tokenizer (`vq.json`, `vq.safetensors`).
    pub tokenizer: Option<PathBuf>,
    /// Tokenizer architecture.
    pub vq: VqArch,
    /// Tokenizer training.
    pub vq_train: VqTrainConfig,
}

impl Default for MapConfig {
    fn default() -> Self {
        Self {
            layers: MapLayer::ALL.iter().map(|l| l.name().to_string()).collect(),
            raster: [256, 256],
            extent_m: 128.0,
            grid: [32, 32],
            codebook_size: 8192,
            tokenizer: None,
            vq: VqArch::paper_map(),
            vq_train: VqTrainConfig {
                loss: umgen_tokenizer_vq::LossConfig {
                    pos_weight: 3.0,
                    ..Default::default()
                },
                ..Default::default()
            },
        }
    }
}

impl MapConfig {
    /// The renderer these settings describe (raster size, extent, layers), checked; `name` is the
    /// modality's name for error keys.
    pub fn map_view(&self, name: &str) -> Result<MapView> {
        let key = |f: &str| format!("modality.{name}.{f}");
        let layers = self
            .layers
            .iter()
            .map(|n| {
                MapLayer::ALL
                    .into_iter()
                    .find(|l| l.name() == n)
                    .ok_or_else(|| ModalityError::Config {
                        key: key("layers"),
                        message: format!(
                            "unknown layer `{n}` (known: {})",
                            MapLayer::ALL.map(MapLayer::name).join(", ")
                        ),
                    })
            })
            .collect::<Result<Vec<_>>>()?;
        if layers.is_empty() || self.extent_m.is_nan() || self.extent_m <= 0.0 {
            return Err(ModalityError::Config {
                key: key("layers"),
                message: "needs at least one layer and a positive extent_m".into(),
            });
        }
        downsampling(&key("grid"), self.raster, self.grid)?;
        if self.raster[0] != self.raster[1] || self.grid[0] != self.grid[1] {
            return Err(ModalityError::Config {
                key: key("raster"),
                message: "the map view is square: raster and grid need equal sides".into(),
            });
        }
        Ok(MapView {
            extent_m: self.extent_m,
            size: self.raster,
            layers,
        })
    }
}

/// The map raster of a frame.
#[derive(Debug, Clone)]
pub struct MapRasterView {
    view: MapView,
}

impl MapRasterView {
    /// The renderer behind it.
    pub fn map_view(&self) -> &MapView {
        &self.view
    }
}

impl RasterView for MapRasterView {
    fn shape(&self) -> [usize; 3] {
        [self.view.layers.len(), self.view.size[0], self.view.size[1]]
    }

    fn render(&self, clip: &SceneClip, t: usize) -> Result<Vec<f32>> {
        let frame = clip.frame(t)?;
        let [c, h, w] = self.shape();
        let raster = match &frame.map {
            Some(m) if (m.channels, m.height, m.width) == (c, h, w) => m.clone(),
            _ => {
                let net = clip.network.as_ref().ok_or_else(|| ModalityError::MissingInput {
                    modality: KIND.into(),
                    frame: t,
                    what: "map raster, and its clip has no road network to render one".into(),
                })?;
                self.view.render(net, &frame.ego.pose2())
            }
        };
        Ok(raster
            .data
            .iter()
            .map(|&v| if v > 127 { 1.0 } else { 0.0 })
            .collect())
    }

    fn write(&self, values: &[f32], frame: &mut Frame) -> Result<()> {
        let [c, h, w] = self.shape();
        let data = values.iter().map(|&p| if p > 0.5 { 255 } else { 0 }).collect();
        frame.map = Some(MapRaster::from_vec(c, h, w, data)?);
        Ok(())
    }
}

/// The map modality.
pub type MapModality = VqModality<MapRasterView>;

/// Builds a map modality called `name` from its settings, loading its tokenizer with `loader`.
pub fn build(name: &str, config: &MapConfig, loader: &CodecLoader) -> Result<MapModality> {
    let view = config.map_view(name)?;
    let [rows, cols] = config.grid;
    let cell_m = config.extent_m / rows as f64;
    let spec =
        ModalitySpec::new(name, KIND, config.codebook_size, rows * cols).with_metric_grid(rows, cols, cell_m);
    let layers = view.layers.clone();
    let view = MapRasterView { view };
    let vq = config
        .vq
        .config(layers.len(), Output::Binary, config.codebook_size as usize);
    let settings =
        serde_json::json!({"layers": config.layers, "raster": config.raster, "extent_m": config.extent_m});
    VqModality::new(spec, view, vq, config.tokenizer.clone(), loader, settings)
}

/// The factory registered under [`KIND`], loading tokenizers on the CPU.
pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
    factory_with(cpu_loader())(name, table)
}

/// A factory that loads tokenizers with `loader` (for example onto a GPU).
pub fn factory_with(
    loader: CodecLoader,
) -> impl Fn(&str, &toml::Table) -> Result<Arc<dyn Modality>> + Send + Sync + 'static {
    vq_factory(build, loader)
}

impl VqModalityConfig for MapConfig {
    fn take_tokenizer(&mut self) -> Option<PathBuf> {
        self.tokenizer.take()
    }

    fn vq_train(&self) -> &VqTrainConfig {
        &self.vq_train
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_defaults_and_config_errors() {
        let m = build("map", &MapConfig::default(), &cpu_loader()).unwrap();
        assert_eq!((m.spec().tokens_per_frame, m.spec().vocab_size), (1024, 8192));
        assert_eq!(m.vq_config().downsampling(), 8);
        let bad = MapConfig {
            grid: [30, 32],
            ..MapConfig::default()
        };
        assert!(
            build("map", &bad, &cpu_loader())
                .unwrap_err()
                .to_string()
                .contains("modality.map.grid")
        );
        let bad = MapConfig {
            grid: [16, 16],
            ..MapConfig::default()
        };
        assert!(
            build("map", &bad, &cpu_loader())
                .unwrap_err()
                .to_string()
                .contains("modality.map.vq.mult")
        );
        let bad = MapConfig {
            layers: vec!["lane".into(), "trees".into()],
            ..MapConfig::default()
        };
        assert!(
            build("map", &bad, &cpu_loader())
                .unwrap_err()
                .to_string()
                .contains("unknown layer `trees`")
        );
        let mut table = toml::Table::new();
        table.insert("tokenizer".into(), toml::Value::String("/no/such/dir".into()));
        let err = factory("map", &table).unwrap_err().to_string();
        assert!(err.contains("/no/such/dir"), "{err}");
    }
}
