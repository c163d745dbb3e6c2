//! Behaviour of the agent modality: round trips, clamps, slot stability and nearest-first choice.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use rand::{Rng, SeedableRng, rngs::StdRng};
use umgen_modality::Modality;
use umgen_modality_agent::{ATTRIBUTES, AgentConfig, AgentModality};
use umgen_scene::{Agent, AgentCategory, Frame, SceneClip};

fn agent(track_id: u64, x: f64, y: f64) -> Agent {
    Agent {
        track_id,
        category: AgentCategory::Vehicle,
        x,
        y,
        z: 0.0,
        vx: 1.0,
        vy: 0.0,
        vz: 0.0,
        heading: 0.0,
        length: 4.5,
        width: 1.8,
        height: 1.5,
    }
}

fn clip(frames: Vec<Vec<Agent>>) -> SceneClip {
    let frames = frames
        .into_iter()
        .enumerate()
        .map(|(t, agents)| Frame {
            time: t as f64,
            agents,
            ..Frame::default()
        })
        .collect();
    SceneClip::new("clip", 1.0, frames).unwrap()
}

fn modality(max_agents: usize) -> AgentModality {
    AgentModality::new(
        "agent",
        AgentConfig {
            max_agents,
            ..AgentConfig::default()
        },
    )
    .unwrap()
}

#[test]
fn paper_vocabulary_and_special_ids() {
    let m = modality(64);
    let s = m.spec();
    assert_eq!(
        (s.vocab_size, s.tokens_per_frame, s.pad_id),
        (1028, 704, Some(1027))
    );
    assert_eq!(m.config().category_id(AgentCategory::Vehicle), 1024);
    assert_eq!(m.config().category_id(AgentCategory::Pedestrian), 1025);
    assert_eq!(m.config().category_id(AgentCategory::Cyclist), 1026);
}

#[test]
fn random_agents_round_trip_within_half_a_bin() {
    let m = modality(64);
    let cfg = m.config().clone();
    let mut rng = StdRng::seed_from_u64(11);
    let agents: Vec<Agent> = (0..40)
        .map(|i| {
            let r = cfg.ranges();
            let mut v = [0.0; 10];
            for (k, out) in v.iter_mut().enumerate() {
                *out = rng.random_range(r[k][0]..r[k][1]);
            }
            Agent {
                track_id: 100 + i,
                category: AgentCategory::ALL[i as usize % 3],
                x: v[0],
                y: v[1],
                z: v[2],
                vx: v[3],
                vy: v[4],
                vz: v[5],
                heading: v[6],
                length: v[7],
                width: v[8],
                height: v[9],
            }
        })
        .collect();
    let c = clip(vec![agents.clone()]);
    let ids = m.tokenize(&c, 0).unwrap();
    assert_eq!(ids.len(), 704);
    assert!(ids.iter().all(|&id| id < 1028));
    let mut f = Frame::default();
    assert_eq!(m.detokenize(&ids, &mut f).unwrap().malformed, 0);
    assert_eq!(f.agents.len(), 40);
    // All tracks appear in frame 0, so slots go nearest first.
    let mut expected = agents.clone();
    expected.sort_by(|a, b| a.distance().total_cmp(&b.distance()));
    let ranges = cfg.ranges();
    for (slot, (src, d)) in expected.iter().zip(&f.agents).enumerate() {
        assert_eq!((d.track_id, d.category), (slot as u64, src.category));
        let (sv, dv) = (values(src), values(d));
        for k in 0..10 {
            let half = (ranges[k][1] - ranges[k][0]) / 2048.0;
            assert!(
                (sv[k] - dv[k]).abs() <= half + 1e-9,
                "field {k}: {} vs {}",
                sv[k],
                dv[k]
            );
        }
    }
    assert!(m.clamp_report().iter().all(|c| c.below == 0 && c.above == 0));
}

fn values(a: &Agent) -> [f64; 10] {
    [
        a.x, a.y, a.z, a.vx, a.vy, a.vz, a.heading, a.length, a.width, a.height,
    ]
}

