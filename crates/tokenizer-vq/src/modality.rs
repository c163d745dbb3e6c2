//! Modalities tokenized by a VQ tokenizer: frame → raster → code ids, and back.

use crate::config::VqConfig;
use crate::error::{Result as VqResult, VqError};
use crate::tokenizer::{TokenizerInfo, VqTokenizer, WEIGHTS_FILE};
use burn::tensor::backend::Backend;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use umgen_modality::{Codebook, DecodeReport, Modality, ModalityError, ModalitySpec, Result};
use umgen_scene::{Frame, SceneClip};

/// How a modality turns a frame into a raster for its tokenizer, and a decoded raster back into the frame.
pub trait RasterView: Send + Sync + std::fmt::Debug {
    /// `[C, H, W]`.
    fn shape(&self) -> [usize; 3];
    /// Frame `t` of `clip` as normalised values (binary layers in {0, 1}, colours in [-1, 1]).
    fn render(&self, clip: &SceneClip, t: usize) -> Result<Vec<f32>>;
    /// Writes decoded values (probabilities, or colours in [-1, 1]) into the frame.
    fn write(&self, values: &[f32], frame: &mut Frame) -> Result<()>;
}

/// A loaded tokenizer behind a backend-agnostic interface.
pub trait Codec: Send + Sync + std::fmt::Debug {
    /// What the tokenizer is.
    fn info(&self) -> &TokenizerInfo;
    /// SHA-256 of its weights file: its identity in layout fingerprints.
    fn weights_sha256(&self) -> &str;
    /// Code ids of `n` rasters of `hw` pixels.
    fn encode(&self, rasters: Vec<f32>, n: usize, hw: [usize; 2]) -> VqResult<Vec<u32>>;
    /// Rasters of `n` grids of ids.
    fn decode(&self, ids: &[u32], n: usize, grid: [usize; 2]) -> VqResult<Vec<f32>>;
    /// The codebook as an embedding matrix.
    fn codebook(&self) -> &Codebook;
}

/// A [`VqTokenizer`] on backend `B` as a [`Codec`]. The model sits behind a mutex: burn modules need not
/// be `Sync`, and one tokenizer serves one batch at a time anyway.
#[derive(Debug)]
pub struct CodecOn<B: Backend> {
    tokenizer: Mutex<VqTokenizer<B>>,
    info: TokenizerInfo,
    sha: String,
    codebook: Codebook,
}

impl<B: Backend> CodecOn<B> {
    /// Loads the tokenizer in `dir` onto `device`.
    pub fn load(dir: &Path, device: &B::Device) -> VqResult<Self> {
        let tokenizer = VqTokenizer::<B>::load(dir, device)?;
        let w = dir.join(WEIGHTS_FILE);
        let bytes = std::fs::read(&w).map_err(|e| VqError::Files {
            path: w.clone(),
            message: e.to_string(),
        })?;
        let sha = Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let info = tokenizer.info().clone();
        let c = &info.config;
        let codebook =
            Codebook::new("vq", c.codebook_size, c.embed_dim, tokenizer.codebook()).map_err(|e| {
                VqError::Files {
                    path: dir.into(),
                    message: e.to_string(),
                }
            })?;
        Ok(Self {
            tokenizer: Mutex::new(tokenizer),
            info,
            sha,
            codebook,
        })
    }

    fn with<T>(&self, f: impl FnOnce(&VqTokenizer<B>) -> VqResult<T>) -> VqResult<T> {
        let t = self
            .tokenizer
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        f(&t)
    }
}

impl<B: Backend> Codec for CodecOn<B> {
    fn info(&self) -> &TokenizerInfo {
        &self.info
    }

    fn weights_sha256(&self) -> &str {
        &self.sha
    }

    fn encode(&self, rasters: Vec<f32>, n: usize, hw: [usize; 2]) -> VqResult<Vec<u32>> {
        self.with(|t| t.encode(rasters, n, hw))
    }

    fn decode(&self, ids: &[u32], n: usize, grid: [usize; 2]) -> VqResult<Vec<f32>> {
        self.with(|t| t.decode(ids, n, grid))
    }

    fn codebook(&self) -> &Codebook {
        &self.codebook
    }
}

/// Loads a tokenizer directory into a codec (on whichever backend the caller chose).
pub type CodecLoader = Arc<dyn Fn(&Path) -> VqResult<Arc<dyn Codec>> + Send + Sync>;

/// The CPU loader (burn's Flex backend).
pub fn cpu_loader() -> CodecLoader {
    Arc::new(|dir: &Path| {
        Ok(Arc::new(CodecOn::<burn::backend::Flex>::load(dir, &Default::default())?) as Arc<dyn Codec>)
    })
}

/// What the settings of a VQ modality (`[modality.<name>]`) have in common.
pub trait VqModalityConfig: serde::de::DeserializeOwned {
    /// The configured tokenizer directory, taken out (for training a new one).
    fn take_tokenizer(&mut self) -> Option<PathBuf>;
    /// The tokenizer training settings.
    fn vq_train(&self) -> &crate::config::VqTrainConfig;
}

/// Builds a VQ modality called `name` from its settings, loading its tokenizer with a loader.
pub type VqBuild<C, V> = fn(&str, &C, &CodecLoader) -> Result<VqModality<V>>;

/// A catalog factory for a VQ modality: parses its settings from the config table and builds it with
/// `build`, loading tokenizers with `loader` (for example onto a GPU).
pub fn vq_factory<C: VqModalityConfig + 'static, V: RasterView + 'static>(
    build: VqBuild<C, V>,
    loader: CodecLoader,
) -> impl Fn(&str, &toml::Table) -> Result<Arc<dyn Modality>> + Send + Sync + 'static {
    move |name, table| {
        Ok(Arc::new(build(
            name,
            &umgen_modality::parse_settings(name, table)?,
            &loader,
        )?) as Arc<dyn Modality>)
    }
}

