//! A trained tokenizer on disk (`vq.json` + `vq.safetensors`) and in memory: rasters ↔ code ids.

use crate::config::{Output, VqConfig};
use crate::error::{Result, VqError};
use crate::model::VqModel;
use burn::tensor::activation::sigmoid;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use std::path::Path;
use umgen_checkpoint::burn_io::{weights_from_bytes, weights_to_bytes};

/// File holding a tokenizer's description.
pub const CONFIG_FILE: &str = "vq.json";
/// File holding its weights (safetensors, names = module paths).
pub const WEIGHTS_FILE: &str = "vq.safetensors";

/// What `vq.json` records.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenizerInfo {
    /// Always `umgen-vq`.
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// Architecture.
    pub config: VqConfig,
    /// Raster `[C, H, W]` it was trained on.
    pub raster: [usize; 3],
    /// Optimisation steps it was trained for.
    pub steps: u64,
    /// Fraction of codebook entries used over the last training batches.
    pub usage: f64,
    /// Perplexity of code use over the last training batches.
    pub perplexity: f64,
}

/// A tokenizer ready to encode and decode.
#[derive(Debug)]
pub struct VqTokenizer<B: Backend> {
    info: TokenizerInfo,
    model: VqModel<B>,
    device: B::Device,
}

impl<B: Backend> VqTokenizer<B> {
    /// Wraps a model.
    pub fn new(info: TokenizerInfo, model: VqModel<B>, device: B::Device) -> Self {
        Self { info, model, device }
    }

    /// Loads `dir/vq.json` and `dir/vq.safetensors`.
    pub fn load(dir: &Path, device: &B::Device) -> Result<Self> {
        let fail = |path: &Path, message: String| VqError::Files {
            path: path.into(),
            message,
        };
        let cfg_path = dir.join(CONFIG_FILE);
        let text = std::fs::read(&cfg_path).map_err(|e| fail(&cfg_path, e.to_string()))?;
        let info: TokenizerInfo =
            serde_json::from_slice(&text).map_err(|e| fail(&cfg_path, e.to_string()))?;
        if info.format != "umgen-vq" || info.version != 1 {
            return Err(fail(
                &cfg_path,
                format!("format {} v{} is not umgen-vq v1", info.format, info.version),
            ));
        }
        info.config.validate("vq")?;
        let w_path = dir.join(WEIGHTS_FILE);
        let bytes = std::fs::read(&w_path).map_err(|e| fail(&w_path, e.to_string()))?;
        let model = weights_from_bytes(
            VqModel::new(&info.config, device),
            bytes,
            &w_path.display().to_string(),
        )?;
        Ok(Self {
            info,
            model,
            device: device.clone(),
        })
    }

    /// Writes `dir/vq.json` and `dir/vq.safetensors` (each through a temporary file).
    pub fn save(&self, dir: &Path) -> Result<()> {
        let fail = |path: &Path, e: String| VqError::Files {
            path: path.into(),
            message: e,
        };
        std::fs::create_dir_all(dir).map_err(|e| fail(dir, e.to_string()))?;
        let json = serde_json::to_vec_pretty(&self.info).map_err(|e| fail(dir, e.to_string()))?;
        for (name, bytes) in [
            (WEIGHTS_FILE, weights_to_bytes(&self.model)?),
            (CONFIG_FILE, json),
        ] {
            let (tmp, dest) = (dir.join(format!("{name}.tmp")), dir.join(name));
            std::fs::write(&tmp, bytes)
                .and_then(|()| std::fs::rename(&tmp, &dest))
                .map_err(|e| fail(&dest, e.to_string()))?;
        }
        Ok(())
    }

    /// Its description.
    pub fn info(&self) -> &TokenizerInfo {
        &self.info
    }

    /// The network.
    pub fn model(&self) -> &VqModel<B> {
        &self.model
    }

    fn check(&self, values: usize, n: usize, hw: [usize; 2]) -> Result<()> {
        let (c, f) = (self.info.config.channels, self.info.config.downsampling());
        if n == 0 || values != n * c * hw[0] * hw[1] || !hw[0].is_multiple_of(f) || !hw[1].is_multiple_of(f) {
            return Err(VqError::Input(format!(
                "{values} values for {n} rasters of {c}×{}×{} (sizes must divide by {f})",
                hw[0], hw[1]
            )));
        }
        Ok(())
    }

    /// Code ids of `n` rasters of `hw` pixels (`[n, C, H, W]` values): `n × (H/f) × (W/f)` ids, row-major.
    pub fn encode(&self, rasters: Vec<f32>, n: usize, hw: [usize; 2]) -> Result<Vec<u32>> {
        self.check(rasters.len(), n, hw)?;
        let c = self.info.config.channels;
        let x = Tensor::<B, 4>::from_data(TensorData::new(rasters, [n, c, hw[0], hw[1]]), &self.device);
        let ids = self.model.encode(x).into_data();
        Ok(ids.iter::<i64>().map(|i| i as u32).collect())
    }

    /// Rasters from ids of `n` grids of `grid` cells: probabilities for binary output, colours in [-1, 1].
    pub fn decode(&self, ids: &[u32], n: usize, grid: [usize; 2]) -> Result<Vec<f32>> {
        let k = self.info.config.codebook_size;
        if ids.len() != n * grid[0] * grid[1] || n == 0 {
            return Err(VqError::Input(format!(
                "{} ids for {n} grids of {}×{}",
                ids.len(),
                grid[0],
                grid[1]
            )));
        }
        if let Some(bad) = ids.iter().find(|&&i| i as usize >= k) {
            return Err(VqError::Input(format!("id {bad} is outside the codebook of {k}")));
        }
        let data: Vec<i64> = ids.iter().map(|&i| i64::from(i)).collect();
        let t = Tensor::<B, 3, Int>::from_data(TensorData::new(data, [n, grid[0], grid[1]]), &self.device);
        let out = self.model.decode(t);
        let out = match self.info.config.output {
            Output::Binary => sigmoid(out),
            Output::Rgb => out.clamp(-1.0, 1.0),
        };
        Ok(out.into_data().iter::<f32>().collect())
    }

    /// The codebook, `codebook_size × embed_dim` values, row-major.
    pub fn codebook(&self) -> Vec<f32> {
        self.model.quantizer.codes().into_data().iter::<f32>().collect()
    }
}
