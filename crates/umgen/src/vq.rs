//! VQ tokenizers of configured modalities: what to train, on which rasters.

use crate::config::UmgenConfig;
use crate::error::{Result, UmgenError};
use std::path::PathBuf;
use umgen_data::Dataset;
use umgen_modality::{ModalityError, parse_settings};
use umgen_tokenizer_vq::{
    CodecLoader, RasterSource, RasterView, VqBuild, VqConfig, VqModalityConfig, VqTrainConfig,
};

/// A configured VQ modality, ready for tokenizer training or evaluation.
#[derive(Debug)]
pub struct VqTarget {
    /// Modality name.
    pub name: String,
    /// How frames become rasters.
    pub view: Box<dyn RasterView>,
    /// Tokenizer architecture.
    pub vq: VqConfig,
    /// Tokenizer training settings.
    pub train: VqTrainConfig,
    /// The configured tokenizer directory, if any.
    pub tokenizer: Option<PathBuf>,
}

/// The VQ modality `name` of `config` (kind `map` or `image`), without loading its tokenizer.
pub fn vq_target(config: &UmgenConfig, name: &str) -> Result<VqTarget> {
    let mut table = config.modality.get(name).cloned().unwrap_or_default();
    let kind = match table.remove("kind") {
        Some(toml::Value::String(k)) => k,
        _ => name.to_string(),
    };
    match kind.as_str() {
        umgen_modality_map::KIND => target(name, &table, umgen_modality_map::build),
        umgen_modality_image::KIND => target(name, &table, umgen_modality_image::build),
        other => Err(UmgenError::Modality(ModalityError::Config {
            key: format!("modality.{name}"),
            message: format!("kind `{other}` has no VQ tokenizer (map and image do)"),
        })),
    }
}

fn target<C: VqModalityConfig + 'static, V: RasterView + 'static>(
    name: &str,
    table: &toml::Table,
    build: VqBuild<C, V>,
) -> Result<VqTarget> {
    let mut c: C = parse_settings(name, table)?;
    let tokenizer = c.take_tokenizer();
    let unused: CodecLoader =
        std::sync::Arc::new(|_| Err(umgen_tokenizer_vq::VqError::Data("not loaded".into())));
    let (_, view, vq) = build(name, &c, &unused)?.into_parts();
    Ok(VqTarget {
        name: name.into(),
        view: Box::new(view),
        vq,
        train: c.vq_train().clone(),
        tokenizer,
    })
}

/// Every frame of the clips of a split, as rasters of a view.
#[derive(Debug)]
pub struct DatasetRasters<'a> {
    data: &'a Dataset,
    view: &'a dyn RasterView,
    items: Vec<(usize, usize)>,
}

impl<'a> DatasetRasters<'a> {
    /// Frames of `split` (every split when `None`), every `stride`-th frame of each clip.
    pub fn new(data: &'a Dataset, view: &'a dyn RasterView, split: Option<&str>, stride: usize) -> Self {
        let items = data
            .clips()
            .iter()
            .enumerate()
            .filter(|(_, c)| split.is_none_or(|s| s == c.split))
            .flat_map(|(i, c)| (0..c.frames).step_by(stride.max(1)).map(move |t| (i, t)))
            .collect();
        Self { data, view, items }
    }

    /// The (clip, frame) of item `i`.
    pub fn item_frame(&self, i: usize) -> Option<(usize, usize)> {
        self.items.get(i).copied()
    }
}

impl RasterSource for DatasetRasters<'_> {
    fn shape(&self) -> [usize; 3] {
        self.view.shape()
    }

    fn len(&self) -> usize {
        self.items.len()
    }

    fn item(&self, index: usize) -> std::result::Result<Vec<f32>, String> {
        let &(clip, t) = self
            .items
            .get(index)
            .ok_or_else(|| format!("no raster {index}"))?;
        let scene = self.data.read_window(clip, t, 1, 1).map_err(|e| e.to_string())?;
        self.view.render(&scene, 0).map_err(|e| e.to_string())
    }
}
