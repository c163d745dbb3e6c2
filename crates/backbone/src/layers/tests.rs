//! The self-attention layer's training paths against each other: the layer as one operation, recomputed
//! (`train.kernels.recompute`) or keeping its activations (`train.kernels.layer = "fused"`), against burn's
//! autodiff of the same layer, and the attention over time on the rows as they lie against the transposed
//! layer.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use super::*;
use crate::testing::{A, normal, param_grads, rel, seeded};
use burn::backend::Flex;
use burn::tensor::Distribution;
use umgen_ops::kernels::LayerKernel;

/// How a layer runs in training.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Path {
    /// One operation, recomputing its activations.
    Recomputed,
    /// One operation, keeping its activations.
    Kept,
    /// burn's autodiff of each operation.
    Autodiff,
}

impl Path {
    /// The kernels that take this path.
    fn kernels(self) -> Kernels {
        Kernels {
            recompute: self == Path::Recomputed,
            layer: match self {
                Path::Kept => LayerKernel::Fused,
                _ => LayerKernel::Burn,
            },
            ..Kernels::DEFAULT
        }
    }
}

/// `blk` applied through the layer's one operation with the kernels `on`, which must take it.
fn one_op(
    blk: &SelfBlock<A>,
    x: Tensor<A, 3>,
    causal: bool,
    over_time: Option<(usize, usize)>,
    on: Kernels,
) -> Tensor<A, 3> {
    let layer = layer_op_for::<A>(&on).expect("the CPU's autodiff backend has the operation");
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

/// A layer whose parameters are drawn from a fixed seed (`testing::seeded`: the same in every run,
/// whatever other tests draw meanwhile).
fn layer(d: usize, heads: usize, dropout: f64, precision: Precision) -> SelfBlock<A> {
    let sizes = LayerSizes {
        d,
        heads,
        ratio: 2,
        dropout,
        precision,
    };
    seeded(SelfBlock::new(sizes, &Default::default()), 11)
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

/// The largest relative error of `ours` against `theirs` over the output, the input gradient and the 14
/// parameter gradients, and which of them it is (0 the output, 1 the input gradient, then the parameters).
fn worst((y1, dx1, dp1): Ran, (y0, dx0, dp0): Ran) -> (f32, usize) {
    assert_eq!(dp0.len(), 14);
    assert_eq!(dp1.len(), 14);
    [rel(y1, y0), rel(dx1, dx0)]
        .into_iter()
        .chain(dp1.into_iter().zip(dp0).map(|(a, b)| rel(a, b)))
        .enumerate()
        .fold((0.0, 0), |w, (i, e)| if e > w.0 { (e, i) } else { w })
}

/// The layer's output and gradients over `len` rows (a TAR temporal layer on `t` frames of `n` with
/// `over_time`) on `path`, its products in `precision`. The weights and inputs are the same for every
/// call.
fn outputs(
    len: usize,
    causal: bool,
    over_time: Option<(usize, usize)>,
    precision: Precision,
    path: Path,
) -> Ran {
    let blk = layer(32, 4, 0.0, precision);
    let x = normal([2, len, 32], 1, 1.0, 0.0);
    let r = normal([2, len, 32], 2, 1.0, 0.0);
    let k = path.kernels();
    run(&blk, &x, &r, |b, x| match (path, over_time) {
        (Path::Recomputed | Path::Kept, _) => one_op(b, x, causal, over_time, k),
        (Path::Autodiff, None) => b.forward_autodiff(x, causal, &k),
        (Path::Autodiff, Some((t, n))) => {
            b.over_time_autodiff(x.reshape([2, t, n, 32]), &k)
                .reshape([2, t * n, 32])
        }
    })
}

/// In f32 the layer's one operation, recomputing and keeping, agrees with burn's autodiff within 1e-4.
fn check(len: usize, causal: bool, over_time: Option<(usize, usize)>) {
    let theirs = || outputs(len, causal, over_time, Precision::F32, Path::Autodiff);
    for path in [Path::Recomputed, Path::Kept] {
        let ours = outputs(len, causal, over_time, Precision::F32, path);
        let (e, i) = worst(ours, theirs());
        assert!(
            e < 1e-4,
            "{path:?}, output {i}: relative error {e}, len {len}, causal {causal}, {over_time:?}"
        );
    }
}

/// In bf16 the paths round, each its own way: the layer's one operation, recomputing and keeping, is no
/// further from the f32 layer than burn's path is (within 1.5×).
fn check_bf16(len: usize, causal: bool, over_time: Option<(usize, usize)>, precision: Precision) {
    let exact = || outputs(len, causal, over_time, Precision::F32, Path::Autodiff);
    let (theirs, j) = worst(
        outputs(len, causal, over_time, precision, Path::Autodiff),
        exact(),
    );
    for path in [Path::Recomputed, Path::Kept] {
        let (ours, i) = worst(outputs(len, causal, over_time, precision, path), exact());
        assert!(
            ours <= 1.5 * theirs,
            "{path:?} {ours} (output {i}) against burn's {theirs} (output {j}), len {len}, causal {causal}, \
             {over_time:?}, {precision:?}"
        );
    }
}

#[test]
fn one_op_layer_matches_autodiff_in_f32() {
    // 300 positions take the tiled attention on both paths, 40 the decomposed one on burn's path.
    check(300, true, None);
    check(300, false, None);
    check(40, true, None);
}

/// A TAR temporal layer (`t` frames of `n` positions, each position over its own frames) as one operation against
/// the same layer through burn's autodiff and the attention-over-time operation.
#[test]
fn one_op_layer_over_time_matches_autodiff() {
    check(35, true, Some((5, 7)));
    check_bf16(33, true, Some((3, 11)), Precision::Bf16);
}

#[test]
fn one_op_layer_in_bf16_is_as_close_to_f32_as_autodiff() {
    check_bf16(300, true, None, Precision::Bf16);
    check_bf16(300, false, None, Precision::Bf16Linear);
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
