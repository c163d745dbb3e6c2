//! Heads cover their own vocabulary only, and the loss is the cross-entropy computed independently.

use super::*;
use umgen_backbone::Kernels;

#[test]
fn each_segment_scores_only_its_own_vocabulary() {
    let m = model::<F>();
    let x = Tensor::<F, 3>::ones([2, spec().n, config().d_model], &Default::default());
    for (s, seg) in spec().segments.iter().enumerate() {
        assert_eq!(
            m.oar_heads.logits(s, x.clone(), &Kernels::DEFAULT).dims(),
            [2, seg.tokens, seg.vocab]
        );
        assert_eq!(
            m.tar_heads.logits(s, x.clone(), &Kernels::DEFAULT).dims(),
            [2, seg.tokens, seg.vocab]
        );
    }
}

#[test]
fn the_loss_is_the_token_weighted_cross_entropy() {
    let m = model::<F>();
    let (b, f, n) = (2, 3, spec().n);
    let ids = tokens(&spec(), b, f, 21);
    let toks = tensor::<F>(&ids, b, f, n);
    let losses = m.loss(toks.clone(), 1.0).unwrap();
    let part = |name: &str| -> f64 {
        f64::from(
            losses
                .parts
                .iter()
                .find(|(k, _)| k == name)
                .unwrap()
                .1
                .clone()
                .into_scalar(),
        )
    };
    // Independent computation in f64 from the raw logits of the OAR.
    let t = f - 1;
    let e = m.embed.forward(toks.clone(), &Kernels::DEFAULT);
    let (cond, next) = (e.clone().narrow(1, 0, t), e.narrow(1, 1, t));
    let h = m.tar(
        toks.clone().narrow(1, 0, t),
        cond,
        next.clone(),
        Some(toks.narrow(1, 1, t).narrow(2, 1, 3)),
    );
    let d = config().d_model;
    let o = m.oar(m.oar_input(next.reshape([b * t, n, d]), h.reshape([b * t, n, d])));
    let (mut all, mut count) = (0.0, 0usize);
    for (s, seg) in spec().segments.iter().enumerate() {
        let logits: Vec<f32> = m
            .oar_heads
            .logits(s, o.clone(), &Kernels::DEFAULT)
            .into_data()
            .iter::<f32>()
            .collect();
        let mut sum = 0.0;
        for r in 0..b * t {
            let (bi, ti) = (r / t, r % t);
            for k in 0..seg.tokens {
                let row = &logits[(r * seg.tokens + k) * seg.vocab..(r * seg.tokens + k + 1) * seg.vocab];
                let max = row.iter().fold(f64::NEG_INFINITY, |a, &v| a.max(f64::from(v)));
                let lse = max + row.iter().map(|&v| (f64::from(v) - max).exp()).sum::<f64>().ln();
                let target = ids[((bi * f) + ti + 1) * n + seg.offset + k] as usize;
                sum += lse - f64::from(row[target]);
            }
        }
        let mean = sum / (b * t * seg.tokens) as f64;
        assert!(
            (part(&format!("oar/{}", seg.label)) - mean).abs() < 1e-4,
            "{}: {} vs {mean}",
            seg.label,
            part(&format!("oar/{}", seg.label))
        );
        all += sum;
        count += b * t * seg.tokens;
    }
    assert!((part("oar") - all / count as f64).abs() < 1e-4);
    let total = f64::from(losses.total.into_scalar());
    assert!((total - (part("oar") + part("tar") + part("ego"))).abs() < 1e-4);
}

#[test]
fn a_dropped_prior_cuts_the_oar_loss_off_the_history() {
    use umgen_backbone::LossOptions;
    let m = model::<F>();
    let (f, n) = (2, spec().n);
    let ids = tokens(&spec(), 1, f, 5);
    // Frame 0 only conditions (frame 1 is the target): its content tokens changed, the action kept.
    let mut other = ids.clone();
    for (p, v) in other.iter_mut().enumerate().take(n).skip(5) {
        if p % 2 == 0 {
            *v = if *v > 0 { *v - 1 } else { *v + 1 };
        }
    }
    let oar = |ids: &[i64], prior_drop: f64| -> (f32, f32) {
        let opts = LossOptions {
            ego_weight: 1.0,
            prior_drop,
            ordinal_sigma: 0.0,
            kernels: Kernels::DEFAULT,
        };
        let l = m.loss_with(tensor::<F>(ids, 1, f, n), opts).unwrap();
        let get = |name: &str| {
            l.parts
                .iter()
                .find(|(k, _)| k == name)
                .unwrap()
                .1
                .clone()
                .into_scalar()
        };
        (get("oar"), get("tar"))
    };
    // Without the drop the history reaches the OAR; `loss` is `loss_with` at prior_drop 0.
    let (kept, tar_kept) = oar(&ids, 0.0);
    assert_ne!(kept, oar(&other, 0.0).0, "the history should move the OAR loss");
    let plain = m
        .loss(tensor::<F>(&ids, 1, f, n), 1.0)
        .unwrap()
        .total
        .into_scalar();
    let with = m
        .loss_with(
            tensor::<F>(&ids, 1, f, n),
            LossOptions {
                ego_weight: 1.0,
                prior_drop: 0.0,
                ordinal_sigma: 0.0,
                kernels: Kernels::DEFAULT,
            },
        )
        .unwrap()
        .total
        .into_scalar();
    assert_eq!(plain, with);
    // Always dropped: the OAR loss ignores the history, the TAR's does not.
    let (dropped, tar_dropped) = oar(&ids, 1.0);
    let (dropped_other, tar_other) = oar(&other, 1.0);
    assert_eq!(dropped, dropped_other);
    assert_ne!(dropped, kept);
    assert_eq!(tar_dropped, tar_kept);
    assert_ne!(tar_dropped, tar_other);
    let bad = LossOptions {
        ego_weight: 1.0,
        prior_drop: 1.5,
        ordinal_sigma: 0.0,
        kernels: Kernels::DEFAULT,
    };
    let err = m.loss_with(tensor::<F>(&ids, 1, f, n), bad).err().unwrap();
    assert!(err.to_string().contains("prior_drop = 1.5"), "{err}");
}

