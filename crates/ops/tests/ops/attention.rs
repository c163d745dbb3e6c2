//! The tiled attention against burn's decomposed attention: outputs and gradients, causal and bidirectional,
//! self- and cross-attention, blocks that do not divide the sequence.

use super::{A, F};
use burn::tensor::backend::Backend;
use burn::tensor::module::attention_fallback;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Distribution, Tensor};
use umgen_ops::attention::{tiled_autodiff, tiled_for};
use umgen_ops::tiled::{tiled_backward, tiled_forward};
use umgen_ops::{Kernels, Precision};

fn random<B: Backend>(shape: [usize; 4], seed: u64) -> Tensor<B, 4> {
    let _one = super::SEEDED
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    B::seed(&Default::default(), seed);
    Tensor::random(shape, Distribution::Normal(0.0, 1.0), &Default::default())
}

fn reference<B: Backend>(q: Tensor<B, 4>, k: Tensor<B, 4>, v: Tensor<B, 4>, causal: bool) -> Tensor<B, 4> {
    let opts = AttentionModuleOptions {
        is_causal: causal,
        ..Default::default()
    };
    attention_fallback(q, k, v, None, None, opts)
}

fn max_abs_diff<B: Backend>(a: Tensor<B, 4>, b: Tensor<B, 4>) -> f32 {
    use burn::tensor::ElementConversion;
    (a - b).abs().max().into_scalar().elem()
}

/// (lq, lk, causal, rows): one block, several blocks with a short last one, cross-attention with more
/// keys than queries (bottom-right causal alignment).
const CASES: [(usize, usize, bool, usize); 5] = [
    (40, 40, true, 64),
    (150, 150, true, 64),
    (150, 150, false, 64),
    (70, 200, true, 32),
    (70, 200, false, 32),
];

#[test]
fn forward_matches_the_decomposed_attention() {
    for (i, &(lq, lk, causal, rows)) in CASES.iter().enumerate() {
        let q = random::<F>([2, 3, lq, 16], 10 * i as u64);
        let k = random::<F>([2, 3, lk, 16], 10 * i as u64 + 1);
        let v = random::<F>([2, 3, lk, 8], 10 * i as u64 + 2);
        let want = reference(q.clone(), k.clone(), v.clone(), causal);
        let (got, lse) = tiled_forward(q, k, v, causal, rows, Precision::F32);
        assert_eq!(got.dims(), [2, 3, lq, 8]);
        assert_eq!(lse.dims(), [2, 3, lq, 1]);
        let err = max_abs_diff(got, want);
        assert!(err < 1e-5, "case {i}: max |Δ| {err}");
    }
}

/// Gradients of `Σ y ∘ w` (a random upstream gradient) with respect to q, k and v, through autodiff of the
/// decomposed attention.
fn reference_grads(
    q: Tensor<F, 4>,
    k: Tensor<F, 4>,
    v: Tensor<F, 4>,
    w: Tensor<F, 4>,
    causal: bool,
    tiled: bool,
) -> [Tensor<F, 4>; 3] {
    let (q, k, v) = (
        Tensor::<A, 4>::from_inner(q).require_grad(),
        Tensor::<A, 4>::from_inner(k).require_grad(),
        Tensor::<A, 4>::from_inner(v).require_grad(),
    );
    let y = if tiled {
        tiled_autodiff(
            q.clone(),
            k.clone(),
            v.clone(),
            causal,
            Precision::F32,
            &Kernels::DEFAULT,
        )
    } else {
        reference(q.clone(), k.clone(), v.clone(), causal)
    };
    let grads = (y * Tensor::from_inner(w)).sum().backward();
    [q.grad(&grads), k.grad(&grads), v.grad(&grads)].map(|g| g.expect("a gradient"))
}

