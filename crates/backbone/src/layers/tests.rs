//! The self-attention layer's training paths against each other: recomputed (`train.kernels.recompute`) against
//! burn's autodiff of the same layer, and the attention over time on the rows as they lie against the
//! transposed layer.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use super::*;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::{Autodiff, Flex};
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Distribution;

type A = Autodiff<Flex>;

/// `blk` applied through the recomputing operation, which must take it.
fn recompute(
    blk: &SelfBlock<A>,
    x: Tensor<A, 3>,
    causal: bool,
    over_time: Option<(usize, usize)>,
) -> Tensor<A, 3> {
    let on = Kernels {
        recompute: true,
        ..Kernels::DEFAULT
    };
    let layer = recomputed_for::<A>(&on).expect("the CPU's autodiff backend has the operation");
    layer(&blk.parts(), x, causal, over_time, &on).unwrap_or_else(|_| panic!("a layer with biases is taken"))
}

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

/// A layer whose parameters are all perturbed, so that a gradient formula that drops a scale or shift
/// (norms start at γ = 1, β = 0) cannot pass.
fn layer(d: usize, heads: usize, dropout: f64, precision: Precision) -> SelfBlock<A> {
    struct Noise;
    impl ModuleMapper<A> for Noise {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<A, D>>) -> Param<Tensor<A, D>> {
            param.map(|t| {
                let noisy = t.clone().inner() + t.inner().random_like(Distribution::Normal(0.0, 0.2));
                Tensor::from_inner(noisy).require_grad()
            })
        }
    }
    Flex::seed(&Default::default(), 11);
    let sizes = LayerSizes {
        d,
        heads,
        ratio: 2,
        dropout,
        precision,
    };
    SelfBlock::new(sizes, &Default::default()).map(&mut Noise)
}

/// Every parameter gradient of `blk` in `grads`, in visiting order.
fn param_grads(blk: &SelfBlock<A>, grads: &Gradients) -> Vec<Tensor<Flex, 1>> {
    struct Collect<'a>(&'a Gradients, Vec<Tensor<Flex, 1>>);
    impl ModuleVisitor<A> for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
            let g = param.val().grad(self.0).expect("every parameter has a gradient");
            self.1.push(g.flatten(0, D - 1));
        }
    }
    let mut c = Collect(grads, Vec::new());
    blk.visit(&mut c);
    c.1
}

/// Largest difference relative to the largest magnitude of `b`.
fn rel<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>) -> f32 {
    let scale = b.clone().abs().max().into_scalar().max(1e-12);
    (a - b).abs().max().into_scalar() / scale
}

/// Output and gradients (input, then parameters) of `(f(x) · r).sum()`.
fn run(
    blk: &SelfBlock<A>,
    x: &Tensor<Flex, 3>,
    r: &Tensor<Flex, 3>,
    f: impl Fn(&SelfBlock<A>, Tensor<A, 3>) -> Tensor<A, 3>,
) -> Ran {
    let x = Tensor::<A, 3>::from_inner(x.clone()).require_grad();
    let y = f(blk, x.clone());
    let grads = (y.clone() * Tensor::from_inner(r.clone())).sum().backward();
    (y.inner(), x.grad(&grads).unwrap(), param_grads(blk, &grads))
}

/// What [`run`] returns.
type Ran = (Tensor<Flex, 3>, Tensor<Flex, 3>, Vec<Tensor<Flex, 1>>);

/// The output, the input gradient and the 14 parameter gradients of `ours` within `tol` of `theirs`.
fn agree((y1, dx1, dp1): Ran, (y0, dx0, dp0): Ran, tol: f32, case: &str) {
    assert!(rel(y1, y0) < tol, "output, {case}");
    assert!(rel(dx1, dx0) < tol, "input gradient, {case}");
    assert_eq!(dp0.len(), 14);
    for (i, (a, b)) in dp1.into_iter().zip(dp0).enumerate() {
        let e = rel(a, b);
        assert!(e < tol, "parameter {i}: relative error {e}, {case}");
    }
}

