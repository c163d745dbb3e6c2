//! The cross-attention layer as one operation, recomputed (`train.kernels.recompute`) or keeping its
//! activations (`train.kernels.layer = "fused"`), against burn's autodiff of the same layer: output, the queries' and the context's gradients, every parameter's gradient, and a context
//! shared by a stack of layers.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use super::*;
use crate::config::Precision;
use crate::testing::{A, normal, param_grads, rel, seeded};
use burn::backend::Flex;
use burn::module::Module;

/// A layer whose parameters are drawn from `seed` (`testing::seeded`: the same in every run, whatever
/// other tests draw meanwhile).
fn layer(d: usize, precision: Precision, seed: u64) -> CrossBlock<A> {
    let sizes = LayerSizes {
        d,
        heads: 4,
        ratio: 2,
        dropout: 0.0,
        precision,
    };
    seeded(CrossBlock::new(sizes, &Default::default()), seed)
}

/// Output, the queries' and the context's gradients and the parameters' of `(stack(x, ctx) · r).sum()`,
/// the stack's layers applied in turn over the same context with the kernels `k`.
fn run(
    blocks: &[CrossBlock<A>],
    x: &Tensor<Flex, 3>,
    ctx: &Tensor<Flex, 3>,
    r: &Tensor<Flex, 3>,
    k: &Kernels,
) -> (
    Tensor<Flex, 3>,
    Tensor<Flex, 3>,
    Tensor<Flex, 3>,
    Vec<Tensor<Flex, 1>>,
) {
    let x = Tensor::<A, 3>::from_inner(x.clone()).require_grad();
    let ctx = Tensor::<A, 3>::from_inner(ctx.clone()).require_grad();
    let y = blocks
        .iter()
        .fold(x.clone(), |h, b| b.forward(h, ctx.clone(), None, k));
    let grads = (y.clone() * Tensor::from_inner(r.clone())).sum().backward();
    let (dx, dctx) = (x.grad(&grads).unwrap(), ctx.grad(&grads).unwrap());
    let dp = blocks.iter().flat_map(|b| param_grads(b, &grads)).collect();
    (y.inner(), dx, dctx, dp)
}

/// A stack of layers and its inputs: 3 queries over `lk` keys, and the output's weights.
struct Case {
    blocks: Vec<CrossBlock<A>>,
    x: Tensor<Flex, 3>,
    ctx: Tensor<Flex, 3>,
    r: Tensor<Flex, 3>,
}

impl Case {
    fn new(layers: usize, lk: usize) -> Self {
        let blocks = (0..layers)
            .map(|i| layer(32, Precision::F32, 11 + i as u64))
            .collect();
        Self {
            blocks,
            x: normal([2, 3, 32], 1, 1.0, 0.0),
            ctx: normal([2, lk, 32], 2, 1.0, 0.0),
            r: normal([2, 3, 32], 3, 1.0, 0.0),
        }
    }

    /// The output, the queries' and the context's gradients, then the parameters', flattened, with the
    /// same weights computed in `precision`.
    fn outputs(&self, precision: Precision, k: &Kernels) -> Vec<Tensor<Flex, 1>> {
        let blocks: Vec<_> = self
            .blocks
            .iter()
            .map(|b| {
                let sizes = LayerSizes {
                    d: 32,
                    heads: 4,
                    ratio: 2,
                    dropout: 0.0,
                    precision,
                };
                CrossBlock::new(sizes, &Default::default()).load_record(b.clone().into_record())
            })
            .collect();
        let (y, dx, dctx, dp) = run(&blocks, &self.x, &self.ctx, &self.r, k);
        let flat = |t: Tensor<Flex, 3>| t.flatten::<1>(0, 2);
        [flat(y), flat(dx), flat(dctx)].into_iter().chain(dp).collect()
    }
}

/// The kernels with recomputation on.
const ON: Kernels = Kernels {
    recompute: true,
    ..Kernels::DEFAULT
};

/// The kernels with the layers as one operation that keeps their activations.
const KEPT: Kernels = Kernels {
    layer: umgen_ops::kernels::LayerKernel::Fused,
    ..Kernels::DEFAULT
};

/// Each of `ours` against `theirs`: the largest relative error, and which output it is.
fn worst(ours: Vec<Tensor<Flex, 1>>, theirs: Vec<Tensor<Flex, 1>>) -> (f32, usize) {
    assert_eq!(ours.len(), theirs.len());
    ours.into_iter()
        .zip(theirs)
        .map(|(a, b)| rel(a, b))
        .enumerate()
        .map(|(i, e)| (e, i))
        .fold((0.0, 0), |a, b| if b.0 > a.0 { b } else { a })
}

/// A stack of `layers` as one operation each (recomputed, then keeping their activations) and through
/// autodiff agree within `tol`, for 3 queries over `lk` keys: the output, the queries' and the context's
/// gradients and all 16 parameters' of each layer.
fn check(layers: usize, lk: usize, tol: f32) {
    let case = Case::new(layers, lk);
    let theirs = case.outputs(Precision::F32, &Kernels::DEFAULT);
    assert_eq!(theirs.len(), 3 + 16 * layers);
    let counted = [
        (ON, umgen_ops::layer::layers_recomputed as fn() -> u64),
        (KEPT, umgen_ops::layer::layers_kept),
    ];
    for (k, count) in counted {
        let before = count();
        let ours = case.outputs(Precision::F32, &k);
        assert!(count() >= before + layers as u64, "the operation ran");
        let (e, i) = worst(ours, theirs.clone());
        assert!(
            e < tol,
            "recompute {}: output {i} (0 the layer's, 1 and 2 the inputs' gradients): relative error {e}, \
             {layers} layer(s) over {lk} keys",
            k.recompute
        );
    }
}

#[test]
fn one_op_cross_layer_matches_autodiff_in_f32() {
    // 300 keys take the tiled attention on both paths.
    check(1, 300, 1e-4);
}

/// Three layers over one context: each layer's share of the context's gradient adds up.
#[test]
fn a_shared_context_gathers_every_layers_gradient() {
    check(3, 300, 1e-4);
}

/// In bf16 the paths round, each its own way (the one operation writes the keys and values in bf16
/// from the product, burn's path rounds them after the bias): the stack as one operation a layer,
/// recomputed or kept, is no further from the f32 layer than burn's bf16 path is.
#[test]
fn one_op_cross_layer_in_bf16_is_as_close_to_f32_as_autodiff() {
    let case = Case::new(2, 300);
    let exact = || case.outputs(Precision::F32, &Kernels::DEFAULT);
    let (theirs, j) = worst(case.outputs(Precision::Bf16, &Kernels::DEFAULT), exact());
    for k in [ON, KEPT] {
        let (ours, i) = worst(case.outputs(Precision::Bf16, &k), exact());
        assert!(
            ours <= 1.5 * theirs && ours < 0.05,
            "recompute {}: {ours} (output {i}) against burn's {theirs} (output {j})",
            k.recompute
        );
    }
}

/// Fewer keys than the tiled attention takes: burn's decomposed attention on the autodiff path, the
/// tiled blocks in the one operation, the same function.
#[test]
fn one_op_cross_layer_matches_autodiff_over_few_keys() {
    check(1, 40, 1e-4);
}