#[test]
fn backward_matches_autodiff_of_the_decomposed_attention() {
    for (i, &(lq, lk, causal, rows)) in CASES.iter().enumerate() {
        let s = 100 + 10 * i as u64;
        let q = random::<F>([2, 2, lq, 16], s);
        let k = random::<F>([2, 2, lk, 16], s + 1);
        let v = random::<F>([2, 2, lk, 8], s + 2);
        let w = random::<F>([2, 2, lq, 8], s + 3);
        let want = reference_grads(q.clone(), k.clone(), v.clone(), w.clone(), causal, false);
        let (out, lse) = tiled_forward(q.clone(), k.clone(), v.clone(), causal, rows, Precision::F32);
        let got = tiled_backward(q, k, v, out, lse, w, causal, rows, Precision::F32);
        for (name, g, r) in [
            ("q", got.0, &want[0]),
            ("k", got.1, &want[1]),
            ("v", got.2, &want[2]),
        ] {
            let err = max_abs_diff(g, r.clone());
            assert!(err < 1e-4, "case {i}: d{name} max |Δ| {err}");
        }
    }
}

#[test]
fn the_autodiff_operation_gives_the_decomposed_gradients() {
    for causal in [true, false] {
        let q = random::<F>([1, 2, 33, 8], 7);
        let k = random::<F>([1, 2, 33, 8], 8);
        let v = random::<F>([1, 2, 33, 8], 9);
        let w = random::<F>([1, 2, 33, 8], 10);
        let want = reference_grads(q.clone(), k.clone(), v.clone(), w.clone(), causal, false);
        let got = reference_grads(q, k, v, w, causal, true);
        for (g, r) in got.into_iter().zip(want) {
            let err = max_abs_diff(g, r);
            assert!(err < 1e-4, "causal {causal}: max |Δ| {err}");
        }
    }
}

#[test]
fn training_backends_take_the_tiled_operation_and_inference_ones_do_not() {
    assert!(tiled_for::<A>().is_some());
    type Balanced =
        burn::backend::Autodiff<F, burn::backend::autodiff::checkpoint::strategy::BalancedCheckpointing>;
    assert!(tiled_for::<Balanced>().is_some());
    assert!(tiled_for::<F>().is_none());
}

#[test]
fn attend_on_the_training_backend_gives_the_decomposed_values_and_gradients() {
    use umgen_ops::attention::attend;
    // Long enough for the tiled path (short sequences take the decomposed one).
    let (q, k, v, w) = (
        random::<F>([1, 2, 300, 8], 21),
        random::<F>([1, 2, 300, 8], 22),
        random::<F>([1, 2, 300, 8], 23),
        random::<F>([1, 2, 300, 8], 24),
    );
    let want = reference_grads(q.clone(), k.clone(), v.clone(), w.clone(), true, false);
    let (qa, ka, va) = (
        Tensor::<A, 4>::from_inner(q.clone()).require_grad(),
        Tensor::<A, 4>::from_inner(k.clone()).require_grad(),
        Tensor::<A, 4>::from_inner(v.clone()).require_grad(),
    );
    let y = attend(
        qa.clone(),
        ka.clone(),
        va.clone(),
        None,
        true,
        Precision::F32,
        &Kernels::DEFAULT,
    );
    let err = max_abs_diff(y.clone().inner(), reference(q, k, v, true));
    assert!(err < 1e-5, "output max |Δ| {err}");
    let grads = (y * Tensor::from_inner(w)).sum().backward();
    let got = [qa.grad(&grads), ka.grad(&grads), va.grad(&grads)].map(|g| g.expect("a gradient"));
    for (g, r) in got.into_iter().zip(want) {
        let err = max_abs_diff(g, r);
        assert!(err < 1e-4, "gradient max |Δ| {err}");
    }
}

/// max |a − b| / max |b|.
fn rel_err(a: Tensor<F, 4>, b: Tensor<F, 4>) -> f32 {
    use burn::tensor::ElementConversion;
    let scale: f32 = b.clone().abs().max().into_scalar().elem();
    max_abs_diff(a, b) / scale
}

