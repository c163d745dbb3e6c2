use super::*;
use crate::kernels::Kernels;
use burn::backend::{Autodiff, Flex};
use burn::tensor::Distribution;

type A = Autodiff<Flex>;

fn close<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>, tol: f32, what: &str) {
    assert_eq!(a.dims(), b.dims(), "{what}: shapes");
    let (a, b) = (a.flatten::<1>(0, D - 1), b.flatten::<1>(0, D - 1));
    let scale = b.clone().abs().max().into_scalar().max(1e-6);
    let err = (a - b).abs().max().into_scalar() / scale;
    assert!(err <= tol, "{what}: relative error {err}");
}

fn random<const D: usize>(dims: [usize; D]) -> Tensor<A, D> {
    Tensor::random(dims, Distribution::Normal(0.0, 1.0), &Default::default())
}

#[test]
fn training_backends_take_the_operation() {
    assert!(over_time_for::<A>().is_some());
    assert!(over_time_for::<Autodiff<Flex, BalancedCheckpointing>>().is_some());
    assert!(over_time_for::<Flex>().is_none());
}

/// The transpositions are inverses, and `to_heads` groups frame `t` of position `n`'s head `h` at
/// `[b · n, h, t]`.
#[test]
fn heads_layout_round_trips() {
    let x = random::<4>([2, 3, 5, 8]).inner();
    let h = to_heads(x.clone(), 2);
    assert_eq!(h.dims(), [10, 2, 3, 4]);
    // Element [b 1, t 2, n 4, h 1 · 4 + 3] → [1 · 5 + 4, 1, 2, 3].
    let want = x.clone().slice([1..2, 2..3, 4..5, 7..8]).into_scalar();
    assert_eq!(h.clone().slice([9..10, 1..2, 2..3, 3..4]).into_scalar(), want);
    close(from_heads(h, 2, 5), x, 0.0, "round trip");
}

/// The operation's output and the gradients of `q` and `kv` equal burn's attention on the transposed
/// operands (the layers' path before), causal and not.
#[test]
fn operation_matches_burns_attention_on_transposed_operands() {
    let (b, t, n, heads, dh) = (2, 5, 3, 2, 8);
    let d = heads * dh;
    for causal in [true, false] {
        let q = random([b, t, n, d]).require_grad();
        let kv = random([b, t, n, 2 * d]).require_grad();
        let w = random([b, t, n, d]);
        let op = over_time_for::<A>().expect("a training backend");
        let ours = op(
            q.clone(),
            kv.clone(),
            heads,
            causal,
            Precision::F32,
            &Kernels::default(),
        );
        let (k, v) = split(kv.clone());
        let h = |x| to_heads(x, heads);
        let theirs = from_heads(
            crate::attention::attend(
                h(q.clone()),
                h(k),
                h(v),
                None,
                causal,
                Precision::F32,
                &Kernels::default(),
            ),
            b,
            n,
        );
        close(ours.clone().inner(), theirs.clone().inner(), 1e-5, "out");
        let g_ours = (ours * w.clone()).sum().backward();
        let g_theirs = (theirs * w).sum().backward();
        close(
            q.grad(&g_ours).expect("q"),
            q.grad(&g_theirs).expect("q"),
            1e-4,
            "dq",
        );
        close(
            kv.grad(&g_ours).expect("kv"),
            kv.grad(&g_theirs).expect("kv"),
            1e-4,
            "dkv",
        );
    }
}

/// The decomposed backward pass gives the same gradients from the forward pass's saved output as when it
/// recomputes them (the path of a backend that keeps nothing, such as CUDA's on a refused shape).
#[test]
fn decomposed_backward_recomputes_what_it_was_not_given() {
    let (b, t, n, heads, d) = (1, 4, 3, 2, 16);
    let (q, kv, dout) = (
        random::<4>([b, t, n, d]).inner(),
        random::<4>([b, t, n, 2 * d]).inner(),
        random::<4>([b, t, n, d]).inner(),
    );
    let saved = forward_decomposed(q.clone(), kv.clone(), heads, true, Precision::F32);
    let given = backward_decomposed(
        q.clone(),
        kv.clone(),
        Some(saved),
        dout.clone(),
        heads,
        true,
        Precision::F32,
    );
    let recomputed = backward_decomposed(q, kv, None, dout, heads, true, Precision::F32);
    close(given.0, recomputed.0, 0.0, "dq");
    close(given.1, recomputed.1, 0.0, "dkv");
}
