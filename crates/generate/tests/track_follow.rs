//! The engine's `track` operation on the host executor against burn's `backbone::track::moved`, with
//! the follow rule on: SUMO-like lanes of slots, standing and moving, over a window whose slots move by
//! constant acceleration, give the same moved ids; the rule brakes many of them. With stop points (a
//! segment of lights-like heads, red ones braked for unless a green one stands at the same place) they
//! agree too, and the red heads brake more slots.
#![allow(clippy::unwrap_used, missing_docs)]

use burn::tensor::{Tensor, TensorData};
use std::f64::consts::PI;
use umgen_backbone::track::moved;
use umgen_backbone::{FollowSpec, SegmentSpec, StopSpec, TrackSpec};
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
        stops: None,
    }
}

/// Head slots per frame: x, y, heading (128 bins each), state `128 + code` (129 red, 130 yellow, 131
/// green), pad 132.
const HEADS: usize = 8;

fn stops() -> StopSpec {
    StopSpec {
        segment: 1,
        slot: 4,
        values: 128,
        fields: [
            (0, (-64.0, 64.0, 128)),
            (1, (-64.0, 64.0, 128)),
            (2, (-PI, PI, 128)),
        ],
        state: 3,
        stop: vec![129],
        go: vec![130, 131],
        gap_m: StopSpec::GAP_M,
    }
}

/// A seeded uniform draw in [0, 1).
fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
    move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// `frames` frames of heads at the ends of the four lanes of [`frames`], mostly red, some pairs at one
/// place (one lane end: the same bins) with a second state, a few empty.
fn heads(frames: usize) -> Vec<i64> {
    let mut draw = uniform(9);
    let bin = |v: f64, lo: f64, hi: f64| ((v - lo) / ((hi - lo) / 128.0)).floor() as i64;
    let mut ids = Vec::new();
    for _ in 0..frames {
        let mut slots = Vec::new();
        while slots.len() < HEADS * 4 {
            if draw() < 0.15 {
                slots.extend([132; 4]);
                continue;
            }
            let lane = (draw() * 4.0).floor();
            let y = (lane - 1.5) * 3.2;
            let h = if lane < 2.0 { 0.0 } else { PI - 1e-3 };
            let x = (draw() - 0.5) * 80.0;
            let state = if draw() < 0.6 {
                129
            } else {
                130 + (draw() * 2.0).floor() as i64
            };
            let head = [bin(x, -64.0, 64.0), bin(y, -64.0, 64.0), bin(h, -PI, PI), state];
            slots.extend(head);
            if slots.len() < HEADS * 4 && draw() < 0.3 {
                slots.extend([head[0], head[1], head[2], 131]);
            }
        }
        ids.extend(slots);
    }
    ids
}

