//! The generation engine on the host executor against the burn decoder (`Generator`): greedy frames are the
//! same frames, on a model with every option the engine runs (a codebook table, the ego module with each
//! frame's own action, AMA, tracked slots moved by constant acceleration and braking for one ahead) and under every rule a control
//! sets (token groups with the new-agent rule, keep redraws, placed tokens, id limits, forced actions),
//! over a rollout that slides the window, from nothing and in chunks of scenes; sampled frames keep the
//! rules and repeat with their seed.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use umgen_backbone::{ActionSpec, AlignSpec, Backbone, BackboneSpec, FollowSpec, Slot, TrackSpec};
use umgen_generate::engine::{Engine, EngineSettings, HostExec};
use umgen_generate::{FrameControl, Generator, GivenSegment, GroupBoxes, Sampling, TokenGroups};

mod common;
use common::{F, config, seeded, seg};

/// Agent slots: 2 of 6 tokens (x, y, vx, vy, heading in 8 bins; then the category 8 or 9); pad 10.
const PAD: u32 = 10;

fn model() -> Backbone<F> {
    let mut map = seg("map", 5, 6, 12);
    map.codebook = Some((5, (0..60).map(|i| ((i * 37 % 19) as f32 - 9.0) / 7.0).collect()));
    let spec = BackboneSpec {
        n: 5 + 8 + 14,
        segments: vec![seg("ego", 0, 3, 16), map, seg("agent", 13, 12, 11)],
        action: Some(ActionSpec {
            segment: 0,
            bins: [(0.0, 8.0, 16), (-1.0, 1.0, 16), (-0.5, 0.5, 16)],
        }),
        align: Some(AlignSpec {
            segment: 1,
            rows: 2,
            cols: 3,
            cell_m: 4.0,
        }),
        track: Some(TrackSpec {
            segment: 2,
            slot: 6,
            values: 8,
            fields: [
                (0, (-8.0, 8.0, 8)),
                (1, (-8.0, 8.0, 8)),
                (2, (-4.0, 4.0, 8)),
                (3, (-4.0, 4.0, 8)),
                (4, (-3.2, 3.2, 8)),
            ],
            step_s: 0.5,
            pad: Some(PAD),
            accel: true,
            // Scaled to slots 2 m apart: a slot brakes for the other from 1 m/s².
            follow: Some(FollowSpec {
                half_width_m: 2.0,
                min_gap_m: 1.0,
                ..FollowSpec::default()
            }),
            stops: None,
        }),
    };
    seeded(&config(), &spec, 11)
}

/// A valid frame: boundary ids, content from a pattern, agent slot `k % 2` empty.
fn frame(m: &Backbone<F>, k: u32) -> Vec<u32> {
    m.slots()
        .iter()
        .enumerate()
        .map(|(p, s)| match *s {
            Slot::Start(i) => m.spec().segments[i].vocab as u32,
            Slot::End(i) => m.spec().segments[i].vocab as u32 + 1,
            Slot::Content(2, j) => {
                let (slot, f) = (j / 6, j % 6);
                if slot as u32 == k % 2 {
                    PAD
                } else if f == 5 {
                    8 + (k % 2)
                } else {
                    (p as u32 * 3 + k) % 8
                }
            }
            Slot::Content(i, _) => (p as u32 * 7 + k * 3) % m.spec().segments[i].vocab as u32,
        })
        .collect()
}

/// The agent slots' groups, with the new-agent rule's boxes (x, y, heading; length and width read from the
/// vx and vy tokens), a budget of 2 boxes (the ego's and one).
fn groups() -> TokenGroups {
    TokenGroups {
        first: 14,
        size: 6,
        count: 2,
        pad: PAD,
        values: 8,
        last: 8..10,
        boxes: Some(GroupBoxes {
            fields: [
                (0, -8.0, 8.0, 8),
                (1, -8.0, 8.0, 8),
                (4, -3.2, 3.2, 8),
                (2, 0.0, 6.0, 8),
                (3, 0.0, 3.0, 8),
            ],
            ego: [4.5, 2.0],
            max_boxes: 2,
            whole_frame: true,
        }),
    }
}

/// The map's content ids (positions 6..12) given to scene `s` on odd frames `k`: other ids in each scene,
/// and the id the even frames place at position 8 and one below the limit at 11.
fn given_map(s: usize, k: usize) -> Vec<u32> {
    (6..12)
        .map(|p| match p {
            8 => 3,
            11 => ((s + k) % 5) as u32,
            _ => ((p * 5 + s * 7 + k) % 12) as u32,
        })
        .collect()
}

/// Frame `k`'s control: groups; keep the slots alive in each scene's newest frame; a limit; the action
/// forced on even frames; a placed token on even frames, the whole map given per scene on odd ones.
fn control(history: &[Vec<Vec<u32>>], k: usize) -> FrameControl {
    let odd = k % 2 == 1;
    let keep = (14..26)
        .filter(|p| (p - 14) % 6 == 0)
        .map(|p| {
            let alive = history
                .iter()
                .map(|h| h.last().is_some_and(|f| f[p] != PAD))
                .collect();
            (p, PAD, alive)
        })
        .collect();
    FrameControl {
        action: k
            .is_multiple_of(2)
            .then(|| vec![vec![(3 + k) as u32 % 16, 7, 9]; history.len()]),
        tokens: if odd { Vec::new() } else { vec![(8, 3)] },
        below: vec![(11, 5)],
        keep,
        groups: vec![groups()],
        given: match odd {
            true => vec![GivenSegment {
                segment: 1,
                ids: (0..history.len()).map(|s| given_map(s, k)).collect(),
            }],
            false => Vec::new(),
        },
    }
}

