//! The architecture part of a VQ tokenizer that a modality's config sets (`[modality.<name>.vq]`); the
//! modality supplies channels, output kind and codebook size.

use crate::config::{Output, VqConfig};
use serde::{Deserialize, Serialize};

/// Network sizes of a VQ tokenizer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VqArch {
    /// Channels of the first level.
    pub base: usize,
    /// Channel multiplier per level (`2^(len-1)` downsampling).
    pub mult: Vec<usize>,
    /// Residual blocks per encoder level.
    pub res_blocks: usize,
    /// Encoder output channels.
    pub z_channels: usize,
    /// Code vector size.
    pub embed_dim: usize,
    /// Self-attention in the middle blocks.
    pub attention: bool,
    /// GroupNorm groups.
    pub groups: usize,
}

impl VqArch {
    /// The paper's map tokenizer (official release: ch 128, mult [1, 2, 2, 4], z 16).
    pub fn paper_map() -> Self {
        Self {
            base: 128,
            mult: vec![1, 2, 2, 4],
            res_blocks: 2,
            z_channels: 16,
            embed_dim: 16,
            attention: false,
            groups: 32,
        }
    }

    /// The paper's image tokenizer (official release: ch 128, mult [1, 1, 2, 2, 4], z 256, attention).
    pub fn paper_image() -> Self {
        Self {
            base: 128,
            mult: vec![1, 1, 2, 2, 4],
            res_blocks: 2,
            z_channels: 256,
            embed_dim: 16,
            attention: true,
            groups: 32,
        }
    }

    /// The full configuration for a modality.
    pub fn config(&self, channels: usize, output: Output, codebook_size: usize) -> VqConfig {
        VqConfig {
            channels,
            output,
            base: self.base,
            mult: self.mult.clone(),
            res_blocks: self.res_blocks,
            z_channels: self.z_channels,
            embed_dim: self.embed_dim,
            codebook_size,
            attention: self.attention,
            groups: self.groups,
        }
    }
}
