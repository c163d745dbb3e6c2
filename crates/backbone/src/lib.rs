//! umgen's generic TAR/OAR backbone (paper §3.2), built only from a frame layout.
//!
//! A [`BackboneSpec`] describes the frame: segments (one per modality) with their positions, vocabularies
//! and optional pre-trained codebooks, which segment carries the ego action (and the bins to decode it),
//! and which is a metric map grid that AMA can move. No modality names are interpreted.
//!
//! The [`Backbone`]:
//! 1. embeds tokens with per-segment tables (codebook-initialised and projected where there is a
//!    codebook), a learned position embedding and an MLP; adds a learned frame (time) embedding;
//! 2. predicts the next ego action from learned queries over the ego history (CA_hist) and the current
//!    environment (CA_env);
//! 3. moves the map features by the next action (AMA: affine grid, bilinear, zero padding) and adds them;
//!    with `backbone.track`, adds to each tracked slot (the agents) the embedding of the slot moved by its
//!    velocity and the next action ([`track`]);
//! 4. runs TAR blocks (temporal causal + spatial bidirectional attention) to a coarse next frame `h`;
//! 5. runs the OAR (causal attention over the next frame; input at position p = embedding of token p − 1 +
//!    `h_p`);
//! 6. scores both with heads whose logits cover only each modality's own vocabulary; the loss is
//!    CE(OAR) + CE(TAR) + CE(ego), reported per modality.
//!
//! The operations it calls (linear products in f32 or bf16, attention, layer norm, bias + GELU, embedding
//! lookups, cross-entropy) and their kernels are `umgen-ops`'; with recomputation on (or `layer =
//! "fused"`), each attention layer runs as one operation with a hand-written backward pass, which keeps
//! only its inputs for the backward pass (or the activations it reads) (`umgen_ops::layer`).
//!
//! For generation, [`Backbone::oar_step`] decodes one position at a time over an [`OarCache`].

mod ama;
mod config;
mod cross;
mod decode;
mod ego;
mod embed;
mod error;
mod heads;
mod layers;
mod logits;
mod losses;
mod model;
pub mod ordinal;
mod plain;
mod ready;
mod spec;
#[cfg(test)]
mod testing;
pub mod track;

pub use ama::align;
pub use config::{BackboneConfig, Precision};
pub use cross::CrossBlock;
pub use decode::{OarCache, Slot, VanillaAr};
pub use ego::{EgoModule, EgoSizes};
pub use embed::FrameEmbedding;
pub use error::{BackboneError, Result};
pub use heads::Heads;
pub use layers::{LayerSizes, Mlp, MultiHead, SelfBlock};
pub use logits::ForcedLogits;
pub use losses::{LossOptions, Losses};
pub use model::{Backbone, TarBlock};
pub use plain::{
    PlainAttention, PlainBackbone, PlainCross, PlainEgo, PlainEmbed, PlainLinear, PlainMlp, PlainNorm,
    PlainSelf, PlainTable,
};
pub use spec::{ActionSpec, AlignSpec, BackboneSpec, FollowSpec, STOP_IDS, SegmentSpec, StopSpec, TrackSpec};
pub use umgen_ops::Kernels;