#[test]
fn out_of_range_values_clamp_to_the_end_bins_and_are_counted() {
    let m = modality(4);
    let mut far = agent(1, 70.0, -80.0);
    far.vz = 1.0;
    let ids = m.tokenize(&clip(vec![vec![far]]), 0).unwrap();
    assert_eq!((ids[0], ids[1], ids[5]), (1023, 0, 1023));
    let r = m.clamp_report();
    let get = |f: &str| {
        r.iter()
            .find(|c| c.field == f)
            .map(|c| (c.below, c.above))
            .unwrap()
    };
    assert_eq!(get("x"), (0, 1));
    assert_eq!(get("y"), (1, 0));
    assert_eq!(get("vz"), (0, 1));
    assert_eq!(get("length"), (0, 0));
}

#[test]
fn a_track_keeps_its_slot_and_is_pad_where_absent() {
    let m = modality(4);
    let c = clip(vec![
        vec![agent(7, 20.0, 0.0), agent(9, 5.0, 0.0)],
        vec![agent(9, 6.0, 0.0), agent(12, 3.0, 0.0)],
        vec![agent(12, 4.0, 0.0), agent(7, 18.0, 0.0)],
    ]);
    let rows = m.tokenize_clip(&c).unwrap();
    let pad = 1027;
    let slot_x = |row: &Vec<u32>, s: usize| row[s * ATTRIBUTES];
    // Frame 0: track 9 (nearer) takes slot 0, track 7 slot 1; track 12 appears later and takes slot 2.
    let bins = |x: f64| ((x + 64.0) / 0.125).floor() as u32;
    assert_eq!(slot_x(&rows[0], 0), bins(5.0));
    assert_eq!(slot_x(&rows[0], 1), bins(20.0));
    assert_eq!(slot_x(&rows[0], 2), pad);
    assert_eq!(slot_x(&rows[1], 1), pad, "track 7 is absent in frame 1");
    assert_eq!(slot_x(&rows[1], 2), bins(3.0));
    assert_eq!(slot_x(&rows[2], 1), bins(18.0), "track 7 returns to its slot");
    assert_eq!(slot_x(&rows[2], 0), pad);
    assert!(
        rows.iter()
            .all(|r| r[3 * ATTRIBUTES..].iter().all(|&id| id == pad))
    );
}

#[test]
fn more_tracks_than_slots_keeps_the_nearest() {
    let m = modality(2);
    let c = clip(vec![
        vec![agent(1, 40.0, 0.0), agent(2, 30.0, 0.0), agent(3, 50.0, 0.0)],
        vec![agent(1, 40.0, 0.0), agent(3, 10.0, 0.0)],
    ]);
    let rows = m.tokenize_clip(&c).unwrap();
    let mut f = Frame::default();
    m.detokenize(&rows[0], &mut f).unwrap();
    let xs: Vec<f64> = f.agents.iter().map(|a| a.x).collect();
    // Track 1 (40 m) is the farthest over the clip and is dropped; 2 and 3 keep slots in appearance order.
    assert_eq!(xs.len(), 2);
    assert!((xs[0] - 30.0).abs() < 0.1 && (xs[1] - 50.0).abs() < 0.1, "{xs:?}");
    let slots = m.clamp_report().into_iter().find(|c| c.field == "slots").unwrap();
    assert_eq!(slots.above, 2, "track 1's two observations had no slot");
}

#[test]
fn duplicate_tracks_and_malformed_slots_are_reported() {
    let m = modality(4);
    let err = m
        .tokenize(&clip(vec![vec![agent(5, 1.0, 0.0), agent(5, 2.0, 0.0)]]), 0)
        .unwrap_err()
        .to_string();
    assert!(err.contains("clip") && err.contains("track 5"), "{err}");
    let mut ids = m
        .tokenize(&clip(vec![vec![agent(5, 1.0, 0.0), agent(6, 2.0, 0.0)]]), 0)
        .unwrap();
    ids[3] = 1027; // a pad inside slot 0's values
    ids[ATTRIBUTES + 10] = 17; // slot 1's category is a value id
    let mut f = Frame::default();
    let report = m.detokenize(&ids, &mut f).unwrap();
    assert_eq!((report.malformed, f.agents.len()), (2, 0));
    assert!(m.detokenize(&ids[..10], &mut f).is_err());
}
