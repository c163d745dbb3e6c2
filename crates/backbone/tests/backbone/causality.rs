//! Later tokens never change earlier outputs.

use super::*;
use burn::tensor::Tensor;
use umgen_backbone::Kernels;

fn h_and_ego(m: &Backbone<F>, ids: &[i64], b: usize, f: usize) -> (Vec<f32>, Vec<f32>) {
    let n = spec().n;
    let toks = tensor::<F>(ids, b, f, n);
    let t = f - 1;
    let e = m.embed.forward(toks.clone(), &Kernels::DEFAULT);
    let (cond, next) = (e.clone().narrow(1, 0, t), e.narrow(1, 1, t));
    let action = toks.clone().narrow(1, 1, t).narrow(2, 1, 3);
    let h = m.tar(toks.clone().narrow(1, 0, t), cond.clone(), next, Some(action));
    let ego = m.ego_logits(cond, false).unwrap();
    (
        h.into_data().iter::<f32>().collect(),
        ego.into_data().iter::<f32>().collect(),
    )
}

/// Values of frames `0..upto` of a `[b=1, t, ...]` tensor flattened per frame of `per` values.
fn frames(v: &[f32], per: usize, upto: usize) -> &[f32] {
    &v[..per * upto]
}

#[test]
fn tar_and_ego_outputs_of_a_frame_ignore_later_frames() {
    let m = model::<F>();
    let (f, n, d) = (5, spec().n, config().d_model);
    let ids = tokens(&spec(), 1, f, 11);
    let (h0, ego0) = h_and_ego(&m, &ids, 1, f);
    for k in 1..f {
        // Non-action tokens of frame k: outputs of frames < k are unchanged, frame k's (if any) move.
        let mut changed = ids.clone();
        for p in 5..n {
            if (k * n + p) % 3 == 0 && ![5, 22, 23, 30, 31, 36].contains(&p) {
                let v = changed[k * n + p];
                changed[k * n + p] = if v > 0 { v - 1 } else { v + 1 };
            }
        }
        let (h1, ego1) = h_and_ego(&m, &changed, 1, f);
        assert_eq!(
            frames(&h0, n * d, k),
            frames(&h1, n * d, k),
            "h of frames < {k} moved"
        );
        assert_eq!(
            frames(&ego0, 3 * 16, k),
            frames(&ego1, 3 * 16, k),
            "ego logits of frames < {k} moved"
        );
        if k < f - 1 {
            assert_ne!(
                frames(&h0, n * d, k + 1),
                frames(&h1, n * d, k + 1),
                "frame {k} itself should matter"
            );
        }
        // Frame k's action is the next action of frame k − 1: outputs of frames < k − 1 stay.
        let mut act = ids.clone();
        act[k * n + 2] = (act[k * n + 2] + 5) % 16;
        let (h2, _) = h_and_ego(&m, &act, 1, f);
        assert_eq!(frames(&h0, n * d, k - 1), frames(&h2, n * d, k - 1));
        assert_ne!(
            frames(&h0, n * d, k),
            frames(&h2, n * d, k),
            "the next action steers frame {}",
            k - 1
        );
    }
}

#[test]
fn oar_logits_at_a_position_ignore_that_token_and_later_ones() {
    for precision in [Precision::F32, Precision::Bf16] {
        oar_causality(&model_in::<F>(precision));
    }
}

fn oar_causality(m: &Backbone<F>) {
    let (f, n) = (3, spec().n);
    let ids = tokens(&spec(), 1, f, 12);
    let run = |ids: &[i64]| -> Vec<Vec<f32>> {
        let toks = tensor::<F>(ids, 1, f, n);
        let e = m.embed.forward(toks.clone(), &Kernels::DEFAULT);
        let t = f - 1;
        let (cond, next) = (e.clone().narrow(1, 0, t), e.narrow(1, 1, t));
        let h = m.tar(
            toks.clone().narrow(1, 0, t),
            cond,
            next.clone(),
            Some(toks.narrow(1, 1, t).narrow(2, 1, 3)),
        );
        let d = h.dims()[3];
        let o = m.oar(m.oar_input(next.reshape([t, n, d]), h.reshape([t, n, d])));
        // Per position of the last target frame, its logits (through its segment's head).
        let last = o.narrow(0, t - 1, 1);
        (0..n)
            .map(|p| {
                let s = spec()
                    .segments
                    .iter()
                    .position(|s| (s.block_start..s.block_start + s.block_len).contains(&p))
                    .unwrap();
                let x: Tensor<F, 2> = last.clone().narrow(1, p, 1).reshape([1, d]);
                m.oar_heads.logits_at(s, x).into_data().iter::<f32>().collect()
            })
            .collect()
    };
    let base = run(&ids);
    for i in [6, 14, 24, 27, 33] {
        let mut changed = ids.clone();
        let p = (f - 1) * n + i;
        changed[p] = if changed[p] > 0 {
            changed[p] - 1
        } else {
            changed[p] + 1
        };
        let after = run(&changed);
        for q in 0..=i {
            assert_eq!(base[q], after[q], "logits at {q} moved when token {i} changed");
        }
        assert!(
            (i + 1..n).any(|q| base[q] != after[q]),
            "token {i} should matter to later positions"
        );
    }
}

#[test]
fn ego_queries_start_from_their_own_frames_action_only_with_ego_last() {
    // No cross-attention layers: the logits of frame i come from the queries alone, plus frame i's own
    // action with `ego_last`. One model per setting, run on both windows: the backend's seed is shared
    // with the tests running beside this one, so two models built from it need not have equal weights.
    let model = |ego_last: bool| {
        let cfg = BackboneConfig {
            ego_hist_layers: 0,
            ego_env_layers: 0,
            ego_last,
            ..config()
        };
        Backbone::<F>::new(&cfg, &spec(), &Default::default()).unwrap()
    };
    let logits = |m: &Backbone<F>, ids: &[i64]| -> Vec<Vec<f32>> {
        let e = m
            .embed
            .forward(tensor::<F>(ids, 1, 3, spec().n), &Kernels::DEFAULT);
        let v: Vec<f32> = m
            .ego_logits(e, false)
            .unwrap()
            .into_data()
            .iter::<f32>()
            .collect();
        v.chunks(3 * 16).map(<[f32]>::to_vec).collect()
    };
    let ids = tokens(&spec(), 1, 3, 21);
    let mut other = ids.clone();
    let n = spec().n;
    // Frame 1's action (positions 1..4) and a map token of frame 1.
    other[n + 2] = (other[n + 2] + 5) % 16;
    other[n + 9] = (other[n + 9] + 1) % 32;
    let (without, with) = (model(false), model(true));
    let (plain, plain_other) = (logits(&without, &ids), logits(&without, &other));
    assert_eq!(
        plain[0], plain[1],
        "without it every frame's queries are the same"
    );
    assert_eq!(plain, plain_other);
    let (own, own_other) = (logits(&with, &ids), logits(&with, &other));
    assert_ne!(own[0], own[1], "frames with other actions");
    assert_eq!(own[0], own_other[0], "frame 0 does not see frame 1");
    assert_eq!(own[2], own_other[2], "nor frame 2 frame 1");
    assert_ne!(own[1], own_other[1], "frame 1 sees its own action");
}
