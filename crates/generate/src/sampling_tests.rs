//! `Sampling`'s draws against the softmax they should follow, filter by filter.

#![allow(clippy::unwrap_used)]
use super::*;
use rand::{SeedableRng, rngs::StdRng};

#[test]
fn per_segment_settings_replace_named_segments_and_refuse_unknown_ones() {
    let labels = ["ego", "map", "agent", "image"];
    let base = Sampling::default();
    let got = base
        .per_segment(
            &[("map".into(), 5), ("agent".into(), 64)],
            &[("agent".into(), 0.8)],
            &["agent".into()],
            &labels,
        )
        .unwrap();
    let ks: Vec<usize> = got.iter().map(|s| s.top_k).collect();
    assert_eq!(ks, [16, 5, 64, 16]);
    let ps: Vec<f64> = got.iter().map(|s| s.top_p).collect();
    assert_eq!(ps, [1.0, 1.0, 0.8, 1.0]);
    let rest: Vec<bool> = got.iter().map(|s| s.top_p_rest).collect();
    assert_eq!(rest, [false, false, true, false]);
    assert!(got.iter().all(|s| s.temperature == base.temperature));
    for (k, p, r, what) in [
        (
            vec![("lidar".to_string(), 5)],
            vec![],
            vec![],
            "top-k for `lidar`",
        ),
        (
            vec![],
            vec![("lidar".to_string(), 0.5)],
            vec![],
            "top-p for `lidar`",
        ),
        (
            vec![],
            vec![],
            vec!["lidar".to_string()],
            "top-p-rest for `lidar`",
        ),
    ] {
        let e = base.per_segment(&k, &p, &r, &labels).unwrap_err().to_string();
        assert!(e.contains(what) && e.contains("ego, map, agent, image"), "{e}");
    }
}

fn counts(s: Sampling, logits: &[f32], draws: usize) -> Vec<usize> {
    let mut rng = StdRng::seed_from_u64(1);
    let mut c = vec![0; logits.len()];
    for _ in 0..draws {
        c[s.draw(logits, &mut rng) as usize] += 1;
    }
    c
}

/// Checks a way of drawing (`count(s, logits, n)`: how often each id came out of `n` draws) against
/// the softmax of logits 0, ln 2, ln 3, `masked`, ln 4 under each filter: probabilities 1:2:3:4, the
/// masked id never.
pub(crate) fn check_draw_frequencies(count: impl Fn(Sampling, &[f32], usize) -> Vec<usize>, masked: f32) {
    let logits = [0.0f32, (2.0f32).ln(), (3.0f32).ln(), masked, (4.0f32).ln()];
    let all = Sampling {
        top_k: 0,
        top_p: 1.0,
        temperature: 1.0,
        top_p_rest: false,
    };
    let share = |c: &[usize], i: usize, n: usize| c[i] as f64 / n as f64;
    let c = count(all, &logits, 100_000);
    for (i, want) in [(0, 0.1), (1, 0.2), (2, 0.3), (4, 0.4)] {
        let got = share(&c, i, 100_000);
        assert!((got - want).abs() < 0.01, "id {i}: {got} vs {want}");
    }
    assert_eq!(c[3], 0, "the masked id is never drawn");
    // top-k 2 keeps ids 4 and 2 (4:3); top-p 0.5 too (0.4 alone is not enough, 0.4 + 0.3 is);
    // top-p 0.3 keeps id 4 alone; top-k 3 keeps 4, 2, 1 and top-p 0.5 of those (4/9, 3/9) 4 and 2.
    for s in [
        Sampling { top_k: 2, ..all },
        Sampling { top_p: 0.5, ..all },
        Sampling {
            top_k: 3,
            top_p: 0.5,
            ..all
        },
    ] {
        let c = count(s, &logits, 50_000);
        assert_eq!(c[0] + c[1] + c[3], 0, "{s:?}: {c:?}");
        assert!((share(&c, 4, 50_000) - 4.0 / 7.0).abs() < 0.01, "{s:?}: {c:?}");
    }
    assert_eq!(count(Sampling { top_p: 0.3, ..all }, &logits, 1_000)[4], 1_000);
    // The nucleus of the rest: id 4 keeps its 0.4; of the rest's 0.6, top-p 0.6 (0.36) keeps ids 2
    // and 1 (0.3 is short of it, 0.5 reaches it), which share 0.6 as 3:2. With top-k 3 the list is
    // 4, 2, 1 (4/9, 3/9, 2/9): top-p 0.5 of the rest's 5/9 is reached by id 2 alone.
    for (s, want) in [
        (
            Sampling {
                top_p: 0.6,
                top_p_rest: true,
                ..all
            },
            [(4, 0.4), (2, 0.36), (1, 0.24), (0, 0.0)],
        ),
        (
            Sampling {
                top_k: 3,
                top_p: 0.5,
                top_p_rest: true,
                ..all
            },
            [(4, 4.0 / 9.0), (2, 5.0 / 9.0), (1, 0.0), (0, 0.0)],
        ),
    ] {
        let c = count(s, &logits, 100_000);
        assert_eq!(c[3], 0);
        for (i, p) in want {
            let got = share(&c, i, 100_000);
            assert!((got - p).abs() < 0.01, "{s:?}: id {i} {got} vs {p}");
        }
    }
    // Without top-p the rest's nucleus changes nothing.
    let c = count(
        Sampling {
            top_p_rest: true,
            ..all
        },
        &logits,
        100_000,
    );
    assert!((share(&c, 0, 100_000) - 0.1).abs() < 0.01, "{c:?}");
    // Temperature 0.5 squares the odds (1:4:9:16); greedy is always the most likely id.
    let c = count(
        Sampling {
            temperature: 0.5,
            ..all
        },
        &logits,
        100_000,
    );
    assert!((share(&c, 4, 100_000) - 16.0 / 30.0).abs() < 0.01, "{c:?}");
    assert_eq!(count(Sampling::greedy(), &logits, 100)[4], 100);
}