/// Rasters encoded per call when tokenizing a clip.
const BATCH: usize = 16;

/// A modality whose tokens are a VQ tokenizer's codes of a raster view of the frame.
#[derive(Debug)]
pub struct VqModality<V: RasterView> {
    spec: ModalitySpec,
    view: V,
    vq: VqConfig,
    codec: Option<Arc<dyn Codec>>,
    tokenizer: Option<PathBuf>,
    settings: serde_json::Value,
}

impl<V: RasterView> VqModality<V> {
    /// A modality with `spec` (its grid and codebook size), `view` and the architecture `vq`, using the
    /// tokenizer in `tokenizer` (loaded with `loader`) when given. `settings` are the view's settings.
    pub fn new(
        spec: ModalitySpec,
        view: V,
        vq: VqConfig,
        tokenizer: Option<PathBuf>,
        loader: &CodecLoader,
        settings: serde_json::Value,
    ) -> Result<Self> {
        let name = spec.name.clone();
        let key = |f: &str| format!("modality.{name}.{f}");
        vq.validate(&key("vq")).map_err(|e| ModalityError::Config {
            key: key("vq"),
            message: e.to_string(),
        })?;
        let [c, h, w] = view.shape();
        let grid = spec.grid.map_or([0, 0], |g| [g.rows, g.cols]);
        if c != vq.channels || h != grid[0] * vq.downsampling() || w != grid[1] * vq.downsampling() {
            return Err(ModalityError::Config {
                key: key("vq.mult"),
                message: format!(
                    "{}× downsampling of {c}×{h}×{w} rasters does not give the {}×{} grid",
                    vq.downsampling(),
                    grid[0],
                    grid[1]
                ),
            });
        }
        let codec = match &tokenizer {
            None => None,
            Some(dir) => {
                let codec = loader(dir).map_err(|e| ModalityError::Tokenizer {
                    modality: name.clone(),
                    message: e.to_string(),
                })?;
                let trained = &codec.info().config;
                if trained != &vq {
                    return Err(ModalityError::Config {
                        key: key("tokenizer"),
                        message: format!(
                            "{} holds a tokenizer of another architecture or codebook ({trained:?})",
                            dir.display()
                        ),
                    });
                }
                Some(codec)
            }
        };
        Ok(Self {
            spec,
            view,
            vq,
            codec,
            tokenizer,
            settings,
        })
    }

    /// The raster view.
    pub fn view(&self) -> &V {
        &self.view
    }

    /// The tokenizer architecture.
    pub fn vq_config(&self) -> &VqConfig {
        &self.vq
    }

    /// The loaded tokenizer, if any.
    pub fn codec(&self) -> Option<&Arc<dyn Codec>> {
        self.codec.as_ref()
    }

    fn codec_or_err(&self) -> Result<&Arc<dyn Codec>> {
        self.codec.as_ref().ok_or_else(|| ModalityError::Tokenizer {
            modality: self.spec.name.clone(),
            message: format!(
                "no tokenizer: set `modality.{}.tokenizer` to a directory made by `umgen tokenizer train --modality {}`",
                self.spec.name, self.spec.name
            ),
        })
    }

    fn err(&self, e: VqError) -> ModalityError {
        ModalityError::Tokenizer {
            modality: self.spec.name.clone(),
            message: e.to_string(),
        }
    }

    fn encode(&self, rasters: Vec<f32>, n: usize) -> Result<Vec<Vec<u32>>> {
        let [_, h, w] = self.view.shape();
        let ids = self
            .codec_or_err()?
            .encode(rasters, n, [h, w])
            .map_err(|e| self.err(e))?;
        Ok(ids
            .chunks(self.spec.tokens_per_frame)
            .map(<[u32]>::to_vec)
            .collect())
    }
}

impl<V: RasterView> Modality for VqModality<V> {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::json!({
            "view": self.settings,
            "vq": self.vq,
            "tokenizer_sha256": self.codec.as_ref().map(|c| c.weights_sha256().to_string()),
        })
    }

    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        let raster = self.view.render(clip, t)?;
        Ok(self.encode(raster, 1)?.into_iter().next().unwrap_or_default())
    }

    fn tokenize_clip(&self, clip: &SceneClip) -> Result<Vec<Vec<u32>>> {
        self.codec_or_err()?;
        let mut out = Vec::with_capacity(clip.len());
        for start in (0..clip.len()).step_by(BATCH) {
            let n = BATCH.min(clip.len() - start);
            let mut rasters = Vec::new();
            for t in start..start + n {
                rasters.extend(self.view.render(clip, t)?);
            }
            out.extend(self.encode(rasters, n)?);
        }
        Ok(out)
    }

    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        let grid = self.spec.grid.map_or([0, 0], |g| [g.rows, g.cols]);
        let values = self
            .codec_or_err()?
            .decode(ids, 1, grid)
            .map_err(|e| self.err(e))?;
        self.view.write(&values, frame)?;
        Ok(DecodeReport::default())
    }

    fn codebook(&self) -> Option<&Codebook> {
        self.codec.as_ref().map(|c| c.codebook())
    }
}

impl<V: RasterView> VqModality<V> {
    /// Where its tokenizer was loaded from.
    pub fn tokenizer_dir(&self) -> Option<&Path> {
        self.tokenizer.as_deref()
    }

    /// Its spec, raster view and tokenizer architecture.
    pub fn into_parts(self) -> (ModalitySpec, V, VqConfig) {
        (self.spec, self.view, self.vq)
    }
}
