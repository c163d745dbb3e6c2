//! The backbone's semantics on the CPU: causality, AMA, heads and loss, sizes.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod ama;
mod causality;
mod decode;
mod heads;
mod layer_op;
mod ordinal;
mod precision;
mod ready;

use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use std::f64::consts::PI;
use umgen_backbone::{
    ActionSpec, AlignSpec, Backbone, BackboneConfig, BackboneSpec, Kernels, Precision, SegmentSpec, TrackSpec,
};

/// Held while a test seeds burn and draws from it (its model, random inputs).
static SEEDED: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub type F = burn::backend::Flex;
pub type A = burn::backend::Autodiff<F>;

/// A block of `tokens` content tokens with start/end tokens around it.
pub fn seg(
    label: &str,
    start: usize,
    tokens: usize,
    vocab: usize,
    codebook_dim: Option<usize>,
) -> SegmentSpec {
    let codebook = codebook_dim.map(|d| {
        (
            d,
            (0..vocab * d)
                .map(|i| ((i * 7919) % 97) as f32 / 97.0 - 0.5)
                .collect(),
        )
    });
    SegmentSpec {
        label: label.into(),
        block_start: start,
        block_len: tokens + 2,
        offset: start + 1,
        tokens,
        vocab,
        embed_vocab: vocab + 2,
        ordinal: 0,
        codebook,
    }
}

/// A block whose ids `0..ordinal` are ordered value bins.
pub fn ordinal(mut s: SegmentSpec, ordinal: usize) -> SegmentSpec {
    s.ordinal = ordinal;
    s
}

/// ego (3 tokens, 16 bins), a 4×4 map with a codebook, 3 agent tokens (8 value bins and 2 other ids), a
/// 2×2 image with a codebook.
pub fn spec() -> BackboneSpec {
    let segments = vec![
        ordinal(seg("ego", 0, 3, 16, None), 16),
        seg("map", 5, 16, 32, Some(4)),
        ordinal(seg("agent", 23, 6, 10, None), 8),
        seg("image", 31, 4, 24, Some(4)),
    ];
    BackboneSpec {
        n: 37,
        segments,
        action: Some(ActionSpec {
            segment: 0,
            bins: [(0.0, 8.0, 16), (-1.0, 1.0, 16), (-0.5, 0.5, 16)],
        }),
        align: Some(AlignSpec {
            segment: 1,
            rows: 4,
            cols: 4,
            cell_m: 2.0,
        }),
        track: Some(TrackSpec {
            segment: 2,
            slot: 6,
            values: 8,
            fields: [
                (0, (-4.0, 4.0, 8)),
                (1, (-4.0, 4.0, 8)),
                (2, (-2.0, 2.0, 8)),
                (3, (-2.0, 2.0, 8)),
                (4, (-PI, PI, 8)),
            ],
            step_s: 0.5,
            pad: Some(9),
            accel: false,
            follow: None,
            stops: None,
        }),
    }
}

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

/// Random valid windows `[b, f, N]`: content ids in each segment's vocabulary, start/end ids around.
pub fn tokens(spec: &BackboneSpec, b: usize, f: usize, seed: u64) -> Vec<i64> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut out = Vec::new();
    for _ in 0..b * f {
        for s in &spec.segments {
            out.push(s.vocab as i64);
            out.extend((0..s.tokens).map(|_| rng.random_range(0..s.vocab as i64)));
            out.push(s.vocab as i64 + 1);
        }
    }
    out
}

pub fn tensor<B: Backend>(ids: &[i64], b: usize, f: usize, n: usize) -> Tensor<B, 3, Int> {
    Tensor::from_data(TensorData::new(ids.to_vec(), [b, f, n]), &Default::default())
}

pub fn model<B: Backend>() -> Backbone<B> {
    model_in(Precision::F32)
}

/// The test model with its products in `precision` (the same parameters whatever the precision).
pub fn model_in<B: Backend>(precision: Precision) -> Backbone<B> {
    // burn's seed is one generator for the process: tests on parallel threads would make their models
    // from it in whatever order the threads take. One at a time, each model is the seed's. burn draws a
    // parameter when it is first read, so the record is taken (every parameter drawn) under the lock and
    // loaded into a second model, whose own draws are never made.
    let _one = SEEDED.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    B::seed(&Default::default(), 3);
    let cfg = BackboneConfig {
        precision,
        ..config()
    };
    let record = Backbone::<B>::new(&cfg, &spec(), &Default::default())
        .unwrap()
        .into_record();
    Backbone::new(&cfg, &spec(), &Default::default())
        .unwrap()
        .load_record(record)
}

