//! The VQ tokenizer on the CPU: shapes, overfitting, dead-code restarts, resume, files.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use burn::tensor::{Int, Tensor, TensorData};
use std::ops::ControlFlow;
use umgen_tokenizer_vq::{
    IouCounter, MemorySource, Output, Quantizer, VqConfig, VqTokenizer, VqTrainConfig, restart_dead, train,
};

type B = burn::backend::Autodiff<burn::backend::Flex>;
type Inner = burn::backend::Flex;

/// A small tokenizer with 4× downsampling (the CPU backend's convolution gradients are slow, so tests
/// stay small).
fn tiny(k: usize) -> VqConfig {
    VqConfig {
        channels: 2,
        output: Output::Binary,
        base: 8,
        mult: vec![1, 2, 2],
        res_blocks: 1,
        z_channels: 8,
        embed_dim: 8,
        codebook_size: k,
        attention: true,
        groups: 4,
    }
}

const S: usize = 16;

/// Four 2×16×16 rasters: boxes in channel 0, one-pixel lines in channel 1.
fn rasters() -> Vec<Vec<f32>> {
    (0..4)
        .map(|i| {
            let mut v = vec![0.0f32; 2 * S * S];
            for r in 0..S {
                for c in 0..S {
                    let block = (2 + 2 * i..6 + 2 * i).contains(&r) && (1..8 + i).contains(&c);
                    let line = c == 4 + 3 * i || r == 14 - 2 * i;
                    v[r * S + c] = f32::from(u8::from(block));
                    v[S * S + r * S + c] = f32::from(u8::from(line));
                }
            }
            v
        })
        .collect()
}

fn quick(steps: u64) -> VqTrainConfig {
    VqTrainConfig {
        steps,
        batch_size: 4,
        lr: 3e-3,
        warmup: 10,
        log_every: 10,
        checkpoint_every: 3,
        threads: 1,
        restart_after: 20,
        ..VqTrainConfig::default()
    }
}

