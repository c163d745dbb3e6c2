//! The rollout against the training forward pass: greedy frames are the argmax of the teacher-forced
//! logits at every position (drawn on the host or on the device); tokens stay in their vocabularies;
//! seeds, forced actions and initial scenes.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use burn::tensor::{Int, Tensor, TensorData};
use umgen_backbone::{ActionSpec, Backbone, BackboneSpec, Kernels, Slot, TrackSpec};
use umgen_generate::{FrameControl, Generator, GivenSegment, Sampling};

mod common;
use common::{F, config, seeded, seg};

fn model() -> Backbone<F> {
    let spec = BackboneSpec {
        n: 5 + 8 + 6,
        segments: vec![seg("ego", 0, 3, 16), seg("map", 5, 6, 12), seg("agent", 13, 4, 9)],
        action: Some(ActionSpec {
            segment: 0,
            bins: [(0.0, 8.0, 16), (-1.0, 1.0, 16), (-0.5, 0.5, 16)],
        }),
        align: None,
        // The map segment's 6 tokens as one tracked slot, so that the comparison with the training
        // pass covers the moved slots too.
        track: Some(TrackSpec {
            segment: 1,
            slot: 6,
            values: 10,
            fields: [
                (0, (-4.0, 4.0, 10)),
                (1, (-4.0, 4.0, 10)),
                (2, (-2.0, 2.0, 10)),
                (3, (-2.0, 2.0, 10)),
                (4, (-3.2, 3.2, 10)),
            ],
            step_s: 0.5,
            pad: None,
            // Constant acceleration reads the window's previous frame: generation must see it as the
            // teacher-forced pass does.
            accel: true,
            follow: None,
            stops: None,
        }),
    };
    seeded(&config(), &spec, 9)
}

/// Valid frames: boundary ids around content ids drawn from a fixed pattern.
fn frame(m: &Backbone<F>, k: u32) -> Vec<u32> {
    m.slots()
        .iter()
        .enumerate()
        .map(|(p, s)| match *s {
            Slot::Start(i) => m.spec().segments[i].vocab as u32,
            Slot::End(i) => m.spec().segments[i].vocab as u32 + 1,
            Slot::Content(i, _) => (p as u32 * 7 + k * 3) % m.spec().segments[i].vocab as u32,
        })
        .collect()
}

/// A generator drawing from the full softmax (no top-k) for every modality.
fn unfiltered(m: &Backbone<F>, seed: u64) -> Generator<'_, F> {
    let all = Sampling {
        top_k: 0,
        ..Sampling::default()
    };
    Generator::new(m, vec![all; 3], 4, seed).unwrap()
}

/// The agent segment (positions 14..18, ids 0..9) as 2 groups of 2 with pad 8, values 0..6 and last ids
/// 6..8, with `boxes` for the new-agent rule.
fn agent_groups(boxes: Option<umgen_generate::GroupBoxes>) -> FrameControl {
    FrameControl {
        groups: vec![umgen_generate::TokenGroups {
            first: 14,
            size: 2,
            count: 2,
            pad: 8,
            values: 6,
            last: 6..8,
            boxes,
        }],
        ..Default::default()
    }
}

fn ids(frames: &[Vec<u32>], n: usize) -> Tensor<F, 3, Int> {
    let v: Vec<i64> = frames.iter().flatten().map(|&x| i64::from(x)).collect();
    Tensor::from_data(TensorData::new(v, [1, frames.len(), n]), &Default::default())
}

fn argmax(t: Tensor<F, 2>) -> Vec<u32> {
    let [r, v] = t.dims();
    let flat: Vec<f32> = t.into_data().iter::<f32>().collect();
    (0..r)
        .map(|i| {
            let row = &flat[i * v..(i + 1) * v];
            (0..v)
                .max_by(|&a, &b| row[a].total_cmp(&row[b]).then(b.cmp(&a)))
                .unwrap() as u32
        })
        .collect()
}