#[test]
fn frequencies_follow_the_softmax_and_the_filters() {
    check_draw_frequencies(counts, f32::NAN);
}

/// The draw as first written: sort every id, then cut to the top k.
fn draw_by_full_sort(s: &Sampling, logits: &[f32], rng: &mut impl Rng) -> u32 {
    let mut order: Vec<usize> = (0..logits.len()).collect();
    order.sort_by(|&a, &b| logits[b].total_cmp(&logits[a]).then(a.cmp(&b)));
    order.retain(|&i| logits[i].is_finite());
    order.truncate(s.top_k);
    let top = f64::from(logits[order[0]]);
    let probs: Vec<f64> = order
        .iter()
        .map(|&i| ((f64::from(logits[i]) - top) / s.temperature).exp())
        .collect();
    let total: f64 = probs.iter().sum();
    let mut u: f64 = rng.random();
    for (p, &i) in probs.iter().zip(&order) {
        if u < *p / total {
            return i as u32;
        }
        u -= *p / total;
    }
    order[order.len() - 1] as u32
}

#[test]
fn selecting_the_top_k_draws_what_sorting_everything_drew() {
    let mut data = StdRng::seed_from_u64(5);
    for k in [1, 2, 16, 100] {
        let s = Sampling {
            top_k: k,
            ..Default::default()
        };
        let (mut a, mut b) = (StdRng::seed_from_u64(9), StdRng::seed_from_u64(9));
        for _ in 0..200 {
            // Few distinct values, so ties are common; some ids masked.
            let logits: Vec<f32> = (0..500)
                .map(|_| match data.random_range(0..10) {
                    0 => f32::NEG_INFINITY,
                    v => v as f32 * 0.5,
                })
                .collect();
            assert_eq!(s.draw(&logits, &mut a), draw_by_full_sort(&s, &logits, &mut b));
        }
    }
}

#[test]
fn a_group_first_draw_keeps_pad_at_its_untruncated_share() {
    // 200 equal values and pad at 9 × their mass: pad's share of the softmax is 0.9, of a top-5 list
    // (pad and four values) 1800 / 1804.
    let pad = 290u32;
    let mut logits = vec![f32::NEG_INFINITY; 300];
    logits[..200].iter_mut().for_each(|x| *x = 0.0);
    logits[pad as usize] = (9.0f32 * 200.0).ln();
    let s = Sampling {
        top_k: 5,
        top_p: 1.0,
        temperature: 1.0,
        top_p_rest: false,
    };
    let d = s.distribution_present(&logits, pad);
    assert_eq!(d[0].0, pad);
    // (The pad logit is ln 1800 in f32.)
    assert!((d[0].1 - 0.9).abs() < 1e-6, "{d:?}");
    // The list's four values (ties to the smaller ids) share the rest equally.
    let values: Vec<u32> = d[1..].iter().map(|(i, _)| *i).collect();
    assert_eq!(values, [0, 1, 2, 3]);
    assert!(d[1..].iter().all(|(_, p)| (p - 0.025).abs() < 1e-6), "{d:?}");
    let plain = s.distribution(&logits);
    assert!((plain[0].1 - 1800.0 / 1804.0).abs() < 1e-6, "{plain:?}");
    // Draws follow it.
    let mut rng = StdRng::seed_from_u64(3);
    let n = 20_000;
    let pads = (0..n)
        .filter(|_| s.draw_present(&logits, pad, &mut rng) == pad)
        .count();
    assert!((pads as f64 / n as f64 - 0.9).abs() < 0.01, "{pads}");
    // Greedy and untruncated draws are the plain ones; a masked pad has no share; no values: pad.
    for k in [0, 1] {
        let t = Sampling { top_k: k, ..s };
        assert_eq!(t.distribution_present(&logits, pad), t.distribution(&logits));
    }
    let mut no_pad = logits.clone();
    no_pad[pad as usize] = f32::NEG_INFINITY;
    let d = s.distribution_present(&no_pad, pad);
    assert_eq!(d[0], (pad, 0.0));
    assert!((d[1..].iter().map(|(_, p)| p).sum::<f64>() - 1.0).abs() < 1e-12);
    let mut only_pad = vec![f32::NEG_INFINITY; 300];
    only_pad[pad as usize] = 0.0;
    assert_eq!(s.distribution_present(&only_pad, pad), [(pad, 1.0)]);
    // With top-p, the values are cut among themselves: 0.5 of their mass keeps two of the four.
    let t = Sampling { top_p: 0.5, ..s };
    let d = t.distribution_present(&logits, pad);
    assert_eq!(d.len(), 3, "{d:?}");
    assert!((d[1].1 - 0.05).abs() < 1e-6, "{d:?}");
}

#[test]
fn bad_settings_are_named() {
    let e = Sampling {
        temperature: 0.0,
        ..Default::default()
    }
    .validate("sampling.map")
    .unwrap_err();
    assert!(e.to_string().contains("sampling.map.temperature = 0"), "{e}");
    let e = Sampling {
        top_p: 1.5,
        ..Default::default()
    }
    .validate("sampling.agent")
    .unwrap_err();
    assert!(e.to_string().contains("sampling.agent.top_p = 1.5"), "{e}");
}
