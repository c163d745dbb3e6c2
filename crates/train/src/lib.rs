//! Training the umgen backbone.
//!
//! [`train`] runs AdamW with warm-up + cosine learning rate, global-norm gradient clipping and gradient
//! accumulation on windows of a token cache. Runs are reproducible: initialisation, the data order
//! ([`Sampler`]: a permutation per epoch from the seed) and every step's randomness (dropout; reseeded
//! from (seed, step)) are functions of the seed, so a run resumed from a checkpoint repeats the
//! uninterrupted one — bitwise on the CPU.
//!
//! Checkpoints (`<out_dir>/checkpoints/step-…/`: `model.safetensors`, `optimizer.bin`, manifest with the
//! run identity and resolved config) are written atomically; a damaged newest checkpoint falls back to
//! the previous one; a checkpoint of another layout or configuration is refused with the differing keys,
//! and a refused run leaves its directory untouched. A step whose loss or gradient norm is not finite is
//! skipped on the device and reported when the losses are read (`guard`, `train.nonfinite`); no
//! checkpoint is written from it. Metrics go to TensorBoard (`<out_dir>/tb`) and `<out_dir>/metrics.jsonl`,
//! with the losses of another split's windows every `train.val_every` steps (`val/…`).

mod config;
mod error;
mod guard;
mod losses;
mod run;
mod sampler;
mod shard;
mod trainer;
mod validate;

pub use config::{NonFinite, TrainConfig};
pub use error::{Result, TrainError};
pub use run::RunSpec;
pub use sampler::Sampler;
pub use trainer::{KIND, StepReport, Summary, train};