#[test]
fn greedy_frames_are_the_argmax_of_the_teacher_forced_pass() {
    let m = model();
    let n = m.spec().n;
    let history = vec![frame(&m, 1), frame(&m, 2)];
    let greedy = |on_device| {
        let mut g = Generator::new(&m, vec![Sampling::greedy(); 3], 8, 0)
            .unwrap()
            .draw_on_device(on_device);
        g.next_frame(std::slice::from_ref(&history), &FrameControl::default())
            .unwrap()
            .remove(0)
    };
    let z = greedy(false);
    assert_eq!(z, greedy(true), "drawn on the host or on the device");

    // The ego module's argmax is the action.
    let e = m.embed.forward(ids(&history, n), &Kernels::DEFAULT);
    let ego = m.ego_logits(e.clone(), true).unwrap().reshape([3, 16]);
    assert_eq!(argmax(ego), z[1..4].to_vec());

    // TAR and OAR over the window and the generated frame, as in training.
    let all = ids(&[history.clone(), vec![z.clone()]].concat(), n);
    let e_all = m.embed.forward(all.clone(), &Kernels::DEFAULT);
    let h = m.tar(
        all.clone().narrow(1, 0, 2),
        e_all.clone().narrow(1, 0, 2),
        e_all.clone().narrow(1, 1, 2),
        Some(all.narrow(1, 1, 2).narrow(2, 1, 3)),
    );
    let h_last = h.narrow(1, 1, 1).reshape([1, n, 32]);
    let o = m.oar(m.oar_input(e_all.narrow(1, 2, 1).reshape([1, n, 32]), h_last));
    for (s, seg) in m.spec().segments.iter().enumerate().skip(1) {
        let logits = m
            .oar_heads
            .logits(s, o.clone(), &Kernels::DEFAULT)
            .reshape([seg.tokens, seg.vocab]);
        assert_eq!(
            argmax(logits),
            z[seg.offset..seg.offset + seg.tokens].to_vec(),
            "{}",
            seg.label
        );
    }
}

#[test]
fn tokens_stay_in_their_vocabularies_and_seeds_repeat() {
    let m = model();
    let history = vec![vec![frame(&m, 1)], vec![frame(&m, 4)], vec![frame(&m, 2)]];
    let run_with = |seed, on_device, pass_frames, block| {
        let mut g = Generator::new(&m, vec![Sampling::default(); 3], 8, seed)
            .unwrap()
            .draw_on_device(on_device)
            .pass_frames(pass_frames)
            .uniform_block(block);
        let mut h = history.clone();
        for _ in 0..3 {
            let next = g.next_frame(&h, &FrameControl::default()).unwrap();
            for (hist, f) in h.iter_mut().zip(next) {
                hist.push(f);
            }
        }
        h
    };
    let run_in = |seed, on_device, pass_frames| {
        run_with(
            seed,
            on_device,
            pass_frames,
            umgen_generate::DEFAULT_UNIFORM_BLOCK,
        )
    };
    let run = |seed, on_device| run_in(seed, on_device, umgen_generate::DEFAULT_PASS_FRAMES);
    let a = run(5, false);
    assert_eq!(a, run(5, false), "same seed, same scenes");
    assert_ne!(a, run(6, false), "another seed, other scenes");
    let d = run(5, true);
    assert_eq!(d, run(5, true), "same seed, same scenes (device draws)");
    assert_ne!(d, run(6, true), "another seed, other scenes (device draws)");
    // The window pass one scene at a time (2 frames of history by the last step, so 2 frames per pass
    // are still one scene) draws the same frames as all scenes at once.
    assert_eq!(a, run_in(5, false, 1), "window pass a scene at a time");
    assert_eq!(
        d,
        run_in(5, true, 2),
        "window pass a scene at a time (device draws)"
    );
    // The device draws' uniform numbers uploaded one position at a time, or a few positions at a time,
    // give the frames of one upload per frame.
    assert_eq!(d, run_with(5, true, 64, 1), "one position per upload");
    assert_eq!(d, run_with(5, true, 64, 100), "a few positions per upload");
    for scene in a.iter().chain(&d) {
        for f in scene {
            for (p, s) in m.slots().iter().enumerate() {
                match *s {
                    Slot::Start(i) => assert_eq!(f[p], m.spec().segments[i].vocab as u32),
                    Slot::End(i) => assert_eq!(f[p], m.spec().segments[i].vocab as u32 + 1),
                    Slot::Content(i, _) => assert!(f[p] < m.spec().segments[i].vocab as u32),
                }
            }
        }
    }
}