/// `frames` frames of slots on four lanes (two each way, 3.2 m apart), a few empty, half standing.
fn frames(frames: usize) -> Vec<i64> {
    let mut draw = uniform(5);
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

fn burn_moved(ids: &[i64], heads: &[i64], acts: &[f32], b: usize, t: usize, k: &TrackSpec) -> Vec<i32> {
    let dev = Default::default();
    let stops = (!heads.is_empty())
        .then(|| Tensor::from_data(TensorData::new(heads.to_vec(), [b, t, HEADS * 4]), &dev));
    moved::<F>(
        Tensor::from_data(TensorData::new(ids.to_vec(), [b, t, SLOTS * K]), &dev),
        stops,
        Tensor::from_data(TensorData::new(acts.to_vec(), [b, t, 3]), &dev),
        k,
    )
    .into_data()
    .iter::<i64>()
    .map(|v| v as i32)
    .collect()
}

/// The engine's host `track` op over frames of the agents' slots followed by the heads' (when given).
fn host_moved(ids: &[i64], heads: &[i64], acts: &[f32], b: usize, t: usize, k: &TrackSpec) -> Vec<i32> {
    let mut x = HostExec::new();
    let (agents, lights) = (SLOTS * K, if heads.is_empty() { 0 } else { HEADS * 4 });
    let n = agents + lights;
    let frames: Vec<i32> = (0..b * t)
        .flat_map(|f| {
            let a = ids[f * agents..(f + 1) * agents].iter();
            a.chain(&heads[f * lights..(f + 1) * lights]).map(|&v| v as i32)
        })
        .collect();
    let tok = x.alloc(Elem::I32, frames.len()).unwrap();
    x.write(tok, Data::I32(&frames)).unwrap();
    let act = x.alloc(Elem::F32, acts.len()).unwrap();
    x.write(act, Data::F32(acts)).unwrap();
    let out = x.alloc(Elem::I32, ids.len()).unwrap();
    let segment = |label: &str, offset: usize, tokens: usize, vocab: usize| SegmentSpec {
        label: label.into(),
        block_start: offset,
        block_len: tokens,
        offset,
        tokens,
        vocab,
        embed_vocab: vocab + 2,
        ordinal: 0,
        codebook: None,
    };
    let segments = [
        segment("agent", 0, agents, 1028),
        segment("lights", agents, HEADS * 4, 133),
    ];
    x.run(&Op::Track(track_op(k, &segments, [tok, act, out], b * t, t, n)))
        .unwrap();
    x.read_i32(out, ids.len()).unwrap()
}

#[test]
fn the_host_track_op_brakes_as_burn_does() {
    let (b, t) = (3, 4);
    let ids = frames(b * t);
    let acts = actions(b * t);
    let (on, off) = (spec(true), spec(false));
    let burn_on = burn_moved(&ids, &[], &acts, b, t, &on);
    assert_eq!(host_moved(&ids, &[], &acts, b, t, &on), burn_on);
    let burn_off = burn_moved(&ids, &[], &acts, b, t, &off);
    assert_eq!(host_moved(&ids, &[], &acts, b, t, &off), burn_off);
    // The rule changes the vx token of many slots, and only by lowering their speed along +x lanes.
    let changed: Vec<usize> = (0..b * t * SLOTS)
        .filter(|s| burn_on[s * K + 2] != burn_off[s * K + 2])
        .collect();
    assert!(changed.len() >= 10, "{} slots braked", changed.len());
}

/// Each frame's next ego action: forward, drifting and turning a little.
fn actions(frames: usize) -> Vec<f32> {
    (0..frames)
        .flat_map(|i| {
            [
                2.0 + 0.3 * i as f32,
                0.02 * i as f32 - 0.1,
                0.03 - 0.01 * i as f32,
            ]
        })
        .collect()
}

#[test]
fn the_host_track_op_stops_at_red_heads_as_burn_does() {
    let (b, t) = (3, 4);
    let (ids, heads) = (frames(b * t), heads(b * t));
    let acts = actions(b * t);
    let follow = spec(true);
    let stopping = TrackSpec {
        stops: Some(stops()),
        ..follow.clone()
    };
    let burn_stops = burn_moved(&ids, &heads, &acts, b, t, &stopping);
    assert_eq!(host_moved(&ids, &heads, &acts, b, t, &stopping), burn_stops);
    // The heads brake slots the follow rule alone leaves.
    let burn_follow = burn_moved(&ids, &[], &acts, b, t, &follow);
    let changed: Vec<usize> = (0..b * t * SLOTS)
        .filter(|s| burn_stops[s * K + 2] != burn_follow[s * K + 2])
        .collect();
    assert!(changed.len() >= 5, "{} slots braked by the heads", changed.len());
    // Without the stop spec the heads are ignored.
    assert_eq!(burn_moved(&ids, &heads, &acts, b, t, &follow), burn_follow);
    // The PyTorch runner's `motion.moved` gives the same ids, from the spec as the manifest writes it.
    python_moved_check(&serde_json::json!({
        "track": stopping,
        "shape": [b, t],
        "ids": ids,
        "heads": heads,
        "actions": acts,
        "want": burn_stops,
        "without_stops": burn_follow,
    }));
}

/// `tests/python/check_motion.py` on `case`, where the suite's Python (`UMGEN_TB_PYTHON`, set by
/// `.ci/run`) is given.
fn python_moved_check(case: &serde_json::Value) {
    let Ok(python) = std::env::var("UMGEN_TB_PYTHON") else {
        return;
    };
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("case.json");
    std::fs::write(&file, case.to_string()).unwrap();
    let out = std::process::Command::new(python)
        .arg(root.join("tests/python/check_motion.py"))
        .arg(&file)
        .env("PYTHONPATH", root.join("runners/python"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "check_motion.py: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