#[test]
fn bf16_products_stay_within_bf16_tolerance_of_f32_and_return_f32() {
    for (i, &(lq, lk, causal, rows)) in CASES.iter().enumerate() {
        let s = 300 + 10 * i as u64;
        let q = random::<F>([2, 2, lq, 16], s);
        let k = random::<F>([2, 2, lk, 16], s + 1);
        let v = random::<F>([2, 2, lk, 8], s + 2);
        let w = random::<F>([2, 2, lq, 8], s + 3);
        let want_out = reference(q.clone(), k.clone(), v.clone(), causal);
        let want = reference_grads(q.clone(), k.clone(), v.clone(), w.clone(), causal, false);
        let (out, lse) = tiled_forward(q.clone(), k.clone(), v.clone(), causal, rows, Precision::Bf16);
        assert_eq!(out.dtype(), burn::tensor::DType::F32);
        // bf16 has 8 significant bits (relative step 2⁻⁸ ≈ 3.9e-3); the error is a few steps, never zero.
        let err = rel_err(out.clone(), want_out);
        assert!(err > 1e-5 && err < 2e-2, "case {i}: output relative error {err}");
        let got = tiled_backward(q, k, v, out, lse, w, causal, rows, Precision::Bf16);
        for (name, g, r) in [
            ("q", got.0, &want[0]),
            ("k", got.1, &want[1]),
            ("v", got.2, &want[2]),
        ] {
            assert_eq!(g.dtype(), burn::tensor::DType::F32);
            let err = rel_err(g, r.clone());
            assert!(err < 3e-2, "case {i}: d{name} relative error {err}");
        }
    }
}

/// Keys and values as one `[b, lk, 2d]` tensor (the layers' kv product): the output and the gradients of the
/// queries and of `kv` equal burn's decomposed attention on the split heads, causal (the OAR's case, 300 keys:
/// the operation's path) and with a mask (burn's path).
#[test]
fn attention_over_one_kv_tensor_gives_the_decomposed_gradients() {
    use umgen_ops::attention::attend_kv;
    let (b, h, l, dh) = (2, 3, 300, 8);
    let d = h * dh;
    let split = |x: Tensor<A, 3>| x.reshape([b, l, h, dh]).swap_dims(1, 2);
    for masked in [false, true] {
        let q = random::<A>([b, h, l, dh], 11).require_grad();
        let kv = Tensor::<A, 3>::random([b, l, 2 * d], Distribution::Normal(0.0, 1.0), &Default::default())
            .require_grad();
        let w = random::<A>([b, h, l, dh], 13);
        let mask = masked.then(|| {
            Tensor::<A, 2, burn::tensor::Bool>::tril_mask([l, l], 0, &Default::default())
                .unsqueeze::<4>()
                .expand([b, h, l, l])
        });
        let ours = attend_kv(
            q.clone(),
            kv.clone(),
            mask.clone(),
            !masked,
            Precision::F32,
            &Kernels::DEFAULT,
        );
        let (k, v) = (
            split(kv.clone().narrow(2, 0, d)),
            split(kv.clone().narrow(2, d, d)),
        );
        let theirs = if masked {
            let opts = AttentionModuleOptions::default();
            attention_fallback(q.clone(), k, v, mask, None, opts)
        } else {
            reference(q.clone(), k, v, true)
        };
        assert!(
            max_abs_diff(ours.clone().inner(), theirs.clone().inner()) < 1e-5,
            "output"
        );
        let g_ours = (ours * w.clone()).sum().backward();
        let g_theirs = (theirs * w).sum().backward();
        let dq = |g| q.grad(g).expect("q");
        assert!(
            max_abs_diff::<F>(dq(&g_ours), dq(&g_theirs)) < 1e-4,
            "dq (masked {masked})"
        );
        let dkv = |g| kv.grad(g).expect("kv").unsqueeze::<4>();
        assert!(
            max_abs_diff::<F>(dkv(&g_ours), dkv(&g_theirs)) < 1e-4,
            "dkv (masked {masked})"
        );
    }
}