/// `ordinal_sigma` rescores the ordered segments (ego, agent) and the ego action and leaves the coded
/// ones (map, image) exactly as they were; a spread that is not a number of bins is refused.
#[test]
fn ordinal_smoothing_touches_only_ordered_bins() {
    use umgen_backbone::LossOptions;
    let m = model::<F>();
    let (b, f, n) = (2, 3, spec().n);
    let ids = tokens(&spec(), b, f, 8);
    let parts = |sigma: f64| -> Vec<(String, f32)> {
        let opts = LossOptions {
            ego_weight: 1.0,
            prior_drop: 0.0,
            ordinal_sigma: sigma,
            kernels: Kernels::DEFAULT,
        };
        let l = m.loss_with(tensor::<F>(&ids, b, f, n), opts).unwrap();
        l.parts.into_iter().map(|(k, v)| (k, v.into_scalar())).collect()
    };
    let (hard, soft) = (parts(0.0), parts(1.5));
    for ((name, h), (_, s)) in hard.iter().zip(&soft) {
        let ordered = name.ends_with("/ego") || name.ends_with("/agent") || name == "ego";
        let coded = name.ends_with("/map") || name.ends_with("/image");
        if ordered {
            assert_ne!(h, s, "{name} should be rescored");
        } else if coded {
            assert_eq!(h, s, "{name} should not change");
        }
    }
    let bad = LossOptions {
        ego_weight: 1.0,
        prior_drop: 0.0,
        ordinal_sigma: -1.0,
        kernels: Kernels::DEFAULT,
    };
    let err = m.loss_with(tensor::<F>(&ids, b, f, n), bad).err().unwrap();
    assert!(err.to_string().contains("ordinal_sigma = -1"), "{err}");
}

/// Mean cross-entropy in f64 of logits `[b, t, tokens, vocab]` against the ids of frames `1..=t` at
/// content positions `offset..offset + tokens` of windows `ids` `[b, t + 1, n]`.
fn mean_xent(logits: &Tensor<F, 4>, ids: &[i64], n: usize, offset: usize) -> f64 {
    let [b, t, tokens, v] = logits.dims();
    let values: Vec<f32> = logits.clone().into_data().iter::<f32>().collect();
    let mut sum = 0.0;
    for (r, row) in values.chunks(v).enumerate() {
        let (bi, ti, k) = (r / (t * tokens), (r / tokens) % t, r % tokens);
        let max = row.iter().fold(f64::NEG_INFINITY, |a, &x| a.max(f64::from(x)));
        let lse = max + row.iter().map(|&x| (f64::from(x) - max).exp()).sum::<f64>().ln();
        let target = ids[(bi * (t + 1) + ti + 1) * n + offset + k] as usize;
        sum += lse - f64::from(row[target]);
    }
    sum / (b * t * tokens) as f64
}

/// The logits `forced_logits` returns (what `umgen export --golden` writes) are the ones the loss scores:
/// every head's cross-entropy computed from them equals the loss's part.
#[test]
fn forced_logits_are_what_the_loss_scores() {
    let m = model::<F>();
    let (b, f, n) = (2, 3, spec().n);
    let ids = tokens(&spec(), b, f, 13);
    let losses = m.loss(tensor::<F>(&ids, b, f, n), 1.0).unwrap();
    let part = |name: &str| -> f64 {
        let (_, v) = losses.parts.iter().find(|(k, _)| k == name).unwrap();
        f64::from(v.clone().into_scalar())
    };
    let logits = m.forced_logits(tensor::<F>(&ids, b, f, n)).unwrap();
    for (s, seg) in spec().segments.iter().enumerate() {
        for (head, x) in [("tar", &logits.tar[s]), ("oar", &logits.oar[s])] {
            assert_eq!(x.dims(), [b, f - 1, seg.tokens, seg.vocab]);
            let name = format!("{head}/{}", seg.label);
            let mine = mean_xent(x, &ids, n, seg.offset);
            assert!(
                (part(&name) - mine).abs() < 1e-4,
                "{name}: {} vs {mine}",
                part(&name)
            );
        }
    }
    let ego = logits.ego.expect("the spec has an ego action");
    let action = &spec().segments[0];
    assert_eq!(ego.dims(), [b, f - 1, action.tokens, action.vocab]);
    assert!((part("ego") - mean_xent(&ego, &ids, n, action.offset)).abs() < 1e-4);
    let err = m.forced_logits(tensor::<F>(&ids[..n], 1, 1, n)).err().unwrap();
    assert!(err.to_string().contains("need ≥ 2 frames"), "{err}");
}
