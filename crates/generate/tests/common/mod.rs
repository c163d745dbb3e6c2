//! What the generation test files share: segment specs, the small backbone's settings, and its model
//! made from a seed without a race between test threads.
#![allow(dead_code, clippy::unwrap_used)]

use burn::module::Module;
use burn::tensor::backend::Backend;
use umgen_backbone::{Backbone, BackboneConfig, BackboneSpec, SegmentSpec};

/// The CPU backend of the tests.
pub type F = burn::backend::Flex;

/// Held while a test seeds burn and makes its model.
static SEEDED: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// A segment of `tokens` content ids below `vocab`, its block starting at `start` (start and end ids
/// around the content).
pub fn seg(label: &str, start: usize, tokens: usize, vocab: usize) -> SegmentSpec {
    SegmentSpec {
        label: label.into(),
        block_start: start,
        block_len: tokens + 2,
        offset: start + 1,
        tokens,
        vocab,
        embed_vocab: vocab + 2,
        ordinal: 0,
        codebook: None,
    }
}

/// A small backbone: D 32, 4 heads, one ego layer of each kind, two TAR and two OAR layers, 8 frames.
pub fn config() -> BackboneConfig {
    BackboneConfig {
        d_model: 32,
        heads: 4,
        embed_dim: 24,
        mlp_ratio: 2,
        dropout: 0.0,
        ego_hist_layers: 1,
        ego_env_layers: 1,
        tar_layers: 2,
        oar_layers: 2,
        max_frames: 8,
        action: None,
        align: None,
        ego_last: true,
        track: None,
        track_accel: false,
        track_follow: false,
        track_stops: None,
        step_s: 0.5,
        precision: Default::default(),
        ordinal_init: true,
    }
}

/// The model of `cfg` and `spec` with burn seeded by `seed`.
pub fn seeded(cfg: &BackboneConfig, spec: &BackboneSpec, seed: u64) -> Backbone<F> {
    // burn's seed is one generator for the process: tests on parallel threads would make their models
    // from it in whatever order the threads take. One at a time, each model is the seed's. burn draws a
    // parameter when it is first read, so the record is taken (every parameter drawn) under the lock and
    // loaded into a second model, whose own draws are never made.
    let _one = SEEDED.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    F::seed(&Default::default(), seed);
    let record = Backbone::<F>::new(cfg, spec, &Default::default())
        .unwrap()
        .into_record();
    Backbone::new(cfg, spec, &Default::default())
        .unwrap()
        .load_record(record)
}
