//! VQ-GAN style tokenizers for umgen's image-like modalities (supplementary B.1.2 of the paper;
//! `official-code-notes.md` §4 describes the authors' design, which this follows).
//!
//! - [`VqModel`]: encoder (residual blocks, stride-2 downsampling, optional attention), a codebook of
//!   unit vectors matched by cosine similarity ([`Quantizer`], EMA updates, dead-code restarts,
//!   straight-through gradients, commitment loss), and a mirrored decoder. Sizes come from [`VqConfig`].
//! - [`train`]: AdamW with warm-up + cosine learning rate and global-norm clipping on a reconstruction loss
//!   (BCE/focal + Dice for binary map layers; L1 + L2 for colour images); checkpoints, TensorBoard scalars
//!   (losses, codebook usage, perplexity) and exact resume.
//! - Convolutions run as im2col matrix products on CUDA (feature `cuda`), burn's own kernel elsewhere
//!   (`conv.rs` says why); group normalisation sums its statistics in two stages (`norm.rs`).
//! - [`VqTokenizer`]: a trained tokenizer (`vq.json` + `vq.safetensors`): rasters ↔ code ids, codebook.
//! - [`IouCounter`], [`PsnrCounter`], [`code_stats`]: reconstruction quality.
//!
//! Training rasters come from a [`RasterSource`]; the map and image modalities render them from datasets.
//! [`VqModality`] turns a [`RasterView`] (frame → raster → frame) and a loaded [`Codec`] into a
//! [`Modality`](umgen_modality::Modality); the map and image modalities are two views.

mod arch;
mod blocks;
mod coder;
mod config;
mod conv;
mod conv_op;
mod error;
mod loss;
mod metrics;
mod modality;
mod model;
mod norm;
mod quantizer;
mod source;
mod tokenizer;
mod train;

pub use arch::VqArch;
pub use config::{LossConfig, Output, VqConfig, VqTrainConfig};
pub use error::{Result, VqError};
pub use metrics::{IouCounter, NearScores, PsnrCounter, code_stats, count_stats};
pub use modality::{
    Codec, CodecLoader, CodecOn, RasterView, VqBuild, VqModality, VqModalityConfig, cpu_loader, vq_factory,
};
pub use model::{Forward, VqModel};
pub use quantizer::{Quantized, Quantizer, normalize};
pub use source::{MemorySource, RasterSource, batch_indices, render};
pub use tokenizer::{CONFIG_FILE, TokenizerInfo, VqTokenizer, WEIGHTS_FILE};
pub use train::{KIND, StepReport, restart_dead, train, train_on};
