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
//! Matrix products run in f32 or, with [`Precision::Bf16`], on bf16 operands with f32 master weights
//! (`precision.rs`); training attention over long sequences runs fused kernels on CUDA ([`flash`]) and tiled
//! passes elsewhere ([`attention`]), and training on CUDA runs the linear layers' products on a named matmul
//! kernel ([`matmul`]). With [`recompute`] on, the self-attention layers keep only their inputs for the
//! backward pass and are recomputed there (activation checkpointing). On the training backends more custom
//! autodiff operations replace burn's where those run on a handful of GPU units, pass over an activation
//! many times or copy it: bias adds (`rows.rs`), embedding lookups (`lookup.rs`), the cross-entropy from
//! logits ([`xent`], with [`smoothing`]'s targets), the layer norm ([`norm`]), the TAR's attention over
//! time on the rows as they lie ([`temporal`]) and the attention over one kv tensor (`attention/kv.rs`);
//! the cross-entropy's, the norm's and the temporal attention's passes are CUDA C kernels on CUDA.
//!
//! For generation, [`Backbone::oar_step`] decodes one position at a time over an [`OarCache`]. The
//! optimizer's multi-tensor kernels for CUDA (AdamW, the gradients' norm) live here too, in [`adamw`],
//! beside the other CUDA C kernels they share their launch path with.

pub mod adamw;
mod ama;
pub mod attention;
mod config;
mod decode;
mod dispatch;
mod ego;
mod embed;
mod error;
pub mod flash;
pub mod gelu;
mod heads;
pub mod kernel_stream;
mod layers;
mod logits;
pub mod lookup;
mod losses;
pub mod matmul;
mod model;
pub mod norm;
pub mod ordinal;
mod plain;
mod precision;
pub mod recompute;
pub mod rows;
#[cfg(feature = "cuda")]
mod side;
pub mod smoothing;
mod spec;
pub mod temporal;
pub mod track;
pub mod xent;

pub use ama::align;
pub use config::{BackboneConfig, Precision};
pub use decode::{OarCache, Slot, VanillaAr};
pub use ego::{EgoModule, EgoSizes};
pub use embed::FrameEmbedding;
pub use error::{BackboneError, Result};
pub use heads::Heads;
pub use layers::{CrossBlock, LayerSizes, Mlp, MultiHead, SelfBlock};
pub use logits::ForcedLogits;
pub use losses::{LossOptions, Losses};
pub use model::{Backbone, TarBlock};
pub use plain::{
    PlainAttention, PlainBackbone, PlainCross, PlainEgo, PlainEmbed, PlainLinear, PlainMlp, PlainNorm,
    PlainSelf, PlainTable,
};
#[cfg(feature = "cuda")]
pub use side::{device_thread_calls, foreign_streams};
pub use spec::{ActionSpec, AlignSpec, BackboneSpec, SegmentSpec, TrackSpec};