#[test]
fn parameter_count_matches_the_built_model() {
    let m = model::<F>();
    assert_eq!(m.num_params(), spec().param_count(&config()));
    let mut untracked = spec();
    untracked.track = None;
    let m = Backbone::<F>::new(&config(), &untracked, &Default::default()).unwrap();
    assert_eq!(m.num_params(), untracked.param_count(&config()));
    assert_eq!(
        spec().param_count(&config()) - untracked.param_count(&config()),
        2 * (32 * 32 + 32),
        "the moved slots' projections"
    );
    let mut no_ego = untracked.clone();
    no_ego.action = None;
    let m = Backbone::<F>::new(&config(), &no_ego, &Default::default()).unwrap();
    assert_eq!(m.num_params(), no_ego.param_count(&config()));
    // Without the ego action nothing says how the ego moves.
    let mut unmoved = spec();
    unmoved.action = None;
    let err = Backbone::<F>::new(&config(), &unmoved, &Default::default()).unwrap_err();
    assert!(
        err.to_string().contains("tracked segment needs the ego action"),
        "{err}"
    );
}

#[test]
fn the_paper_layout_runs_at_a_small_width() {
    // The paper's frame (2251 positions, vocabularies 1024 / 8192 / 1028 / 8192) with a small model.
    let segments = vec![
        ordinal(seg("ego", 0, 3, 1024, None), 1024),
        seg("map", 5, 1024, 8192, None),
        ordinal(seg("agent", 1031, 704, 1028, None), 1024),
        seg("image", 1737, 512, 8192, None),
    ];
    let spec = BackboneSpec {
        n: 2251,
        segments,
        action: Some(ActionSpec {
            segment: 0,
            bins: [(0.0, 10.0, 1024), (-0.5, 0.5, 1024), (-0.25, 0.25, 1024)],
        }),
        align: Some(AlignSpec {
            segment: 1,
            rows: 32,
            cols: 32,
            cell_m: 4.0,
        }),
        // The agent modality's slots at its default ranges.
        track: Some(TrackSpec {
            segment: 2,
            slot: 11,
            values: 1024,
            fields: [
                (0, (-64.0, 64.0, 1024)),
                (1, (-64.0, 64.0, 1024)),
                (3, (-20.0, 20.0, 1024)),
                (4, (-20.0, 20.0, 1024)),
                (6, (-PI, PI, 1024)),
            ],
            step_s: 0.5,
            pad: Some(1027),
            accel: false,
            follow: None,
            stops: None,
        }),
    };
    let cfg = BackboneConfig {
        d_model: 16,
        heads: 2,
        tar_layers: 1,
        oar_layers: 1,
        ego_hist_layers: 1,
        ego_env_layers: 1,
        ..config()
    };
    let m = Backbone::<F>::new(&cfg, &spec, &Default::default()).unwrap();
    let ids = tokens(&spec, 1, 3, 1);
    let losses = m.loss(tensor(&ids, 1, 3, 2251), 1.0).unwrap();
    let names: Vec<&str> = losses.parts.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "oar/ego",
            "oar/map",
            "oar/agent",
            "oar/image",
            "oar",
            "tar/ego",
            "tar/map",
            "tar/agent",
            "tar/image",
            "tar",
            "ego"
        ]
    );
    let total: f32 = losses.total.into_scalar();
    // An untrained model is near chance: ln(vocab) per term, weighted by token counts.
    let chance = 2.0
        * (3.0 * 1024f64.ln() + 1024.0 * 8192f64.ln() + 704.0 * 1028f64.ln() + 512.0 * 8192f64.ln())
        / 2243.0
        + 1024f64.ln();
    assert!(
        (f64::from(total) - chance).abs() < 0.1 * chance,
        "{total} vs chance {chance}"
    );
    let e = m.embed.forward(tensor(&ids, 1, 3, 2251), &Kernels::DEFAULT);
    assert_eq!(e.dims(), [1, 3, 2251, 16]);
    // The paper config's size, from the formula checked against built models above.
    let paper = BackboneConfig::default();
    let count = spec.param_count(&paper);
    assert!((700_000_000..760_000_000).contains(&count), "{count}");
}
