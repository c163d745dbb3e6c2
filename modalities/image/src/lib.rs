//! The image modality (paper supplementary B.2.4): the front camera view (default 3×256×512 RGB), encoded
//! by a VQ tokenizer into a `grid` of codebook ids (default 16×32 codes from 8192 entries, 16×
//! downsampling).
//!
//! The image is the frame's own `image` when it has one of the right size, else it is rendered by the
//! configured pinhole camera from the clip's road network and the frame's agents. Decoding writes
//! `frame.image`. Tokenizing needs `tokenizer = "<dir>"` (made by `umgen tokenizer train --modality image`).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use umgen_modality::{Modality, ModalityError, ModalitySpec, Result, downsampling};
use umgen_render::Camera;
use umgen_scene::{CameraImage, Frame, SceneClip};
use umgen_tokenizer_vq::{
    CodecLoader, Output, RasterView, VqArch, VqModality, VqModalityConfig, VqTrainConfig, cpu_loader,
    vq_factory,
};

/// The kind name used in configs.
pub const KIND: &str = "image";

/// The camera's mounting and optics.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Horizontal field of view (degrees).
    pub hfov_deg: f64,
    /// Height above the ground (m).
    pub height_m: f64,
    /// Downward pitch (degrees).
    pub pitch_deg: f64,
    /// Forward offset from the ego origin (m).
    pub mount_x: f64,
    /// Distance at which the ground fades into haze (m).
    pub max_distance: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            hfov_deg: 90.0,
            height_m: 1.6,
            pitch_deg: 3.0,
            mount_x: 1.0,
            max_distance: 80.0,
        }
    }
}

/// Settings of the image modality (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImageConfig {
    /// Image rows and columns.
    pub size: [usize; 2],
    /// Token grid rows and columns.
    pub grid: [usize; 2],
    /// Codebook entries (the vocabulary).
    pub codebook_size: u32,
    /// The camera.
    pub camera: CameraConfig,
    /// Directory of a trained tokenizer (`vq.json`, `vq.safetensors`).
    pub tokenizer: Option<PathBuf>,
    /// Tokenizer architecture.
    pub vq: VqArch,
    /// Tokenizer training.
    pub vq_train: VqTrainConfig,
}

impl Default for ImageConfig {
    fn default() -> Self {
        Self {
            size: [256, 512],
            grid: [16, 32],
            codebook_size: 8192,
            camera: CameraConfig::default(),
            tokenizer: None,
            vq: VqArch::paper_image(),
            vq_train: VqTrainConfig::default(),
        }
    }
}

/// The camera image of a frame.
#[derive(Debug)]
pub struct CameraView {
    camera: Camera,
}

impl CameraView {
    /// The renderer behind it.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }
}

impl RasterView for CameraView {
    fn shape(&self) -> [usize; 3] {
        [3, self.camera.size[0], self.camera.size[1]]
    }

    fn render(&self, clip: &SceneClip, t: usize) -> Result<Vec<f32>> {
        let frame = clip.frame(t)?;
        let [_, h, w] = self.shape();
        let image = match &frame.image {
            Some(im) if (im.height, im.width) == (h, w) => im.clone(),
            _ => {
                let net = clip.network.as_ref().ok_or_else(|| ModalityError::MissingInput {
                    modality: KIND.into(),
                    frame: t,
                    what: "camera image, and its clip has no road network to render one".into(),
                })?;
                self.camera.render(net, &frame.ego.pose2(), &frame.agents)
            }
        };
        Ok(image.data.iter().map(|&v| f32::from(v) / 127.5 - 1.0).collect())
    }

    fn write(&self, values: &[f32], frame: &mut Frame) -> Result<()> {
        let [_, h, w] = self.shape();
        let data = values
            .iter()
            .map(|&v| ((v.clamp(-1.0, 1.0) + 1.0) * 127.5).round() as u8)
            .collect();
        frame.image = Some(CameraImage::from_vec(h, w, data)?);
        Ok(())
    }
}

/// The image modality.
pub type ImageModality = VqModality<CameraView>;

/// Builds an image modality called `name` from its settings, loading its tokenizer with `loader`.
pub fn build(name: &str, config: &ImageConfig, loader: &CodecLoader) -> Result<ImageModality> {
    downsampling(&format!("modality.{name}.grid"), config.size, config.grid)?;
    let c = &config.camera;
    if !(c.hfov_deg > 0.0 && c.hfov_deg < 180.0 && c.height_m > 0.0 && c.max_distance > 0.0) {
        return Err(ModalityError::Config {
            key: format!("modality.{name}.camera"),
            message: "needs 0 < hfov_deg < 180 and positive height_m and max_distance".into(),
        });
    }
    let [rows, cols] = config.grid;
    let spec = ModalitySpec::new(name, KIND, config.codebook_size, rows * cols).with_grid(rows, cols);
    let camera = Camera::new(
        config.size,
        c.hfov_deg,
        c.height_m,
        c.pitch_deg,
        c.mount_x,
        c.max_distance,
    );
    let vq = config.vq.config(3, Output::Rgb, config.codebook_size as usize);
    let settings = serde_json::json!({"size": config.size, "camera": config.camera});
    VqModality::new(
        spec,
        CameraView { camera },
        vq,
        config.tokenizer.clone(),
        loader,
        settings,
    )
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

impl VqModalityConfig for ImageConfig {
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
        let m = build("image", &ImageConfig::default(), &cpu_loader()).unwrap();
        assert_eq!((m.spec().tokens_per_frame, m.spec().vocab_size), (512, 8192));
        assert_eq!(m.vq_config().downsampling(), 16);
        let bad = ImageConfig {
            grid: [16, 16],
            ..ImageConfig::default()
        };
        assert!(
            build("image", &bad, &cpu_loader())
                .unwrap_err()
                .to_string()
                .contains("modality.image.grid")
        );
        let bad = ImageConfig {
            camera: CameraConfig {
                hfov_deg: 200.0,
                ..CameraConfig::default()
            },
            ..ImageConfig::default()
        };
        assert!(
            build("image", &bad, &cpu_loader())
                .unwrap_err()
                .to_string()
                .contains("modality.image.camera")
        );
    }
}
