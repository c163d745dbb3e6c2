//! The engine's `track` operation on the host executor against burn's `backbone::track::moved`, with
//! the follow rule on: SUMO-like lanes of slots, standing and moving, over a window whose slots move by
//! constant acceleration, give the same moved ids; the rule brakes many of them.
#![allow(clippy::unwrap_used, missing_docs)]

use burn::tensor::{Tensor, TensorData};
use std::f64::consts::PI;
use umgen_backbone::track::moved;
use umgen_backbone::{FollowSpec, SegmentSpec, TrackSpec};
use umgen_cuda::ops::{Data, Elem, Exec, Op};
use umgen_generate::engine::{HostExec, track_op};

type F = burn::backend::Flex;

const SLOTS: usize = 24;
const K: usize = 6;

fn spec(follow: bool) -> TrackSpec {
    TrackSpec {
        segment: 0,
        slot: K,
        values: 1024,
        fields: [
            (0, (-64.0, 64.0, 1024)),
            (1, (-64.0, 64.0, 1024)),
            (2, (-20.0, 20.0, 1024)),
            (3, (-20.0, 20.0, 1024)),
            (4, (-PI, PI, 1024)),
        ],
        step_s: 0.5,
        pad: Some(1027),
        accel: true,
        follow: follow.then(FollowSpec::default),
    }
}

/// `frames` frames of slots on four lanes (two each way, 3.2 m apart), a few empty, half standing.
fn frames(frames: usize) -> Vec<i64> {
    let mut seed = 5u64;
    let mut draw = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let bin = |v: f64, lo: f64, hi: f64| ((v - lo) / ((hi - lo) / 1024.0)).floor() as i64;
    let mut ids = Vec::new();
    for _ in 0..frames * SLOTS {
        if draw() < 0.15 {
            ids.extend([1027; K]);
            continue;
        }
        let lane = (draw() * 4.0).floor();
        let y = (lane - 1.5) * 3.2 + (draw() - 0.5) * 0.6;
        let h = if lane < 2.0 { 0.0 } else { PI - 1e-3 } + (draw() - 0.5) * 0.2;
        let v = if draw() < 0.5 {
            draw() * 0.5
        } else {
            3.0 + draw() * 12.0
        };
        let x = (draw() - 0.5) * 110.0;
        ids.extend([
            bin(x, -64.0, 64.0),
            bin(y, -64.0, 64.0),
            bin(v * h.cos(), -20.0, 20.0),
            bin(v * h.sin(), -20.0, 20.0),
            bin(h, -PI, PI),
            1024,
        ]);
    }
    ids
}

fn burn_moved(ids: &[i64], acts: &[f32], b: usize, t: usize, k: &TrackSpec) -> Vec<i32> {
    let dev = Default::default();
    moved::<F>(
        Tensor::from_data(TensorData::new(ids.to_vec(), [b, t, SLOTS * K]), &dev),
        Tensor::from_data(TensorData::new(acts.to_vec(), [b, t, 3]), &dev),
        k,
    )
    .into_data()
    .iter::<i64>()
    .map(|v| v as i32)
    .collect()
}

fn host_moved(ids: &[i64], acts: &[f32], b: usize, t: usize, k: &TrackSpec) -> Vec<i32> {
    let mut x = HostExec::new();
    let n = SLOTS * K;
    let tok = x.alloc(Elem::I32, ids.len()).unwrap();
    let ids32: Vec<i32> = ids.iter().map(|&v| v as i32).collect();
    x.write(tok, Data::I32(&ids32)).unwrap();
    let act = x.alloc(Elem::F32, acts.len()).unwrap();
    x.write(act, Data::F32(acts)).unwrap();
    let out = x.alloc(Elem::I32, ids.len()).unwrap();
    let seg = SegmentSpec {
        label: "agent".into(),
        block_start: 0,
        block_len: n + 2,
        offset: 0,
        tokens: n,
        vocab: 1028,
        embed_vocab: 1030,
        ordinal: 1024,
        codebook: None,
    };
    x.run(&Op::Track(track_op(k, &seg, [tok, act, out], b * t, t, n)))
        .unwrap();
    x.read_i32(out, ids.len()).unwrap()
}

#[test]
fn the_host_track_op_brakes_as_burn_does() {
    let (b, t) = (3, 4);
    let ids = frames(b * t);
    let acts: Vec<f32> = (0..b * t)
        .flat_map(|i| {
            [
                2.0 + 0.3 * i as f32,
                0.02 * i as f32 - 0.1,
                0.03 - 0.01 * i as f32,
            ]
        })
        .collect();
    let (on, off) = (spec(true), spec(false));
    let burn_on = burn_moved(&ids, &acts, b, t, &on);
    assert_eq!(host_moved(&ids, &acts, b, t, &on), burn_on);
    let burn_off = burn_moved(&ids, &acts, b, t, &off);
    assert_eq!(host_moved(&ids, &acts, b, t, &off), burn_off);
    // The rule changes the vx token of many slots, and only by lowering their speed along +x lanes.
    let changed: Vec<usize> = (0..b * t * SLOTS)
        .filter(|s| burn_on[s * K + 2] != burn_off[s * K + 2])
        .collect();
    assert!(changed.len() >= 10, "{} slots braked", changed.len());
}