#[test]
fn forced_actions_initial_scenes_and_bad_settings() {
    let m = model();
    let mut g = Generator::new(&m, vec![Sampling::default(); 3], 4, 1).unwrap();
    let control = FrameControl {
        action: Some(vec![vec![15, 0, 7]]),
        tokens: vec![(7, 11), (15, 2)],
        ..Default::default()
    };
    let f = g.next_frame(&[vec![frame(&m, 2)]], &control).unwrap();
    assert_eq!(f[0][1..4], [15, 0, 7]);
    assert_eq!((f[0][7], f[0][15]), (11, 2), "placed tokens");
    // Keep: where the OAR can only draw id 0 (a stand-in for pad), scenes marked true redraw from the TAR
    // head, which may say 0 again (the agent leaves: the TAR decides); the others keep 0.
    let mut redrawn = Vec::new();
    for seed in 0..5 {
        let mut g = Generator::new(&m, vec![Sampling::default(); 3], 4, seed).unwrap();
        let keep = FrameControl {
            below: vec![(8, 1)],
            keep: vec![(8, 0, vec![true, false])],
            ..Default::default()
        };
        let f = g
            .next_frame(&[vec![frame(&m, 2)], vec![frame(&m, 3)]], &keep)
            .unwrap();
        assert!(f[0][8] < 12, "redrawn: {}", f[0][8]);
        assert_eq!(f[1][8], 0);
        redrawn.push(f[0][8]);
    }
    assert!(redrawn.iter().any(|&id| id != 0), "never redrawn: {redrawn:?}");
    // A kept slot whose first token came out pad stays empty: its later tokens are not redrawn into a
    // slot that mixes pad and values.
    for seed in 0..5 {
        let mut g = unfiltered(&m, seed);
        let mut control = agent_groups(None);
        control.tokens = vec![(14, 8)];
        control.keep = vec![(15, 8, vec![true])];
        let f = g.next_frame(&[vec![frame(&m, 2)]], &control).unwrap();
        assert_eq!((f[0][14], f[0][15]), (8, 8), "seed {seed}");
    }
    // Token groups (`agent_groups`): every group comes out all-pad or values-then-last.
    for seed in 0..20 {
        let mut g = unfiltered(&m, seed);
        let grouped = agent_groups(None);
        let f = g.next_frame(&[vec![frame(&m, 2)]], &grouped).unwrap();
        for k in [14, 16] {
            let (a, b) = (f[0][k], f[0][k + 1]);
            assert!(
                (a == 8 && b == 8) || (a < 6 && (6..8).contains(&b)),
                "seed {seed}: group ({a}, {b})"
            );
        }
    }
    // The new-agent rule with every box decoded at the origin, on the ego: in an initial scene every
    // group is new, so every agent drawn is dropped, and the generator counts each one.
    let (mut tested, mut dropped) = (0, 0);
    for seed in 0..20 {
        let mut g = unfiltered(&m, seed);
        let at_origin = |lo: f64, hi: f64| (0, lo, hi, 6);
        let boxed = agent_groups(Some(umgen_generate::GroupBoxes {
            fields: [
                at_origin(-0.1, 0.1),
                at_origin(-0.1, 0.1),
                at_origin(0.0, 0.1),
                at_origin(4.0, 4.1),
                at_origin(2.0, 2.1),
            ],
            ego: [5.0, 2.0],
            max_boxes: 30,
            whole_frame: true,
        }));
        let f = g.next_frame(&[vec![]], &boxed).unwrap();
        assert!(
            f[0][14..18].iter().all(|&x| x == 8),
            "seed {seed}: {:?}",
            &f[0][14..18]
        );
        let (t, d) = g.new_agents();
        assert_eq!(t, d, "seed {seed}: every new agent is on the ego");
        (tested, dropped) = (tested + t, dropped + d);
    }
    assert!(
        tested > 0 && tested == dropped,
        "{tested} tested, {dropped} dropped"
    );
    // A limit of 1 leaves only id 0 at that position, whatever the draws.
    for seed in 0..5 {
        let mut g = Generator::new(&m, vec![Sampling::default(); 3], 4, seed).unwrap();
        let limited = FrameControl {
            below: vec![(8, 1), (16, 1)],
            ..Default::default()
        };
        let f = g.next_frame(&[vec![frame(&m, 2)]], &limited).unwrap();
        assert_eq!((f[0][8], f[0][16]), (0, 0));
    }
    // From nothing: no TAR, the OAR draws every token, the action too.
    let f = g.next_frame(&[vec![]], &FrameControl::default()).unwrap();
    assert_eq!(f[0].len(), m.spec().n);
    // Long rollouts slide the window (4 frames here) instead of failing past max_frames.
    let long: Vec<Vec<u32>> = (0..12).map(|k| frame(&m, k)).collect();
    assert!(g.next_frame(&[long], &FrameControl::default()).is_ok());
    let bad = FrameControl {
        action: Some(vec![vec![1, 2]]),
        ..Default::default()
    };
    let e = g.next_frame(&[vec![frame(&m, 2)]], &bad).unwrap_err().to_string();
    assert!(e.contains("3 tokens"), "{e}");
    let e = Generator::new(&m, vec![Sampling::default(); 2], 4, 1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("2 sampling settings for 3 modalities"), "{e}");
}

