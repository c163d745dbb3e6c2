//! Incremental decoding equals the full forward pass: the KV-cached OAR step and the single-token
//! embedding reproduce, position by position, the teacher-forced outputs that training computes.

use super::*;
use umgen_backbone::Kernels;
use umgen_backbone::Slot;

/// A model, a frame of 2 scenes (`flat` `[b, n]`), its embedding `e`, a random prior `h` (any prior
/// works) and the full causal OAR pass over them.
struct Frame {
    m: Backbone<F>,
    b: usize,
    n: usize,
    flat: Tensor<F, 2, Int>,
    e: Tensor<F, 3>,
    h: Tensor<F, 3>,
    full: Tensor<F, 3>,
}

fn frame_with_prior(seed: u64) -> Frame {
    let m = model::<F>();
    let sp = spec();
    let (b, n) = (2, sp.n);
    let frame = tensor::<F>(&tokens(&sp, b, 1, seed), b, 1, n);
    let e = m
        .embed
        .forward(frame.clone(), &Kernels::DEFAULT)
        .reshape([b, n, 32]);
    let h = Tensor::<F, 3>::random(
        [b, n, 32],
        burn::tensor::Distribution::Normal(0.0, 1.0),
        &Default::default(),
    );
    let full = m.oar(m.oar_input(e.clone(), h.clone()));
    Frame {
        m,
        b,
        n,
        flat: frame.reshape([b, n]),
        e,
        h,
        full,
    }
}

#[test]
fn cached_oar_steps_equal_the_full_causal_pass() {
    let Frame {
        m,
        b,
        n,
        flat,
        h,
        full,
        ..
    } = frame_with_prior(11);
    let mut cache = m.oar_cache();
    let mut worst = 0f32;
    for p in 0..n {
        let prev = (p > 0).then(|| flat.clone().narrow(1, p - 1, 1).reshape([b]));
        let w = m.oar_input_at(p, prev, h.clone().narrow(1, p, 1).reshape([b, 32]));
        let step = m.oar_step(w, &mut cache).unwrap();
        let want = full.clone().narrow(1, p, 1).reshape([b, 32]);
        let diff: f32 = (step - want).abs().max().into_scalar();
        worst = worst.max(diff);
    }
    assert_eq!(cache.len(), n);
    assert_eq!(cache.capacity(), n);
    assert!(worst < 1e-4, "largest difference {worst}");
    // A frame's cache has room for N positions, no more.
    let w = m.oar_input_at(0, None, h.narrow(1, 0, 1).reshape([b, 32]));
    let err = m.oar_step(w, &mut cache).unwrap_err().to_string();
    assert!(err.contains("full"), "{err}");
}

#[test]
fn blocks_of_positions_equal_single_steps_and_rewinding_redoes_them() {
    let Frame {
        m,
        b,
        n,
        flat,
        e,
        h,
        full,
    } = frame_with_prior(12);
    // Positions 7..11 lie in segment 1's content; position 7's input embeds token 6 (its first id).
    for l in [2, 3, 4] {
        let p = 7;
        let mut cache = m.oar_cache();
        for q in 0..p {
            let prev = (q > 0).then(|| flat.clone().narrow(1, q - 1, 1).reshape([b]));
            let w = m.oar_input_at(q, prev, h.clone().narrow(1, q, 1).reshape([b, 32]));
            m.oar_step(w, &mut cache).unwrap();
        }
        let block_input = |cache_len: usize| {
            assert_eq!(cache_len, p);
            let first = m.oar_input_at(
                p,
                Some(flat.clone().narrow(1, p - 1, 1).reshape([b])),
                h.clone().narrow(1, p, 1).reshape([b, 32]),
            );
            let rest = m
                .embed
                .forward_block(p, flat.clone().narrow(1, p, l - 1))
                .unwrap()
                + h.clone().narrow(1, p + 1, l - 1);
            Tensor::cat(vec![first.reshape([b, 1, 32]), rest], 1)
        };
        // The embedding of a block is the full pass's rows.
        let emb = m
            .embed
            .forward_block(p, flat.clone().narrow(1, p, l - 1))
            .unwrap();
        let diff: f32 = (emb - e.clone().narrow(1, p, l - 1)).abs().max().into_scalar();
        assert!(diff < 1e-5, "{diff}");
        assert!(
            m.embed.forward_block(4, flat.clone().narrow(1, 4, 3)).is_none(),
            "crosses a segment"
        );
        let want = full.clone().narrow(1, p, l);
        let got = m.oar_steps(block_input(cache.len()), &mut cache).unwrap();
        let diff: f32 = (got - want.clone()).abs().max().into_scalar();
        assert!(diff < 1e-4, "block of {l} against the full pass: {diff}");
        assert_eq!(cache.len(), p + l);
        // Rewound, the same block again gives the same outputs (what was written after `p` is hidden).
        cache.rewind(p);
        let again = m.oar_steps(block_input(cache.len()), &mut cache).unwrap();
        let diff: f32 = (again - want).abs().max().into_scalar();
        assert!(diff < 1e-4, "after a rewind: {diff}");
        // A block longer than the room left is refused.
        let w = Tensor::<F, 3>::zeros([b, n, 32], &Default::default());
        let err = m.oar_steps(w, &mut cache).unwrap_err().to_string();
        assert!(err.contains("no room"), "{err}");
    }
}

#[test]
fn slots_name_every_position() {
    let m = model::<F>();
    let slots = m.slots();
    assert_eq!(slots.len(), spec().n);
    assert_eq!(slots[0], Slot::Start(0));
    assert_eq!(slots[1], Slot::Content(0, 0));
    assert_eq!(slots[4], Slot::End(0));
    assert_eq!(slots[6], Slot::Content(1, 0));
    assert_eq!(slots[36], Slot::End(3));
}
