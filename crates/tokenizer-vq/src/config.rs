//! Sizes of a VQ tokenizer and settings of its training.

use crate::error::{Result, VqError};
use serde::{Deserialize, Serialize};

/// What the decoder reconstructs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Output {
    /// Independent binary channels (map layers): the decoder gives logits, reconstructions are
    /// `sigmoid(logit) > 0.5`.
    Binary,
    /// Colour in [-1, 1] (camera images).
    Rgb,
}

/// The architecture (VQ-GAN style, official-code-notes §4): encoder levels of residual blocks with
/// stride-2 downsampling, an optional attention block in the middle, a cosine-similarity codebook, and a
/// mirrored decoder with nearest-neighbour upsampling.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VqConfig {
    /// Input channels (6 for the map, 3 for images).
    pub channels: usize,
    /// What the decoder reconstructs.
    pub output: Output,
    /// Channels of the first level.
    pub base: usize,
    /// Channel multiplier per level; `len - 1` downsamplings, so the grid is `2^(len-1)` times smaller.
    pub mult: Vec<usize>,
    /// Residual blocks per encoder level (the decoder uses one more).
    pub res_blocks: usize,
    /// Channels of the encoder output before the projection to `embed_dim`.
    pub z_channels: usize,
    /// Codebook vector size.
    pub embed_dim: usize,
    /// Codebook entries.
    pub codebook_size: usize,
    /// Self-attention in the middle blocks.
    pub attention: bool,
    /// GroupNorm groups (must divide every level's channels).
    pub groups: usize,
}

impl Default for VqConfig {
    /// The paper's map tokenizer: 6 channels, 8× downsampling, 8192 × 16 codebook.
    fn default() -> Self {
        Self {
            channels: 6,
            output: Output::Binary,
            base: 128,
            mult: vec![1, 2, 2, 4],
            res_blocks: 2,
            z_channels: 16,
            embed_dim: 16,
            codebook_size: 8192,
            attention: false,
            groups: 32,
        }
    }
}

impl VqConfig {
    /// How many input pixels one code covers along each axis.
    pub fn downsampling(&self) -> usize {
        1 << self.mult.len().saturating_sub(1)
    }

    /// Checks the sizes; errors name `key` (the config table, e.g. `modality.map.vq`).
    pub fn validate(&self, key: &str) -> Result<()> {
        let fail = |field: &str, message: String| {
            Err(VqError::Config {
                key: format!("{key}.{field}"),
                message,
            })
        };
        if self.channels == 0 {
            return fail("channels", "must be positive".into());
        }
        if self.mult.is_empty() || self.mult.contains(&0) || self.base == 0 {
            return fail("mult", "needs at least one level and positive multipliers".into());
        }
        if let Some(c) = self
            .mult
            .iter()
            .map(|m| m * self.base)
            .find(|c| c % self.groups.max(1) != 0)
        {
            return fail(
                "groups",
                format!("{} groups do not divide {c} channels", self.groups),
            );
        }
        if self.embed_dim == 0 || self.z_channels == 0 || self.codebook_size < 2 {
            return fail(
                "codebook_size",
                "codebook needs at least 2 entries of positive size".into(),
            );
        }
        Ok(())
    }
}

/// Reconstruction losses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossConfig {
    /// Binary: weight of the binary cross-entropy (with `focal_gamma > 0`, the focal loss).
    pub bce: f64,
    /// Binary: focusing exponent of the focal loss; 0 is plain BCE.
    pub focal_gamma: f64,
    /// Binary: weight on positive pixels inside the BCE (thin layers are rare).
    pub pos_weight: f64,
    /// Binary: weight of the soft Dice loss per channel.
    pub dice: f64,
    /// RGB: weight of the L1 loss.
    pub l1: f64,
    /// RGB: weight of the squared error.
    pub l2: f64,
    /// Weight of the commitment loss between encoder outputs and their codes.
    pub commitment: f64,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            bce: 1.0,
            focal_gamma: 0.0,
            pos_weight: 2.0,
            dice: 1.0,
            l1: 1.0,
            l2: 1.0,
            commitment: 0.25,
        }
    }
}

/// How a tokenizer is trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VqTrainConfig {
    /// Optimisation steps.
    pub steps: u64,
    /// Rasters per step and process: a data-parallel run's global batch is `batch_size × world size`.
    pub batch_size: usize,
    /// Peak learning rate (AdamW).
    pub lr: f64,
    /// AdamW ε (1 makes the update linear in the gradient; see `train.eps`).
    pub eps: f64,
    /// Linear warm-up steps.
    pub warmup: u64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// Global gradient-norm clip (0 = none).
    pub grad_clip: f64,
    /// Decay of the codebook's moving averages.
    pub ema_decay: f64,
    /// A code unused for this many steps is restarted from a random encoder output.
    pub restart_after: u64,
    /// Losses.
    pub loss: LossConfig,
    /// Steps between log lines.
    pub log_every: u64,
    /// Steps between checkpoints.
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    pub keep_checkpoints: usize,
    /// Seed of initialisation and sampling.
    pub seed: u64,
    /// Threads rendering training rasters.
    pub threads: usize,
}

impl Default for VqTrainConfig {
    fn default() -> Self {
        Self {
            steps: 20_000,
            batch_size: 16,
            lr: 2e-4,
            eps: 1e-8,
            warmup: 500,
            weight_decay: 0.0,
            grad_clip: 1.0,
            ema_decay: 0.99,
            restart_after: 200,
            loss: LossConfig::default(),
            log_every: 50,
            checkpoint_every: 1000,
            keep_checkpoints: 2,
            seed: 0,
            threads: 0,
        }
    }
}