#[test]
fn encode_decode_shapes_and_id_ranges() {
    let dev = Default::default();
    let cfg = tiny(64);
    let src = MemorySource::new([2, S, S], rasters()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let tok = train::<B>(&cfg, &quick(2), &src, dir.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    let data: Vec<f32> = rasters().concat();
    let ids = tok.encode(data.clone(), 4, [S, S]).unwrap();
    assert_eq!(ids.len(), 4 * 4 * 4, "4× downsampling: a 4×4 grid per raster");
    assert!(ids.iter().all(|&i| i < 64));
    let back = tok.decode(&ids, 4, [4, 4]).unwrap();
    assert_eq!(back.len(), data.len());
    assert!(
        back.iter().all(|v| (0.0..=1.0).contains(v)),
        "binary output decodes to probabilities"
    );
    assert_eq!(tok.codebook().len(), 64 * 8);
    assert!(
        tok.encode(data[..100].to_vec(), 4, [S, S])
            .unwrap_err()
            .to_string()
            .contains("100 values")
    );
    assert!(
        tok.decode(&[64; 16], 1, [4, 4])
            .unwrap_err()
            .to_string()
            .contains("outside the codebook")
    );
    // Saved files reload to the same tokenizer.
    let again = VqTokenizer::<Inner>::load(dir.path(), &dev).unwrap();
    assert_eq!(again.encode(data, 4, [S, S]).unwrap(), ids);
    assert_eq!(again.info(), tok.info());
}

#[test]
fn a_tiny_vq_overfits_a_handful_of_rasters() {
    let dev = Default::default();
    let t0 = std::time::Instant::now();
    let src = MemorySource::new([2, S, S], rasters()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut tc = quick(250);
    tc.checkpoint_every = 1000;
    let tok = train::<B>(&tiny(64), &tc, &src, dir.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    let data: Vec<f32> = rasters().concat();
    let ids = tok.encode(data.clone(), 4, [S, S]).unwrap();
    let pred = tok.decode(&ids, 4, [4, 4]).unwrap();
    let mut iou = IouCounter::default();
    iou.add(2, [S, S], &pred, &data);
    for (c, v) in iou.iou().into_iter().enumerate() {
        let v = v.unwrap();
        assert!(v > 0.95, "channel {c}: IoU {v:.3}");
    }
    eprintln!("overfit: {:?}", t0.elapsed());
}

#[test]
fn a_dead_code_is_restarted_from_the_batch() {
    let dev = Default::default();
    let q = Quantizer::<B>::new(4, 3, &dev);
    // Codes along the axes; code 3 points away from all data.
    let codes = Tensor::<B, 2>::from_data(
        [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [-1.0, -1.0, -1.0],
        ],
        &dev,
    );
    let q = q.restart(Tensor::<B, 1, Int>::arange(0..4, &dev), codes);
    let rows = Tensor::<B, 2>::from_data(
        [[0.9, 0.3, 0.1], [0.1, 0.8, 0.5], [0.2, 0.1, 0.9], [0.6, 0.6, 0.5]],
        &dev,
    );
    let before: Vec<i64> = q
        .nearest(umgen_tokenizer_vq::normalize(rows.clone()))
        .into_data()
        .iter::<i64>()
        .collect();
    assert!(!before.contains(&3));
    let tc = VqTrainConfig {
        restart_after: 5,
        ..VqTrainConfig::default()
    };
    let (q, restarted) = restart_dead(
        q,
        &[10, 10, 10, 0],
        10,
        &tc,
        umgen_tokenizer_vq::normalize(rows.clone()),
        &dev,
    );
    assert_eq!(restarted, 1, "only code 3 was unused for 5 steps");
    let after: Vec<i64> = q
        .nearest(umgen_tokenizer_vq::normalize(rows))
        .into_data()
        .iter::<i64>()
        .collect();
    assert!(after.contains(&3), "the restarted code now wins a row: {after:?}");
    // Live codes are untouched.
    let e: Vec<f32> = q.codes().narrow(0, 0, 1).into_data().iter::<f32>().collect();
    assert!(
        (e[0] - 1.0).abs() < 1e-6 && e[1].abs() < 1e-6 && e[2].abs() < 1e-6,
        "{e:?}"
    );
}

#[test]
fn resumed_training_matches_uninterrupted_training() {
    let dev = Default::default();
    let src = MemorySource::new([2, S, S], rasters()).unwrap();
    let cfg = tiny(32);
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let straight = train::<B>(&cfg, &quick(6), &src, a.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    // Stop after step 3 (as a kill would, after its checkpoint), then continue to 6 in a fresh call.
    let stop = |r: &umgen_tokenizer_vq::StepReport| {
        if r.step == 3 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    };
    train::<B>(&cfg, &quick(6), &src, b.path(), &dev, stop).unwrap();
    let resumed = train::<B>(&cfg, &quick(6), &src, b.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap();
    let w = |t: &VqTokenizer<Inner>| umgen_checkpoint::burn_io::weights_to_bytes(t.model()).unwrap();
    assert!(
        w(&straight) == w(&resumed),
        "resumed weights differ from the uninterrupted run's"
    );
    // Another architecture refuses the checkpoints.
    let err = train::<B>(&tiny(16), &quick(6), &src, b.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap_err()
    .to_string();
    assert!(err.contains("does not match this run"), "{err}");
}

#[test]
fn wrong_sized_data_is_refused() {
    let dev = Default::default();
    let src = MemorySource::new([3, S, S], vec![vec![0.0; 3 * S * S]]).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let err = train::<B>(&tiny(16), &quick(1), &src, dir.path(), &dev, |_| {
        ControlFlow::Continue(())
    })
    .unwrap_err()
    .to_string();
    assert!(err.contains("3×16×16") && err.contains("2-channel"), "{err}");
    let _ = TensorData::new(vec![0.0f32], [1]);
}