/// A rollout of `frames` frames from `history` with `next`.
fn roll(
    history: &[Vec<Vec<u32>>],
    frames: usize,
    mut next: impl FnMut(&[Vec<Vec<u32>>], &FrameControl) -> Vec<Vec<u32>>,
) -> Vec<Vec<Vec<u32>>> {
    let mut h = history.to_vec();
    for k in 0..frames {
        let c = control(&h, k);
        let frames = next(&h, &c);
        for (hist, f) in h.iter_mut().zip(frames) {
            hist.push(f);
        }
    }
    h
}

fn engine(
    m: &Backbone<F>,
    sampling: Sampling,
    window: usize,
    seed: u64,
    pass_frames: usize,
) -> Engine<HostExec> {
    let settings = EngineSettings {
        sampling: vec![sampling; 3],
        window,
        seed,
        pass_frames,
    };
    Engine::new(HostExec::new(), &m.plain(), settings).unwrap()
}

fn histories(m: &Backbone<F>) -> Vec<Vec<Vec<u32>>> {
    (0..3u32)
        .map(|s| (0..4).map(|k| frame(m, k * 3 + s)).collect())
        .collect()
}

#[test]
fn greedy_frames_are_the_burn_decoders() {
    let m = model();
    let history = histories(&m);
    let mut g = Generator::new(&m, vec![Sampling::greedy(); 3], 3, 0).unwrap();
    let burn = roll(&history, 4, |h, c| g.next_frame(h, c).unwrap());
    let mut e = engine(&m, Sampling::greedy(), 3, 0, 64);
    let ours = roll(&history, 4, |h, c| e.next_frame(h, c).unwrap());
    assert_eq!(ours, burn);
    for (s, scene) in ours.iter().enumerate() {
        for k in [1, 3] {
            assert_eq!(
                scene[4 + k][6..12],
                given_map(s, k),
                "scene {s}, frame {k}: the given map"
            );
        }
    }
    assert_eq!(e.new_agents(), g.new_agents(), "new agents tested and dropped");
    assert!(e.new_agents().0 > 0, "the rollout tests no new agent");
    // The window pass a scene at a time draws the same frames.
    let mut one = engine(&m, Sampling::greedy(), 3, 0, 1);
    assert_eq!(roll(&history, 4, |h, c| one.next_frame(h, c).unwrap()), burn);
    // From nothing: no TAR, the OAR draws every token.
    let empty = vec![Vec::new(); 2];
    let mut g = Generator::new(&m, vec![Sampling::greedy(); 3], 3, 0).unwrap();
    let mut e = engine(&m, Sampling::greedy(), 3, 0, 64);
    assert_eq!(
        roll(&empty, 2, |h, c| e.next_frame(h, c).unwrap()),
        roll(&empty, 2, |h, c| g.next_frame(h, c).unwrap())
    );
}

#[test]
fn sampled_frames_keep_the_rules_and_repeat_with_their_seed() {
    let m = model();
    let history = histories(&m);
    let smp = Sampling {
        top_k: 4,
        top_p: 0.9,
        temperature: 0.8,
        top_p_rest: false,
    };
    let run = |seed, smp| {
        let mut e = engine(&m, smp, 3, seed, 64);
        roll(&history, 3, |h, c| e.next_frame(h, c).unwrap())
    };
    let a = run(5, smp);
    assert_eq!(a, run(5, smp), "same seed, same frames");
    for (s, scene) in a.iter().enumerate() {
        assert_eq!(scene[5][6..12], given_map(s, 1), "scene {s}: the given map");
    }
    assert_ne!(a, run(6, smp), "another seed, other frames");
    let all = Sampling {
        top_k: 0,
        top_p: 1.0,
        temperature: 1.0,
        top_p_rest: false,
    };
    for scene in a.iter().chain(&run(2, all)) {
        for f in &scene[4..] {
            assert_eq!(f[8], 3, "the placed token");
            assert!(f[11] < 5, "the limit");
            for (p, s) in m.slots().iter().enumerate() {
                match *s {
                    Slot::Start(i) => assert_eq!(f[p], m.spec().segments[i].vocab as u32),
                    Slot::End(i) => assert_eq!(f[p], m.spec().segments[i].vocab as u32 + 1),
                    Slot::Content(i, _) => assert!(f[p] < m.spec().segments[i].vocab as u32),
                }
            }
            for g in [14, 20] {
                let slot = &f[g..g + 6];
                let empty = slot.iter().all(|&t| t == PAD);
                let agent = slot[..5].iter().all(|&t| t < 8) && (8..10).contains(&slot[5]);
                assert!(empty || agent, "a slot that mixes pad and values: {slot:?}");
            }
        }
    }
    // Top-p without a top-k list is refused, naming the setting.
    let settings = EngineSettings {
        sampling: vec![
            Sampling {
                top_k: 0,
                top_p: 0.5,
                temperature: 1.0,
                top_p_rest: false,
            };
            3
        ],
        window: 3,
        seed: 0,
        pass_frames: 64,
    };
    let e = Engine::new(HostExec::new(), &m.plain(), settings)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("sampling.ego") && e.contains("top-p 0.5"), "{e}");
}