#[test]
fn given_segments_come_out_per_scene_and_bad_ones_are_refused() {
    let m = model();
    let history = [vec![frame(&m, 2)], vec![frame(&m, 3)]];
    // The map's 6 content ids (positions 6..12), other ones in each scene.
    let map = |s: u32| (0..6).map(|i| (i * 5 + s * 7) % 12).collect::<Vec<u32>>();
    let given = |segment, ids| FrameControl {
        given: vec![GivenSegment { segment, ids }],
        ..Default::default()
    };
    for seed in 0..3 {
        let mut g = unfiltered(&m, seed);
        let f = g.next_frame(&history, &given(1, vec![map(0), map(1)])).unwrap();
        assert_eq!(
            (&f[0][6..12], &f[1][6..12]),
            (&map(0)[..], &map(1)[..]),
            "seed {seed}"
        );
    }
    let mut g = unfiltered(&m, 0);
    let mut refused = |c: FrameControl| g.next_frame(&history, &c).unwrap_err().to_string();
    let e = refused(given(0, vec![vec![1, 2, 3]; 2]));
    assert!(e.contains("`ego` is the ego action"), "{e}");
    let e = refused(given(1, vec![map(0)]));
    assert!(e.contains("given for 1 scenes, the batch has 2"), "{e}");
    let e = refused(given(1, vec![map(0), vec![1, 2]]));
    assert!(e.contains("`map` of scene 1 has 2 tokens, the segment 6"), "{e}");
    let e = refused(given(1, vec![map(0), vec![0, 0, 12, 0, 0, 0]]));
    assert!(e.contains("scene 1 holds id 12, outside its 12 ids"), "{e}");
    let e = refused(given(7, vec![map(0), map(1)]));
    assert!(e.contains("given segment 7: this layout has 3 segments"), "{e}");
    let mut twice = given(1, vec![map(0), map(1)]);
    twice.given.push(twice.given[0].clone());
    let e = refused(twice);
    assert!(e.contains("`map` is given twice"), "{e}");
    let mut both = given(1, vec![map(0), map(1)]);
    both.tokens = vec![(7, 1)];
    let e = refused(both);
    assert!(e.contains("a token is also placed at its position 7"), "{e}");
}

#[test]
fn speculative_blocks_keep_greedy_frames() {
    let m = model();
    let history = vec![frame(&m, 1), frame(&m, 2)];
    let greedy = |k| {
        let mut g = Generator::new(&m, vec![Sampling::greedy(); 3], 8, 0)
            .unwrap()
            .speculate(k);
        g.next_frame(std::slice::from_ref(&history), &FrameControl::default())
            .unwrap()
            .remove(0)
    };
    // Greedy: a draft is accepted exactly when it is the OAR's argmax, so every block ends as the
    // position-by-position decoding does.
    let z = greedy(0);
    assert_eq!(z, greedy(4), "blocks of 4");
    assert_eq!(z, greedy(2), "blocks of 2");
    // Sampling: the draws differ from position-by-position decoding but stay in the vocabularies (the
    // acceptance rule's distribution is tested in `rollout/speculate.rs`).
    let sample = |k| {
        let mut g = Generator::new(&m, vec![Sampling::default(); 3], 8, 1)
            .unwrap()
            .speculate(k);
        g.next_frame(&vec![history.clone(); 8], &FrameControl::default())
            .unwrap()
    };
    let (plain, fast) = (sample(0), sample(4));
    assert_ne!(plain, fast);
    assert_eq!(fast, sample(4), "same seed, same frames");
    for f in &fast {
        for (p, s) in m.slots().iter().enumerate() {
            if let Slot::Content(i, _) = *s {
                assert!(f[p] < m.spec().segments[i].vocab as u32);
            }
        }
    }
}