fn check(len: usize, causal: bool, precision: Precision, tol: f32) {
    let dev = Default::default();
    let blk = layer(32, 4, 0.0, precision);
    let x = Tensor::<Flex, 3>::random([2, len, 32], Distribution::Normal(0.0, 1.0), &dev);
    let r = Tensor::<Flex, 3>::random([2, len, 32], Distribution::Normal(0.0, 1.0), &dev);
    let (y0, dx0, dp0) = run(&blk, &x, &r, |b, x| {
        b.forward_autodiff(x, causal, &Kernels::DEFAULT)
    });
    let (y1, dx1, dp1) = run(&blk, &x, &r, |b, x| recompute(b, x, causal, None));
    agree(
        (y1, dx1, dp1),
        (y0, dx0, dp0),
        tol,
        &format!("len {len}, causal {causal}, {precision:?}"),
    );
}

#[test]
fn recomputed_layer_matches_autodiff_in_f32() {
    // 300 positions take the tiled attention on both paths, 40 the decomposed one on burn's path.
    check(300, true, Precision::F32, 1e-4);
    check(300, false, Precision::F32, 1e-4);
    check(40, true, Precision::F32, 1e-4);
}

/// A TAR temporal layer (`t` frames of `n` positions, each position over its own frames) recomputed against
/// the same layer through burn's autodiff and the attention-over-time operation.
fn check_over_time(t: usize, n: usize, precision: Precision, tol: f32) {
    let dev = Default::default();
    let blk = layer(32, 4, 0.0, precision);
    let x = Tensor::<Flex, 3>::random([2, t * n, 32], Distribution::Normal(0.0, 1.0), &dev);
    let r = Tensor::<Flex, 3>::random([2, t * n, 32], Distribution::Normal(0.0, 1.0), &dev);
    let (y0, dx0, dp0) = run(&blk, &x, &r, |b, x| {
        b.over_time_autodiff(x.reshape([2, t, n, 32]), &Kernels::DEFAULT)
            .reshape([2, t * n, 32])
    });
    let (y1, dx1, dp1) = run(&blk, &x, &r, |b, x| recompute(b, x, true, Some((t, n))));
    agree(
        (y1, dx1, dp1),
        (y0, dx0, dp0),
        tol,
        &format!("{t} frames of {n}, {precision:?}"),
    );
}

#[test]
fn recomputed_layer_over_time_matches_autodiff() {
    check_over_time(5, 7, Precision::F32, 1e-4);
    check_over_time(3, 11, Precision::Bf16, 2e-2);
}

#[test]
fn recomputed_layer_matches_autodiff_in_bf16() {
    check(300, true, Precision::Bf16, 2e-2);
    check(300, false, Precision::Bf16Linear, 2e-2);
}

/// A temporal layer on the rows as they lie gives the transposed layer's output and input gradient, and a
/// later frame never changes an earlier one's output.
#[test]
fn layer_over_time_matches_the_transposed_layer_and_is_causal() {
    let dev = Default::default();
    let sizes = LayerSizes {
        d: 16,
        heads: 2,
        ratio: 2,
        dropout: 0.0,
        precision: Precision::F32,
    };
    let blk = SelfBlock::<A>::new(sizes, &dev);
    let (b, t, n, d) = (2, 4, 3, 16);
    let x = random([b, t, n, d]).require_grad();
    let w = random([b, t, n, d]);
    let ours = blk.forward_over_time(x.clone(), &Kernels::DEFAULT);
    let theirs = blk
        .forward(
            x.clone().swap_dims(1, 2).reshape([b * n, t, d]),
            true,
            &Kernels::DEFAULT,
        )
        .reshape([b, n, t, d])
        .swap_dims(1, 2);
    close(ours.clone().inner(), theirs.clone().inner(), 1e-5, "layer output");
    let g_ours = (ours.clone() * w.clone()).sum().backward();
    let g_theirs = (theirs * w).sum().backward();
    close(
        x.grad(&g_ours).expect("x"),
        x.grad(&g_theirs).expect("x"),
        1e-4,
        "dx",
    );
    // Frame 3 changed: frames 0-2 unchanged, frame 3 changed.
    let moved = x
        .clone()
        .inner()
        .slice_assign([0..b, 3..4, 0..n, 0..d], random([b, 1, n, d]).inner());
    let again = blk
        .forward_over_time(Tensor::from_inner(moved), &Kernels::DEFAULT)
        .inner();
    let ours = ours.inner();
    close(
        again.clone().narrow(1, 0, 3),
        ours.clone().narrow(1, 0, 3),
        0.0,
        "earlier frames",
    );
    let changed = (again.narrow(1, 3, 1) - ours.narrow(1, 3, 1))
        .abs()
        .max()
        .into_scalar();
    assert!(changed > 1e-3, "the changed frame's output moved by {changed}");
}
