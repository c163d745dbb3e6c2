//! Incremental decoding equals the full forward pass: the KV-cached OAR step and the single-token
//! embedding reproduce, position by position, the teacher-forced outputs that training computes.

use super::*;
use umgen_backbone::Slot;

#[test]
fn cached_oar_steps_equal_the_full_causal_pass() {
    let m = model::<F>();
    let sp = spec();
    let (b, n) = (2, sp.n);
    let ids = tokens(&sp, b, 1, 11);
    let frame = tensor::<F>(&ids, b, 1, n);
    let e = m.embed.forward(frame.clone()).reshape([b, n, 32]);
    // Any prior h works: a fixed random one.
    let h = Tensor::<F, 3>::random(
        [b, n, 32],
        burn::tensor::Distribution::Normal(0.0, 1.0),
        &Default::default(),
    );
    let full = m.oar(m.oar_input(e, h.clone()));
    let mut cache = m.oar_cache();
    let flat = frame.reshape([b, n]);
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
fn slots_name_every_position() {
    let m = model::<F>();
    let slots = m.slots();
    assert_eq!(slots.len(), spec().n);
    assert_eq!(slots[0], Slot::Start(0));
    assert_eq!(slots[1], Slot::Content(0, 0));
    assert_eq!(slots[4], Slot::End(0));
    assert_eq!(slots[6], Slot::Content(1, 0));
    assert_eq!(slots[33], Slot::End(3));
}
